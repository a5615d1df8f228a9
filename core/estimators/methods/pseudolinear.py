"""3D pseudolinear estimator (PLE) and weighted Stansfield in 3D (WS3D), the paper-000 baselines.

Both extend a 2D bearing method to 3D in two stages (ALGORITHMS.md section 4):

1. the horizontal position from the azimuth planes alone,
   ``n_i . p = n_i . r_i`` (the ``c'`` rows of paper 000), solved by least
   squares for east and north at the current height;
2. the height from each station's elevation: the point of station i's line of
   sight at the horizontal distance (in the station's own frame) of the
   stage-1 point has the height ``z_i``, about ``z_s + tan(el_i) d_i``; the
   height is their mean (PLE, Dogancay & Ibal 2005) or their inverse-variance
   mean with weights ``cos^4(el_i) / (sigma_el^2 d_i^2)`` (WS3D, Adib &
   Douglas 2018 as rendered in ALGORITHMS.md), where WS3D also weights the
   horizontal rows by ``1 / (sigma_az^2 d_i^2)`` with ``d_i`` from a PLE pass.

On the ellipsoid a station's vertical is not the common frame's, so the two
stages are repeated a fixed number of times; this converges to the exact
point for noise-free data (each pass shrinks the error by about the stations'
spread over the earth radius times tan(el)). A known target altitude replaces
stage 2 (the elevations are then not used).

Both fail, by construction, when the azimuth lines are parallel in the
horizontal plane (target above a straight station track): they refuse the
problem with :class:`~core.errors.UnobservableGeometry` saying so, using the
test of :func:`core.estimators.azimuth_lines.crossing_errors`.

Covariance: first-order propagation of the angle noise through the whole
two-stage computation (weights and passes included), ``C = G diag(sigma^2) G^T``
with ``G = d position / d angles`` carried exactly alongside the passes
(forward-mode differentiation; the foot on a known altitude surface is
differentiated by central differences of 10 m, which the surface's curvature
makes exact to about 1e-12).

The passes run one problem at a time in a compiled kernel (the lines of
sight and their derivatives are a few dozen numbers: numpy's call overhead
over the batch cost ws3d about 20 us a problem), the same code for a problem
alone and in any batch.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from core.errors import LocalizationError, TooFewMeasurements
from core.estimators.azimuth_lines import Lines, azimuth_directions_point, crossing_errors, has_elevations
from core.estimators.base import ANGLES, SolveOptions, register
from core.estimators.result import Estimates
from core.linalg import gram_point
from core.problem.batch import ProblemBatch
from core.problem.frame import frame_placements, onto_altitude_point

#: Horizontal/height passes; fixed so that the estimator is one smooth map of the data.
PASSES = 6
#: Step (m) of the central differences of the foot on the altitude surface.
FOOT_STEP_M = 10.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _horizontal_point(position, origins, rotations, horizontal, gradient):
    """Horizontal distance ``(n,)`` of a point ``(3,)`` from each line's station (its frame), and its
    gradient ``(n, 3)``, into ``horizontal`` and ``gradient``."""
    for k in range(origins.shape[0]):
        east = north = 0.0
        for i in range(3):
            delta = position[i] - origins[k, i]
            east += rotations[k, 0, i] * delta
            north += rotations[k, 1, i] * delta
        horizontal[k] = math.hypot(east, north)
        safe = horizontal[k] if horizontal[k] > 0 else 1.0
        for i in range(3):
            gradient[k, i] = (east * rotations[k, 0, i] + north * rotations[k, 1, i]) / safe


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _foot_up(point, altitude_m, geodetic, origin_ecef_m, origin_rotation):
    """The up coordinate of ``point``'s foot on the altitude surface."""
    foot = point.copy()
    onto_altitude_point(foot, altitude_m, geodetic, origin_ecef_m, origin_rotation)
    return foot[2]


