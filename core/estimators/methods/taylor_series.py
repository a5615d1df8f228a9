"""Iterative Taylor-series weighted least squares with bearing-error estimation (paper 004).

The patent (ALGORITHMS.md section 8) linearises each bearing at the current
estimate ``X0`` and keeps the error term in the equation,
``A dX = Z - dtheta`` with ``Z_i = wrap(beta_i - theta_i(X0))`` and
``A_i = d theta_i / dX`` (for a compass azimuth ``[n, -e] / d^2``), solves
``dX = (A^T Q^-1 A)^-1 A^T Q^-1 Z``, moves ``X0 <- X0 + dX`` and repeats
until ``|dX|`` is below the tolerance. The bearing errors are then estimated
as ``dtheta_hat = Z - A dX`` of the last iteration.

What this module adds to the patent, and why:

- Frames: every bearing is taken in its station's own ENU (exact on the
  ellipsoid); the patent's 2D plane is a ``local`` frame with a known target
  altitude. A known altitude (``problem.altitude_m``) makes the unknowns the
  local east/north at the estimate, and the estimate is put back on the
  altitude surface after each step.
- 3D without an altitude: azimuths alone leave the height undetermined, so
  the elevations are used when given (rows ``d el / dX`` of section 2, the
  same iteration in three unknowns); without altitude and without any
  elevation the method raises :class:`~core.errors.TooFewMeasurements`.
  Bearing errors are still reported one per bearing (the azimuth errors, in
  request order); the elevation errors are in ``details``.
- Unknown sigmas (NaN in ``problem.sigmas``, azimuths only): those bearings
  share one unknown sigma, estimated from their estimated errors as
  ``sum dtheta_hat^2 / sum (1 - h_ii)`` with ``h`` the WLS hat matrix. With
  every sigma unknown and azimuths only this is the patent's
  ``sum dtheta_hat^2 / (N - 2)`` (N - 2 degrees of freedom, N - 3 in 3D);
  with a mix of known and unknown sigmas the weights change with the
  estimate, so the iteration is repeated until the estimate settles. The
  covariance, the CRLB and the normalised residuals then use the estimated
  sigma, and the fix carries a ``sigma_estimated`` warning.
- Divergence: the patent keeps the previous ``X0`` when the iteration does
  not converge. Here a step that raises the weighted cost (or leaves the
  finite numbers) counts as divergence: the previous iterate is returned
  with a ``not_converged`` warning saying so; reaching ``max_iterations``
  also returns the last (lowest-cost) iterate with that warning.
- Start: ``problem.initial_guess_enu_m`` or the unweighted orthogonal-vector
  solution (azimuth-only: the pseudolinear Stansfield least squares).

Every step runs over the whole batch at once (the problems still iterating,
and still re-estimating a sigma, form the working set); the sums over
measurements are added in measurement order, so a problem's fix does not
depend on what else is in the batch.

Covariance: ``(A^T Q^-1 A)^-1`` at the fix, the inverse Fisher information,
i.e. the CRLB at the estimate (with estimated sigmas where they were
estimated); ``covariance_source`` is ``"information"``. The method is
Gauss-Newton on the ML cost, so this is its own first-order covariance.
"""

from __future__ import annotations

import numpy as np

from core.crlb import OBSERVABILITY_THRESHOLD
from core.errors import InvalidInput, LocalizationError, TooFewMeasurements, UnobservableGeometry
from core.estimators.base import ANGLES, SolveOptions, register
from core.estimators.methods.orthogonal_vector import eove_start
from core.estimators.result import Estimates, FixWarning
from core.measurements import AZIMUTH, ELEVATION, KIND_NAMES, MeasurementModel
from core.problem.batch import ProblemBatch
from core.problem.frame import local_axes

#: Relative cost increase a step may make before it counts as divergence (round-off allowance).
COST_INCREASE_TOLERANCE = 1e-9
#: Outer passes re-estimating a shared unknown sigma when known sigmas are mixed in.
SIGMA_PASSES = 10
NAME = "taylor_wls"


