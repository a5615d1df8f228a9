"""Closed-form starting points for the ML iteration, chosen by measurement mix.

- bearings: weighted EOVE (``core.estimators.orthogonal_vector``);
- a station with a bearing and a range: its polar point ``s + R u``, fused
  over stations by inverse covariance;
- four or more TOAs: Bancroft's algebraic solution (exact without noise);
- three or more ranges: linear trilateration by differencing, with the
  mirror ambiguity of coplanar stations resolved upwards.
"""

from __future__ import annotations

import numpy as np

from core.errors import LocalizationError, TooFewMeasurements, UnobservableGeometry
from core.estimators.orthogonal_vector import solve_orthogonal
from core.measurements import Kind
from core.problem import Problem


def polar_points(problem: Problem):
    """Per-station polar fixes from a bearing with elevation and a range at one station.

    Returns
    -------
    points_enu_m : ndarray, shape (P, 3)
    covariances_enu_m2 : ndarray, shape (P, 3, 3)
        First-order: ``R^2 sigma_el^2`` and ``(R cos el)^2 sigma_az^2``
        across the line of sight, ``sigma_R^2`` along it.
    """
    los = problem.lines_of_sight()
    is_range = problem.kinds == Kind.RANGE
    points, covariances = [], []
    for k in np.flatnonzero(los.has_elevation):
        station = los.station_index[k]
        rows = np.flatnonzero(is_range & (problem.station_index == station))
        if rows.size == 0:
            continue
        weights = 1.0 / problem.sigmas[rows] ** 2
        range_m = float(np.sum(weights * problem.values[rows]) / np.sum(weights))
        range_var = 1.0 / float(np.sum(weights))
        az, el = los.azimuth_rad[k], los.elevation_rad[k]
        along = np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
        across_az = np.array([np.cos(az), -np.sin(az), 0.0])
        across_el = np.array([-np.sin(el) * np.sin(az), -np.sin(el) * np.cos(az), np.cos(el)])
        basis = np.stack([along, across_az, across_el], axis=-1)
        sd = [np.sqrt(range_var), range_m * np.cos(el) * los.sigma_azimuth_rad[k], range_m * los.sigma_elevation_rad[k]]
        cov_local = basis @ np.diag(np.square(np.maximum(sd, 1e-9))) @ basis.T
        to_common = los.rotations[k].T
        points.append(los.origins_enu_m[k] + to_common @ (range_m * along))
        covariances.append(to_common @ cov_local @ to_common.T)
    return np.reshape(points, (-1, 3)), np.reshape(covariances, (-1, 3, 3))


def fuse_points(points, covariances):
    """Inverse-covariance fusion of point estimates ``(P, 3)``; returns ``(3,)`` and ``(3, 3)``."""
    information = np.linalg.inv(covariances)
    total = np.linalg.inv(information.sum(axis=0))
    return total @ np.einsum("pij,pj->i", information, points), total