class LinesOfSight(NamedTuple):
    """One problem's ``n`` lines of sight (a slice of :class:`core.estimators.azimuth_lines.Lines`).

    Attributes
    ----------
    origins_enu_m : ndarray, shape (n, 3)
    rotations : ndarray, shape (n, 3, 3)
        Station ENU <- common ENU.
    azimuth_rad, elevation_rad : ndarray, shape (n,)
    has_elevation : ndarray of bool, shape (n,)
    """

    origins_enu_m: np.ndarray
    rotations: np.ndarray
    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    has_elevation: np.ndarray


class AltitudeSurface(NamedTuple):
    """The known target altitude of one problem and its frame's placement (:func:`core.problem.frame.frame_placements`).

    Attributes
    ----------
    altitude_m : float
        NaN where the height comes from the elevations.
    geodetic : bool
    origin_ecef_m : ndarray, shape (3,)
    origin_rotation : ndarray, shape (3, 3)
    """

    altitude_m: float
    geodetic: bool
    origin_ecef_m: np.ndarray
    origin_rotation: np.ndarray


class StageWeights(NamedTuple):
    """The two stages' row weights and their derivatives w.r.t. the ``P = 2n`` angles.

    Attributes
    ----------
    horizontal, height : ndarray, shape (n,)
        Horizontal and height weights (heights: zero on lines without elevation).
    d_horizontal, d_height : ndarray, shape (n, P)
        Their derivatives, used when ``weighted``.
    weighted : bool
    """

    horizontal: np.ndarray
    d_horizontal: np.ndarray
    height: np.ndarray
    d_height: np.ndarray
    weighted: bool


class StageFix(NamedTuple):
    """The two stages' fixed point and its derivatives w.r.t. the ``P = 2n`` angles (written by
    :func:`_stages_point`).

    Attributes
    ----------
    position : ndarray, shape (3,)
        ENU (m).
    d_position : ndarray, shape (3, P)
    horizontal : ndarray, shape (n,)
        Horizontal distance (m) of the fix from each line's station, in the station's frame.
    d_horizontal : ndarray, shape (n, P)
    """

    position: np.ndarray
    d_position: np.ndarray
    horizontal: np.ndarray
    d_horizontal: np.ndarray