def _column_sum(values):
    """``sum_m values[..., m]`` added in column order (padding adds exact zeros, so no batch dependence)."""
    total = np.zeros(values.shape[:-1])
    for m in range(values.shape[-1]):
        total = total + values[..., m]
    return total


class _Rows:
    """The angle rows of R problems of a batch, as the iteration needs them (``take`` keeps a subset)."""

    def __init__(self, batch: ProblemBatch, problems, weights):
        self.batch = batch
        self.problems = np.asarray(problems, dtype=np.intp)
        stations, rotations = batch.measurement_stations()
        self.model = MeasurementModel(stations[self.problems], rotations[self.problems], batch.kinds[self.problems])
        self.values = batch.values[self.problems]
        self.weights = weights
        self.constrained = batch.constrained[self.problems]

    def take(self, rows) -> "_Rows":
        out = object.__new__(_Rows)
        out.batch, out.problems, out.model = self.batch, self.problems[rows], self.model.take(rows)
        out.values, out.weights, out.constrained = self.values[rows], self.weights[rows], self.constrained[rows]
        return out

    def linearise(self, positions_enu_m):
        """``Z`` ``(R, M)``, ``A`` ``(R, 3, M)`` over the free parameters (zero row for a frozen up), axes ``(R, 3, 3)``."""
        predicted, jacobian = self.model.predict(positions_enu_m, np.zeros(positions_enu_m.shape[0]))
        used = self.weights > 0
        z = np.where(used, self.model.residuals(self.values, predicted), 0.0)
        a = np.where(used[:, None, :], jacobian[:, :3], 0.0)
        axes = np.broadcast_to(np.eye(3), (z.shape[0], 3, 3)).copy()
        c = np.flatnonzero(self.constrained)
        if c.size:
            b = self.problems[c]
            axes[c] = local_axes(positions_enu_m[c], self.batch.origin[b], self.batch.geodetic[b])
            j = a[c]
            for p in range(2):
                a[c, p] = axes[c, p, 0, None] * j[:, 0] + axes[c, p, 1, None] * j[:, 1] + axes[c, p, 2, None] * j[:, 2]
            a[c, 2] = 0.0
        return z, a, axes

    def step(self, positions_enu_m, axes, delta):
        moved = positions_enu_m + (delta[:, 0, None] * axes[:, 0] + delta[:, 1, None] * axes[:, 1]
                                   + delta[:, 2, None] * axes[:, 2])
        return self.batch.onto_altitude(moved, self.problems)

    def cost(self, z):
        return _column_sum(self.weights * z * z)


def _normal_inverse(a, weights, constrained):
    """``(A^T W A)^-1`` ``(R, 3, 3)`` (zero for a frozen up) and the reason it does not exist (None where it does)."""
    size = a.shape[0]
    weighted = a * weights[:, None, :]
    information = _column_sum(weighted[:, :, None, :] * a[:, None, :, :])
    information[constrained, 2, 2] = 1.0
    diag = np.einsum("rii->ri", information)
    scale = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    outer = scale[:, :, None] * scale[:, None, :]
    scaled = information * outer
    no_diagonal = np.any(diag <= 0, axis=-1)
    finite = np.all(np.isfinite(scaled), axis=(-2, -1))
    scaled = np.where((finite & ~no_diagonal)[:, None, None], scaled, np.eye(3))
    rank_deficient = ~no_diagonal & ~finite
    unsure = np.flatnonzero(~no_diagonal & finite & (_determinant(scaled) <= 9.0 * OBSERVABILITY_THRESHOLD))
    if unsure.size:
        rank_deficient[unsure] = np.linalg.eigvalsh(scaled[unsure])[:, 0] <= OBSERVABILITY_THRESHOLD
    fails = no_diagonal | rank_deficient
    inverse = np.linalg.inv(np.where(fails[:, None, None], np.eye(3), scaled)) * outer
    inverse[constrained, 2, :] = 0.0
    inverse[constrained, :, 2] = 0.0
    reasons = [None] * size
    for r in np.flatnonzero(fails).tolist():
        reasons[r] = (f"{NAME}: the bearings do not determine the position" if no_diagonal[r] else
                      f"{NAME}: the bearings do not determine the position (the linearised equations are "
                      "rank-deficient: lines of sight parallel or all from one place)")
    return inverse, reasons