def bancroft(stations_enu_m, pseudoranges_m, weights=None):
    """Bancroft's closed-form solution of ``rho_i = |p - s_i| + b``.

    Parameters
    ----------
    stations_enu_m : ndarray, shape (N, 3), N >= 4
    pseudoranges_m : ndarray, shape (N,)
    weights : ndarray, shape (N,), optional

    Returns
    -------
    position_enu_m : ndarray, shape (3,)
    bias_m : float
    """
    s = np.asarray(stations_enu_m, dtype=float)
    rho = np.asarray(pseudoranges_m, dtype=float)
    w = np.ones(rho.size) if weights is None else np.sqrt(weights)
    # The linear system is singular when the stations lie in a plane through the origin
    # (ground receivers of a local frame): solve from a point below their centroid instead.
    centroid = s.mean(axis=0)
    _, spread, axes = np.linalg.svd(s - centroid)
    below = centroid - np.copysign(1.0, axes[-1][2]) * axes[-1] * max(spread[0], 1.0)
    s = s - below
    m = np.column_stack([s, -rho])
    half_norm = 0.5 * (np.sum(s * s, axis=1) - rho * rho)
    pinv = np.linalg.pinv(m * w[:, None]) * w[None, :]
    if np.linalg.matrix_rank(m) < 4:
        raise UnobservableGeometry("TOA stations are coplanar or too few for an algebraic TDOA solution")
    u, v = pinv @ np.ones(rho.size), pinv @ half_norm

    def lorentz(a, b):
        return a[:3] @ b[:3] - a[3] * b[3]

    qa, qb, qc = 0.5 * lorentz(u, u), lorentz(u, v) - 1.0, 0.5 * lorentz(v, v)
    if abs(qa) < 1e-300:
        roots = [-qc / qb]
    else:
        disc = max(qb * qb - 4 * qa * qc, 0.0)
        roots = [(-qb + sg * np.sqrt(disc)) / (2 * qa) for sg in (1.0, -1.0)]
    fits = sorted(((float(np.sum(w * w * (np.linalg.norm(s - y[:3], axis=1) + y[3] - rho) ** 2)), y)
                   for y in (lam * u + v for lam in roots)), key=lambda fit: fit[0])
    best = fits[0][1]
    # Near-coplanar stations barely tell a point from its mirror image through their plane:
    # when the other root fits as well (chi-square within 9), take the upper one, as trilaterate does.
    if len(fits) == 2 and fits[1][0] - fits[0][0] < 9.0 and fits[1][1][2] > best[2]:
        best = fits[1][1]
    return best[:3] + below, float(best[3])


def trilaterate(stations_enu_m, ranges_m):
    """Linear trilateration by differencing squared ranges; coplanar mirror resolved upwards.

    Parameters
    ----------
    stations_enu_m : ndarray, shape (N, 3), N >= 3
    ranges_m : ndarray, shape (N,)

    Returns
    -------
    ndarray, shape (3,)
    """
    s = np.asarray(stations_enu_m, dtype=float)
    r = np.asarray(ranges_m, dtype=float)
    a = 2.0 * (s[1:] - s[0])
    b = r[0] ** 2 - r[1:] ** 2 + np.sum(s[1:] ** 2, axis=1) - np.sum(s[0] ** 2)
    u, sv, vt = np.linalg.svd(a, full_matrices=True)
    rank = int(np.sum(sv > 1e-9 * sv[0]))
    if rank < 2:
        raise UnobservableGeometry("range stations are collinear: the target lies on a circle")
    k = min(rank, 3)
    point = vt[:k].T @ ((u[:, :k].T @ b) / sv[:k])
    if rank == 3:
        return point
    normal = vt[2]
    if normal[2] < 0:
        normal = -normal
    gap = r[0] ** 2 - np.sum((point - s[0]) ** 2)
    return point + normal * np.sqrt(max(gap, 0.0)) if gap > 0 else point


def initial_position(problem: Problem):
    """A closed-form start for the measurement mix.

    Returns
    -------
    position_enu_m : ndarray, shape (3,)
    name : str
        Which start was used.

    Raises
    ------
    LocalizationError
        When no closed form applies (too few or unobservable measurements).
    """
    if problem.initial_guess_enu_m is not None:
        return np.asarray(problem.initial_guess_enu_m, dtype=float), "initial_guess"
    failure: LocalizationError | None = None
    if problem.count(Kind.AZIMUTH):
        try:
            return solve_orthogonal(problem, True, True, True, "weighted_eove")[0], "weighted_eove"
        except LocalizationError as error:
            failure = error
    points, covariances = polar_points(problem)
    if len(points):
        return fuse_points(points, covariances)[0], "polar"
    is_toa = problem.kinds == Kind.TOA
    if np.count_nonzero(is_toa) >= 4:
        s = problem.stations_enu_m[problem.station_index[is_toa]]
        weights = 1.0 / problem.model_sigmas()[is_toa] ** 2
        return bancroft(s, problem.model_values()[is_toa], weights)[0], "bancroft"
    is_range = problem.kinds == Kind.RANGE
    if np.count_nonzero(is_range) >= 3:
        s = problem.stations_enu_m[problem.station_index[is_range]]
        return trilaterate(s, problem.values[is_range]), "trilateration"
    if failure is not None:
        raise failure
    raise TooFewMeasurements(
        "too few measurements for a fix: need bearings from 2 stations, a bearing and a range, "
        "4 TOAs or 3 ranges", ("measurements",))
