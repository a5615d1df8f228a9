"""Orthogonal-vector estimators (paper 000): OVE, EOVE and weighted EOVE, over a batch.

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
the ML fix. A known altitude adds the local up row, weighted
``ALTITUDE_ROW_WEIGHT`` times the strongest row, and the fix is put on the
altitude surface.

Every problem of a batch is solved at once: its rows are stacked into a
``(B, R, 3)`` array (padding rows weigh zero) and each least-squares system
is solved by its SVD (:func:`core.linalg.jacobi_svd`), which also judges
rank per problem: a problem whose smallest singular value is below
``RANK_TOLERANCE`` of its largest is unobservable.

Covariance: first-order propagation of the angle noise through the (weighted)
least squares, the sandwich ``G A^T W S W A G`` with ``G = (A^T W A)^+`` and
``S = diag(rho^2 sigma_az^2, r^2 sigma_el^2)`` evaluated at the estimate
(over the local east/north axes when the altitude is known).
"""

from __future__ import annotations

import math
from enum import Enum
from typing import NamedTuple

import numba
import numpy as np

from core.errors import LocalizationError, TooFewMeasurements, UnobservableGeometry
from core.estimators.base import ANGLES, SolveOptions, register
from core.estimators.result import Estimates
from core.kernel_data import Frames, Measurements
from core.linalg import SVD_LANES, jacobi_svd, matvec, svd_in_place, weighted_gram
from core.measurements import seen_from_station
from core.problem.batch import ProblemBatch
from core.problem.frame import Problem, local_axes, local_axes_point, onto_altitude_point

#: Relative singular value below which the stacked rows are rank-deficient.
RANK_TOLERANCE = 1e-9
#: Weight of the known-altitude row relative to the strongest bearing row.
ALTITUDE_ROW_WEIGHT = 1e3
#: Eigenvalues of the weighted normal matrix below this share of the largest are dropped from the
#: propagated covariance (``np.linalg.pinv``'s default cut-off).
PINV_CUTOFF = 1e-15
#: Distances (m) are clamped to at least this in the row weights.
MIN_DISTANCE_M = 1e-9
#: A problem's status after :func:`_positions_kernel`: solved, without a used row, or with rank-deficient rows.
SOLVED, NO_ROWS, RANK_DEFICIENT = 0, 1, 2


class Normals(Enum):
    """Which orthogonal-vector rows each line of sight contributes."""

    #: ``c`` only, from lines with elevation (OVE).
    ELEVATION_PLANE = "elevation_plane"
    #: ``c`` where there is an elevation and ``c'`` always (EOVE).
    BOTH = "both"
    #: ``c'`` only: the vertical planes of the azimuths.
    AZIMUTH_PLANE = "azimuth_plane"


class Weighting(Enum):
    """How the rows are weighted."""

    #: Every row weighs 1 (one pass; with a known altitude, more passes re-take the up row).
    UNIT = "unit"
    #: Inverse first-order noise ``1 / (sigma r)`` from the previous pass (from the second pass on).
    FIRST_ORDER = "first_order"


#: Passes of an orthogonal-vector estimator: the unit-weight one, then two that re-weigh the rows (and re-take
#: a known altitude's up row) at the previous fix.
PASSES = 3


class StackedRows(NamedTuple):
    """Each problem's orthogonal-vector rows (:func:`_rows_kernel`): measurement ``m``'s ``c`` row at ``m``, its
    ``c'`` row at ``M + m``.

    Attributes
    ----------
    rows : ndarray, shape (B, 2M, 3)
        Unit normals, common frame.
    rhs : ndarray, shape (B, 2M)
        ``c . r`` (m).
    used : ndarray of bool, shape (B, 2M)
    sigma : ndarray, shape (B, 2M)
        The row's angle sigma (rad; 1 where none).
    """

    rows: np.ndarray
    rhs: np.ndarray
    used: np.ndarray
    sigma: np.ndarray