def _determinant(m):
    """Determinants ``(R,)`` of ``(R, 3, 3)`` matrices.

    For a unit-diagonal positive semi-definite matrix the eigenvalues are at
    most its trace, 3, so the smallest is at least ``det / 9``: only where
    that bound is not enough does the observability test need the eigenvalues.
    """
    return (m[:, 0, 0] * (m[:, 1, 1] * m[:, 2, 2] - m[:, 1, 2] * m[:, 2, 1])
            - m[:, 0, 1] * (m[:, 1, 0] * m[:, 2, 2] - m[:, 1, 2] * m[:, 2, 0])
            + m[:, 0, 2] * (m[:, 1, 0] * m[:, 2, 1] - m[:, 1, 1] * m[:, 2, 0]))


def _apply(matrix, vector):
    """``matrix @ vector`` for ``(R, 3, 3)`` and ``(R, 3)``, summed in index order."""
    return matrix[:, :, 0] * vector[:, 0, None] + matrix[:, :, 1] * vector[:, 1, None] + matrix[:, :, 2] * vector[:, 2, None]


def iterate(rows: _Rows, start_enu_m, max_iterations: int, tolerance_m: float):
    """Run the Taylor-series WLS iteration of every problem of ``rows`` from its start.

    Returns
    -------
    dict of ndarray (leading axis R)
        ``position_enu_m`` (R, 3), ``errors_rad`` (R, M) the estimated errors
        ``Z - A dX`` of the iteration that produced the position (0 off the
        angle rows), ``normal_inverse`` (R, 3, 3), ``axes`` (R, 3, 3),
        ``leverage`` (R, M), ``iterations``, ``converged``, ``diverged``
        (list of str or None), ``failure`` (list of str or None: the normal
        equations became singular).
    """
    size = rows.problems.size
    position = np.array(start_enu_m, dtype=float)
    z, a, axes = rows.linearise(position)
    cost = rows.cost(z)
    errors = z.copy()
    iterations = np.zeros(size, dtype=int)
    converged = np.zeros(size, dtype=bool)
    diverged: list[str | None] = [None] * size
    failure: list[str | None] = [None] * size
    active = np.arange(size)
    for iteration in range(1, max_iterations + 1):
        if active.size == 0:
            break
        sub = rows.take(active)
        gain, reasons = _normal_inverse(a[active], sub.weights, sub.constrained)
        broken = np.array([r is not None for r in reasons], dtype=bool)
        for k in np.flatnonzero(broken).tolist():
            failure[active[k]] = reasons[k]
        keep = np.flatnonzero(~broken)
        active, sub, gain = active[keep], sub.take(keep), gain[keep]
        a_act, z_act = a[active], z[active]
        delta = _apply(gain, _column_sum(a_act * (sub.weights * z_act)[:, None, :]))
        moved = sub.step(position[active], axes[active], delta)
        z_new, a_new, axes_new = sub.linearise(moved)
        cost_new = sub.cost(z_new)
        old = cost[active]
        bad = ~(np.all(np.isfinite(moved), axis=-1) & np.isfinite(cost_new)) | \
            (cost_new > old * (1.0 + COST_INCREASE_TOLERANCE) + 1e-300)
        for k in np.flatnonzero(bad).tolist():
            diverged[active[k]] = (f"{NAME} diverged at iteration {iteration} (weighted cost {old[k]:.4g} -> "
                                   f"{cost_new[k]:.4g}); the iterate before it is returned")
            iterations[active[k]] = iteration - 1
        good = ~bad
        g = active[good]
        errors[g] = z_act[good] - (a_act[good] * delta[good][:, :, None]).sum(axis=1)
        step_m = np.linalg.norm(moved[good] - position[g], axis=-1)
        position[g], z[g], a[g], axes[g], cost[g] = moved[good], z_new[good], a_new[good], axes_new[good], cost_new[good]
        iterations[g] = iteration
        done = step_m < tolerance_m
        converged[g[done]] = True
        active = g[~done]
    ok = np.array([f is None for f in failure], dtype=bool)
    gain = np.zeros((size, 3, 3))
    leverage = np.zeros(z.shape)
    if np.any(ok):
        chosen = np.flatnonzero(ok)
        sub = rows.take(chosen)
        gain[chosen], reasons = _normal_inverse(a[chosen], sub.weights, sub.constrained)
        for k, reason in enumerate(reasons):
            if reason is not None:
                failure[chosen[k]] = reason
        a_ok = a[chosen]
        spread = (gain[chosen][:, :, :, None] * a_ok[:, None, :, :]).sum(axis=2)
        leverage[chosen] = (a_ok * spread).sum(axis=1) * sub.weights
    return {"position_enu_m": position, "errors_rad": errors, "normal_inverse": gain, "axes": axes,
            "leverage": leverage, "iterations": iterations, "converged": converged, "diverged": diverged,
            "failure": failure, "cost": cost}


