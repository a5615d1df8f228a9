"""Line-of-sight intersection by the common perpendicular (paper 002, ALGORITHMS.md section 5).

Two measured lines of sight ``s_1 + t u_1`` and ``s_2 + t u_2`` rarely meet;
their common perpendicular touches them at the feet ``X_1`` and ``X_2``. Per
axis (east, north, up separately, as the paper does) the two feet are fused
by weighted least squares with ``C = [1, 1]^T`` and ``S = A R A^T``, where
``A`` holds the derivatives of that axis of both feet with respect to the
four angles ``(az_1, el_1, az_2, el_2)`` (analytic here) and
``R = diag(sigma^2)``. With more than two lines every pair gives a fused
point and per-axis variances, and the pairs are combined by inverse-variance
weights. That point ``X_s`` is the linearisation point of one extended
weighted-least-squares pass over every measured angle,
``X = X_s + (K^T R^-1 K)^-1 K^T R^-1 dZ``, whose covariance
``(K^T R^-1 K)^-1`` is the one reported. When an angle's normalised residual
at ``X_s`` reaches :data:`REFERENCE_RATIO_LIMIT` (``R_p >= 6``), ``X_s`` is
too close to that line's station for linearisation: the pass is linearised
instead at the point of that station's measured line of sight at the same
distance ``|X_s - s_p|``.

Everything is vectorised over the problems of a :class:`~core.problem.batch.ProblemBatch`
(a Monte Carlo over one geometry is one batch:
:func:`core.simulation.measurements.trial_batch`). Only angles are used; ranges
and TOAs in a problem are ignored by this method (they still enter the fix's
residuals and CRLB).
"""

from __future__ import annotations

import numpy as np

from core.angles import line_of_sight_derivatives, line_of_sight_enu, station_to_common
from core.crlb import invert_information, normal_matrix, parameterisation
from core.errors import LocalizationError, TooFewMeasurements, UnobservableGeometry
from core.estimators.base import ANGLES, SolveOptions, register
from core.estimators.result import Estimates, FixWarning
from core.linalg import row_sums
from core.measurements import AZIMUTH, ELEVATION, RANGE, TOA, MeasurementModel
from core.problem.batch import ProblemBatch

#: ``R_p`` (largest normalised angle residual at ``X_s``) from which the
#: linearisation point is moved onto the worst line of sight (paper: 6).
REFERENCE_RATIO_LIMIT = 6.0
#: ``D = sin^2`` of the angle between two lines below which they count as
#: parallel (about 1e-5 rad apart): that pair gives no point.
PARALLEL_SIN2 = 1e-10
#: Lines whose stations are closer than this (m) meet at the station: that pair gives no point.
SAME_ORIGIN_M = 1e-3
#: Smallest per-axis variance (m^2) given to a pair's point.
MIN_VARIANCE_M2 = 1e-12
#: A batch is intersected in chunks of at most about this many pairs of lines (problems x pairs each; the
#: pairs of one problem with many bearings in chunks of its own).
CHUNK_PAIRS = 1 << 14


def common_perpendicular(origins_enu_m, rotations, azimuth_rad, elevation_rad):
    """Feet of the common perpendicular of pairs of lines of sight, and their angle derivatives.

    Parameters
    ----------
    origins_enu_m : ndarray, shape (..., 2, 3)
        Station of each line of the pair, common frame.
    rotations : ndarray, shape (..., 2, 3, 3)
        Station ENU <- common ENU.
    azimuth_rad, elevation_rad : ndarray, shape (..., 2)

    Returns
    -------
    feet_enu_m : ndarray, shape (..., 2, 3)
        ``X_1`` on the first line, ``X_2`` on the second.
    jacobian : ndarray, shape (..., 2, 3, 4)
        ``d X_k / d (az_1, el_1, az_2, el_2)`` in metres per radian.
    sin2 : ndarray, shape (...)
        ``D = a c - b^2``, the squared sine of the angle between the lines
        (the feet are undefined where it is ~0).
    """
    u, du_az, du_el = (np.moveaxis(station_to_common(v, rotations), (-2, -1), (0, 1))
                       for v in line_of_sight_derivatives(azimuth_rad, elevation_rad))
    feet, jacobian, sin2 = _perpendicular(np.moveaxis(origins_enu_m, (-2, -1), (0, 1)), u,
                                          np.stack([du_az, du_el], axis=1))
    return np.moveaxis(feet, (0, 1), (-2, -1)), np.moveaxis(jacobian, (0, 1, 2), (-3, -2, -1)), sin2