def normal_vectors(azimuth_rad, elevation_rad):
    """The two unit vectors orthogonal to lines of sight, in the station's ENU.

    Parameters
    ----------
    azimuth_rad, elevation_rad : ndarray, shape (...)
        Elevation 0 for an azimuth-only line.

    Returns
    -------
    vertical, horizontal : ndarray, shape (..., 3)
        ``a`` (in the line's vertical plane) and ``a'`` (horizontal).
    """
    sin_az, cos_az, sin_el, cos_el = np.sin(azimuth_rad), np.cos(azimuth_rad), np.sin(elevation_rad), np.cos(elevation_rad)
    vertical = np.stack([-sin_el * sin_az, -sin_el * cos_az, cos_el], axis=-1)
    horizontal = np.stack([cos_az, -sin_az, np.zeros_like(sin_az)], axis=-1)
    return vertical, horizontal


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _noise_scale(position_enu_m, stations_enu_m, rotations, out):
    """Each row's noise per unit angle at a position into ``out`` ``(2M,)``: the slant distance for
    measurement ``m``'s ``c`` row (at ``m``), the horizontal distance for its ``c'`` row (at ``M + m``)."""
    width = stations_enu_m.shape[0]
    for m in range(width):
        e, n, u = seen_from_station(position_enu_m[0], position_enu_m[1], position_enu_m[2], stations_enu_m,
                                    rotations, m)
        horizontal = math.hypot(e, n)
        out[m], out[width + m] = math.hypot(horizontal, u), horizontal


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _rows_kernel(measurements, use_vertical, use_horizontal):
    """Each line of sight's normals ``c`` (in its vertical plane, where it has an elevation) and ``c'``
    (horizontal) in the common frame, ``(B, 2M, 3)``, their right-hand sides ``c . r`` ``(B, 2M)``, which
    are used and their angle sigmas (1 where none), from the batch's :class:`~core.kernel_data.Measurements`
    (an azimuth row's value and sigma are the line's azimuth); the normals of :func:`normal_vectors`, compiled."""
    is_line, azimuth_rad, sigma_rad = measurements.is_line, measurements.values, measurements.sigmas
    elevation_rad, sigma_elevation_rad = measurements.elevation_rad, measurements.sigma_elevation_rad
    stations_enu_m, rotations = measurements.stations_enu_m, measurements.rotations
    size, width = is_line.shape
    rows, rhs = np.zeros((size, 2 * width, 3)), np.zeros((size, 2 * width))
    used, sigma = np.zeros((size, 2 * width), dtype=np.bool_), np.ones((size, 2 * width))
    local = np.empty((2, 3))
    for b in range(size):
        for m in range(width):
            line = is_line[b, m]
            has_el = not math.isnan(elevation_rad[b, m])
            az = azimuth_rad[b, m] if line else 0.0
            el = elevation_rad[b, m] if has_el else 0.0
            sin_az, cos_az, sin_el, cos_el = math.sin(az), math.cos(az), math.sin(el), math.cos(el)
            local[0, 0], local[0, 1], local[0, 2] = -sin_el * sin_az, -sin_el * cos_az, cos_el
            local[1, 0], local[1, 1], local[1, 2] = cos_az, -sin_az, 0.0
            r, s = rotations[b, m], stations_enu_m[b, m]
            for k in range(2):
                row = m + k * width
                for i in range(3):
                    rows[b, row, i] = r[0, i] * local[k, 0] + r[1, i] * local[k, 1] + r[2, i] * local[k, 2]
                rhs[b, row] = rows[b, row, 0] * s[0] + rows[b, row, 1] * s[1] + rows[b, row, 2] * s[2]
            used[b, m] = has_el and use_vertical
            used[b, width + m] = line and use_horizontal
            if math.isfinite(sigma_elevation_rad[b, m]):
                sigma[b, m] = sigma_elevation_rad[b, m]
            if line and math.isfinite(sigma_rad[b, m]):
                sigma[b, width + m] = sigma_rad[b, m]
    return rows, rhs, used, sigma


def _where(mask):
    """Indices of ``mask``; a slice when that is all of them (indexing by a slice does not copy)."""
    return slice(None) if np.all(mask) else np.flatnonzero(mask)