class PlaneRows(NamedTuple):
    """Each line's azimuth plane ``n_k . p = rhs_k`` and line-of-sight height slope (:func:`_plane_rows`).

    Attributes
    ----------
    normals, along : ndarray, shape (n, 3)
        ``n_k`` and the horizontal line-of-sight direction ``h_k`` (``d n_k / d az_k = -h_k``), common frame.
    rhs, along_rhs : ndarray, shape (n,)
        ``n_k . r_k`` and ``h_k . r_k`` (m).
    slope : ndarray, shape (n,)
        Height gained per metre of horizontal distance along the line of sight.
    d_slope_az, d_slope_el : ndarray, shape (n,)
        Its derivatives w.r.t. the line's azimuth and elevation.
    """

    normals: np.ndarray
    along: np.ndarray
    rhs: np.ndarray
    along_rhs: np.ndarray
    slope: np.ndarray
    d_slope_az: np.ndarray
    d_slope_el: np.ndarray


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _plane_rows(lines):
    """The :class:`PlaneRows` of a problem's lines of sight."""
    origins, rotations = lines.origins_enu_m, lines.rotations
    azimuth, elevation, has_elevation = lines.azimuth_rad, lines.elevation_rad, lines.has_elevation
    n = origins.shape[0]
    normals = np.empty((n, 3))
    along = np.empty((n, 3))
    rhs, along_rhs = np.empty(n), np.empty(n)
    slope, d_slope_az, d_slope_el = np.empty(n), np.empty(n), np.empty(n)
    for k in range(n):
        azimuth_directions_point(azimuth[k], rotations[k], normals[k], along[k])
        c, s = math.cos(azimuth[k]), math.sin(azimuth[k])
        rhs[k] = along_rhs[k] = 0.0
        for i in range(3):
            rhs[k] += normals[k, i] * origins[k, i]
            along_rhs[k] += along[k, i] * origins[k, i]
        slope[k] = rotations[k, 0, 2] * s + rotations[k, 1, 2] * c + rotations[k, 2, 2] * math.tan(elevation[k])
        d_slope_az[k] = rotations[k, 0, 2] * c - rotations[k, 1, 2] * s
        d_slope_el[k] = rotations[k, 2, 2] / math.cos(elevation[k]) ** 2 if has_elevation[k] else 0.0
    return PlaneRows(normals, along, rhs, along_rhs, slope, d_slope_az, d_slope_el)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _horizontal_normal(normals, along, hw, dhw, weighted):
    """Stage 1's weighted normal matrix ``G = [[g00, g01], [g01, g11]]`` of the east/north columns, the up
    column's products ``c0, c1`` and the derivatives ``dg00, dg01, dg11`` ``(P,)`` of ``G`` w.r.t. the angles
    (``hw``, ``dhw``: the horizontal weights, :class:`StageWeights`)."""
    n = normals.shape[0]
    p_count = 2 * n
    g00 = g01 = g11 = c0 = c1 = 0.0
    dg00, dg01, dg11 = np.zeros(p_count), np.zeros(p_count), np.zeros(p_count)
    for k in range(n):
        n0, n1, n2, h0, h1 = normals[k, 0], normals[k, 1], normals[k, 2], along[k, 0], along[k, 1]
        hw2 = hw[k] * hw[k]
        g00 += n0 * n0 * hw2
        g01 += n0 * n1 * hw2
        g11 += n1 * n1 * hw2
        c0 += n0 * n2 * hw2
        c1 += n1 * n2 * hw2
        dg00[k] = -2 * h0 * n0 * hw2
        dg01[k] = -(h0 * n1 + n0 * h1) * hw2
        dg11[k] = -2 * h1 * n1 * hw2
    if weighted:
        for p in range(p_count):
            for k in range(n):
                n0, n1 = normals[k, 0], normals[k, 1]
                dg00[p] += 2 * n0 * n0 * hw[k] * dhw[k, p]
                dg01[p] += 2 * n0 * n1 * hw[k] * dhw[k, p]
                dg11[p] += 2 * n1 * n1 * hw[k] * dhw[k, p]
    return (g00, g01, g11), (c0, c1), (dg00, dg01, dg11)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _foot_gradient(point, altitude_m, geodetic, origin_ecef_m, origin_rotation, out):
    """The gradient ``(3,)`` of the foot's up coordinate w.r.t. ``point``, by central differences of
    ``FOOT_STEP_M`` (exact to about 1e-12 on the ellipsoid's curvature), into ``out``."""
    for i in range(3):
        shifted = point.copy()
        shifted[i] = point[i] + FOOT_STEP_M
        high = _foot_up(shifted, altitude_m, geodetic, origin_ecef_m, origin_rotation)
        shifted[i] = point[i] - FOOT_STEP_M
        low = _foot_up(shifted, altitude_m, geodetic, origin_ecef_m, origin_rotation)
        out[i] = (high - low) / (2 * FOOT_STEP_M)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _stages_point(lines, weights, surface, fix):
    """Run one problem's two stages to their fixed point, with the derivatives w.r.t. every angle.

    The angles are ``P = 2n`` parameters: each line's azimuth, then each line's elevation; a term of line
    k that depends on its own angle only lands in that angle's slot.

    Parameters
    ----------
    lines : LinesOfSight
    weights : StageWeights
    surface : AltitudeSurface
        A known altitude replaces stage 2.
    fix : StageFix
        Written.
    """
    origins, rotations = lines.origins_enu_m, lines.rotations
    hw, dhw, weighted = weights.horizontal, weights.d_horizontal, weights.weighted
    vw, dvw = weights.height, weights.d_height
    altitude_m, geodetic = surface.altitude_m, surface.geodetic
    origin_ecef_m, origin_rotation = surface.origin_ecef_m, surface.origin_rotation
    d_position, horizontal = fix.d_position, fix.horizontal
    n = origins.shape[0]
    p_count = 2 * n
    constrained = not math.isnan(altitude_m)
    rows = _plane_rows(lines)
    normals, along, rhs, along_rhs = rows.normals, rows.along, rows.rhs, rows.along_rhs
    slope, d_slope_az, d_slope_el = rows.slope, rows.d_slope_az, rows.d_slope_el
    (g00, g01, g11), (c0, c1), (dg00, dg01, dg11) = _horizontal_normal(normals, along, hw, dhw, weighted)
    inverse_det = 1.0 / (g00 * g11 - g01 * g01)
    if constrained:
        up = altitude_m
    else:
        up = 0.0
        for k in range(n):
            up += origins[k, 2]
        up /= max(n, 1)
    d_up = np.zeros(p_count)
    vw_total = 0.0
    for k in range(n):
        vw_total += vw[k]
    if not vw_total > 0:
        vw_total = 1.0
    d_right0, d_right1 = np.empty(p_count), np.empty(p_count)
    residual = np.empty(n)
    heights = np.empty(n)
    gradient = np.empty((n, 3))
    point = np.empty(3)
    foot_gradient = np.empty(3)
    east = north = 0.0
    for _ in range(PASSES):
        # Stage 1: the horizontal least squares at the current height, and its derivatives.
        right0 = right1 = 0.0
        d_right0[:] = 0.0
        d_right1[:] = 0.0
        for k in range(n):
            residual[k] = rhs[k] - normals[k, 2] * up
            data = residual[k] * hw[k]
            own = (along[k, 2] * up - along_rhs[k]) * hw[k]
            right0 += normals[k, 0] * hw[k] * data
            right1 += normals[k, 1] * hw[k] * data
            d_right0[k] = -along[k, 0] * hw[k] * data + normals[k, 0] * hw[k] * own
            d_right1[k] = -along[k, 1] * hw[k] * data + normals[k, 1] * hw[k] * own
        for p in range(p_count):
            d_right0[p] -= c0 * d_up[p]
            d_right1[p] -= c1 * d_up[p]
            if weighted:
                for k in range(n):
                    d_right0[p] += 2 * normals[k, 0] * residual[k] * hw[k] * dhw[k, p]
                    d_right1[p] += 2 * normals[k, 1] * residual[k] * hw[k] * dhw[k, p]
        east = (g11 * right0 - g01 * right1) * inverse_det
        north = (g00 * right1 - g01 * right0) * inverse_det
        for p in range(p_count):
            r0 = d_right0[p] - dg00[p] * east - dg01[p] * north
            r1 = d_right1[p] - dg01[p] * east - dg11[p] * north
            d_position[0, p] = (g11 * r0 - g01 * r1) * inverse_det
            d_position[1, p] = (g00 * r1 - g01 * r0) * inverse_det
            d_position[2, p] = d_up[p]
        point[0], point[1], point[2] = east, north, up
        # Stage 2: the height, on the known altitude surface or from the elevations.
        if constrained:
            up = _foot_up(point, altitude_m, geodetic, origin_ecef_m, origin_rotation)
            _foot_gradient(point, altitude_m, geodetic, origin_ecef_m, origin_rotation, foot_gradient)
            for p in range(p_count):
                d_up[p] = (foot_gradient[0] * d_position[0, p] + foot_gradient[1] * d_position[1, p]
                           + foot_gradient[2] * d_position[2, p])
        else:
            # The (weighted) mean of each line of sight's height at the point's horizontal distance.
            _horizontal_point(point, origins, rotations, horizontal, gradient)
            new_up = 0.0
            toward = np.zeros(3)
            for k in range(n):
                heights[k] = origins[k, 2] + horizontal[k] * slope[k]
                new_up += vw[k] * heights[k]
                for i in range(3):
                    toward[i] += vw[k] * slope[k] * gradient[k, i]
            new_up /= vw_total
            for p in range(p_count):
                d_new_up = toward[0] * d_position[0, p] + toward[1] * d_position[1, p] + toward[2] * d_position[2, p]
                if p < n:
                    d_new_up += vw[p] * horizontal[p] * d_slope_az[p]
                else:
                    d_new_up += vw[p - n] * horizontal[p - n] * d_slope_el[p - n]
                if weighted:
                    for k in range(n):
                        d_new_up += (heights[k] - new_up) * dvw[k, p]
                d_up[p] = d_new_up / vw_total
            up = new_up
    _fix_at(east, north, up, d_up, origins, rotations, fix, gradient)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fix_at(east, north, up, d_up, origins, rotations, fix, gradient):
    """Write the fixed point into ``fix``: its position, the up row of its derivatives, and the horizontal
    distances from the stations with their derivatives (``gradient`` ``(n, 3)`` is scratch)."""
    position, d_position, horizontal, d_horizontal = fix.position, fix.d_position, fix.horizontal, fix.d_horizontal
    p_count = d_position.shape[1]
    position[0], position[1], position[2] = east, north, up
    for p in range(p_count):
        d_position[2, p] = d_up[p]
    _horizontal_point(position, origins, rotations, horizontal, gradient)
    for k in range(origins.shape[0]):
        for p in range(p_count):
            d_horizontal[k, p] = (gradient[k, 0] * d_position[0, p] + gradient[k, 1] * d_position[1, p]
                                  + gradient[k, 2] * d_position[2, p])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _first_order_weights(lines, sigma_azimuth, sigma_elevation, fix):
    """WS3D's :class:`StageWeights` from a PLE pass ``fix``: ``1 / (sigma_az d)`` horizontally and
    ``cos^4(el) / (sigma_el d)^2`` for the heights (``d`` the horizontal distance), with their derivatives."""
    elevation, has_elevation = lines.elevation_rad, lines.has_elevation
    horizontal, d_horizontal = fix.horizontal, fix.d_horizontal
    n = elevation.size
    p_count = 2 * n
    hw, vw = np.empty(n), np.empty(n)
    dhw, dvw = np.empty((n, p_count)), np.empty((n, p_count))
    for k in range(n):
        near = horizontal[k] < 1e-9
        distance = 1e-9 if near else horizontal[k]
        hw[k] = 1.0 / (sigma_azimuth[k] * distance)
        cos_el = math.cos(elevation[k])
        vw[k] = (1.0 if has_elevation[k] else 0.0) * cos_el**4 / (sigma_elevation[k] * distance) ** 2
        for p in range(p_count):
            d_distance = 0.0 if near else d_horizontal[k, p]
            dhw[k, p] = -(hw[k] / distance) * d_distance
            dvw[k, p] = -(2 * vw[k] / distance) * d_distance
        dvw[k, n + k] -= 4 * math.tan(elevation[k]) * vw[k]
    return StageWeights(hw, dhw, vw, dvw, True)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pseudolinear_point(lines, sigma_azimuth, sigma_elevation, surface, weighted, position, covariance):
    """One problem's PLE (or, ``weighted``, WS3D) position ``(3,)`` and first-order covariance ``(3, 3)``."""
    n = lines.azimuth_rad.size
    p_count = 2 * n
    has_elevation = lines.has_elevation
    height_ones = np.zeros(n)
    for k in range(n):
        if has_elevation[k]:
            height_ones[k] = 1.0
    constant = np.zeros((n, p_count))  # the first pass's weights do not depend on the angles
    fix = StageFix(position, np.empty((3, p_count)), np.empty(n), np.empty((n, p_count)))
    _stages_point(lines, StageWeights(np.ones(n), constant, height_ones, constant, False), surface, fix)
    if weighted:
        _stages_point(lines, _first_order_weights(lines, sigma_azimuth, sigma_elevation, fix), surface, fix)
    variance = np.empty(p_count)
    constrained = not math.isnan(surface.altitude_m)
    for k in range(n):
        variance[k] = sigma_azimuth[k] ** 2
        variance[n + k] = sigma_elevation[k] ** 2 if has_elevation[k] and not constrained else 0.0
    gram_point(fix.d_position, variance, covariance)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pseudolinear_kernel(count, origins, rotations, azimuth, elevation, has_elevation, sigma_azimuth,
                         sigma_elevation, altitude_m, geodetic, origin_ecef_m, origin_rotation, weighted, position,
                         covariance):
    """PLE or WS3D positions and covariances of every problem (see :func:`pseudolinear_positions`):
    :class:`core.estimators.azimuth_lines.Lines`' arrays and the frames' placements, named per problem here
    (:class:`LinesOfSight`, :class:`AltitudeSurface`). Flat at this boundary because numba types a
    named-tuple argument in Python, which costs more than a problem's solution."""
    for b in range(count.size):
        n = count[b]
        lines = LinesOfSight(origins[b, :n], rotations[b, :n], azimuth[b, :n], elevation[b, :n], has_elevation[b, :n])
        surface = AltitudeSurface(altitude_m[b], geodetic[b], origin_ecef_m[b], origin_rotation[b])
        _pseudolinear_point(lines, sigma_azimuth[b, :n], sigma_elevation[b, :n], surface, weighted, position[b],
                            covariance[b])