def _perpendicular(origins, directions, tangents):
    """:func:`common_perpendicular`, component-first: the arithmetic runs on whole planes of pairs.

    Parameters
    ----------
    origins, directions : ndarray, shape (2, 3, ...)
        Per line of the pair: station and unit line of sight (common frame).
    tangents : ndarray, shape (2, 2, 3, ...)
        Per line: ``du/daz`` and ``du/del``.

    Returns
    -------
    feet : ndarray, shape (2, 3, ...)
    jacobian : ndarray, shape (2, 3, 4, ...)
    sin2 : ndarray, shape (...)
    """
    u1, u2 = directions[0], directions[1]
    w = origins[0] - origins[1]
    a = np.sum(u1 * u1, axis=0)
    b = np.sum(u1 * u2, axis=0)
    c = np.sum(u2 * u2, axis=0)
    d = np.sum(u1 * w, axis=0)
    e = np.sum(u2 * w, axis=0)
    sin2 = a * c - b * b
    safe = np.where(sin2 > 0, sin2, 1.0)
    t1 = (b * e - c * d) / safe
    t2 = (a * e - b * d) / safe
    feet = np.stack([origins[0] + t1 * u1, origins[1] + t2 * u2])

    d_sin2_du1 = 2 * c * u1 - 2 * b * u2
    d_sin2_du2 = 2 * a * u2 - 2 * b * u1
    dt1_du1 = (e * u2 - c * w - t1 * d_sin2_du1) / safe
    dt1_du2 = (e * u1 + b * w - 2 * d * u2 - t1 * d_sin2_du2) / safe
    dt2_du1 = (2 * e * u1 - d * u2 - b * w - t2 * d_sin2_du1) / safe
    dt2_du2 = (a * w - d * u1 - t2 * d_sin2_du2) / safe

    v1, v2 = tangents[0], tangents[1]  # (az, el) x component
    jacobian = np.empty((2, 3, 4) + sin2.shape)
    jacobian[0, :, 0:2] = u1[:, None] * np.sum(dt1_du1 * v1, axis=1) + t1 * np.swapaxes(v1, 0, 1)
    jacobian[0, :, 2:4] = u1[:, None] * np.sum(dt1_du2 * v2, axis=1)
    jacobian[1, :, 0:2] = u2[:, None] * np.sum(dt2_du1 * v1, axis=1)
    jacobian[1, :, 2:4] = u2[:, None] * np.sum(dt2_du2 * v2, axis=1) + t2 * np.swapaxes(v2, 0, 1)
    return feet, jacobian, sin2


def fuse_feet(feet_enu_m, jacobian, angle_variances_rad2):
    """Per-axis weighted-least-squares fusion of the two feet of each pair.

    For each axis, ``x = (C^T S^-1 C)^-1 C^T S^-1 [X_1, X_2]^T`` and its
    variance ``(C^T S^-1 C)^-1`` with ``S = A R A^T`` (2 x 2).

    Parameters
    ----------
    feet_enu_m : ndarray, shape (..., 2, 3)
    jacobian : ndarray, shape (..., 2, 3, 4)
    angle_variances_rad2 : ndarray, shape (..., 4)
        ``(sigma_az_1^2, sigma_el_1^2, sigma_az_2^2, sigma_el_2^2)``.

    Returns
    -------
    point_enu_m : ndarray, shape (..., 3)
    variance_enu_m2 : ndarray, shape (..., 3)
        Per-axis variances (the paper's ``sigma_x^2, sigma_y^2, sigma_z^2``).
    """
    point, variance = _fuse(np.moveaxis(feet_enu_m, (-2, -1), (0, 1)),
                            np.moveaxis(jacobian, (-3, -2, -1), (0, 1, 2)), np.moveaxis(angle_variances_rad2, -1, 0))
    return np.moveaxis(point, 0, -1), np.moveaxis(variance, 0, -1)