class LaneSystems(NamedTuple):
    """The weighted systems of the problems :func:`_positions_kernel` solves side by side, one a lane
    (``L`` = ``SVD_LANES``; ``R`` rows a problem): each its problem's :class:`StackedRows` then an up row.

    Attributes
    ----------
    up : ndarray, shape (L, 3)
        The up row: the known altitude's local vertical, common frame.
    up_rhs : ndarray, shape (L,)
        Its right-hand side (m).
    weights : ndarray, shape (L, R + 1)
        Each row's weight, the up row's last (0: unused).
    kept : ndarray of int64, shape (L, R + 1)
        The rows stacked, in order: the first three and every row that can weigh more than 0.
    stacked : ndarray of int64, shape (L,)
        How many of ``kept`` are.
    """

    up: np.ndarray
    up_rhs: np.ndarray
    weights: np.ndarray
    kept: np.ndarray
    stacked: np.ndarray


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _stack_lane(rows, rhs, systems, i, depth, columns, side, lane):
    """System ``i`` of ``systems`` (:class:`LaneSystems`) into lane ``lane`` of ``columns`` ``(L, 3, R)`` and
    ``side`` ``(L, 1, R)``, zero from its row count to ``depth``.

    The system's rows are its problem's ``rows`` ``(N, 3)`` (right-hand sides ``rhs`` ``(N,)``) then its up row,
    of which only rows ``kept[i, :stacked[i]]`` are stacked: the others must weigh 0 and come after the first
    three (the SVD then only adds zeros in their place, as it does for the zero rows at the end, and the
    Householder pivots are the same rows).
    """
    last, count = rows.shape[0], systems.stacked[i]
    kept, weights = systems.kept, systems.weights
    for k in range(count):
        t = kept[i, k]
        w = weights[i, t]
        if t < last:
            for j in range(3):
                columns[lane, j, k] = rows[t, j] * w
            side[lane, 0, k] = rhs[t] * w
        else:
            for j in range(3):
                columns[lane, j, k] = systems.up[i, j] * w
            side[lane, 0, k] = systems.up_rhs[i] * w
    for k in range(count, depth):
        for j in range(3):
            columns[lane, j, k] = 0.0
        side[lane, 0, k] = 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _least_squares(s, v, projected, lane, out):
    """The least-squares solution ``(3,)`` into ``out`` from lane ``lane`` of a stacked system's SVD
    (:func:`core.linalg.svd_in_place`); returns whether the rows are rank-deficient (smallest singular
    value below ``RANK_TOLERANCE`` of the largest; ``out`` then untouched)."""
    a, b, c = s[lane, 0], s[lane, 1], s[lane, 2]
    if not min(a, b, c) > RANK_TOLERANCE * max(a, b, c):
        return True
    for i in range(3):
        total = 0.0
        for j in range(3):
            sj = s[lane, j]
            total += v[lane, i, j] * (projected[lane, j, 0] / (sj * sj if sj > 0 else np.inf))
        out[i] = total
    return False


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _positions_kernel(stacked_rows, measurements, frames, weighted, passes):
    """Each problem's orthogonal-vector fix (see :func:`solve_orthogonal_batch`), its status (``SOLVED``,
    ``NO_ROWS`` or ``RANK_DEFICIENT``) and each row's noise per unit angle at the fix (:func:`_noise_scale`;
    1 where no fix), from its :class:`StackedRows`, the stations of its :class:`~core.kernel_data.Measurements`
    and the altitude surfaces of its :class:`~core.kernel_data.Frames`;
    ``weighted``: the rows weighed by their first-order noise from the second of ``passes`` on.

    The known altitude's up row is the last of the stacked system (zero weight without one). Rows of zero
    weight past the first three are left out of the SVD (:func:`_stack_lane`). ``SVD_LANES`` problems are solved side
    by side, each pass's systems in one :func:`core.linalg.svd_in_place` (each problem gets its own bits),
    except a system of three rows or fewer, which is not reduced first and goes alone.
    """
    # The pass loop stays in one function: a helper taking the bundles, called per group of problems, pays for
    # their arguments and refcounts on every call, a visible share of a four-line problem's solution.
    rows, rhs, used, sigma = stacked_rows.rows, stacked_rows.rhs, stacked_rows.used, stacked_rows.sigma
    stations, rotations = measurements.stations_enu_m, measurements.rotations
    altitude_m, geodetic = frames.altitude_m, frames.geodetic
    origin_ecef_m, origin_rotation = frames.origin_ecef_m, frames.origin_rotation
    size, count, _ = rows.shape
    position = np.full((size, 3), np.nan)
    status = np.full(size, NO_ROWS, dtype=np.int8)
    scale = np.ones((size, count))
    w, kept = np.zeros((SVD_LANES, count + 1)), np.empty((SVD_LANES, count + 1), dtype=np.int64)
    stacked, members, order = (np.empty(SVD_LANES, dtype=np.int64), np.empty(SVD_LANES, dtype=np.int64),
                               np.empty(SVD_LANES, dtype=np.int64))
    active = np.zeros(SVD_LANES, dtype=np.bool_)
    up, up_rhs = np.empty((SVD_LANES, 3)), np.empty(SVD_LANES)
    systems = LaneSystems(up, up_rhs, w, kept, stacked)
    columns, side = np.empty((SVD_LANES, 3, count + 1)), np.empty((SVD_LANES, 1, count + 1))
    s, v, projected = np.empty((SVD_LANES, 3)), np.empty((SVD_LANES, 3, 3)), np.empty((SVD_LANES, 3, 1))
    reflector, norms = np.empty((SVD_LANES, count + 1)), np.empty((SVD_LANES, 3))
    x, point, axes = np.empty((SVD_LANES, 3)), np.empty(3), np.empty((3, 3))
    b = 0
    while b < size:
        members_count = 0
        while members_count < SVD_LANES and b < size:
            for r in range(count):
                if used[b, r]:
                    status[b] = SOLVED
                    members[members_count] = b
                    members_count += 1
                    break
            b += 1
        for i in range(members_count):
            p = members[i]
            constrained = not math.isnan(altitude_m[p])
            up[i, 0], up[i, 1], up[i, 2] = 0.0, 0.0, 1.0
            up_rhs[i] = altitude_m[p] if constrained else 0.0
            n = 0
            for t in range(count + 1):
                if t < count:
                    w[i, t] = 1.0 if used[p, t] else 0.0
                if t < 3 or (used[p, t] if t < count else constrained):
                    kept[i, n] = t
                    n += 1
            stacked[i] = n
            active[i] = True
        for sweep in range(passes):
            tall, short = 0, 0
            for i in range(members_count):
                if not active[i]:
                    continue
                p = members[i]
                constrained = not math.isnan(altitude_m[p])
                if sweep > 0:
                    if not (weighted or constrained):
                        continue
                    if constrained:
                        point[:] = x[i]
                        onto_altitude_point(point, altitude_m[p], geodetic[p], origin_ecef_m[p], origin_rotation[p])
                        local_axes_point(point, geodetic[p], origin_ecef_m[p], origin_rotation[p], axes)
                        up[i, 0], up[i, 1], up[i, 2] = axes[2, 0], axes[2, 1], axes[2, 2]
                        up_rhs[i] = axes[2, 0] * point[0] + axes[2, 1] * point[1] + axes[2, 2] * point[2]
                    if weighted:
                        _noise_scale(x[i], stations[p], rotations[p], scale[p])
                        for r in range(count):
                            w[i, r] = 1.0 / (sigma[p, r] * max(scale[p, r], MIN_DISTANCE_M)) if used[p, r] else 0.0
                strongest = 0.0
                for r in range(count):
                    strongest = max(strongest, w[i, r])
                w[i, count] = ALTITUDE_ROW_WEIGHT * strongest if constrained else 0.0
                if stacked[i] > 3:
                    order[tall] = i
                    tall += 1
                else:
                    short += 1
                    order[SVD_LANES - short] = i
            if tall + short == 0:
                break
            depth = 0
            for lane in range(tall):
                depth = max(depth, stacked[order[lane]])
            for lane in range(tall):
                i = order[lane]
                p = members[i]
                _stack_lane(rows[p], rhs[p], systems, i, depth, columns, side, lane)
            if tall:
                svd_in_place(columns[:tall, :, :depth], side[:tall, :, :depth], s, v, projected, reflector, norms)
            for lane in range(SVD_LANES - short, SVD_LANES):
                i = order[lane]
                p = members[i]
                n = stacked[i]
                _stack_lane(rows[p], rhs[p], systems, i, n, columns, side, lane)
                svd_in_place(columns[lane:lane + 1, :, :n], side[lane:lane + 1, :, :n], s[lane:lane + 1],
                             v[lane:lane + 1], projected[lane:lane + 1], reflector, norms)
            for lane in range(SVD_LANES):
                if tall <= lane < SVD_LANES - short:
                    continue
                i = order[lane]
                if _least_squares(s, v, projected, lane, x[i]):
                    status[members[i]] = RANK_DEFICIENT
                    active[i] = False
        for i in range(members_count):
            if not active[i]:
                continue
            p = members[i]
            if not math.isnan(altitude_m[p]):
                onto_altitude_point(x[i], altitude_m[p], geodetic[p], origin_ecef_m[p], origin_rotation[p])
            position[p] = x[i]
            _noise_scale(x[i], stations[p], rotations[p], scale[p])
    return position, status, scale


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _orthogonal_kernel(measurements, frames, use_vertical, use_horizontal, weighted, passes):
    """:func:`_rows_kernel` then :func:`_positions_kernel`, in one call: the stacked rows, which are used and
    their sigmas (what the propagated covariance needs), then each problem's fix, its status and each row's noise
    scale. The structures: plain tuples or named (:mod:`core.kernel_data`)."""
    measurements, frames = Measurements(*measurements), Frames(*frames)
    rows, rhs, used, sigma = _rows_kernel(measurements, use_vertical, use_horizontal)
    position, status, scale = _positions_kernel(StackedRows(rows, rhs, used, sigma), measurements, frames, weighted,
                                                passes)
    return rows, used, sigma, position, status, scale


