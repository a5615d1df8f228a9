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

Covariance: ``(A^T Q^-1 A)^-1`` at the fix, the inverse Fisher information,
i.e. the CRLB at the estimate (with estimated sigmas where they were
estimated); ``covariance_source`` is ``"information"``. The method is
Gauss-Newton on the ML cost, so this is its own first-order covariance.
"""

from __future__ import annotations

import numpy as np

from core.crlb import OBSERVABILITY_THRESHOLD
from core.errors import InvalidInput, TooFewMeasurements, UnobservableGeometry
from core.estimators.base import Estimate, SolveOptions, per_problem, register
from core.estimators.result import FixWarning
from core.estimators.orthogonal_vector import Normals, Weighting, solve_orthogonal
from core.measurements import Kind, predict, residuals
from core.problem import Problem

#: Relative cost increase a step may make before it counts as divergence (round-off allowance).
COST_INCREASE_TOLERANCE = 1e-9
#: Outer passes re-estimating a shared unknown sigma when known sigmas are mixed in.
SIGMA_PASSES = 10


class _Iteration:
    """State of the Gauss-Newton iteration on a fixed set of angle rows."""

    def __init__(self, problem: Problem, rows: np.ndarray):
        self.problem = problem
        self.rows = rows
        s = problem.station_index[rows]
        self.stations = problem.stations_enu_m[s][None]
        self.rotations = problem.station_rotations[s][None]
        self.kinds = problem.kinds[rows]
        self.values = problem.values[rows]
        self.constrained = problem.altitude_m is not None

    def linearise(self, position_enu_m):
        """``Z`` ``(R,)``, ``A`` ``(R, P)`` in the free parameters, and the axes ``(P, 3)``."""
        predicted, jacobian = predict(position_enu_m[None], np.zeros(1), self.stations, self.rotations,
                                      self.kinds[None])
        z = residuals(self.values, predicted[0], self.kinds)
        if self.constrained:
            axes = self.problem.frame.local_axes(position_enu_m)[:2]
        else:
            axes = np.eye(3)
        return z, jacobian[0, :, :3] @ axes.T, axes

    def step(self, position_enu_m, axes, delta):
        moved = position_enu_m + delta @ axes
        if self.constrained:
            moved = self.problem.frame.onto_altitude(moved, self.problem.altitude_m)
        return moved


def _normal_inverse(a, weights, name):
    information = a.T @ (a * weights[:, None])
    diag = np.diag(information)
    if np.any(diag <= 0):
        raise UnobservableGeometry(f"{name}: the bearings do not determine the position")
    scale = 1.0 / np.sqrt(diag)
    scaled = information * np.outer(scale, scale)
    if np.linalg.eigvalsh(scaled)[0] <= OBSERVABILITY_THRESHOLD:
        raise UnobservableGeometry(
            f"{name}: the bearings do not determine the position (the linearised equations are rank-deficient: "
            "lines of sight parallel or all from one place)")
    return np.linalg.inv(scaled) * np.outer(scale, scale)


def iterate(problem: Problem, rows, sigmas, start_enu_m, max_iterations: int, tolerance_m: float,
            name: str = "taylor_wls"):
    """Run the Taylor-series WLS iteration from a start.

    Parameters
    ----------
    problem : Problem
    rows : ndarray of int, shape (R,)
        Angle measurements used.
    sigmas : ndarray, shape (R,)
        Their sigmas (rad), all finite.
    start_enu_m : ndarray, shape (3,)
    max_iterations : int
    tolerance_m : float

    Returns
    -------
    dict
        ``position_enu_m`` (3,), ``errors_rad`` (R,) the estimated errors
        ``Z - A dX`` of the iteration that produced the position,
        ``normal_inverse`` (P, P), ``axes`` (P, 3), ``leverage`` (R,),
        ``iterations``, ``converged``, ``diverged`` (str or None).
    """
    it = _Iteration(problem, rows)
    weights = 1.0 / sigmas**2
    position = np.asarray(start_enu_m, dtype=float)
    z, a, axes = it.linearise(position)
    cost = float(np.sum(weights * z * z))
    errors = z.copy()
    converged, diverged, iterations = False, None, 0
    for iterations in range(1, max_iterations + 1):
        gain = _normal_inverse(a, weights, name)
        delta = gain @ (a.T @ (weights * z))
        moved = it.step(position, axes, delta)
        z_new, a_new, axes_new = it.linearise(moved)
        cost_new = float(np.sum(weights * z_new * z_new))
        if not (np.all(np.isfinite(moved)) and np.isfinite(cost_new)) or \
                cost_new > cost * (1.0 + COST_INCREASE_TOLERANCE) + 1e-300:
            diverged = (f"{name} diverged at iteration {iterations} (weighted cost {cost:.4g} -> {cost_new:.4g}); "
                        f"the iterate before it is returned")
            iterations -= 1
            break
        errors = z - a @ delta
        step_m = float(np.linalg.norm(moved - position))
        position, z, a, axes, cost = moved, z_new, a_new, axes_new, cost_new
        if step_m < tolerance_m:
            converged = True
            break
    gain = _normal_inverse(a, weights, name)
    leverage = np.einsum("rp,pq,rq->r", a, gain, a) * weights
    return {"position_enu_m": position, "errors_rad": errors, "normal_inverse": gain, "axes": axes,
            "leverage": leverage, "iterations": iterations, "converged": converged, "diverged": diverged,
            "cost": cost}


def _angle_rows(problem: Problem, name: str) -> np.ndarray:
    other = np.flatnonzero((problem.kinds == Kind.RANGE) | (problem.kinds == Kind.TOA))
    if other.size:
        i = int(problem.source_index[other[0]])
        raise InvalidInput(f"{name} uses bearings only; measurement {i} is a "
                           f"{Kind(problem.kinds[other[0]]).name.lower()}: use ml for a mix", ("measurements", i))
    is_elevation = problem.kinds == Kind.ELEVATION
    if problem.altitude_m is None and not np.any(is_elevation):
        raise TooFewMeasurements(
            f"{name} from azimuths alone needs the target altitude (constraints.altitude_m): azimuths do not "
            "determine the height; give elevations or the altitude", ("constraints", "altitude_m"))
    return np.flatnonzero((problem.kinds == Kind.AZIMUTH) | is_elevation)


def _start(problem: Problem, name: str) -> tuple[np.ndarray, str]:
    if problem.initial_guess_enu_m is not None:
        return np.asarray(problem.initial_guess_enu_m, dtype=float), "initial_guess"
    has_elevation = bool(np.any(problem.kinds == Kind.ELEVATION))
    position, _ = solve_orthogonal(problem, normals=Normals.BOTH, weighting=Weighting.UNIT, name=name)
    return position, "eove" if has_elevation else "pseudolinear"


def _taylor_wls(problem: Problem, options: SolveOptions) -> Estimate:
    """Taylor-series WLS fix with estimated bearing errors; see the module docstring.

    Returns
    -------
    Fix
        ``estimated_bearing_errors_rad`` ``(K,)``: one azimuth error per
        bearing, request order. ``details``: ``start``,
        ``estimated_sigma_azimuth_rad`` (when estimated),
        ``estimated_elevation_errors_rad`` (NaN where no elevation).

    Raises
    ------
    TooFewMeasurements
        Azimuths only without a known altitude; or too few bearings to
        estimate an unknown sigma (more than 2 needed in 2D).
    UnobservableGeometry
        When the linearised equations are rank-deficient.
    """
    name = "taylor_wls"
    rows = _angle_rows(problem, name)
    sigmas = problem.sigmas[rows].copy()
    unknown = np.isnan(sigmas)
    n_parameters = 2 if problem.altitude_m is not None else 3
    if rows.size < n_parameters:
        raise TooFewMeasurements(f"{name} needs at least {n_parameters} angles here; got {rows.size}",
                                 ("measurements",))
    if np.any(unknown & (problem.kinds[rows] != Kind.AZIMUTH)):
        raise InvalidInput(f"{name} estimates azimuth sigmas only; give sigma_elevation_deg", ("measurements",))
    if np.all(unknown) and rows.size <= n_parameters:
        raise TooFewMeasurements(
            f"{name} estimates the unknown bearing sigma from the estimated errors with N - {n_parameters} "
            f"degrees of freedom: give more than {n_parameters} bearings, or their sigmas", ("measurements",))
    start, start_name = _start(problem, name)

    estimated_sigma = None
    sigmas[unknown] = 1.0
    for _ in range(SIGMA_PASSES if np.any(unknown) else 1):
        result = iterate(problem, rows, sigmas, start, options.max_iterations, options.tolerance_m, name)
        if not np.any(unknown):
            break
        dof = float(np.sum(1.0 - result["leverage"][unknown]))
        if dof <= 1e-9:
            raise TooFewMeasurements(f"{name}: no degrees of freedom left to estimate the bearing sigma; "
                                     "give more bearings or their sigmas", ("measurements",))
        used = sigmas[unknown][0]
        estimated_sigma = float(np.sqrt(np.sum(result["errors_rad"][unknown] ** 2) / dof))
        sigmas[unknown] = estimated_sigma
        if np.all(unknown) or abs(estimated_sigma / used - 1.0) < 1e-6:
            break

    position = result["position_enu_m"]
    axes = result["axes"]
    covariance = axes.T @ result["normal_inverse"] @ axes
    if estimated_sigma is not None and np.all(unknown):
        covariance = covariance * estimated_sigma**2  # the last pass weighted every row by 1

    warnings = []
    if result["diverged"]:
        warnings.append(FixWarning("not_converged", result["diverged"]))
    elif not result["converged"]:
        warnings.append(FixWarning("not_converged",
                                   f"{name} did not converge in {result['iterations']} iterations "
                                   f"(tolerance {options.tolerance_m:g} m); the last iterate is returned"))
    all_sigmas = problem.sigmas.copy()
    if estimated_sigma is not None:
        all_sigmas[rows[unknown]] = estimated_sigma
        warnings.append(FixWarning(
            "sigma_estimated",
            f"sigma of {np.count_nonzero(unknown)} azimuths estimated from the estimated bearing errors: "
            f"{np.rad2deg(estimated_sigma):.3f} deg; the covariance and CRLB use it"))

    los = problem.lines_of_sight()
    per_row = np.full(problem.n_measurements, np.nan)
    per_row[rows] = result["errors_rad"]
    azimuth_errors = per_row[los.azimuth_row]
    elevation_errors = np.where(los.elevation_row >= 0, per_row[np.maximum(los.elevation_row, 0)], np.nan)
    details = {"start": start_name, "estimated_elevation_errors_rad": elevation_errors}
    if estimated_sigma is not None:
        details["estimated_sigma_azimuth_rad"] = estimated_sigma
    return Estimate(position, covariance, converged=result["converged"], iterations=result["iterations"],
                    warnings=tuple(warnings), estimated_bearing_errors_rad=azimuth_errors,
                    sigmas=all_sigmas if estimated_sigma is not None else None, details=details)


register("taylor_wls", "iterative Taylor-series WLS that estimates each bearing's error (paper 004); "
                       "estimates an unknown bearing sigma", needs_sigmas=False)(
    per_problem(_taylor_wls, "information"))