def _fuse(feet, jacobian, variances):
    """:func:`fuse_feet`, component-first: feet ``(2, 3, ...)``, jacobian ``(2, 3, 4, ...)``, variances
    ``(4, ...)``; returns point and per-axis variance ``(3, ...)``."""
    a1, a2 = jacobian[0], jacobian[1]
    p = np.sum(a1 * a1 * variances, axis=1)
    q = np.sum(a1 * a2 * variances, axis=1)
    s = np.sum(a2 * a2 * variances, axis=1)
    spread = p + s - 2 * q
    degenerate = spread <= 1e-12 * (p + s)
    safe = np.where(degenerate, 1.0, spread)
    x1, x2 = feet[0], feet[1]
    point = np.where(degenerate, 0.5 * (x1 + x2), ((s - q) * x1 + (p - q) * x2) / safe)
    variance = np.where(degenerate, 0.5 * (p + s), (p * s - q * q) / safe)
    return point, np.maximum(variance, MIN_VARIANCE_M2)


class _Lines:
    """The lines of sight of B problems laid out per bearing, ``(B, K)`` (see :meth:`ProblemBatch.by_bearing`).

    Attributes
    ----------
    exists, has_elevation : ndarray of bool, shape (B, K)
    station : ndarray of int, shape (B, K)
    origins_enu_m : ndarray, shape (B, K, 3)
    rotations : ndarray, shape (B, K, 3, 3)
    azimuth_rad, elevation_rad : ndarray, shape (B, K)
        Elevation 0 where a line has none.
    sigma_azimuth_rad, sigma_elevation_rad : ndarray, shape (B, K)
    """

    def __init__(self, batch: ProblemBatch):
        self.exists = batch.by_bearing(np.ones(batch.kinds.shape, dtype=bool), AZIMUTH, False)
        self.has_elevation = batch.by_bearing(np.ones(batch.kinds.shape, dtype=bool), ELEVATION, False)
        self.station = batch.by_bearing(batch.station_index, AZIMUTH, 0)
        rows = np.arange(batch.size)[:, None]
        self.origins_enu_m = batch.stations_enu_m[rows, self.station]
        self.rotations = batch.station_rotations[rows, self.station]
        self.azimuth_rad = batch.by_bearing(batch.values, AZIMUTH, 0.0)
        self.elevation_rad = batch.by_bearing(batch.values, ELEVATION, 0.0)
        self.sigma_azimuth_rad = batch.by_bearing(batch.sigmas, AZIMUTH, 1.0)
        self.sigma_elevation_rad = batch.by_bearing(batch.sigmas, ELEVATION, 1.0)


def _pairs(lines: _Lines):
    """Every pair ``i < j`` of bearing columns ``(P,)``, and which pairs join two lines with elevation
    from distinct station positions ``(B, P)``."""
    width = lines.exists.shape[1]
    first, second = np.triu_indices(width, k=1)
    both = lines.has_elevation[:, first] & lines.has_elevation[:, second]
    apart = np.linalg.norm(lines.origins_enu_m[:, first] - lines.origins_enu_m[:, second], axis=-1) > SAME_ORIGIN_M
    return first, second, both & apart