def _checks(batch: ProblemBatch) -> dict[int, LocalizationError]:
    """The documented input failures, in the order the method meets them."""
    valid = batch.valid
    is_az = valid & (batch.kinds == AZIMUTH)
    is_el = valid & (batch.kinds == ELEVATION)
    angle = is_az | is_el
    other = valid & ~angle
    unknown = angle & np.isnan(batch.sigmas)
    n_parameters = np.where(batch.constrained, 2, 3)
    n_angles = np.count_nonzero(angle, axis=-1)
    errors: dict[int, LocalizationError] = {}
    first_other = np.argmax(other, axis=-1)
    for b in np.flatnonzero(np.any(other, axis=-1)).tolist():
        m = int(first_other[b])
        i = int(batch.source_index[b, m])
        errors[b] = InvalidInput(f"{NAME} uses bearings only; measurement {i} is a "
                                 f"{KIND_NAMES[batch.kinds[b, m]]}: use ml for a mix", ("measurements", i))
    checks = [
        (~batch.constrained & ~np.any(is_el, axis=-1), lambda b: TooFewMeasurements(
            f"{NAME} from azimuths alone needs the target altitude (constraints.altitude_m): azimuths do not "
            "determine the height; give elevations or the altitude", ("altitude_m",))),
        (n_angles < n_parameters, lambda b: TooFewMeasurements(
            f"{NAME} needs at least {n_parameters[b]} angles here; got {n_angles[b]}", ("measurements",))),
        (np.any(unknown & ~is_az, axis=-1), lambda b: InvalidInput(
            f"{NAME} estimates azimuth sigmas only; give sigma_elevation_deg", ("measurements",))),
        ((np.count_nonzero(unknown, axis=-1) == n_angles) & (n_angles <= n_parameters), lambda b: TooFewMeasurements(
            f"{NAME} estimates the unknown bearing sigma from the estimated errors with N - {n_parameters[b]} "
            f"degrees of freedom: give more than {n_parameters[b]} bearings, or their sigmas", ("measurements",))),
    ]
    for fails, error in checks:
        for b in np.flatnonzero(fails).tolist():
            errors.setdefault(b, error(b))
    return errors


def _starts(batch: ProblemBatch, rows):
    """Start ``(R, 3)`` of problems ``rows``: the initial guess, else EOVE (azimuth planes only without
    elevations, the pseudolinear solution); its names and the failures of the start."""
    starts = batch.initial_guess_enu_m[rows].copy()
    guessed = ~np.isnan(starts[:, 0])
    has_elevation = batch.kind_counts[rows, ELEVATION] > 0
    names = np.where(guessed, "initial_guess", np.where(has_elevation, "eove", "pseudolinear")).tolist()
    failures: dict[int, LocalizationError] = {}
    need = np.flatnonzero(~guessed)
    if need.size:
        eove = eove_start(batch.take(rows[need]))
        starts[need] = eove.position_enu_m
        for k, error in eove.errors.items():
            message = error.message
            if message.startswith("eove"):
                message = NAME + message[len("eove"):]
            failures[int(need[k])] = type(error)(message, error.loc)
    return starts, names, failures


