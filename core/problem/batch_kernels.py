"""The compiled passes a :class:`~core.problem.batch.ProblemBatch` derives its masks and geometry with.

Each takes the batch's ``(B, M)`` arrays and writes what the batch caches
(:attr:`~core.problem.batch.ProblemBatch._masks` and ``_geometry``) into arrays
its caller allocated (``out``), several ``(B, M)`` results as planes of one
array: a compiled call costs more for each array it returns, or is given,
than for each plane, a cost a batch of one feels.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from core.measurements import AZIMUTH, ELEVATION, SPEED_OF_LIGHT_MPS, TOA


@numba.njit(cache=True, nogil=True, error_model="numpy")
def lines_of_sight_kernel(valid, kinds, bearing_index, values, sigmas):
    """:meth:`ProblemBatch.lines_of_sight` of ``(B, M)`` arrays: each used elevation joins the used azimuth row of
    its bearing (and is left out of the lines where that azimuth is not used)."""
    size, width = kinds.shape
    is_line = np.zeros((size, width), dtype=np.bool_)
    elevation, sigma = np.full((size, width), np.nan), np.full((size, width), np.nan)
    azimuth_row = np.empty(width, dtype=np.int64)
    for b in range(size):
        azimuth_row[:] = -1
        for m in range(width):
            if valid[b, m] and kinds[b, m] == AZIMUTH:
                is_line[b, m] = True
                if 0 <= bearing_index[b, m] < width:
                    azimuth_row[bearing_index[b, m]] = m
        for m in range(width):
            if valid[b, m] and kinds[b, m] == ELEVATION and 0 <= bearing_index[b, m] < width:
                row = azimuth_row[bearing_index[b, m]]
                if row >= 0:
                    elevation[b, row], sigma[b, row] = values[b, m], sigmas[b, m]
    return is_line, elevation, sigma


@numba.njit(cache=True, nogil=True, error_model="numpy")
def model_kernel(kinds, values, sigmas, valid):
    """Values ``(B, M)`` in model units (TOA seconds as metres) and the weights ``1 / sigma^2`` ``(B, M)`` in
    model units of the ``valid`` measurements with a finite sigma (0 elsewhere)."""
    size, width = kinds.shape
    model_values, weights = np.empty((size, width)), np.zeros((size, width))
    for b in range(size):
        for m in range(width):
            unit = SPEED_OF_LIGHT_MPS if kinds[b, m] == TOA else 1.0
            model_values[b, m] = values[b, m] * unit
            sigma = sigmas[b, m]
            if valid[b, m] and math.isfinite(sigma):
                weights[b, m] = 1.0 / (sigma * unit) ** 2
    return model_values, weights


@numba.njit(cache=True, nogil=True, error_model="numpy")
def masks_kernel(n_measurements, kinds, used, sigmas, altitude_m, out):
    """The masks and counts a batch derives from its own, in one pass (see :attr:`core.problem.batch.ProblemBatch._masks`),
    into ``out``: ``(2, B, M)`` bool (present, valid), ``(3, B)`` bool (has_toa, constrained, lacks_sigma),
    the kind counts ``(B, 4)`` and the dof ``(B,)`` (int64).

    ``used`` is ``(B, M)``, or ``(0, 0)`` for every present measurement.
    """
    size, width = kinds.shape
    measured, facts, kind_counts, dof = out
    measured[:] = False
    present, valid = measured[0], measured[1]
    for b in range(size):
        present[b, :n_measurements[b]] = True
        for m in range(width):
            valid[b, m] = present[b, m] and (used.shape[0] == 0 or used[b, m])
    facts[:] = False
    has_toa, constrained, lacks_sigma = facts[0], facts[1], facts[2]
    kind_counts[:] = 0
    for b in range(size):
        constrained[b] = not math.isnan(altitude_m[b])
        known = 0
        for m in range(width):
            has_toa[b] |= kinds[b, m] == TOA
            if valid[b, m]:
                kind_counts[b, kinds[b, m]] += 1
                lacks_sigma[b] |= math.isnan(sigmas[b, m])
                known += 1 if math.isfinite(sigmas[b, m]) else 0
        dof[b] = known - (2 if constrained[b] else 3) - (1 if has_toa[b] else 0)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def geometry_kernel(valid, kinds, station_index, values, sigmas, bearing_index, stations_enu_m, station_rotations,
                    out):
    """The model values and weights, each measurement's station and rotation, and the lines of sight, in one
    call (see :attr:`core.problem.batch.ProblemBatch._geometry`), into ``out``: ``(4, B, M)`` (model values,
    weights, a line's elevation and its sigma), the stations ``(B, M, 3)``, their rotations ``(B, M, 3, 3)`` and
    ``is_line`` ``(B, M)``."""
    size, width = kinds.shape
    planes, stations, rotations, is_line_out = out
    for b in range(size):
        for m in range(width):
            s = station_index[b, m]
            stations[b, m] = stations_enu_m[b, s]
            rotations[b, m] = station_rotations[b, s]
    model_values, weights = model_kernel(kinds, values, sigmas, valid)
    is_line, elevation, sigma_elevation = lines_of_sight_kernel(valid, kinds, bearing_index, values, sigmas)
    planes[0], planes[1], planes[2], planes[3] = model_values, weights, elevation, sigma_elevation
    is_line_out[:] = is_line