def _pair_errors(batch: ProblemBatch, lines: _Lines, pair_ok) -> dict[int, LocalizationError]:
    """Problems whose lines of sight give no pair, with the documented errors."""
    has_el = lines.has_elevation
    same_station = lines.station[:, :, None] == lines.station[:, None, :]
    earlier = np.tril(np.ones((has_el.shape[1],) * 2, dtype=bool), k=-1)
    repeated = np.any(same_station & earlier & has_el[:, None, :], axis=-1)
    with_elevation = np.count_nonzero(has_el, axis=-1)
    stations = np.count_nonzero(has_el & ~repeated, axis=-1)
    errors: dict[int, LocalizationError] = {}
    for b in np.flatnonzero(stations < 2).tolist():
        errors[b] = TooFewMeasurements(
            "los_intersection needs bearings with elevation from at least 2 stations; got "
            f"{with_elevation[b]} such bearing(s) from {stations[b]} station(s)", ("measurements",))
    for b in np.flatnonzero((stations >= 2) & ~np.any(pair_ok, axis=-1)).tolist():
        errors[b] = UnobservableGeometry("los_intersection: every line of sight with elevation starts at one point")
    return errors


def _sum_over_pairs(values, used, start):
    """``start + sum_p values[:, p]`` over used pairs, added one pair after the other in pair order (a
    sequential accumulation, so a problem's sums depend neither on the batch nor on the chunks of pairs).

    Parameters
    ----------
    values : ndarray, shape (B, P, 3)
    used : ndarray of bool, shape (B, P)
    start : ndarray, shape (B, 3)
        The sum over the pairs before these.
    """
    terms = np.concatenate([start[:, None], np.where(used[..., None], values, 0.0)], axis=1)
    return row_sums(np.swapaxes(terms, 1, 2))