@register("taylor_wls", "iterative Taylor-series WLS that estimates each bearing's error (paper 004); "
                        "estimates an unknown bearing sigma", needs_sigmas=False, uses=ANGLES)
def taylor_wls(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """Taylor-series WLS fixes with estimated bearing errors; see the module docstring.

    Returns
    -------
    Estimates
        ``estimated_bearing_errors_rad`` ``(K,)`` per problem: one azimuth
        error per bearing, request order. ``details``: ``start``,
        ``estimated_sigma_azimuth_rad`` (when estimated),
        ``estimated_elevation_errors_rad`` (NaN where no elevation).

    Errors (in ``errors``)
    ----------------------
    InvalidInput
        A range or TOA in the mix; an unknown elevation sigma.
    TooFewMeasurements
        Azimuths only without a known altitude; or too few bearings to
        estimate an unknown sigma (more than 2 needed in 2D).
    UnobservableGeometry
        When the linearised equations are rank-deficient.
    """
    size = batch.size
    errors = _checks(batch)
    candidates = np.array(sorted(set(range(size)) - set(errors)), dtype=np.intp)
    position = np.full((size, 3), np.nan)
    covariance = np.full((size, 3, 3), np.nan)
    converged = np.zeros(size, dtype=bool)
    iterations = np.zeros(size, dtype=int)
    warnings: list[tuple] = [()] * size
    details: list[dict] = [{} for _ in range(size)]
    bearing_errors: list = [None] * size
    nothing = Estimates(position, "information", covariance, errors, converged, iterations, warnings,
                        estimated_bearing_errors_rad=bearing_errors, details=details)
    if candidates.size == 0:
        return nothing
    starts, start_names, failures = _starts(batch, candidates)
    errors.update({int(candidates[k]): e for k, e in failures.items()})
    keep = np.array([k not in failures for k in range(candidates.size)], dtype=bool)
    problems, starts = candidates[keep], starts[keep]
    start_names = [n for n, k in zip(start_names, keep) if k]
    if problems.size == 0:
        return nothing

    valid = batch.valid[problems]
    angle = valid & ((batch.kinds[problems] == AZIMUTH) | (batch.kinds[problems] == ELEVATION))
    unknown = angle & np.isnan(batch.sigmas[problems])
    any_unknown = np.any(unknown, axis=-1)
    all_unknown = np.count_nonzero(unknown, axis=-1) == np.count_nonzero(angle, axis=-1)
    sigmas = np.where(unknown, 1.0, np.where(angle, batch.sigmas[problems], 1.0))
    estimated = np.full(problems.size, np.nan)
    results: dict[str, np.ndarray | list] = {}
    failed = np.zeros(problems.size, dtype=bool)
    pending = np.arange(problems.size)
    for _ in range(SIGMA_PASSES):
        if pending.size == 0:
            break
        weights = np.where(angle[pending], 1.0 / sigmas[pending] ** 2, 0.0)
        rows = _Rows(batch, problems[pending], weights)
        result = iterate(rows, starts[pending], options.max_iterations, options.tolerance_m)
        for key, value in result.items():
            if key not in results:
                results[key] = [None] * problems.size if isinstance(value, list) else \
                    np.zeros((problems.size,) + value.shape[1:], dtype=value.dtype)
            if isinstance(value, list):
                for k, v in zip(pending.tolist(), value):
                    results[key][k] = v
            else:
                results[key][pending] = value
        broken = np.array([f is not None for f in result["failure"]], dtype=bool)
        for k in np.flatnonzero(broken).tolist():
            failed[pending[k]] = True
            errors[int(problems[pending[k]])] = UnobservableGeometry(result["failure"][k])
        going = ~broken & any_unknown[pending]
        p = pending[going]
        u = unknown[p]
        dof = _column_sum(np.where(u, 1.0 - result["leverage"][going], 0.0))
        no_dof = dof <= 1e-9
        for k in np.flatnonzero(no_dof).tolist():
            failed[p[k]] = True
            errors[int(problems[p[k]])] = TooFewMeasurements(
                f"{NAME}: no degrees of freedom left to estimate the bearing sigma; "
                "give more bearings or their sigmas", ("measurements",))
        p, u, dof, errs = p[~no_dof], u[~no_dof], dof[~no_dof], result["errors_rad"][going][~no_dof]
        used = sigmas[p, u.argmax(axis=-1)]
        sigma_hat = np.sqrt(_column_sum(np.where(u, errs, 0.0) ** 2) / dof)
        estimated[p] = sigma_hat
        sigmas[p] = np.where(u, sigma_hat[:, None], sigmas[p])
        settled = all_unknown[p] | (np.abs(sigma_hat / used - 1.0) < 1e-6)
        pending = p[~settled]

    solved = np.flatnonzero(~failed)
    b_solved = problems[solved]
    axes = results["axes"][solved]
    gain = results["normal_inverse"][solved]
    cov = np.einsum("rpi,rpq,rqj->rij", axes, gain, axes)
    scale = np.where(all_unknown[solved] & ~np.isnan(estimated[solved]), estimated[solved] ** 2, 1.0)
    position[b_solved] = results["position_enu_m"][solved]
    covariance[b_solved] = cov * scale[:, None, None]
    converged[b_solved] = results["converged"][solved]
    iterations[b_solved] = results["iterations"][solved]

    errors_rad = np.zeros(batch.kinds.shape)
    errors_rad[b_solved] = results["errors_rad"][solved]
    azimuth_errors = batch.by_bearing(errors_rad, AZIMUTH)
    elevation_errors = batch.by_bearing(errors_rad, ELEVATION)
    n_bearings = batch.kind_counts[:, AZIMUTH]
    with_sigma = solved[~np.isnan(estimated[solved])]
    all_sigmas = batch.sigmas.copy()
    b_estimated = problems[with_sigma]
    all_sigmas[b_estimated] = np.where(unknown[with_sigma], estimated[with_sigma, None], all_sigmas[b_estimated])
    diverged, did_converge = results["diverged"], results["converged"].tolist()
    taken, counts, n_unknown = results["iterations"].tolist(), n_bearings.tolist(), np.count_nonzero(unknown, -1).tolist()
    sigma_hats = estimated.tolist()
    for k, b in zip(solved.tolist(), b_solved.tolist()):
        n = counts[b]
        detail = {"start": start_names[k], "estimated_elevation_errors_rad": elevation_errors[b, :n]}
        found = []
        if diverged[k]:
            found.append(FixWarning("not_converged", diverged[k]))
        elif not did_converge[k]:
            found.append(FixWarning("not_converged",
                                    f"{NAME} did not converge in {taken[k]} iterations "
                                    f"(tolerance {options.tolerance_m:g} m); the last iterate is returned"))
        sigma_hat = sigma_hats[k]
        if sigma_hat == sigma_hat:
            found.append(FixWarning(
                "sigma_estimated",
                f"sigma of {n_unknown[k]} azimuths estimated from the estimated bearing errors: "
                f"{np.rad2deg(sigma_hat):.3f} deg; the covariance and CRLB use it"))
            detail["estimated_sigma_azimuth_rad"] = sigma_hat
        if found:
            warnings[b] = tuple(found)
        details[b] = detail
        bearing_errors[b] = azimuth_errors[b, :n]
    return Estimates(position, "information", covariance, errors, converged, iterations, warnings,
                     estimated_bearing_errors_rad=bearing_errors,
                     sigmas=all_sigmas if with_sigma.size else None, details=details)
