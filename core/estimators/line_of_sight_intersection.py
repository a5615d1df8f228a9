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

Everything is vectorised over a leading trial axis ``T``: the geometry
(stations, rotations, sigmas) is the problem's, the measured values may be a
``(T, M)`` batch of noise draws, so a Monte Carlo over one scenario is one
call of :func:`intersect_lines_of_sight`. Only angles are used; ranges and
TOAs in the problem are ignored by this method (they still enter the fix's
residuals and CRLB).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from core.crlb import invert_information, normal_matrix, parameterisation
from core.errors import TooFewMeasurements, UnobservableGeometry
from core.estimators.base import Estimate, SolveOptions, per_problem, register
from core.estimators.result import FixWarning
from core.measurements import Kind, predict, residuals
from core.problem import Problem

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


def line_of_sight_derivatives(azimuth_rad, elevation_rad, rotations):
    """Unit lines of sight and their derivatives with respect to azimuth and elevation.

    Parameters
    ----------
    azimuth_rad, elevation_rad : ndarray, shape (...)
        Compass azimuth and elevation in each station's own ENU.
    rotations : ndarray, shape (..., 3, 3)
        Station ENU <- common ENU.

    Returns
    -------
    direction, d_azimuth, d_elevation : ndarray, shape (..., 3)
        ``u``, ``du/daz`` and ``du/del`` in the common frame (per radian).
    """
    sin_az, cos_az = np.sin(azimuth_rad), np.cos(azimuth_rad)
    sin_el, cos_el = np.sin(elevation_rad), np.cos(elevation_rad)
    zero = np.zeros_like(sin_az)
    local = np.stack([
        np.stack([cos_el * sin_az, cos_el * cos_az, sin_el], axis=-1),
        np.stack([cos_el * cos_az, -cos_el * sin_az, zero], axis=-1),
        np.stack([-sin_el * sin_az, -sin_el * cos_az, cos_el], axis=-1),
    ])
    common = (local[..., None, :] @ rotations)[..., 0, :]
    return common[0], common[1], common[2]


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
    u, du_az, du_el = line_of_sight_derivatives(azimuth_rad, elevation_rad, rotations)
    u1, u2 = u[..., 0, :], u[..., 1, :]
    w = origins_enu_m[..., 0, :] - origins_enu_m[..., 1, :]
    a = np.sum(u1 * u1, axis=-1)
    b = np.sum(u1 * u2, axis=-1)
    c = np.sum(u2 * u2, axis=-1)
    d = np.sum(u1 * w, axis=-1)
    e = np.sum(u2 * w, axis=-1)
    sin2 = a * c - b * b
    safe = np.where(sin2 > 0, sin2, 1.0)[..., None]
    t1 = (b * e - c * d) / safe[..., 0]
    t2 = (a * e - b * d) / safe[..., 0]
    feet = np.stack([origins_enu_m[..., 0, :] + t1[..., None] * u1,
                     origins_enu_m[..., 1, :] + t2[..., None] * u2], axis=-2)

    def x(scalar):
        return scalar[..., None]

    d_sin2_du1 = 2 * x(c) * u1 - 2 * x(b) * u2
    d_sin2_du2 = 2 * x(a) * u2 - 2 * x(b) * u1
    dt1_du1 = (x(e) * u2 - x(c) * w - x(t1) * d_sin2_du1) / safe
    dt1_du2 = (x(e) * u1 + x(b) * w - 2 * x(d) * u2 - x(t1) * d_sin2_du2) / safe
    dt2_du1 = (2 * x(e) * u1 - x(d) * u2 - x(b) * w - x(t2) * d_sin2_du1) / safe
    dt2_du2 = (x(a) * w - x(d) * u1 - x(t2) * d_sin2_du2) / safe

    # columns: derivative of u_1 (az_1, el_1), then of u_2 (az_2, el_2)
    v1 = np.stack([du_az[..., 0, :], du_el[..., 0, :]], axis=-2)
    v2 = np.stack([du_az[..., 1, :], du_el[..., 1, :]], axis=-2)

    def dot(gradient, tangents):
        return np.sum(gradient[..., None, :] * tangents, axis=-1)

    foot1 = np.concatenate([
        u1[..., :, None] * dot(dt1_du1, v1)[..., None, :] + t1[..., None, None] * np.swapaxes(v1, -1, -2),
        u1[..., :, None] * dot(dt1_du2, v2)[..., None, :],
    ], axis=-1)
    foot2 = np.concatenate([
        u2[..., :, None] * dot(dt2_du1, v1)[..., None, :],
        u2[..., :, None] * dot(dt2_du2, v2)[..., None, :] + t2[..., None, None] * np.swapaxes(v2, -1, -2),
    ], axis=-1)
    return feet, np.stack([foot1, foot2], axis=-3), sin2


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
    r = angle_variances_rad2[..., None, :]
    a1, a2 = jacobian[..., 0, :, :], jacobian[..., 1, :, :]
    p = np.sum(a1 * a1 * r, axis=-1)
    q = np.sum(a1 * a2 * r, axis=-1)
    s = np.sum(a2 * a2 * r, axis=-1)
    spread = p + s - 2 * q
    degenerate = spread <= 1e-12 * (p + s)
    safe = np.where(degenerate, 1.0, spread)
    x1, x2 = feet_enu_m[..., 0, :], feet_enu_m[..., 1, :]
    point = np.where(degenerate, 0.5 * (x1 + x2), ((s - q) * x1 + (p - q) * x2) / safe)
    variance = np.where(degenerate, 0.5 * (p + s), (p * s - q * q) / safe)
    return point, np.maximum(variance, MIN_VARIANCE_M2)


