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

The bearing errors these methods imply are the conventional ones (measured
minus the azimuth of the fix), i.e. the azimuth ``residuals`` of the fix;
the patent compares its own estimates with those.
"""

from __future__ import annotations

import numpy as np

from core.errors import InvalidInput, UnobservableGeometry
from core.estimators.azimuth_lines import (
    AzimuthEquations,
    azimuth_equations,
    azimuth_only_lines,
    DIFFERENCE_STEP_RAD,
    require_crossing,
    tangent_plane,
)
from core.estimators.base import Estimate, SolveOptions, per_problem, register
from core.estimators.result import FixWarning
from core.estimators.orthogonal_vector import Normals, Weighting, solve_orthogonal
from core.measurements import Kind
from core.problem import LinesOfSight, Problem

#: Re-takes of the tangent plane at the solution (exact on the ellipsoid after two).
PLANE_PASSES = 3
#: The patent's chi_0: normalised reduced-rank error at which the projected CTLS stops.
PROJECTED_THRESHOLD = 1e-4
#: Newton iterations on each row's azimuth when projecting it onto the structure.
ROW_PROJECTION_STEPS = 3
#: Step halvings the Newton CTLS tries before it gives up on a step.
MAX_HALVINGS = 30
CTLS_VARIANTS = ("newton", "projected")


def _plane_passes(problem: Problem, name: str, solve_in_plane):
    """Solve in the tangent plane at the current point, move onto the surface, repeat."""
    los = azimuth_only_lines(problem, name)
    require_crossing(los, name)
    position, _ = solve_orthogonal(problem, normals=Normals.AZIMUTH_PLANE, weighting=Weighting.UNIT, name=name)
    state = None
    for _ in range(PLANE_PASSES):
        plane = tangent_plane(problem, position, los.origins_enu_m)
        equations = azimuth_equations(los, plane)
        plane_m, state = solve_in_plane(los, plane, equations, plane.coordinates(position), state)
        position = problem.frame.onto_altitude(plane.point(plane_m), problem.altitude_m)
    return position, plane, equations, plane_m, state


def _scaled_matrix(equations: AzimuthEquations, spread_m: float):
    return np.column_stack([equations.rows, equations.rhs / spread_m])


def _spread_m(los: LinesOfSight, plane) -> float:
    offsets = np.array([plane.coordinates(r) for r in los.origins_enu_m])
    return max(float(np.sqrt(np.mean(np.sum(offsets**2, axis=1)))), 1.0)


def _null_vector_point(v, spread_m, name):
    if abs(v[2]) < 1e-12 * np.linalg.norm(v):
        raise UnobservableGeometry(f"{name}: the total-least-squares solution lies at infinity "
                                   "(the azimuth lines are parallel)")
    return -spread_m * v[:2] / v[2]


def tls_position(problem: Problem):
    """TLS fix and its first-order covariance.

    Returns
    -------
    position_enu_m : ndarray, shape (3,)
    covariance_enu_m2 : ndarray, shape (3, 3)
    """
    name = "tls"

    def solve_in_plane(los, plane, equations, _current, _state):
        spread = _spread_m(los, plane)
        matrix = _scaled_matrix(equations, spread)
        _, _, vt = np.linalg.svd(matrix, full_matrices=False)
        return _null_vector_point(vt[-1], spread, name), (matrix, spread)

    position, plane, equations, plane_m, (matrix, spread) = _plane_passes(problem, name, solve_in_plane)
    los = problem.lines_of_sight()
    eigenvalues, vectors = np.linalg.eigh(matrix.T @ matrix)
    v = vectors[:, 0]
    derivative_rows = -np.column_stack([equations.along_rows, equations.along_rhs / spread])
    ds_v = derivative_rows * (matrix @ v)[:, None] + matrix * (derivative_rows @ v)[:, None]
    resolvent = vectors[:, 1:] / (eigenvalues[1:] - eigenvalues[0])
    dv = -(ds_v @ resolvent) @ vectors[:, 1:].T
    d_plane = -spread * (dv[:, :2] * v[2] - v[:2] * dv[:, 2:3]) / v[2] ** 2
    covariance_plane = (d_plane * los.sigma_azimuth_rad[:, None] ** 2).T @ d_plane
    return position, plane.axes_enu.T @ covariance_plane @ plane.axes_enu


def _ctls_terms(equations: AzimuthEquations, plane_m, weights):
    """CTLS cost, gradient, Hessian and Gauss-Newton matrix at plane coordinates."""
    a, d = equations.rows, equations.along_rows
    e = a @ plane_m - equations.rhs
    rho = d @ plane_m - equations.along_rhs
    f = e / rho
    grad_f = (a * rho[:, None] - d * e[:, None]) / rho[:, None] ** 2
    cost = float(np.sum(weights * f * f))
    gradient = 2.0 * (weights * f) @ grad_f
    gauss_newton = 2.0 * (grad_f * weights[:, None]).T @ grad_f
    ad = np.einsum("ki,kj->kij", a, d)
    hess_f = -(ad + np.swapaxes(ad, 1, 2)) / rho[:, None, None] ** 2 \
        + 2.0 * (e / rho**3)[:, None, None] * np.einsum("ki,kj->kij", d, d)
    hessian = gauss_newton + 2.0 * np.einsum("k,kij->ij", weights * f, hess_f)
    return cost, gradient, hessian, gauss_newton, f, grad_f


def newton_ctls_position(problem: Problem, options: SolveOptions):
    """First-derivative (Newton) CTLS fix; see the module docstring.

    Returns
    -------
    position_enu_m : ndarray, shape (3,)
    covariance_enu_m2 : ndarray, shape (3, 3)
    converged : bool
    iterations : int
    """
    name = "ctls"
    los = problem.lines_of_sight()
    weights = 1.0 / los.sigma_azimuth_rad**2

    def solve_in_plane(_los, _plane, equations, current, state):
        iterations, converged = (0, False) if state is None else state
        q = current
        cost, gradient, hessian, gauss_newton, _, _ = _ctls_terms(equations, q, weights)
        converged = False
        for _ in range(options.max_iterations):
            try:
                np.linalg.cholesky(hessian)
                matrix = hessian
            except np.linalg.LinAlgError:
                matrix = gauss_newton
            step = -np.linalg.solve(matrix, gradient)
            for _ in range(MAX_HALVINGS):
                candidate = q + step
                new = _ctls_terms(equations, candidate, weights)
                if np.isfinite(new[0]) and new[0] <= cost * (1 + 1e-12) + 1e-300:
                    break
                step = 0.5 * step
            else:
                break
            iterations += 1
            q = candidate
            cost, gradient, hessian, gauss_newton, _, _ = new
            if np.linalg.norm(step) < options.tolerance_m:
                converged = True
                break
        return q, (iterations, converged)

    position, plane, equations, plane_m, (iterations, converged) = _plane_passes(problem, name, solve_in_plane)
    _, _, hessian, _, f, grad_f = _ctls_terms(equations, plane_m, weights)
    inverse = np.linalg.inv(hessian)
    gain = 2.0 * (weights * (1.0 + 3.0 * f * f))[:, None] * grad_f @ inverse
    covariance_plane = (gain * los.sigma_azimuth_rad[:, None] ** 2).T @ gain
    return position, plane.axes_enu.T @ covariance_plane @ plane.axes_enu, converged, iterations


def _row_basis(los: LinesOfSight, plane, spread_m):
    """Rows an azimuth ``g`` can produce: ``cos g U_i + sin g V_i``, each ``(K, 3)``."""
    to_common = np.swapaxes(los.rotations, -1, -2)
    east, north = to_common[:, :, 0], to_common[:, :, 1]
    relative = los.origins_enu_m - plane.centre_enu_m

    def row(vector):
        return np.column_stack([vector @ plane.axes_enu.T, np.einsum("ki,ki->k", vector, relative) / spread_m])

    return row(east), -row(north)


def _projected_passes(basis_cos, basis_sin, azimuth_rad, weights_sqrt, max_passes: int, frozen: bool):
    """Alternating projections for a batch of azimuth sets.

    Parameters
    ----------
    basis_cos, basis_sin : ndarray, shape (K, 3)
    azimuth_rad : ndarray, shape (B, K)
        Measured azimuths (each set is projected independently).
    weights_sqrt : ndarray, shape (K,)
    max_passes : int
    frozen : bool
        Run exactly ``max_passes`` passes instead of stopping at the threshold.

    Returns
    -------
    null_vectors : ndarray, shape (B, 3)
    passes : int
    converged : bool
        Every set reached the threshold.
    """
    azimuth = np.array(azimuth_rad, dtype=float)
    done = False
    for passes in range(1, max_passes + 1):
        c, sn = np.cos(azimuth)[..., None], np.sin(azimuth)[..., None]
        matrix = (c * basis_cos + sn * basis_sin) * weights_sqrt[:, None]
        u, s, vt = np.linalg.svd(matrix, full_matrices=False)
        done = bool(np.all(s[:, -1] / np.linalg.norm(s, axis=-1) < PROJECTED_THRESHOLD))
        if passes == max_passes or (done and not frozen):
            break
        target = (matrix - s[:, -1, None, None] * u[:, :, -1:] * vt[:, -1:, :]) / weights_sqrt[:, None]
        for _ in range(ROW_PROJECTION_STEPS):
            c, sn = np.cos(azimuth)[..., None], np.sin(azimuth)[..., None]
            row = c * basis_cos + sn * basis_sin
            slope = -sn * basis_cos + c * basis_sin
            gap = row - target
            first = np.einsum("bki,bki->bk", slope, gap)
            slope2 = np.einsum("bki,bki->bk", slope, slope)
            second = slope2 - np.einsum("bki,bki->bk", row, gap)
            azimuth = azimuth - first / np.where(second > 0, second, slope2)
    return vt[:, -1, :], passes, done


def projected_ctls_position(problem: Problem, options: SolveOptions):
    """Projected CTLS fix and its first-order covariance; see the module docstring.

    Returns
    -------
    position_enu_m : ndarray, shape (3,)
    covariance_enu_m2 : ndarray, shape (3, 3)
    passes : int
        Projection passes of the last plane.
    converged : bool
    """
    name = "ctls"
    los = problem.lines_of_sight()
    weights_sqrt = 1.0 / los.sigma_azimuth_rad
    weights_sqrt = weights_sqrt / np.mean(weights_sqrt)

    def solve_in_plane(_los, plane, _equations, _current, _state):
        spread = _spread_m(los, plane)
        basis = _row_basis(los, plane, spread)
        v, used, converged = _projected_passes(*basis, los.azimuth_rad[None], weights_sqrt,
                                               options.max_iterations, False)
        return _null_vector_point(v[0], spread, name), (used, converged, basis, spread)

    position, plane, _, _, (used, converged, basis, spread) = _plane_passes(problem, name, solve_in_plane)
    count = los.count
    step = DIFFERENCE_STEP_RAD * np.eye(count)
    perturbed = np.concatenate([los.azimuth_rad + step, los.azimuth_rad - step])
    v, _, _ = _projected_passes(*basis, perturbed, weights_sqrt, used, True)
    plane_m = np.array([_null_vector_point(row, spread, name) for row in v])
    gain = (plane_m[:count] - plane_m[count:]) / (2 * DIFFERENCE_STEP_RAD)
    covariance_plane = (gain * los.sigma_azimuth_rad[:, None] ** 2).T @ gain
    return position, plane.axes_enu.T @ covariance_plane @ plane.axes_enu, used, converged


def _tls(problem: Problem, options: SolveOptions) -> Estimate:
    """TLS baseline of paper 004; see the module docstring."""
    position, covariance = tls_position(problem)
    return Estimate(position, covariance, details=_details(problem))


def _ctls(problem: Problem, options: SolveOptions) -> Estimate:
    """CTLS baselines of paper 004; ``options.variant`` in {"newton", "projected"}, default newton."""
    variant = options.variant or "newton"
    if variant not in CTLS_VARIANTS:
        raise InvalidInput(f"ctls variant must be one of {', '.join(CTLS_VARIANTS)}; got {variant!r}",
                           ("options", "variant"))
    warnings = []
    if variant == "newton":
        position, covariance, converged, iterations = newton_ctls_position(problem, options)
    else:
        position, covariance, iterations, converged = projected_ctls_position(problem, options)
        if not converged:
            warnings.append(FixWarning(
                "not_converged", f"projected CTLS: normalised reduced-rank error still above {PROJECTED_THRESHOLD:g} "
                                 f"after {iterations} passes; the last pass is returned"))
    return Estimate(position, covariance, converged=converged, iterations=iterations, warnings=tuple(warnings),
                    details={"variant": variant, **_details(problem)})


register("tls", "total least squares on the azimuth pseudolinear equations (azimuth-only, known altitude)")(
    per_problem(_tls, "propagated"))
register("ctls", "constrained total least squares on the azimuth equations (azimuth-only, known altitude); "
                 "variant newton (default) or projected", variants=CTLS_VARIANTS)(per_problem(_ctls, "propagated"))


def _details(problem: Problem) -> dict:
    details = {"bearing_errors": "conventional: the azimuth residuals at the fix"}
    if problem.count(Kind.ELEVATION):
        details["unused_measurements"] = "elevations: an azimuth-only method with the altitude known"
    return details