def solve_orthogonal_batch(batch: ProblemBatch, *, normals: Normals, weighting: Weighting, name: str,
                           with_covariance: bool = True, passes: int = PASSES) -> Estimates:
    """Positions and propagated covariances of an orthogonal-vector estimator for every problem of a batch.

    Parameters
    ----------
    batch : ProblemBatch
    normals : Normals
        Which rows to stack (OVE: ``ELEVATION_PLANE``; EOVE: ``BOTH``).
    weighting : Weighting
    name : str
        The method, for messages.
    with_covariance : bool
        False skips the propagated covariance (None), for a start.
    passes : int
        How many times the rows are solved (:data:`PASSES`); a start for ML takes fewer.

    Returns
    -------
    Estimates
        ``covariance_source`` ``"propagated"``; a problem without rows
        carries TooFewMeasurements, one whose rows are rank-deficient
        UnobservableGeometry.
    """
    size = batch.size
    weighted = weighting is Weighting.FIRST_ORDER
    rows, used, sigma, position, status, scale = _orthogonal_kernel(
        tuple(batch.kernel_measurements), tuple(batch.kernel_frames), normals is not Normals.AZIMUTH_PLANE,
        normals is not Normals.ELEVATION_PLANE, weighted, int(passes))
    errors: dict[int, LocalizationError] = {}
    failed = status != SOLVED
    if np.count_nonzero(failed):
        for b in np.flatnonzero(status == NO_ROWS).tolist():
            errors[b] = TooFewMeasurements(f"{name} needs bearings")
        why = f"{name}: the lines of sight do not determine a point (parallel or too few independent lines)"
        for b in np.flatnonzero(status == RANK_DEFICIENT).tolist():
            errors[b] = UnobservableGeometry(why)
    if not with_covariance:
        return Estimates(position_enu_m=position, covariance_source="propagated", errors=errors)
    covariance = np.full((size, 3, 3), np.nan)
    if not np.all(failed):
        k = _where(~failed)
        covariance[k] = _propagated_covariance(rows[k], used[k], sigma[k], position[k], scale[k],
                                               batch.constrained[k], batch, k, weighted)
    return Estimates(position_enu_m=position, covariance_source="propagated", covariance_enu_m2=covariance,
                     errors=errors)


