"""Orthogonal-vector estimators (paper 000): OVE, EOVE and weighted EOVE.

Each line of sight ``i`` from station ``r_i`` gives, in the station's ENU,
two unit vectors orthogonal to it:

- ``a_i  = [-sin el sin az, -sin el cos az, cos el]`` (in the vertical plane
  of the line of sight), and
- ``a'_i = [cos az, -sin az, 0]`` (horizontal).

Rotated into the common frame (``c = R_i^T a``), each gives a linear equation
``c^T p = c^T r_i``. OVE uses the ``c`` rows only; EOVE adds the ``c'`` rows,
so two lines of sight suffice and an azimuth-only bearing still contributes
its ``c'`` row. Weighted EOVE weights the rows by ``1 / (sigma_el r_i)`` and
``1 / (sigma_az rho_i)`` (``r_i`` slant and ``rho_i`` horizontal distance from
a first pass): the row residuals are then ``-r_i d_el`` and ``-rho_i d_az`` to
first order, so this is the small-noise BLUE and one Gauss-Newton step from
the ML fix.

Covariance: first-order propagation of the angle noise through the (weighted)
least squares, the sandwich ``G A^T W S W A G`` with ``G = (A^T W A)^-1`` and
``S = diag(rho^2 sigma_az^2, r^2 sigma_el^2)`` evaluated at the estimate.
"""

from __future__ import annotations

import numpy as np

from core.errors import TooFewMeasurements, UnobservableGeometry
from core.estimators.base import ANGLES, Estimate, SolveOptions, per_problem, register
from core.problem import LinesOfSight, Problem

#: Relative singular value below which the stacked rows are rank-deficient.
RANK_TOLERANCE = 1e-9
#: Weight of the known-altitude row relative to the strongest bearing row.
ALTITUDE_ROW_WEIGHT = 1e3


def orthogonal_rows(los: LinesOfSight, use_vertical: bool = True, use_horizontal: bool = True):
    """Stack the orthogonal-vector equations of lines of sight.

    Returns
    -------
    rows : ndarray, shape (R, 3)
        Unit normals ``c`` in the common frame.
    rhs : ndarray, shape (R,)
        ``c . r_i``.
    line : ndarray of int, shape (R,)
        Line of sight of each row.
    vertical : ndarray of bool, shape (R,)
        True for a ``c`` (elevation) row, False for a ``c'`` (azimuth) row.
    """
    az, el = los.azimuth_rad, np.where(los.has_elevation, los.elevation_rad, 0.0)
    a_vertical = np.stack([-np.sin(el) * np.sin(az), -np.sin(el) * np.cos(az), np.cos(el)], axis=-1)
    a_horizontal = np.stack([np.cos(az), -np.sin(az), np.zeros_like(az)], axis=-1)
    parts = []
    if use_vertical:
        k = np.flatnonzero(los.has_elevation)
        parts.append((a_vertical[k], k, True))
    if use_horizontal:
        k = np.arange(los.count)
        parts.append((a_horizontal[k], k, False))
    local = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 3))
    line = np.concatenate([p[1] for p in parts]).astype(int) if parts else np.zeros(0, int)
    vertical = np.concatenate([np.full(p[1].size, p[2]) for p in parts]) if parts else np.zeros(0, bool)
    rows = np.einsum("rji,rj->ri", los.rotations[line], local)
    rhs = np.einsum("ri,ri->r", rows, los.origins_enu_m[line])
    return rows, rhs, line, vertical


def _distances(los: LinesOfSight, position_enu_m):
    """Slant and horizontal distances ``(K,)`` from each line's station to a point."""
    local = np.einsum("kij,kj->ki", los.rotations, position_enu_m - los.origins_enu_m)
    horizontal = np.hypot(local[:, 0], local[:, 1])
    return np.linalg.norm(local, axis=-1), horizontal


def _weighted_solve(rows, rhs, weights, what: str):
    """Weighted least squares by SVD, refusing rank-deficient systems."""
    a = rows * weights[:, None]
    u, s, vt = np.linalg.svd(a, full_matrices=False)
    if s.size < 3 or s[-1] <= RANK_TOLERANCE * s[0]:
        raise UnobservableGeometry(what)
    solution = vt.T @ ((u.T @ (rhs * weights)) / s)
    gain = vt.T @ np.diag(1.0 / s**2) @ vt
    return solution, gain


