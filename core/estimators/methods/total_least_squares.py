"""Total least squares (TLS) and constrained TLS (CTLS) for azimuth-only fixes: paper 004's baselines.

All three solve the pseudolinear azimuth equations ``A q = b`` of
:mod:`core.estimators.azimuth_lines` (``A_i = n_i``, ``b_i = n_i . r_i`` in
two coordinates of the plane tangent to the known altitude surface) in a way
that admits errors in ``A`` as well as ``b``. They are azimuth-only 2D
methods: they need the target altitude (``problem.altitude_m``) and use no
elevation; a flat ``local`` problem with a known altitude is the patent's
plane. On the ellipsoid the plane is re-taken at the solution until it
settles (three passes).

``tls``
    The smallest right singular vector of ``[A | b / L]`` (Dogancay 2005),
    with ``b`` measured from the stations' centroid and scaled by ``L``, the
    rms distance of the stations from it, so that every column carries noise
    of the same order (about ``sigma``) and the answer does not depend on the
    unit of length or where the frame's origin is.

``ctls``, ``variant="newton"`` (default; the patent's "first-derivative CTLS")
    The structured perturbation of ``[A | b]`` is ``dA_i = -d_i h_i``,
    ``db_i = -d_i h_i . r_i`` for an azimuth error ``d_i``, so the
    constraint ``(A + dA) q = b + db`` makes the least-norm errors
    ``d_i = e_i / rho_i`` with ``e = A q - b`` and ``rho_i = h_i . (p - r_i)``.
    CTLS minimises ``J(q) = sum e_i^2 / (sigma_i^2 rho_i^2)``; this variant
    does it by Newton's method on the second-order Taylor expansion of
    ``J`` (exact gradient and Hessian), started from the pseudolinear least
    squares, with step halving when a step does not lower ``J`` and the
    Gauss-Newton matrix when the Hessian is not positive definite.

``ctls``, ``variant="projected"``
    Structured low-rank approximation by alternating projections (the
    patent's "projected CTLS": the equation keeps the structure of the LS
    equation, each ``b_i`` the inner product of row ``A_i`` with the station
    position). Each pass takes the rank-2 approximation of the row-weighted
    ``[A | b / L]`` (the "reduced-rank matrix") and projects every row back
    onto the set of rows an azimuth can produce, i.e. re-estimates each
    azimuth as the one whose row is nearest. It stops when the smallest
    singular value relative to the Frobenius norm (the normalised
    reduced-rank error) is below ``PROJECTED_THRESHOLD = 1e-4``, the
    patent's ``chi_0``, or after ``max_iterations`` passes (then
    ``not_converged``). The position is the null vector of the final
    structured matrix.

Covariance (``covariance_source``):

- ``tls``: ``"propagated"``, first-order perturbation of the smallest
  singular vector, ``dv = -(S - lambda I)^+ dS v`` with ``S = M^T M``.
- ``ctls`` newton: ``"propagated"``, by the implicit-function theorem at the
  minimum: ``dq / d az_i = H^-1 2 w_i (1 + 3 f_i^2) grad f_i`` with ``H`` the
  Hessian of ``J``, ``f_i = e_i / rho_i`` (``d f_i / d az_i = -(1 + f_i^2)``
  and ``d grad f_i / d az_i = -2 f_i grad f_i``).
- ``ctls`` projected: ``"propagated"`` as well, by central differences of the
  projection passes in the final plane, with the pass count frozen at the one
  the data needed (all perturbed azimuth sets run as one batch).

The start is the EOVE fix on the altitude surface (the pseudolinear least
squares), its position only. Every problem of a batch runs at once: the
plane passes, Newton iterations, step halvings and projection passes are a
fixed or bounded number of vectorised steps over the problems still running.

The bearing errors these methods imply are the conventional ones (measured
minus the azimuth of the fix), i.e. the azimuth ``residuals`` of the fix;
the patent compares its own estimates with those.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from core.errors import LocalizationError, UnobservableGeometry
from core.estimators.azimuth_lines import (
    AzimuthEquations,
    Lines,
    TangentPlane,
    azimuth_only_errors,
    crossing_errors,
    has_elevations,
    plane_and_equations,
    plane_spread_m,
)
from core.estimators.base import AZIMUTHS, SolveOptions, register
from core.estimators.methods.orthogonal_vector import eove_start
from core.estimators.result import Estimates, FixWarning
from core.linalg import inverse_2x2, jacobi_svd, row_sums, solve_2x2, weighted_gram
from core.problem.batch import ProblemBatch

#: Re-takes of the tangent plane at the solution (exact on the ellipsoid after two).
PLANE_PASSES = 3
#: The patent's chi_0: normalised reduced-rank error at which the projected CTLS stops.
PROJECTED_THRESHOLD = 1e-4
#: Newton iterations on each row's azimuth when projecting it onto the structure.
ROW_PROJECTION_STEPS = 3
#: Step halvings the Newton CTLS tries before it gives up on a step.
MAX_HALVINGS = 30
#: Step (rad) of the central differences of the projected CTLS covariance.
DIFFERENCE_STEP_RAD = 1e-6
CTLS_VARIANTS = ("newton", "projected")


class _Solution:
    """Problems of a batch that passed the refusals, carried through the plane passes.

    ``rows`` index the batch; every other array is over ``rows``. ``alive``
    turns False when a problem fails in a pass (its error is in ``errors``).
    """

    def __init__(self, batch: ProblemBatch, name: str, options: SolveOptions):
        self.name = name
        self.errors: dict[int, LocalizationError] = azimuth_only_errors(batch, name)
        lines = Lines.of(batch)
        for b, error in crossing_errors(lines, name).items():
            self.errors.setdefault(b, error)
        rows = np.setdiff1d(np.arange(batch.size), list(self.errors))
        position = np.zeros((0, 3))
        if rows.size:
            start = eove_start(batch.take(rows))
            self.errors.update({int(rows[j]): error for j, error in start.errors.items()})
            kept = np.setdiff1d(np.arange(rows.size), list(start.errors))
            rows, position = rows[kept], np.asarray(start.position_enu_m)[kept]
        self.rows = rows
        self.lines = lines.take(rows)
        self.position = position
        self.alive = np.ones(rows.size, dtype=bool)

    def fail(self, failed, message: str) -> None:
        for j in np.flatnonzero(failed & self.alive).tolist():
            self.errors.setdefault(int(self.rows[j]), UnobservableGeometry(message))
        self.alive &= ~failed

    def null_vector_points(self, v, spread_m):
        """Plane points ``(..., 2)`` of homogeneous null vectors ``(..., 3)``; True where one lies at infinity."""
        at_infinity = ~(np.abs(v[..., 2]) >= 1e-12 * np.linalg.norm(v, axis=-1))
        scale = np.expand_dims(spread_m, tuple(range(1, v.ndim - 1))) if v.ndim > 2 else spread_m
        with np.errstate(divide="ignore", invalid="ignore"):
            points = -scale[..., None] * v[..., :2] / np.where(at_infinity, 1.0, v[..., 2])[..., None]
        return points, at_infinity

    def passes(self, solve_in_plane):
        """Solve in the tangent plane at the current point, move onto the surface, repeat.

        ``solve_in_plane(plane, equations, current_m, state) -> (plane_m, state, at_infinity)``.
        """
        state = None
        for _ in range(PLANE_PASSES):
            plane, equations = plane_and_equations(self.lines, self.position)
            current = plane.coordinates(self.position)
            plane_m, state, at_infinity = solve_in_plane(plane, equations, current, state)
            self.fail(at_infinity, f"{self.name}: the total-least-squares solution lies at infinity "
                                   "(the azimuth lines are parallel)")
            plane_m = np.where(self.alive[:, None], plane_m, current)
            self.position = self.lines.onto_altitude(plane.point(plane_m))
        return plane, equations, plane_m, state

    def estimates(self, batch: ProblemBatch, covariance_plane_m2, plane: TangentPlane, details, **per_row) -> Estimates:
        """Estimates of the whole batch; ``per_row`` arrays over ``rows`` go into the same-named fields."""
        size = batch.size
        position = np.full((size, 3), np.nan)
        covariance = np.full((size, 3, 3), np.nan)
        alive = self.rows[self.alive]
        position[alive] = self.position[self.alive]
        covariance[alive] = plane.to_common(covariance_plane_m2)[self.alive]
        fields = {}
        for name, (values, fill) in per_row.items():
            full = np.full(size, fill, dtype=np.asarray(values).dtype)
            full[self.rows] = values
            fields[name] = full
        errors = {b: self.errors[b] for b in sorted(self.errors)}
        return Estimates(position_enu_m=position, covariance_source="propagated", covariance_enu_m2=covariance,
                         errors=errors, details=details, **fields)


def _variance(lines: Lines) -> np.ndarray:
    return np.where(lines.mask, lines.sigma_azimuth_rad, 0.0) ** 2


def _scaled_matrix(equations: AzimuthEquations, spread_m):
    return np.concatenate([equations.rows, (equations.rhs / spread_m[:, None])[..., None]], axis=-1)


def _tls(batch: ProblemBatch, options: SolveOptions):
    """TLS fixes and their first-order covariances, as a :class:`_Solution` and plane covariances."""
    run = _Solution(batch, "tls", options)

    def solve_in_plane(plane, equations, _current, _state):
        spread = plane_spread_m(run.lines, plane)
        matrix = _scaled_matrix(equations, spread)
        singular, vectors, _ = jacobi_svd(matrix)
        smallest = np.take_along_axis(vectors, np.argmin(singular, axis=-1)[:, None, None], axis=-1)[..., 0]
        points, at_infinity = run.null_vector_points(smallest, spread)
        return points, (matrix, spread), at_infinity

    plane, equations, _, (matrix, spread) = run.passes(solve_in_plane)
    eigenvalues, vectors = np.linalg.eigh(weighted_gram(np.swapaxes(matrix, 1, 2), np.ones(matrix.shape[:2])))
    v = vectors[..., 0]
    derivative_rows = -np.concatenate([equations.along_rows, (equations.along_rhs / spread[:, None])[..., None]],
                                      axis=-1)
    ds_v = (derivative_rows * np.einsum("bki,bi->bk", matrix, v)[..., None]
            + matrix * np.einsum("bki,bi->bk", derivative_rows, v)[..., None])
    with np.errstate(divide="ignore", invalid="ignore"):
        resolvent = vectors[..., 1:] / (eigenvalues[:, 1:] - eigenvalues[:, :1])[:, None, :]
        dv = -np.einsum("bki,bij,blj->bkl", ds_v, resolvent, vectors[..., 1:])
        v2 = v[:, 2, None, None]
        d_plane = -spread[:, None, None] * (dv[..., :2] * v2 - v[:, None, :2] * dv[..., 2:3]) / v2**2
    covariance_plane = weighted_gram(np.swapaxes(d_plane, 1, 2), _variance(run.lines))
    return run, plane, covariance_plane


def _take(equations: AzimuthEquations, rows) -> AzimuthEquations:
    return AzimuthEquations(equations.rows[rows], equations.rhs[rows], equations.along_rows[rows],
                            equations.along_rhs[rows])


def _residuals(equations: AzimuthEquations, plane_m, weights):
    """``e`` and ``rho`` ``(B, K)`` at plane coordinates ``(B, 2)`` (``rho`` 1 on padding)."""
    q0, q1 = plane_m[:, 0, None], plane_m[:, 1, None]
    a, d = equations.rows, equations.along_rows
    e = a[..., 0] * q0 + a[..., 1] * q1 - equations.rhs
    rho = d[..., 0] * q0 + d[..., 1] * q1 - equations.along_rhs
    return e, np.where(weights > 0, rho, 1.0)


def _ctls_cost(equations: AzimuthEquations, plane_m, weights):
    e, rho = _residuals(equations, plane_m, weights)
    f = e / rho
    return row_sums(weights * f * f)


def _ctls_terms(equations: AzimuthEquations, plane_m, weights):
    """CTLS cost, gradient, Hessian and Gauss-Newton matrix at plane coordinates ``(B, 2)``.

    Returns
    -------
    cost : ndarray, shape (B,)
    gradient : ndarray, shape (B, 2)
    hessian, gauss_newton : ndarray, shape (B, 2, 2)
    f : ndarray, shape (B, K)
        ``e / rho``.
    grad_f : ndarray, shape (B, K, 2)
    """
    e, rho = _residuals(equations, plane_m, weights)
    a0, a1 = equations.rows[..., 0], equations.rows[..., 1]
    d0, d1 = equations.along_rows[..., 0], equations.along_rows[..., 1]
    f = e / rho
    rho2 = rho * rho
    g0, g1 = (a0 * rho - d0 * e) / rho2, (a1 * rho - d1 * e) / rho2
    wf = weights * f
    cost = row_sums(wf * f)
    gradient = 2.0 * np.stack([row_sums(wf * g0), row_sums(wf * g1)], -1)
    wg0, wg1 = weights * g0, weights * g1
    gn00, gn01, gn11 = 2.0 * row_sums(wg0 * g0), 2.0 * row_sums(wg0 * g1), 2.0 * row_sums(wg1 * g1)
    curvature = 2.0 * e / (rho2 * rho)
    h00 = row_sums(wf * (-2.0 * a0 * d0 / rho2 + curvature * d0 * d0))
    h01 = row_sums(wf * (-(a0 * d1 + a1 * d0) / rho2 + curvature * d0 * d1))
    h11 = row_sums(wf * (-2.0 * a1 * d1 / rho2 + curvature * d1 * d1))

    def matrix(m00, m01, m11):
        return np.stack([np.stack([m00, m01], -1), np.stack([m01, m11], -1)], -2)

    gauss_newton = matrix(gn00, gn01, gn11)
    hessian = matrix(gn00 + 2.0 * h00, gn01 + 2.0 * h01, gn11 + 2.0 * h11)
    return cost, gradient, hessian, gauss_newton, f, np.stack([g0, g1], -1)


def _positive_definite(matrix) -> np.ndarray:
    """``(B,)``: the 2x2 matrices pass a Cholesky factorisation (lower triangle, as LAPACK reads it)."""
    h00, h10, h11 = matrix[:, 0, 0], matrix[:, 1, 0], matrix[:, 1, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        l10 = h10 / np.sqrt(h00)
        return (h00 > 0) & (h11 - l10 * l10 > 0)


def _newton_ctls(batch: ProblemBatch, options: SolveOptions):
    """First-derivative (Newton) CTLS fixes; see the module docstring."""
    run = _Solution(batch, "ctls", options)
    weights = np.where(run.lines.mask, 1.0 / run.lines.sigma_azimuth_rad**2, 0.0)
    tolerance = options.tolerance_m

    def solve_in_plane(_plane, equations, current, state):
        iterations = np.zeros(current.shape[0], dtype=int) if state is None else state[0]
        converged = np.zeros(current.shape[0], dtype=bool)
        q = current.copy()
        cost, gradient, hessian, gauss_newton, _, _ = _ctls_terms(equations, q, weights)
        active = run.alive.copy()
        for _ in range(options.max_iterations):
            rows = np.flatnonzero(active)
            if rows.size == 0:
                break
            part, w = _take(equations, rows), weights[rows]
            matrix = np.where(_positive_definite(hessian[rows])[:, None, None], hessian[rows], gauss_newton[rows])
            step = -solve_2x2(matrix, gradient[rows])
            accepted = np.zeros(rows.size, dtype=bool)
            for _ in range(MAX_HALVINGS):
                pending = np.flatnonzero(~accepted)
                if pending.size == 0:
                    break
                with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                    trial = _ctls_cost(_take(part, pending), q[rows[pending]] + step[pending], w[pending])
                good = np.isfinite(trial) & (trial <= cost[rows[pending]] * (1 + 1e-12) + 1e-300)
                accepted[pending[good]] = True
                step[pending[~good]] *= 0.5
            active[rows[~accepted]] = False
            moved = rows[accepted]
            step = step[accepted]
            iterations[moved] += 1
            q[moved] = q[moved] + step
            cost[moved], gradient[moved], hessian[moved], gauss_newton[moved], _, _ = _ctls_terms(
                _take(equations, moved), q[moved], weights[moved])
            small = np.linalg.norm(step, axis=-1) < tolerance
            converged[moved[small]] = True
            active[moved[small]] = False
        return q, (iterations, converged), np.zeros(q.shape[0], dtype=bool)

    plane, equations, plane_m, (iterations, converged) = run.passes(solve_in_plane)
    _, _, hessian, _, f, grad_f = _ctls_terms(equations, plane_m, weights)
    gain = 2.0 * (weights * (1.0 + 3.0 * f * f))[..., None] * np.einsum("bki,bij->bkj", grad_f, inverse_2x2(hessian))
    covariance_plane = weighted_gram(np.swapaxes(gain, 1, 2), _variance(run.lines))
    return run, plane, covariance_plane, iterations, converged


def _row_basis(lines: Lines, plane: TangentPlane, spread_m):
    """Rows an azimuth ``g`` can produce: ``cos g U_i + sin g V_i``, each ``(B, K, 3)`` (zero on padding)."""
    relative = lines.origins_enu_m - plane.centre_enu_m[:, None, :]
    mask = lines.mask[..., None]

    def row(vector):
        return np.concatenate([np.einsum("bki,bji->bkj", vector, plane.axes_enu),
                               (np.einsum("bki,bki->bk", vector, relative) / spread_m[:, None])[..., None]],
                              axis=-1) * mask

    return row(lines.rotations[..., 0, :]), -row(lines.rotations[..., 1, :])


def _projected_passes(basis_cos, basis_sin, azimuth_rad, weights_sqrt, max_passes, frozen: bool):
    """Alternating projections for S azimuth sets, each with its own basis.

    Parameters
    ----------
    basis_cos, basis_sin : ndarray, shape (S, K, 3)
    azimuth_rad : ndarray, shape (S, K)
        Measured azimuths (each set is projected independently).
    weights_sqrt : ndarray, shape (S, K)
        Zero on padding.
    max_passes : ndarray of int, shape (S,)
    frozen : bool
        Run exactly ``max_passes`` passes instead of stopping at the threshold.

    Returns
    -------
    null_vectors : ndarray, shape (S, 3)
    passes : ndarray of int, shape (S,)
    converged : ndarray of bool, shape (S,)
        The set reached the threshold.
    """
    count = azimuth_rad.shape[0]
    azimuth = np.asarray(azimuth_rad, dtype=float)
    null_vectors = np.zeros((count, 3))
    passes = np.zeros(count, dtype=int)
    done = np.zeros(count, dtype=bool)
    running = np.arange(count)
    bc, bs, w, az, limit = basis_cos, basis_sin, weights_sqrt[..., None], azimuth, max_passes
    divisor = np.where(w > 0, w, 1.0)
    for number in range(1, int(np.max(max_passes, initial=0)) + 1):
        c, sn = np.cos(az)[..., None], np.sin(az)[..., None]
        matrix = (c * bc + sn * bs) * w
        eigenvalues, vectors = np.linalg.eigh(np.matmul(np.swapaxes(matrix, -1, -2), matrix))
        smallest = vectors[..., 0]
        frobenius2 = np.sum(matrix * matrix, axis=(-2, -1))
        reached = np.sqrt(np.maximum(eigenvalues[:, 0], 0.0) / frobenius2) < PROJECTED_THRESHOLD
        null_vectors[running], passes[running], done[running] = smallest, number, reached
        going = ~((number == limit) | (reached & (not frozen)))
        if not np.any(going):
            break
        if not np.all(going):
            running, matrix, smallest, limit = running[going], matrix[going], smallest[going], limit[going]
            bc, bs, az, w, divisor = bc[going], bs[going], az[going], w[going], divisor[going]
        # the rank-2 approximation M (I - v v^T), v the smallest right singular vector
        reduced = matrix - np.sum(matrix * smallest[:, None, :], axis=-1)[..., None] * smallest[:, None, :]
        target = reduced / divisor
        for _ in range(ROW_PROJECTION_STEPS):
            c, sn = np.cos(az)[..., None], np.sin(az)[..., None]
            row = c * bc + sn * bs
            slope = -sn * bc + c * bs
            gap = row - target
            first = np.einsum("bki,bki->bk", slope, gap)
            slope2 = np.einsum("bki,bki->bk", slope, slope)
            second = slope2 - np.einsum("bki,bki->bk", row, gap)
            denominator = np.where(second > 0, second, slope2)
            az = az - first / np.where(denominator != 0, denominator, 1.0)
    return null_vectors, passes, done


def _projected_ctls(batch: ProblemBatch, options: SolveOptions):
    """Projected CTLS fixes and their first-order covariances; see the module docstring."""
    run = _Solution(batch, "ctls", options)
    lines = run.lines
    inverse_sigma = np.where(lines.mask, 1.0 / lines.sigma_azimuth_rad, 0.0)
    weights_sqrt = inverse_sigma / (row_sums(inverse_sigma) / np.maximum(lines.count, 1))[:, None]
    allowed = np.full(lines.count.size, options.max_iterations)

    def solve_in_plane(plane, _equations, _current, _state):
        spread = plane_spread_m(lines, plane)
        basis = _row_basis(lines, plane, spread)
        v, used, converged = _projected_passes(*basis, lines.azimuth_rad, weights_sqrt, allowed, False)
        points, at_infinity = run.null_vector_points(v, spread)
        return points, (used, converged, basis, spread), at_infinity

    plane, _, _, (used, converged, basis, spread) = run.passes(solve_in_plane)
    size, k = lines.mask.shape
    step = DIFFERENCE_STEP_RAD * np.eye(k)
    perturbed = np.concatenate([lines.azimuth_rad[:, None, :] + step, lines.azimuth_rad[:, None, :] - step], axis=1)
    sets = 2 * k

    def each_set(values):
        return np.repeat(values, sets, axis=0)

    v, _, _ = _projected_passes(each_set(basis[0]), each_set(basis[1]), perturbed.reshape(size * sets, k),
                                each_set(weights_sqrt), each_set(np.where(run.alive, used, 0)), True)
    points, at_infinity = run.null_vector_points(v.reshape(size, sets, 3), spread)
    run.fail(np.any(at_infinity & run.alive[:, None], axis=-1),
             "ctls: the total-least-squares solution lies at infinity (the azimuth lines are parallel)")
    gain = (points[:, :k] - points[:, k:]) / (2 * DIFFERENCE_STEP_RAD)
    with np.errstate(invalid="ignore"):
        covariance_plane = weighted_gram(np.swapaxes(gain, 1, 2), _variance(lines))
    return run, plane, covariance_plane, used, converged


def _details(batch: ProblemBatch, **first) -> list[dict]:
    unused = has_elevations(batch)
    base = {"bearing_errors": "conventional: the azimuth residuals at the fix"}
    with_unused = {**base, "unused_measurements": "elevations: an azimuth-only method with the altitude known"}
    return [{**first, **(with_unused if unused[b] else base)} for b in range(batch.size)]


@register("tls", "total least squares on the azimuth pseudolinear equations (azimuth-only, known altitude)",
          uses=AZIMUTHS)
def tls(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """TLS baseline of paper 004; see the module docstring."""
    run, plane, covariance_plane = _tls(batch, options)
    return run.estimates(batch, covariance_plane, plane, _details(batch))


@register("ctls", "constrained total least squares on the azimuth equations (azimuth-only, known altitude); "
                  "variant newton (default) or projected", variants=CTLS_VARIANTS, uses=AZIMUTHS)
def ctls(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """CTLS baselines of paper 004; ``options.variant`` in {"newton", "projected"}, default newton."""
    variant = options.variant or "newton"
    details = _details(batch, variant=variant)
    if variant == "newton":
        run, plane, covariance_plane, iterations, converged = _newton_ctls(batch, options)
        return run.estimates(batch, covariance_plane, plane, details, converged=(converged, True),
                             iterations=(iterations, 0))
    run, plane, covariance_plane, passes, converged = _projected_ctls(batch, options)
    warnings: list[tuple] = [()] * batch.size
    for j in np.flatnonzero(run.alive & ~converged).tolist():
        warnings[int(run.rows[j])] = (FixWarning(
            "not_converged", f"projected CTLS: normalised reduced-rank error still above {PROJECTED_THRESHOLD:g} "
                             f"after {int(passes[j])} passes; the last pass is returned"),)
    estimates = run.estimates(batch, covariance_plane, plane, details, converged=(converged, True),
                              iterations=(passes, 0))
    return replace(estimates, warnings=warnings)