@dataclass(frozen=True)
class IntersectionBatch:
    """Line-of-sight intersection of one geometry over ``T`` sets of measured values.

    Attributes
    ----------
    position_enu_m : ndarray, shape (T, 3)
        After the extended-WLS pass (NaN where ``valid`` is False).
    covariance_enu_m2 : ndarray, shape (T, 3, 3)
        ``(K^T R^-1 K)^-1`` at the linearisation point.
    coarse_position_enu_m : ndarray, shape (T, 3)
        ``X_s``, the inverse-variance combination of the pairs' points.
    coarse_variance_enu_m2 : ndarray, shape (T, 3)
        Its per-axis variances.
    reference_enu_m : ndarray, shape (T, 3)
        Where the pass was linearised (``X_s`` unless moved).
    reference_ratio : ndarray, shape (T,)
        ``R_p`` at ``X_s``.
    reference_line : ndarray of int, shape (T,)
        Line of sight giving ``R_p``.
    moved : ndarray of bool, shape (T,)
        ``R_p >= 6``: the reference point was moved onto that line.
    pairs_used : ndarray of int, shape (T,)
        Pairs that gave a point (not parallel, distinct stations).
    pairs_total : int
    valid : ndarray of bool, shape (T,)
        A usable pair existed and the pass was observable.
    """

    position_enu_m: np.ndarray
    covariance_enu_m2: np.ndarray
    coarse_position_enu_m: np.ndarray
    coarse_variance_enu_m2: np.ndarray
    reference_enu_m: np.ndarray
    reference_ratio: np.ndarray
    reference_line: np.ndarray
    moved: np.ndarray
    pairs_used: np.ndarray
    pairs_total: int
    valid: np.ndarray


def _pairs(los):
    """Pairs of lines with elevation from distinct station positions, as index arrays ``(P,)``."""
    with_elevation = np.flatnonzero(los.has_elevation)
    stations = np.unique(los.station_index[with_elevation])
    if stations.size < 2:
        raise TooFewMeasurements(
            "los_intersection needs bearings with elevation from at least 2 stations; got "
            f"{with_elevation.size} such bearing(s) from {stations.size} station(s)", ("measurements",))
    first, second = [], []
    for i, j in combinations(with_elevation, 2):
        if np.linalg.norm(los.origins_enu_m[i] - los.origins_enu_m[j]) > SAME_ORIGIN_M:
            first.append(i)
            second.append(j)
    if not first:
        raise UnobservableGeometry("los_intersection: every line of sight with elevation starts at one point")
    return np.array(first), np.array(second)