def _propagated_covariance(rows, used, sigma, position_enu_m, scale, bound, batch: ProblemBatch, k, weighted: bool):
    """First-order covariance ``(K, 3, 3)`` of K problems at their fixes (see the module docstring), from
    their stacked ``rows`` ``(K, 2M, 3)``, which are ``used`` and their angle ``sigma`` ``(K, 2M)``, given each
    row's noise per unit angle there ``scale`` ``(K, 2M)``; ``k`` picks the problems out of ``batch``.

    A problem with a known altitude is solved over its local east/north
    axes: its rows are expressed in the local axes and the up column is
    zeroed (a zero singular value, dropped like ``np.linalg.pinv`` drops it).
    """
    noise_sd = sigma * scale
    if weighted:
        weights = np.where(used, 1.0 / (sigma * np.maximum(scale, MIN_DISTANCE_M)), 0.0)
    else:
        weights = used.astype(float)
    axes = np.broadcast_to(np.eye(3), (position_enu_m.shape[0], 3, 3)).copy()
    if np.any(bound):
        c = np.flatnonzero(bound)
        problems = np.arange(batch.size)[k][c]
        axes[c] = local_axes(position_enu_m[c], batch.origin[problems], batch.geodetic[problems])
        rows = matvec(axes[:, None], rows)
        rows[c, :, 2] = 0.0
    s, v, _ = jacobi_svd(rows * weights[..., None])
    eigenvalues = s * s
    kept = eigenvalues > PINV_CUTOFF * eigenvalues.max(axis=-1, keepdims=True)
    scaled = v * np.where(kept, 1.0 / np.where(kept, eigenvalues, 1.0), 0.0)[:, None, :]
    gain = scaled @ np.swapaxes(v, -1, -2)
    middle = weighted_gram(np.swapaxes(rows, -1, -2), np.where(used, weights * weights * noise_sd, 0.0) ** 2)
    local = gain @ middle @ gain
    return np.swapaxes(axes, -1, -2) @ local @ axes