def pseudolinear_positions(lines: Lines, weighted: bool):
    """Positions of PLE (``weighted=False``) or WS3D (``weighted=True``) and their first-order covariances.

    Parameters
    ----------
    lines : Lines
        Problems that pass :func:`_refusals`.
    weighted : bool

    Returns
    -------
    position_enu_m : ndarray, shape (B, 3)
    covariance_enu_m2 : ndarray, shape (B, 3, 3)
    """
    size = lines.mask.shape[0]
    position = np.full((size, 3), np.nan)
    covariance = np.full((size, 3, 3), np.nan)
    origin_ecef_m, origin_rotation = frame_placements(lines.origin)
    _pseudolinear_kernel(lines.count, np.ascontiguousarray(lines.origins_enu_m),
                         np.ascontiguousarray(lines.rotations), np.ascontiguousarray(lines.azimuth_rad),
                         np.ascontiguousarray(lines.elevation_rad), np.ascontiguousarray(lines.has_elevation),
                         np.ascontiguousarray(lines.sigma_azimuth_rad), np.ascontiguousarray(lines.sigma_elevation_rad),
                         np.ascontiguousarray(lines.altitude_m, dtype=float), np.ascontiguousarray(lines.geodetic),
                         np.ascontiguousarray(origin_ecef_m), np.ascontiguousarray(origin_rotation), weighted,
                         position, covariance)
    return position, covariance


