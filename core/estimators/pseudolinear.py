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
horizontal plane (target above a straight station track): they raise
:class:`~core.errors.UnobservableGeometry` saying so, using the test of
:func:`core.estimators.azimuth_lines.require_crossing`.

Covariance: first-order propagation of the angle noise through the estimator,
by central differences of the whole two-stage computation (weights included).
"""

from __future__ import annotations

import numpy as np

from core.errors import TooFewMeasurements
from core.estimators.azimuth_lines import DIFFERENCE_STEP_RAD, require_crossing
from core.estimators.base import Estimate, SolveOptions, per_problem, register
from core.problem import Problem

#: Horizontal/height passes; fixed so that the estimator is one smooth map of the data.
PASSES = 6


def _stages(problem: Problem, los, azimuth_rad, elevation_rad, horizontal_weights, height_weights):
    """Run the two stages to their fixed point, for a batch of angle sets.

    Parameters
    ----------
    problem : Problem
    los : LinesOfSight
        Stations, rotations and which lines have an elevation.
    azimuth_rad, elevation_rad : ndarray, shape (B, K)
    horizontal_weights, height_weights : ndarray, shape (B, K)

    Returns
    -------
    position_enu_m : ndarray, shape (B, 3)
    horizontal_m : ndarray, shape (B, K)
        Horizontal distance of the fix from each line's station, in the
        station's frame.
    """
    zero = np.zeros_like(azimuth_rad)
    normal_local = np.stack([np.cos(azimuth_rad), -np.sin(azimuth_rad), zero], axis=-1)
    normals = np.einsum("kji,bkj->bki", los.rotations, normal_local)
    rhs = np.einsum("bki,ki->bk", normals, los.origins_enu_m)
    flat = normals[..., :2] * horizontal_weights[..., None]
    has_elevation = los.has_elevation
    altitude = problem.altitude_m
    batch = azimuth_rad.shape[0]
    up = np.full(batch, np.mean(los.origins_enu_m[:, 2]) if altitude is None else float(altitude))
    tan_el = np.tan(np.where(has_elevation, elevation_rad, 0.0))
    sin_az, cos_az = np.sin(azimuth_rad), np.cos(azimuth_rad)
    gram = np.einsum("bki,bkj->bij", flat, flat)
    for _ in range(PASSES):
        data = (rhs - normals[..., 2] * up[:, None]) * horizontal_weights
        east_north = np.linalg.solve(gram, np.einsum("bki,bk->bi", flat, data)[..., None])[..., 0]
        candidate = np.concatenate([east_north, up[:, None]], axis=-1)
        if altitude is not None:
            up = problem.frame.onto_altitude(candidate, altitude)[:, 2]
            continue
        local = np.einsum("kij,bkj->bki", los.rotations, candidate[:, None, :] - los.origins_enu_m)
        horizontal = np.hypot(local[..., 0], local[..., 1])
        along_local = np.stack([horizontal * sin_az, horizontal * cos_az, horizontal * tan_el], axis=-1)
        heights = los.origins_enu_m[:, 2] + np.einsum("kji,bkj->bki", los.rotations, along_local)[..., 2]
        w = height_weights * has_elevation
        up = np.sum(w * heights, axis=-1) / np.sum(w, axis=-1)
    position = np.concatenate([east_north, up[:, None]], axis=-1)
    local = np.einsum("kij,bkj->bki", los.rotations, position[:, None, :] - los.origins_enu_m)
    return position, np.hypot(local[..., 0], local[..., 1])


def pseudolinear_positions(problem: Problem, weighted: bool, azimuth_rad=None, elevation_rad=None) -> np.ndarray:
    """Positions of PLE (``weighted=False``) or WS3D (``weighted=True``) for a batch of angle sets.

    Parameters
    ----------
    problem : Problem
    weighted : bool
    azimuth_rad, elevation_rad : ndarray, shape (B, K), optional
        Angles per line of sight (default the problem's, ``B = 1``).

    Returns
    -------
    ndarray, shape (B, 3)
    """
    los = problem.lines_of_sight()
    az = los.azimuth_rad[None] if azimuth_rad is None else np.asarray(azimuth_rad)
    el = los.elevation_rad[None] if elevation_rad is None else np.asarray(elevation_rad)
    ones = np.ones_like(az)
    position, horizontal = _stages(problem, los, az, el, ones, ones)
    if not weighted:
        return position
    distance = np.maximum(horizontal, 1e-9)
    cos_el = np.cos(np.where(los.has_elevation, el, 0.0))
    horizontal_weights = 1.0 / (los.sigma_azimuth_rad * distance)
    height_weights = cos_el**4 / (np.where(los.has_elevation, los.sigma_elevation_rad, 1.0) * distance) ** 2
    return _stages(problem, los, az, el, horizontal_weights, height_weights)[0]


def _covariance(problem: Problem, weighted: bool) -> np.ndarray:
    """First-order propagation by central differences over every angle the estimator reads."""
    los = problem.lines_of_sight()
    count = los.count
    step = DIFFERENCE_STEP_RAD * np.eye(count)
    az, el = los.azimuth_rad[None], los.elevation_rad[None]
    sets_az = [az + step, az - step]
    sets_el = [np.repeat(el, count, 0)] * 2
    sigmas = [los.sigma_azimuth_rad]
    if problem.altitude_m is None:
        lines = np.flatnonzero(los.has_elevation)
        sets_az += [np.repeat(az, lines.size, 0)] * 2
        sets_el += [el + step[lines], el - step[lines]]
        sigmas.append(los.sigma_elevation_rad[lines])
    positions = pseudolinear_positions(problem, weighted, np.concatenate(sets_az), np.concatenate(sets_el))
    sizes = [count] + ([lines.size] if len(sigmas) == 2 else [])
    gains, offset = [], 0
    for size in sizes:
        plus = positions[offset:offset + size]
        minus = positions[offset + size:offset + 2 * size]
        gains.append((plus - minus) / (2 * DIFFERENCE_STEP_RAD))
        offset += 2 * size
    gain = np.concatenate(gains)
    variance = np.concatenate(sigmas) ** 2
    return (gain * variance[:, None]).T @ gain


def _fix(problem: Problem, weighted: bool):
    name = "ws3d" if weighted else "ple3d"
    los = problem.lines_of_sight()
    require_crossing(los, name)
    if problem.altitude_m is None and not np.any(los.has_elevation):
        raise TooFewMeasurements(
            f"{name} takes the height from elevations: give an elevation on at least one line of sight, "
            "or the target altitude (constraints.altitude_m)", ("measurements",))
    position = pseudolinear_positions(problem, weighted)[0]
    details = {"passes": PASSES}
    if problem.altitude_m is not None and np.any(los.has_elevation):
        details["unused_measurements"] = "elevations: the known altitude gives the height"
    return Estimate(position, _covariance(problem, weighted), details=details)


def _ple3d(problem: Problem, options: SolveOptions) -> Estimate:
    """3D PLE (Dogancay & Ibal 2005); see the module docstring."""
    return _fix(problem, weighted=False)


def _ws3d(problem: Problem, options: SolveOptions) -> Estimate:
    """WS3D (Adib & Douglas 2018, as rendered in ALGORITHMS.md); see the module docstring."""
    return _fix(problem, weighted=True)


register("ple3d", "3D pseudolinear estimator: horizontal Stansfield from azimuths, then mean height from "
                  "elevations; fails above a straight station track")(per_problem(_ple3d, "propagated"))
register("ws3d", "weighted Stansfield in 3D: PLE with inverse-variance weights from a first pass; "
                 "fails above a straight station track")(per_problem(_ws3d, "propagated"))