def intersect_lines_of_sight(problem: Problem, values=None) -> IntersectionBatch:
    """The common-perpendicular fix of one geometry for a batch of measured values.

    Parameters
    ----------
    problem : Problem
        Stations, kinds, sigmas and frame; a known altitude constrains the
        extended-WLS pass to the local east/north at the reference point.
    values : ndarray, shape (T, M), optional
        Measured values in problem units (rad, m, s); default the problem's
        own, ``T = 1``.

    Returns
    -------
    IntersectionBatch

    Raises
    ------
    TooFewMeasurements
        Fewer than 2 stations give a bearing with elevation.
    UnobservableGeometry
        All lines with elevation start at one point.
    """
    values = np.atleast_2d(problem.values if values is None else np.asarray(values, dtype=float))
    trials = values.shape[0]
    los = problem.lines_of_sight()
    first, second = _pairs(los)

    elevation = np.where(los.has_elevation, values[:, los.elevation_row], 0.0)
    azimuth = values[:, los.azimuth_row]
    pair = np.stack([first, second], axis=-1)
    feet, jacobian, sin2 = common_perpendicular(
        los.origins_enu_m[pair], los.rotations[pair], azimuth[:, pair], elevation[:, pair])
    variances = np.stack([los.sigma_azimuth_rad, los.sigma_elevation_rad], axis=-1)[pair].reshape(-1, 4) ** 2
    points, point_variance = fuse_feet(feet, jacobian, variances)
    usable = (sin2 > PARALLEL_SIN2) & np.all(np.isfinite(points), axis=-1) & np.all(np.isfinite(point_variance), axis=-1)
    weights = np.where(usable[..., None], 1.0 / np.where(usable[..., None], point_variance, 1.0), 0.0)
    total = weights.sum(axis=1)
    has_pair = np.all(total > 0, axis=-1)
    safe_total = np.where(total > 0, total, 1.0)
    coarse = np.einsum("tpi,tpi->ti", weights, np.where(usable[..., None], points, 0.0)) / safe_total
    coarse_variance = 1.0 / safe_total
    coarse = np.where(has_pair[:, None], coarse, 0.0)

    constrained = problem.altitude_m is not None
    if constrained:
        coarse_on = problem.frame.onto_altitude(coarse, problem.altitude_m)
    else:
        coarse_on = coarse
    rows = np.flatnonzero((problem.kinds == Kind.AZIMUTH) | (problem.kinds == Kind.ELEVATION))
    s = problem.station_index[rows]
    stations, rotations = problem.stations_enu_m[s], problem.station_rotations[s]
    kinds = np.broadcast_to(problem.kinds[rows], (trials, rows.size))
    sigma = problem.sigmas[rows]
    measured = values[:, rows]
    bias = np.zeros(trials)

    predicted, _ = predict(coarse_on, bias, stations, rotations, kinds)
    normalised = np.abs(residuals(measured, predicted, kinds)) / sigma
    worst = np.argmax(normalised, axis=-1)
    ratio = normalised[np.arange(trials), worst]
    line = problem.bearing_index[rows][worst]
    moved = has_pair & (ratio >= REFERENCE_RATIO_LIMIT)
    if np.any(moved):
        origin = los.origins_enu_m[line]
        distance = np.linalg.norm(coarse_on - origin, axis=-1)
        seen = np.einsum("tij,tj->ti", los.rotations[line], coarse_on - origin)
        seen_elevation = np.arctan2(seen[:, 2], np.hypot(seen[:, 0], seen[:, 1]))
        line_elevation = np.where(los.has_elevation[line], elevation[np.arange(trials), line], seen_elevation)
        direction, _, _ = line_of_sight_derivatives(azimuth[np.arange(trials), line], line_elevation,
                                                    los.rotations[line])
        reference = np.where(moved[:, None], origin + distance[:, None] * direction, coarse_on)
        if constrained:
            reference = problem.frame.onto_altitude(reference, problem.altitude_m)
    else:
        reference = coarse_on

    predicted, jac = predict(reference, bias, stations, rotations, kinds)
    delta_z = residuals(measured, predicted, kinds)
    altitude = np.full(trials, np.nan if problem.altitude_m is None else problem.altitude_m)
    origin = np.broadcast_to(problem.frame.origin_array(), (trials, 3))
    geodetic = np.full(trials, problem.frame.is_geodetic)
    axes, free = parameterisation(reference, altitude, np.zeros(trials, dtype=bool), origin, geodetic)
    w = np.broadcast_to(1.0 / sigma**2, (trials, rows.size))
    information, local_jacobian = normal_matrix(np.swapaxes(jac, -1, -2), w, axes, free)
    inverse = invert_information(information, axes, free)
    gradient = np.einsum("tim,tm,tm->ti", local_jacobian, w, delta_z)
    step = np.einsum("tij,tj->ti", inverse.covariance_params, gradient)
    position = reference + (step[:, :3] if axes is None else np.einsum("ti,tij->tj", step[:, :3], axes))
    if constrained:
        position = problem.frame.onto_altitude(position, problem.altitude_m)

    valid = has_pair & inverse.observable & np.all(np.isfinite(position), axis=-1)
    return IntersectionBatch(
        position_enu_m=np.where(valid[:, None], position, np.nan),
        covariance_enu_m2=inverse.covariance_enu_m2,
        coarse_position_enu_m=np.where(has_pair[:, None], coarse, np.nan),
        coarse_variance_enu_m2=np.where(has_pair[:, None], coarse_variance, np.nan),
        reference_enu_m=reference,
        reference_ratio=ratio,
        reference_line=line,
        moved=moved,
        pairs_used=np.count_nonzero(usable, axis=-1),
        pairs_total=int(first.size),
        valid=valid,
    )


