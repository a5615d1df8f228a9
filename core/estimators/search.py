"""Candidate starting points from the geometry, where no closed form applies.

Hybrid mixes (one bearing with ranges or TOAs, too few TOAs for Bancroft,
ranges from two stations with a known altitude) have no closed form here,
yet the information matrix may well call them observable. ML runs from
every candidate and keeps the lowest cost (:func:`core.estimators.ties.searched_starts`):
scoring the candidates themselves would not do, since precise TOAs make the
cost a narrow valley that a grid misses while a far plateau scores better.
Candidates come from the geometry:

- along every line of sight, at log-spaced distances (an azimuth-only
  bearing also over a fan of elevations);
- without a line of sight, around the stations' centroid, over a sphere
  (or, with a known altitude, a circle) of directions at log-spaced distances.

With a known altitude every candidate is put on that surface first.
"""

from __future__ import annotations

import numpy as np

from core.angles import line_of_sight_enu
from core.problem.batch import ProblemBatch
from core.problem.frame import onto_altitude

#: Distances (m) at which candidates are placed from a station or the stations' centroid (a factor 2.15
#: apart: every basin of a precise TOA or range is reached from one of them).
DISTANCES_M = np.geomspace(100.0, 1e6, 13)
#: Elevations (rad) tried along an azimuth-only line of sight.
FAN_ELEVATIONS_RAD = np.deg2rad([-2.0, 1.0, 5.0, 12.0, 25.0, 50.0])
#: At most about this many candidate-measurement pairs per problem (each candidate is an LM run over all
#: the problem's measurements): beyond it the lines of sight that carry candidates, or the directions around
#: the centroid, are thinned evenly. The largest fix (256 stations, 1,024 bearings) with bearings that fit
#: no point had 3,328 candidates, 12.5 s of LM for one problem; 1,024 TOAs that fit no point, 338.
SEARCH_PAIRS = 2**17
#: Directions around the centroid: a Fibonacci sphere (free height) or a circle (known altitude).
SPHERE_DIRECTIONS = 26
CIRCLE_DIRECTIONS = 12


def _sphere(count: int) -> np.ndarray:
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    phi = np.pi * (1.0 + 5.0**0.5) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def _circle(count: int) -> np.ndarray:
    a = 2.0 * np.pi * np.arange(count) / count
    return np.stack([np.cos(a), np.sin(a), np.zeros(count)], axis=-1)


def _thinned(carriers, candidates_each: int, rows):
    """``carriers`` ``(B, K)`` (lines of sight or directions) with every stride-th one kept, so that a
    problem's kept carriers x ``candidates_each`` x its ``rows`` ``(B,)`` stay within :data:`SEARCH_PAIRS`
    (one carrier at the least)."""
    allowed = np.maximum(SEARCH_PAIRS // (candidates_each * np.maximum(rows, 1)), 1)
    stride = np.maximum(-(-carriers.sum(axis=-1) // allowed), 1)
    return carriers & ((carriers.cumsum(axis=-1) - 1) % stride[:, None] == 0)


def candidates(batch: ProblemBatch) -> np.ndarray:
    """Candidate points ``(B, C, 3)`` of every problem (common frame; NaN where a problem has fewer).

    Returns
    -------
    ndarray, shape (B, C, 3)
    """
    size = batch.size
    stations, rotations = batch.measurement_stations()
    is_line, elevation, _ = batch.lines_of_sight()
    # One line per station: repeated looks from a station point the same way (to within their noise).
    rows = np.arange(is_line.shape[1])
    earlier = (batch.station_index[:, :, None] == batch.station_index[:, None, :]) & is_line[:, None, :] \
        & (rows[None, :] < rows[:, None])
    is_line = is_line & ~np.any(earlier, axis=-1)
    # Each line's candidates counted at their most (the fan).
    is_line = _thinned(is_line, DISTANCES_M.size * FAN_ELEVATIONS_RAD.size, batch.n_measurements)
    constrained = batch.constrained
    fan = np.concatenate([[np.nan], FAN_ELEVATIONS_RAD])
    # Along each line of sight: (B, M lines, E elevations, D distances); the measured elevation where given.
    el = np.where(np.isnan(elevation)[..., None], fan[None, None, 1:], np.nan)
    el = np.concatenate([elevation[..., None], el], axis=-1)
    az = np.where(is_line, batch.values, 0.0)
    local = line_of_sight_enu(az[..., None], np.nan_to_num(el))
    direction = np.einsum("bmji,bmej->bmei", rotations, local)
    along = stations[:, :, None, None, :] + direction[..., None, :] * DISTANCES_M[:, None]
    along = np.where((is_line[:, :, None] & ~np.isnan(el))[..., None, None], along, np.nan)
    along = along.reshape(size, -1, 3)
    # Around the stations' centroid.
    n = batch.n_stations
    present = np.arange(batch.stations_enu_m.shape[1])[None, :] < n[:, None]
    centroid = np.sum(np.where(present[..., None], batch.stations_enu_m, 0.0), axis=1) / np.maximum(n, 1)[:, None]
    sphere, circle = _sphere(SPHERE_DIRECTIONS), _circle(CIRCLE_DIRECTIONS)
    circle = np.concatenate([circle, np.full((SPHERE_DIRECTIONS - CIRCLE_DIRECTIONS, 3), np.nan)])
    directions = np.where(constrained[:, None, None], circle[None], sphere[None])
    kept = _thinned(~np.isnan(directions[..., 0]), DISTANCES_M.size, batch.n_measurements)
    directions = np.where(kept[..., None], directions, np.nan)
    around = centroid[:, None, None, :] + directions[:, :, None, :] * DISTANCES_M[:, None]
    around = np.where(np.any(is_line, axis=-1)[:, None, None, None], np.nan, around)
    points = np.concatenate([along, around.reshape(size, -1, 3)], axis=1)
    if np.any(constrained):
        flat = points.reshape(size, -1, 3)
        moved = onto_altitude(flat, np.where(constrained, batch.altitude_m, 0.0)[:, None],
                              batch.origin[:, None, :], batch.geodetic[:, None])
        points = np.where(constrained[:, None, None], moved, flat)
    return points
