"""Closed-form starting points for the ML iteration, chosen by measurement mix.

- bearings: weighted EOVE (``core.estimators.orthogonal_vector``), over a
  whole batch at once in :func:`weighted_eove_batch`;
- a station with a bearing and a range: its polar point ``s + R u``, fused
  over stations by inverse covariance;
- four or more TOAs: Bancroft's algebraic solution (exact without noise);
- three or more ranges: linear trilateration by differencing, with the
  mirror ambiguity of coplanar stations resolved upwards.
"""

from __future__ import annotations

import numpy as np

from core.batch import AZIMUTH, ProblemBatch
from core.errors import LocalizationError, TooFewMeasurements, UnobservableGeometry
from core.estimators.orthogonal_vector import ALTITUDE_ROW_WEIGHT, solve_orthogonal
from core.measurements import Kind
from core.problem import Problem, local_axes, onto_altitude

#: Smallest eigenvalue ratio of a batched weighted-EOVE normal matrix that is
#: solved in the batch; a problem below it is started one by one (SVD, with
#: the per-problem fallbacks), so a near-degenerate geometry is judged exactly.
BATCH_CONDITION_LIMIT = 1e-12


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


def _solve_normal(normal, right):
    """Solve ``(B, 3, 3)`` symmetric systems; also their smallest-to-largest eigenvalue ratio ``(B,)``.

    LAPACK solves each system on its own, so a problem's start does not
    depend on what else is in the batch; the ratio comes in closed form.
    """
    entries = (normal[:, 0, 0], normal[:, 0, 1], normal[:, 0, 2], normal[:, 1, 1], normal[:, 1, 2], normal[:, 2, 2])
    ratio = _eigenvalue_ratio(*entries)
    safe = np.where((ratio > BATCH_CONDITION_LIMIT)[:, None, None], normal, np.eye(3))
    return np.linalg.solve(safe, right[..., None])[..., 0], ratio