def solve_orthogonal(problem: Problem, use_vertical: bool, use_horizontal: bool, weighted: bool, name: str):
    """Position and propagated covariance of an orthogonal-vector estimator.

    Parameters
    ----------
    problem : Problem
    use_vertical, use_horizontal : bool
        Which rows to stack (OVE: vertical only; EOVE: both).
    weighted : bool
        Weight rows by their inverse first-order noise (two passes).
    name : str
        For messages.

    Returns
    -------
    position_enu_m : ndarray, shape (3,)
    covariance_enu_m2 : ndarray, shape (3, 3)
    """
    los = problem.lines_of_sight()
    rows, rhs, line, vertical = orthogonal_rows(los, use_vertical, use_horizontal)
    if rows.shape[0] == 0:
        raise TooFewMeasurements(f"{name} needs bearings")
    sigma = np.where(vertical, los.sigma_elevation_rad[line], los.sigma_azimuth_rad[line])
    sigma = np.where(np.isfinite(sigma), sigma, 1.0)
    altitude = problem.altitude_m
    why = f"{name}: the lines of sight do not determine a point (parallel or too few independent lines)"

    def solve(weights, up_axis, up_rhs):
        if altitude is None:
            return _weighted_solve(rows, rhs, weights, why)
        strong = ALTITUDE_ROW_WEIGHT * np.max(weights)
        stacked = np.vstack([rows, up_axis])
        return _weighted_solve(stacked, np.append(rhs, up_rhs), np.append(weights, strong), why)

    up_axis, up_rhs = np.array([0.0, 0.0, 1.0]), 0.0 if altitude is None else altitude
    position, _ = solve(np.ones(rows.shape[0]), up_axis, up_rhs)
    passes = 3 if weighted or altitude is not None else 1
    for _ in range(passes - 1):
        if altitude is not None:
            on_surface = problem.frame.onto_altitude(position, altitude)
            up_axis = problem.frame.local_axes(on_surface)[2]
            up_rhs = up_axis @ on_surface
        if weighted:
            slant, horizontal = _distances(los, position)
            scale = np.where(vertical, slant[line], horizontal[line])
            weights = 1.0 / (sigma * np.maximum(scale, 1e-9))
        else:
            weights = np.ones(rows.shape[0])
        position, _ = solve(weights, up_axis, up_rhs)
    if altitude is not None:
        position = problem.frame.onto_altitude(position, altitude)

    slant, horizontal = _distances(los, position)
    noise_sd = sigma * np.where(vertical, slant[line], horizontal[line])
    weights = 1.0 / (sigma * np.maximum(np.where(vertical, slant[line], horizontal[line]), 1e-9)) if weighted \
        else np.ones(rows.shape[0])
    if altitude is None:
        a = rows
    else:
        axes = problem.frame.local_axes(position)
        a = rows @ axes[:2].T
    w2 = weights**2
    gain = np.linalg.pinv(a.T @ (a * w2[:, None]))
    middle = a.T @ (a * (w2**2 * noise_sd**2)[:, None])
    covariance = gain @ middle @ gain
    if altitude is not None:
        covariance = axes[:2].T @ covariance @ axes[:2]
    return position, covariance


def _ove(problem: Problem, options: SolveOptions) -> Estimate:
    los = problem.lines_of_sight()
    with_elevation = int(np.count_nonzero(los.has_elevation))
    if with_elevation < 3:
        raise TooFewMeasurements(
            f"ove needs at least 3 lines of sight with elevation; got {with_elevation}", ("measurements",))
    return Estimate(*solve_orthogonal(problem, True, False, False, "ove"))


def _eove(problem: Problem, options: SolveOptions) -> Estimate:
    return Estimate(*solve_orthogonal(problem, True, True, False, "eove"))


def _weighted_eove(problem: Problem, options: SolveOptions) -> Estimate:
    return Estimate(*solve_orthogonal(problem, True, True, True, "weighted_eove"))


register("ove", "orthogonal vector estimator: elevation-plane normals only, needs >= 3 lines of sight", uses=ANGLES)(
    per_problem(_ove, "propagated"))
register("eove", "extended orthogonal vector estimator: both normals per line of sight (paper 000)", uses=ANGLES)(
    per_problem(_eove, "propagated"))
register("weighted_eove", "EOVE with rows weighted by their first-order noise: the small-noise BLUE",
         uses=ANGLES)(
    per_problem(_weighted_eove, "propagated"))