def _refusals(lines: Lines, name: str) -> dict[int, LocalizationError]:
    errors = crossing_errors(lines, name)
    for b in np.flatnonzero(~lines.constrained & ~np.any(lines.has_elevation, axis=-1)).tolist():
        errors.setdefault(b, TooFewMeasurements(
            f"{name} takes the height from elevations: give an elevation on at least one line of sight, "
            "or the target altitude (constraints.altitude_m)", ("measurements",)))
    return errors


def _estimate(batch: ProblemBatch, name: str, weighted: bool) -> Estimates:
    lines = Lines.of(batch)
    errors = _refusals(lines, name)
    size = batch.size
    position = np.full((size, 3), np.nan)
    covariance = np.full((size, 3, 3), np.nan)
    ok = np.ones(size, dtype=bool)
    ok[list(errors)] = False
    rows = np.flatnonzero(ok)
    if rows.size:
        position[rows], covariance[rows] = pseudolinear_positions(lines.take(rows), weighted)
    unused = batch.constrained & has_elevations(batch)
    details = [{"passes": PASSES, **({"unused_measurements": "elevations: the known altitude gives the height"}
                                    if unused[b] else {})} for b in range(size)]
    return Estimates(position_enu_m=position, covariance_source="propagated", covariance_enu_m2=covariance,
                     errors=errors, details=details)


@register("ple3d", "3D pseudolinear estimator: horizontal Stansfield from azimuths, then mean height from "
                   "elevations; fails above a straight station track", uses=ANGLES)
def ple3d(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """3D PLE (Dogancay & Ibal 2005); see the module docstring."""
    return _estimate(batch, "ple3d", weighted=False)


@register("ws3d", "weighted Stansfield in 3D: PLE with inverse-variance weights from a first pass; "
                  "fails above a straight station track", uses=ANGLES)
def ws3d(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """WS3D (Adib & Douglas 2018, as rendered in ALGORITHMS.md); see the module docstring."""
    return _estimate(batch, "ws3d", weighted=True)