def _eigenvalue_ratio(a, b, c, d, e, f):
    """Smallest over largest eigenvalue of symmetric 3x3 matrices ``[[a, b, c], [b, d, e], [c, e, f]]`` ``(B,)``.

    The trigonometric closed form: accurate to ~1e-16 of the largest eigenvalue, which is all the
    rank test needs; 0 for a zero matrix.
    """
    q = (a + d + f) / 3.0
    off = b * b + c * c + e * e
    p = np.sqrt(((a - q) ** 2 + (d - q) ** 2 + (f - q) ** 2 + 2.0 * off) / 6.0)
    ps = np.where(p > 0, p, 1.0)
    ba, bd, bf = (a - q) / ps, (d - q) / ps, (f - q) / ps
    bb, bc, be = b / ps, c / ps, e / ps
    half_det = 0.5 * (ba * (bd * bf - be * be) - bb * (bb * bf - be * bc) + bc * (bb * be - bd * bc))
    phi = np.arccos(np.clip(half_det, -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return np.where(largest > 0, smallest / np.where(largest > 0, largest, 1.0), 0.0)


def weighted_eove_batch(batch: ProblemBatch):
    """Weighted EOVE (three passes, as :func:`~core.estimators.orthogonal_vector.solve_orthogonal`) for a batch.

    Each line of sight gives its elevation-plane row (when it has an
    elevation) and its azimuth-plane row; a known altitude adds the local up
    row with weight ``ALTITUDE_ROW_WEIGHT`` times the strongest row. Every pass
    solves the ``(B, 3, 3)`` normal equations at once, element-wise.

    Parameters
    ----------
    batch : ProblemBatch

    Returns
    -------
    position_enu_m : ndarray, shape (B, 3)
    solved : ndarray of bool, shape (B,)
        False where the rows are too few or too close to rank-deficient for
        the normal equations (see ``BATCH_CONDITION_LIMIT``); those problems
        need the per-problem start.
    """
    is_az, elevation, sigma_elevation = batch.lines_of_sight()
    has_el = ~np.isnan(elevation)
    az = np.where(is_az, batch.values, 0.0)
    el = np.where(has_el, elevation, 0.0)
    stations, rotations = batch.measurement_stations()
    size, width = az.shape
    sin_az, cos_az, sin_el, cos_el = np.sin(az), np.cos(az), np.sin(el), np.cos(el)
    local = np.zeros((size, 2, width, 3))
    local[:, 0, :, 0], local[:, 0, :, 1], local[:, 0, :, 2] = -sin_el * sin_az, -sin_el * cos_az, cos_el
    local[:, 1, :, 0], local[:, 1, :, 1] = cos_az, -sin_az
    rows = (local[..., None, :] @ rotations[:, None]).reshape(size, 2 * width, 3)
    rhs = np.einsum("bri,bri->br", rows, np.concatenate([stations, stations], axis=1))
    used = np.concatenate([has_el, is_az], axis=1)
    sigma = np.concatenate([np.where(has_el, sigma_elevation, 1.0), np.where(is_az, batch.sigmas, 1.0)], axis=1)
    sigma = np.where(np.isfinite(sigma), sigma, 1.0)

    constrained = batch.constrained
    any_constrained = bool(np.any(constrained))
    altitude = np.where(constrained, batch.altitude_m, 0.0)
    up_axis = np.zeros((size, 3))
    up_axis[:, 2] = 1.0
    up_rhs = altitude
    solved = np.count_nonzero(used, axis=-1) + constrained >= 3

    def solve(weights):
        weights = np.where(used, weights, 0.0)
        weighted = rows * (weights * weights)[..., None]
        normal = np.swapaxes(weighted, -1, -2) @ rows
        right = np.einsum("bri,br->bi", weighted, rhs)
        if any_constrained:
            strong2 = (ALTITUDE_ROW_WEIGHT * np.max(weights, axis=-1)) ** 2 * constrained
            normal += strong2[:, None, None] * up_axis[:, :, None] * up_axis[:, None, :]
            right += (strong2 * up_rhs)[:, None] * up_axis
        return _solve_normal(normal, right)

    position, ratio = solve(np.ones_like(sigma))
    solved &= ratio > BATCH_CONDITION_LIMIT
    for _ in range(2):
        if any_constrained:
            on_surface = onto_altitude(position, altitude, batch.origin, batch.geodetic)
            axes_up = local_axes(on_surface, batch.origin, batch.geodetic)[:, 2]
            up_axis = np.where(constrained[:, None], axes_up, up_axis)
            up_rhs = np.where(constrained, np.einsum("bi,bi->b", up_axis, on_surface), up_rhs)
        seen = (rotations @ (position[:, None, :] - stations)[..., None])[..., 0]
        horizontal = np.hypot(seen[..., 0], seen[..., 1])
        slant = np.sqrt(horizontal**2 + seen[..., 2] ** 2)
        scale = np.concatenate([slant, horizontal], axis=1)
        position, ratio = solve(1.0 / (sigma * np.maximum(scale, 1e-9)))
        solved &= ratio > BATCH_CONDITION_LIMIT
    if any_constrained:
        position = np.where(constrained[:, None],
                            onto_altitude(position, altitude, batch.origin, batch.geodetic), position)
    solved &= np.all(np.isfinite(position), axis=-1)
    return position, solved


def initial_positions(batch: ProblemBatch):
    """:func:`initial_position` for every problem of a batch.

    The initial guess where one is given; else the batched weighted EOVE for
    problems with bearings; the rest (and the few the batch cannot solve) one
    by one through :func:`initial_position`.

    Returns
    -------
    position_enu_m : ndarray, shape (B, 3)
        NaN rows where no start could be found.
    names : list of str or None
        Which start was used; None where none could be found.
    failures : dict of int to LocalizationError
        Why a problem has no start.
    """
    size = batch.size
    positions = np.full((size, 3), np.nan)
    names: list[str | None] = [None] * size
    failures: dict[int, LocalizationError] = {}
    guessed = ~np.isnan(batch.initial_guess_enu_m[:, 0])
    positions[guessed] = batch.initial_guess_enu_m[guessed]
    for b in np.flatnonzero(guessed):
        names[b] = "initial_guess"
    with_bearings = ~guessed & np.any(batch.valid & (batch.kinds == AZIMUTH), axis=-1)
    pending = set(np.flatnonzero(~guessed & ~with_bearings).tolist())
    if np.any(with_bearings):
        subset = np.flatnonzero(with_bearings)
        start, solved = weighted_eove_batch(batch if subset.size == size else batch.take(subset))
        positions[subset[solved]] = start[solved]
        for b in subset[solved]:
            names[b] = "weighted_eove"
        pending.update(subset[~solved].tolist())
    for b in sorted(pending):
        try:
            position, names[b] = initial_position(batch.problem(b))
            positions[b] = position
        except LocalizationError as error:
            failures[b] = error
    return positions, names, failures