def _line_of_sight_intersection(problem: Problem, options: SolveOptions) -> Estimate:
    """Fix by the common-perpendicular method (:func:`intersect_lines_of_sight` with ``T = 1``).

    The covariance is the extended-WLS ``(K^T R^-1 K)^-1`` at the
    linearisation point; ``coarse_position_enu_m`` is ``X_s``, the pairs'
    combined point before that pass.

    Raises
    ------
    TooFewMeasurements
        Fewer than 2 stations give a bearing with elevation.
    UnobservableGeometry
        Every pair of lines is parallel (or starts at one point), or the
        angles do not determine the position at the reference point.
    """
    result = intersect_lines_of_sight(problem)
    if result.pairs_used[0] == 0:
        raise UnobservableGeometry(
            f"los_intersection: all {result.pairs_total} pair(s) of lines of sight are parallel, "
            "so no common perpendicular defines a point")
    if not result.valid[0]:
        raise UnobservableGeometry(
            "los_intersection: the angles do not determine the position at the reference point "
            "(singular extended-WLS normal matrix)")
    los = problem.lines_of_sight()
    line = int(result.reference_line[0])
    station = problem.station_ids[los.station_index[line]]
    warnings = []
    if result.moved[0]:
        warnings.append(FixWarning(
            "reference_point_moved",
            f"R_p = {result.reference_ratio[0]:.1f} >= {REFERENCE_RATIO_LIMIT:g} at station {station}: "
            "linearised on its line of sight at the same distance"))
    details = {
        "pairs_used": int(result.pairs_used[0]),
        "pairs_total": result.pairs_total,
        "reference_ratio": float(result.reference_ratio[0]),
        "reference_station": station if result.moved[0] else None,
        "ignored_measurements": int(np.count_nonzero((problem.kinds == Kind.RANGE) | (problem.kinds == Kind.TOA))),
    }
    return Estimate(result.position_enu_m[0], result.covariance_enu_m2[0], iterations=1, warnings=tuple(warnings),
                    coarse_position_enu_m=result.coarse_position_enu_m[0], details=details)


register("los_intersection",
         "common-perpendicular line-of-sight intersection, pairwise WLS fusion and an extended-WLS pass (paper 002)")(
    per_problem(_line_of_sight_intersection, "propagated"))
