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

Every problem of a batch runs at once: the passes are a fixed number of
vectorised steps over the batch.
"""

from __future__ import annotations

import numpy as np

from core.errors import LocalizationError, TooFewMeasurements
from core.estimators.azimuth_lines import Lines, azimuth_normals, crossing_errors, has_elevations, solve_2x2
from core.estimators.base import ANGLES, SolveOptions, register
from core.estimators.result import Estimates
from core.linalg import row_sums, weighted_gram
from core.problem_batch import ProblemBatch

#: Horizontal/height passes; fixed so that the estimator is one smooth map of the data.
PASSES = 6
#: Step (m) of the central differences of the foot on the altitude surface.
FOOT_STEP_M = 10.0


def _foot_gradient(lines: Lines, candidate_enu_m) -> np.ndarray:
    """Gradient ``(B, 3)`` of the up coordinate of the foot on the altitude surface w.r.t. the point."""
    offsets = FOOT_STEP_M * np.concatenate([np.eye(3), -np.eye(3)])
    feet = lines.onto_altitude(candidate_enu_m[:, None, :] + offsets)[..., 2]
    return (feet[:, :3] - feet[:, 3:]) / (2 * FOOT_STEP_M)


def _stages(lines: Lines, horizontal_weights, d_horizontal_weights, height_weights, d_height_weights):
    """Run the two stages to their fixed point, with the derivatives w.r.t. every angle.

    The angles are ``P = 2K`` parameters: each line's azimuth, then each
    line's elevation. A term of line k that depends on its own angle only
    lands in that angle's slot directly, so a pass works on ``(B, K)`` and
    ``(B, P)`` arrays.

    Parameters
    ----------
    lines : Lines
    horizontal_weights, height_weights : ndarray, shape (B, K)
        Zero on padding (and, for heights, on lines without elevation).
    d_horizontal_weights, d_height_weights : ndarray, shape (B, K, P), or None
        None where the weights do not depend on the angles.

    Returns
    -------
    position_enu_m : ndarray, shape (B, 3)
    d_position : ndarray, shape (B, 3, P)
    horizontal_m : ndarray, shape (B, K)
        Horizontal distance of the fix from each line's station, in the station's frame.
    d_horizontal : ndarray, shape (B, K, P)
    """
    size, k = lines.mask.shape
    zeros = np.zeros((size, k))

    def slots(azimuth_part, elevation_part=zeros):
        return np.concatenate([azimuth_part, elevation_part], axis=-1)

    rotations, origins = lines.rotations, lines.origins_enu_m
    az, el = lines.azimuth_rad, lines.elevation_rad
    sin_az, cos_az = np.sin(az), np.cos(az)
    normals, along = azimuth_normals(lines)
    n0, n1, n2 = normals[..., 0], normals[..., 1], normals[..., 2]
    h0, h1, h2 = along[..., 0], along[..., 1], along[..., 2]
    rhs = np.sum(normals * origins, axis=-1)
    along_rhs = np.sum(along * origins, axis=-1)
    hw, dhw = horizontal_weights, d_horizontal_weights
    hw2 = hw * hw
    g00, g01, g11 = row_sums(n0 * n0 * hw2), row_sums(n0 * n1 * hw2), row_sums(n1 * n1 * hw2)
    gram = np.stack([np.stack([g00, g01], -1), np.stack([g01, g11], -1)], -2)
    dg00, dg01, dg11 = slots(-2 * h0 * n0 * hw2), slots(-(h0 * n1 + n0 * h1) * hw2), slots(-2 * h1 * n1 * hw2)
    if dhw is not None:
        dg00 = dg00 + _contract(2 * n0 * n0 * hw, dhw)
        dg01 = dg01 + _contract(2 * n0 * n1 * hw, dhw)
        dg11 = dg11 + _contract(2 * n1 * n1 * hw, dhw)
    c0, c1 = row_sums(n0 * n2 * hw2), row_sums(n1 * n2 * hw2)

    constrained = lines.constrained
    free = ~constrained
    up = np.where(constrained, lines.altitude_m, lines.mean_origin()[:, 2])
    d_up = np.zeros((size, 2 * k))
    # stage 2's heights: z_s + d_i (R_i^T [sin az, cos az, tan el])_z
    slope = rotations[..., 0, 2] * sin_az + rotations[..., 1, 2] * cos_az + rotations[..., 2, 2] * np.tan(el)
    d_slope_az = rotations[..., 0, 2] * cos_az - rotations[..., 1, 2] * sin_az
    d_slope_el = rotations[..., 2, 2] / np.cos(el) ** 2 * lines.has_elevation
    vw, dvw = height_weights, d_height_weights
    vw_total = row_sums(vw)
    vw_total = np.where(vw_total > 0, vw_total, 1.0)
    foot_rows = np.flatnonzero(constrained)
    foot_lines = lines.take(foot_rows) if foot_rows.size else None
    any_free = bool(np.any(free))
    for _ in range(PASSES):
        residual = rhs - n2 * up[:, None]
        data = residual * hw
        own = (h2 * up[:, None] - along_rhs) * hw
        right0, right1 = row_sums(n0 * hw * data), row_sums(n1 * hw * data)
        d_right0 = slots(-h0 * hw * data + n0 * hw * own) - c0[:, None] * d_up
        d_right1 = slots(-h1 * hw * data + n1 * hw * own) - c1[:, None] * d_up
        if dhw is not None:
            d_right0 = d_right0 + _contract(2 * n0 * residual * hw, dhw)
            d_right1 = d_right1 + _contract(2 * n1 * residual * hw, dhw)
        east_north = solve_2x2(gram, np.stack([right0, right1], -1))
        east, north = east_north[:, 0, None], east_north[:, 1, None]
        d_east_north = solve_2x2(gram, np.stack([d_right0 - dg00 * east - dg01 * north,
                                                 d_right1 - dg01 * east - dg11 * north], 1))
        candidate = np.concatenate([east_north, up[:, None]], axis=-1)
        d_candidate = np.concatenate([d_east_north, d_up[:, None, :]], axis=1)
        if any_free:
            horizontal, gradient = _horizontal(lines, candidate)
            heights = origins[..., 2] + horizontal * slope
            new_up = row_sums(vw * heights) / vw_total
            toward = row_sums(np.swapaxes((vw * slope)[..., None] * gradient, 1, 2))
            d_new_up = (np.einsum("bi,bip->bp", toward, d_candidate)
                        + slots(vw * horizontal * d_slope_az, vw * horizontal * d_slope_el))
            if dvw is not None:
                d_new_up = d_new_up + _contract(heights - new_up[:, None], dvw)
            up = np.where(free, new_up, up)
            d_up = np.where(free[:, None], d_new_up / vw_total[:, None], d_up)
        if foot_lines is not None:
            c = candidate[foot_rows]
            up[foot_rows] = foot_lines.onto_altitude(c)[:, 2]
            d_up[foot_rows] = np.einsum("bi,bip->bp", _foot_gradient(foot_lines, c), d_candidate[foot_rows])
    position = np.concatenate([east_north, up[:, None]], axis=-1)
    d_position = np.concatenate([d_east_north, d_up[:, None, :]], axis=1)
    horizontal, gradient = _horizontal(lines, position)
    return position, d_position, horizontal, np.matmul(gradient, d_position)


def _contract(per_line, d_per_line):
    """``sum_k x_k dy_k`` ``(B, P)`` of ``x`` ``(B, K)`` and ``dy`` ``(B, K, P)``, added in line order (so
    that padding lines change no bit)."""
    return row_sums(np.swapaxes(per_line[..., None] * d_per_line, 1, 2))


def _horizontal(lines: Lines, position_enu_m):
    """Horizontal distance ``(B, K)`` of points from each line's station (its frame) and its gradient ``(B, K, 3)``."""
    delta = position_enu_m[:, None, :] - lines.origins_enu_m
    rotations = lines.rotations
    east = np.sum(rotations[..., 0, :] * delta, axis=-1)
    north = np.sum(rotations[..., 1, :] * delta, axis=-1)
    horizontal = np.hypot(east, north)
    safe = np.where(horizontal > 0, horizontal, 1.0)[..., None]
    return horizontal, (east[..., None] * rotations[..., 0, :] + north[..., None] * rotations[..., 1, :]) / safe


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
    mask = lines.mask
    size, k = mask.shape
    ones = mask.astype(float)
    height_ones = ones * lines.has_elevation
    position, d_position, horizontal, d_horizontal = _stages(lines, ones, None, height_ones, None)
    if weighted:
        near = horizontal < 1e-9
        distance = np.where(near, 1e-9, horizontal)
        d_distance = np.where(near[..., None], 0.0, d_horizontal)
        hw = ones / (lines.sigma_azimuth_rad * distance)
        dhw = -(hw / distance)[..., None] * d_distance
        cos_el = np.cos(lines.elevation_rad)
        vw = height_ones * cos_el**4 / (lines.sigma_elevation_rad * distance) ** 2
        own_el = np.concatenate([np.zeros((k, k)), np.eye(k)], axis=1)
        dvw = -(2 * vw / distance)[..., None] * d_distance - (4 * np.tan(lines.elevation_rad) * vw)[..., None] * own_el
        position, d_position, _, _ = _stages(lines, hw, dhw, vw, dvw)
    elevation_variance = np.where(lines.has_elevation & ~lines.constrained[:, None], lines.sigma_elevation_rad**2, 0)
    variance = np.concatenate([np.where(mask, lines.sigma_azimuth_rad**2, 0.0), elevation_variance], axis=-1)
    covariance = weighted_gram(d_position, variance)
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