def intersect_lines_of_sight(batch: ProblemBatch, options: SolveOptions | None = None) -> Estimates:
    """The common-perpendicular fix of every problem of a batch.

    A known altitude constrains the extended-WLS pass to the local
    east/north at the reference point. The covariance is that pass's
    ``(K^T R^-1 K)^-1`` at the linearisation point; ``coarse_position_enu_m``
    is ``X_s``, the pairs' combined point before it.

    Parameters
    ----------
    batch : ProblemBatch
    options : SolveOptions, optional
        Unused (a closed form).

    Returns
    -------
    Estimates
        ``covariance_source`` ``"propagated"``; ``position_enu_m`` NaN on
        problems in ``errors``. ``details`` per solved problem:
        ``pairs_used`` (pairs that gave a point), ``pairs_total``,
        ``reference_ratio`` (``R_p`` at ``X_s``), ``reference_station``
        (the station whose line of sight the pass was moved onto, or None),
        ``coarse_variance_enu_m2`` (``(3,)``, the per-axis variances of
        ``X_s``) and ``ignored_measurements`` (ranges and TOAs).

    Errors (in ``errors``)
    ----------------------
    TooFewMeasurements
        Fewer than 2 stations give a bearing with elevation.
    UnobservableGeometry
        All lines with elevation start at one point; every pair of lines is
        parallel; or the angles do not determine the position at the
        reference point.
    """
    width = int(batch.bearing_index.max(initial=0)) + 1
    rows = max(1, CHUNK_PAIRS // max(width * (width - 1) // 2, 1))
    if batch.size <= rows:
        return _intersect(batch)
    parts = [_intersect(batch.take(np.arange(start, min(start + rows, batch.size))))
             for start in range(0, batch.size, rows)]
    errors = {start + b: e for start, part in zip(range(0, batch.size, rows), parts) for b, e in part.errors.items()}
    return Estimates(
        position_enu_m=np.concatenate([p.position_enu_m for p in parts]),
        covariance_source="propagated",
        covariance_enu_m2=np.concatenate([p.covariance_enu_m2 for p in parts]),
        errors=errors,
        iterations=np.ones(batch.size, dtype=int),
        warnings=[w for p in parts for w in p.warnings],
        coarse_position_enu_m=np.concatenate([p.coarse_position_enu_m for p in parts]),
        details=[d for p in parts for d in p.details],
    )


def _intersect(batch: ProblemBatch) -> Estimates:
    """:func:`intersect_lines_of_sight` of one chunk."""
    size = batch.size
    lines = _Lines(batch)
    first, second, pair_ok = _pairs(lines)
    errors = _pair_errors(batch, lines, pair_ok)
    if len(errors) == size:
        return Estimates(position_enu_m=np.full((size, 3), np.nan), covariance_source="propagated",
                         covariance_enu_m2=np.full((size, 3, 3), np.nan), errors=errors,
                         iterations=np.ones(size, dtype=int), warnings=[()] * size,
                         coarse_position_enu_m=np.full((size, 3), np.nan), details=[{} for _ in range(size)])

    directions, d_azimuth, d_elevation = (
        np.moveaxis(station_to_common(v, lines.rotations), -1, 0)
        for v in line_of_sight_derivatives(lines.azimuth_rad, lines.elevation_rad))
    origins = np.moveaxis(lines.origins_enu_m, -1, 0)
    total = np.zeros((size, 3))
    weighted = np.zeros((size, 3))
    pairs_used = np.zeros(size, dtype=int)
    # One problem with many bearings has many pairs (1,024 bearings: 523,776): its pairs go in chunks too.
    per_chunk = max(1, CHUNK_PAIRS // size)
    for start in range(0, first.size, per_chunk):
        i, j = first[start:start + per_chunk], second[start:start + per_chunk]

        def paired(planes):
            return np.stack([planes[..., i], planes[..., j]])

        feet, jacobian, sin2 = _perpendicular(paired(origins), paired(directions),
                                              np.stack([paired(d_azimuth), paired(d_elevation)], axis=1))
        variances = np.stack([lines.sigma_azimuth_rad[:, i], lines.sigma_elevation_rad[:, i],
                              lines.sigma_azimuth_rad[:, j], lines.sigma_elevation_rad[:, j]]) ** 2
        points, point_variance = (np.moveaxis(x, 0, -1) for x in _fuse(feet, jacobian, variances))
        del feet, jacobian, variances
        usable = (pair_ok[:, start:start + per_chunk] & (sin2 > PARALLEL_SIN2)
                  & np.all(np.isfinite(points), axis=-1) & np.all(np.isfinite(point_variance), axis=-1))
        weights = 1.0 / np.where(usable[..., None], point_variance, 1.0)
        total = _sum_over_pairs(weights, usable, total)
        weighted = _sum_over_pairs(weights * points, usable, weighted)
        pairs_used += np.count_nonzero(usable, axis=-1)
    has_pair = np.all(total > 0, axis=-1)
    safe_total = np.where(total > 0, total, 1.0)
    coarse = np.where(has_pair[:, None], weighted / safe_total, 0.0)
    coarse_variance = 1.0 / safe_total
    coarse_on = batch.onto_altitude(coarse)

    stations, rotations = batch.measurement_stations()
    model = MeasurementModel(stations, rotations, batch.kinds)
    angle = batch.valid & ((batch.kinds == AZIMUTH) | (batch.kinds == ELEVATION))
    sigma = np.where(angle, batch.sigmas, 1.0)
    zero_bias = np.zeros(size)
    predicted, _ = model.predict(coarse_on, zero_bias)
    normalised = np.where(angle, np.abs(model.residuals(batch.values, predicted)) / sigma, -1.0)
    worst = np.argmax(normalised, axis=-1)
    every = np.arange(size)
    ratio = normalised[every, worst]
    line = np.maximum(batch.bearing_index[every, worst], 0)
    moved = has_pair & (ratio >= REFERENCE_RATIO_LIMIT)
    reference = coarse_on.copy()
    if np.any(moved):
        b, k = np.flatnonzero(moved), line[moved]
        origin = lines.origins_enu_m[b, k]
        rotation = lines.rotations[b, k]
        offset = coarse_on[b] - origin
        distance = np.linalg.norm(offset, axis=-1)
        seen = np.einsum("tij,tj->ti", rotation, offset)
        seen_elevation = np.arctan2(seen[:, 2], np.hypot(seen[:, 0], seen[:, 1]))
        line_elevation = np.where(lines.has_elevation[b, k], lines.elevation_rad[b, k], seen_elevation)
        direction = station_to_common(line_of_sight_enu(lines.azimuth_rad[b, k], line_elevation), rotation)
        reference[b] = batch.onto_altitude(origin + distance[:, None] * direction, b)

    predicted, jac = model.predict(reference, zero_bias)
    delta_z = np.where(angle, model.residuals(batch.values, predicted), 0.0)
    w = np.where(angle, 1.0 / sigma**2, 0.0)
    axes, free = parameterisation(reference, batch.altitude_m, np.zeros(size, dtype=bool), batch.origin,
                                  batch.geodetic, batch.frame_placements())
    information, local_jacobian = normal_matrix(jac, w, axes, free)
    inverse = invert_information(information, axes, free)
    gradient = row_sums(local_jacobian * (w * delta_z)[:, None, :])
    step = np.einsum("bij,bj->bi", inverse.covariance_params, gradient)[:, :3]
    position = batch.onto_altitude(reference + (step if axes is None else np.einsum("bi,bij->bj", step, axes)))
    valid = has_pair & inverse.observable & np.all(np.isfinite(position), axis=-1)

    pairs_total = np.count_nonzero(pair_ok, axis=-1)
    for b in np.flatnonzero(~valid).tolist():
        if b in errors:
            continue
        if pairs_used[b] == 0:
            errors[b] = UnobservableGeometry(
                f"los_intersection: all {pairs_total[b]} pair(s) of lines of sight are parallel, "
                "so no common perpendicular defines a point")
        else:
            errors[b] = UnobservableGeometry(
                "los_intersection: the angles do not determine the position at the reference point "
                "(singular extended-WLS normal matrix)")

    ignored = np.count_nonzero(batch.valid & ((batch.kinds == RANGE) | (batch.kinds == TOA)), axis=-1).tolist()
    reference_station = lines.station[every, line].tolist()
    warnings: list[tuple] = [()] * size
    details: list[dict] = [{} for _ in range(size)]
    for b, (used, total_pairs, r_p, was_moved, station, n_ignored, axis_variance) in enumerate(zip(
            pairs_used.tolist(), pairs_total.tolist(), ratio.tolist(), moved.tolist(), reference_station, ignored,
            coarse_variance)):
        if b in errors:
            continue
        name = batch.station_ids[b][station] if was_moved else None
        if was_moved:
            warnings[b] = (FixWarning(
                "reference_point_moved",
                f"R_p = {r_p:.1f} >= {REFERENCE_RATIO_LIMIT:g} at station {name}: "
                "linearised on its line of sight at the same distance"),)
        details[b] = {"pairs_used": used, "pairs_total": total_pairs, "reference_ratio": r_p,
                      "reference_station": name, "coarse_variance_enu_m2": axis_variance,
                      "ignored_measurements": n_ignored}
    return Estimates(
        position_enu_m=np.where(valid[:, None], position, np.nan),
        covariance_source="propagated",
        covariance_enu_m2=inverse.covariance_enu_m2,
        errors=errors,
        iterations=np.ones(size, dtype=int),
        warnings=warnings,
        coarse_position_enu_m=np.where(has_pair[:, None], coarse, np.nan),
        details=details,
    )


register("los_intersection",
         "common-perpendicular line-of-sight intersection, pairwise WLS fusion and an extended-WLS pass (paper 002)",
         uses=ANGLES)(
    intersect_lines_of_sight)