def solve_orthogonal(problem: Problem, *, normals: Normals, weighting: Weighting, name: str):
    """One problem's fix by :func:`solve_orthogonal_batch` (a batch of one).

    Returns
    -------
    position_enu_m : ndarray, shape (3,)
    covariance_enu_m2 : ndarray, shape (3, 3)

    Raises
    ------
    LocalizationError
        As the batch reports it.
    """
    result = solve_orthogonal_batch(ProblemBatch.from_problems([problem]), normals=normals, weighting=weighting,
                                    name=name)
    if result.errors:
        raise result.errors[0]
    return result.position_enu_m[0], result.covariance_enu_m2[0]


@register("ove", "orthogonal vector estimator: elevation-plane normals only, needs >= 3 lines of sight", uses=ANGLES)
def ove(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    estimates = solve_orthogonal_batch(batch, normals=Normals.ELEVATION_PLANE, weighting=Weighting.UNIT, name="ove")
    with_elevation = np.count_nonzero(~np.isnan(batch.lines_of_sight()[1]), axis=-1)
    errors = dict(estimates.errors)
    for b in np.flatnonzero(with_elevation < 3):
        errors[int(b)] = TooFewMeasurements(
            f"ove needs at least 3 lines of sight with elevation; got {int(with_elevation[b])}", ("measurements",))
    return Estimates(position_enu_m=estimates.position_enu_m, covariance_source="propagated",
                     covariance_enu_m2=estimates.covariance_enu_m2, errors=errors)


@register("eove", "extended orthogonal vector estimator: both normals per line of sight (paper 000)", uses=ANGLES)
def eove(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    return solve_orthogonal_batch(batch, normals=Normals.BOTH, weighting=Weighting.UNIT, name="eove")


def eove_start(batch: ProblemBatch) -> Estimates:
    """:func:`eove`'s positions and errors without the covariance: the start of the iterative azimuth methods."""
    return solve_orthogonal_batch(batch, normals=Normals.BOTH, weighting=Weighting.UNIT, name="eove",
                                  with_covariance=False)


@register("weighted_eove", "EOVE with rows weighted by their first-order noise: the small-noise BLUE",
          uses=ANGLES)
def weighted_eove(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    return solve_orthogonal_batch(batch, normals=Normals.BOTH, weighting=Weighting.FIRST_ORDER, name="weighted_eove")
