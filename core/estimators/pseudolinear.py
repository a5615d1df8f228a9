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

from core.batch import ProblemBatch
from core.errors import LocalizationError, TooFewMeasurements
from core.estimators.azimuth_lines import Lines, azimuth_normals, crossing_errors, has_elevations, solve_2x2
from core.estimators.base import SolveOptions, register
from core.estimators.result import Estimates

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
    line's elevation.

    Parameters
    ----------
    lines : Lines
    horizontal_weights, height_weights : ndarray, shape (B, K)
        Zero on padding (and, for heights, on lines without elevation).
    d_horizontal_weights, d_height_weights : ndarray, shape (B, K, P)

    Returns
    -------
    position_enu_m : ndarray, shape (B, 3)
    d_position : ndarray, shape (B, 3, P)
    horizontal_m : ndarray, shape (B, K)
        Horizontal distance of the fix from each line's station, in the station's frame.
    d_horizontal : ndarray, shape (B, K, P)
    """
    size, k = lines.mask.shape
    own_az = np.concatenate([np.eye(k), np.zeros((k, k))], axis=1)
    own_el = np.concatenate([np.zeros((k, k)), np.eye(k)], axis=1)
    rotations, origins = lines.rotations, lines.origins_enu_m
    az, el = lines.azimuth_rad, lines.elevation_rad
    sin_az, cos_az = np.sin(az), np.cos(az)
    normals, along = azimuth_normals(lines)
    rhs = np.einsum("bki,bki->bk", normals, origins)
    d_rhs = -np.einsum("bki,bki->bk", along, origins)[..., None] * own_az
    d_normals = -along[..., None] * own_az[:, None, :]
    hw, dhw = horizontal_weights, d_horizontal_weights
    flat = normals[..., :2] * hw[..., None]
    d_flat = d_normals[..., :2, :] * hw[..., None, None] + normals[..., :2, None] * dhw[..., None, :]
    gram = np.einsum("bki,bkj->bij", flat, flat)
    d_gram = np.einsum("bkip,bkj->bijp", d_flat, flat)
    d_gram = d_gram + np.swapaxes(d_gram, 1, 2)

    constrained = lines.constrained
    free = ~constrained
    up = np.where(constrained, lines.altitude_m, lines.mean_origin()[:, 2])
    d_up = np.zeros((size, 2 * k))
    # stage 2's heights: z_s + d_i (R_i^T [sin az, cos az, tan el])_z
    slope = rotations[..., 0, 2] * sin_az + rotations[..., 1, 2] * cos_az + rotations[..., 2, 2] * np.tan(el)
    d_slope = ((rotations[..., 0, 2] * cos_az - rotations[..., 1, 2] * sin_az)[..., None] * own_az
               + (rotations[..., 2, 2] / np.cos(el) ** 2 * lines.has_elevation)[..., None] * own_el)
    vw, dvw = height_weights, d_height_weights
    vw_total = np.sum(vw, axis=-1)
    vw_total = np.where(vw_total > 0, vw_total, 1.0)
    foot_rows = np.flatnonzero(constrained)
    foot_lines = lines.take(foot_rows) if foot_rows.size else None
    for _ in range(PASSES):
        residual = rhs - normals[..., 2] * up[:, None]
        data = residual * hw
        d_data = ((d_rhs - d_normals[..., 2, :] * up[:, None, None] - normals[..., 2, None] * d_up[:, None, :])
                  * hw[..., None] + residual[..., None] * dhw)
        right = np.einsum("bki,bk->bi", flat, data)
        d_right = np.einsum("bkip,bk->bip", d_flat, data) + np.einsum("bki,bkp->bip", flat, d_data)
        east_north = solve_2x2(gram, right)
        d_east_north = solve_2x2(gram, d_right - np.einsum("bijp,bj->bip", d_gram, east_north))
        candidate = np.concatenate([east_north, up[:, None]], axis=-1)
        d_candidate = np.concatenate([d_east_north, d_up[:, None, :]], axis=1)
        local, d_local = _local(lines, candidate, d_candidate)
        horizontal = np.hypot(local[..., 0], local[..., 1])
        d_horizontal = _d_hypot(local, d_local, horizontal)
        heights = origins[..., 2] + horizontal * slope
        d_heights = d_horizontal * slope[..., None] + horizontal[..., None] * d_slope
        new_up = np.sum(vw * heights, axis=-1) / vw_total
        d_new_up = (np.einsum("bkp,bk->bp", dvw, heights) + np.einsum("bk,bkp->bp", vw, d_heights)
                    - new_up[:, None] * np.sum(dvw, axis=1)) / vw_total[:, None]
        up = np.where(free, new_up, up)
        d_up = np.where(free[:, None], d_new_up, d_up)
        if foot_lines is not None:
            c = candidate[foot_rows]
            up[foot_rows] = foot_lines.onto_altitude(c)[:, 2]
            d_up[foot_rows] = np.einsum("bi,bip->bp", _foot_gradient(foot_lines, c), d_candidate[foot_rows])
    position = np.concatenate([east_north, up[:, None]], axis=-1)
    d_position = np.concatenate([d_east_north, d_up[:, None, :]], axis=1)
    local, d_local = _local(lines, position, d_position)
    horizontal = np.hypot(local[..., 0], local[..., 1])
    return position, d_position, horizontal, _d_hypot(local, d_local, horizontal)


def _local(lines: Lines, position_enu_m, d_position):
    """Points in each line's station frame ``(B, K, 3)`` and their derivatives ``(B, K, 3, P)``."""
    local = np.einsum("bkij,bkj->bki", lines.rotations, position_enu_m[:, None, :] - lines.origins_enu_m)
    return local, np.einsum("bkij,bjp->bkip", lines.rotations, d_position)


def _d_hypot(local, d_local, horizontal):
    safe = np.where(horizontal > 0, horizontal, 1.0)
    return (local[..., 0, None] * d_local[..., 0, :] + local[..., 1, None] * d_local[..., 1, :]) / safe[..., None]


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
    no_change = np.zeros((size, k, 2 * k))
    height_ones = ones * lines.has_elevation
    position, d_position, horizontal, d_horizontal = _stages(lines, ones, no_change, height_ones, no_change)
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
    covariance = np.einsum("bip,bp,bjp->bij", d_position, variance, d_position)
    return position, covariance


def _refusals(batch: ProblemBatch, lines: Lines, name: str) -> dict[int, LocalizationError]:
    errors = crossing_errors(lines, name)
    for b in np.flatnonzero(~lines.constrained & ~np.any(lines.has_elevation, axis=-1)).tolist():
        errors.setdefault(b, TooFewMeasurements(
            f"{name} takes the height from elevations: give an elevation on at least one line of sight, "
            "or the target altitude (constraints.altitude_m)", ("measurements",)))
    return errors


def _estimate(batch: ProblemBatch, name: str, weighted: bool) -> Estimates:
    lines = Lines.of(batch)
    errors = _refusals(batch, lines, name)
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
                   "elevations; fails above a straight station track")
def ple3d(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """3D PLE (Dogancay & Ibal 2005); see the module docstring."""
    return _estimate(batch, "ple3d", weighted=False)


@register("ws3d", "weighted Stansfield in 3D: PLE with inverse-variance weights from a first pass; "
                  "fails above a straight station track")
def ws3d(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """WS3D (Adib & Douglas 2018, as rendered in ALGORITHMS.md); see the module docstring."""
    return _estimate(batch, "ws3d", weighted=True)
