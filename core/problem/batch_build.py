"""Build a :class:`~core.problem.batch.ProblemBatch` from the flat inputs of many problems at once.

:func:`build_problem_batch` is :func:`core.problem.build.build_problem` over a batch,
for inputs that already passed its checks: each problem's common frame is
placed (exact geodesy, the stations' centroid on the ellipsoid as the default
origin), its stations and measurements padded, and the batch's masks and
geometry derived, in one compiled call (:func:`_build_kernel`: :func:`_place`,
:func:`_pad_measurements`, then the batch's own kernels), so that a batch of
one costs one call.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numba
import numpy as np

from core import geodesy
from core.measurements import TOA
from core.problem.batch import PAD_KIND, ProblemBatch, _Geometry, _Masks
from core.problem.batch_kernels import geometry_kernel, masks_kernel
from core.problem.frame import local_axes_point

#: :data:`core.problem.batch.PAD_KIND` as the compiled padding pass writes it.
_PAD_KIND_CODE = int(PAD_KIND)


class _Stations(NamedTuple):
    """The flat station inputs of B problems (see :func:`build_problem_batch`): ``coordinates`` ``(S, 3)``,
    ``counts`` ``(B,)``, ``geodetic`` ``(B,)``, the given ``origin`` ``(B, 3)`` and initial ``guess`` ``(B, 3)``
    (NaN rows: none) and whether that guess is geodetic ``(B,)``."""

    coordinates: np.ndarray
    counts: np.ndarray
    geodetic: np.ndarray
    origin: np.ndarray
    guess: np.ndarray
    geodetic_guess: np.ndarray


class _Placed(NamedTuple):
    """Each problem's common frame, filled by :func:`_place`: its origin ``(B, 3)`` (zeros for a flat plane),
    whether it is geodetic ``(B,)``, its placement ``(B, 3)`` and ``(B, 3, 3)``
    (:func:`core.problem.frame.frame_placements` of the origin), the stations ``(B, N, 3)`` and their rotations
    ``(B, N, 3, 3)`` (zero and identity on padding) and the guesses in the frame ``(B, 3)``."""

    origin: np.ndarray
    geodetic: np.ndarray
    origin_ecef_m: np.ndarray
    origin_rotation: np.ndarray
    stations_enu_m: np.ndarray
    rotations: np.ndarray
    guess_enu_m: np.ndarray


class _FlatMeasurements(NamedTuple):
    """The flat measurements of B problems: ``counts`` ``(B,)``, then ``(T,)`` each (see
    :func:`build_problem_batch`)."""

    counts: np.ndarray
    kinds: np.ndarray
    station_index: np.ndarray
    values: np.ndarray
    sigmas: np.ndarray
    bearing_index: np.ndarray
    source_index: np.ndarray


class _Padded(NamedTuple):
    """The measurements padded to ``(B, M)`` by :func:`_pad_measurements`, and each problem's TOA reference
    ``(B,)``."""

    kinds: np.ndarray
    station_index: np.ndarray
    values: np.ndarray
    sigmas: np.ndarray
    bearing_index: np.ndarray
    source_index: np.ndarray
    toa_reference_s: np.ndarray


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _place(given, placed):
    """Each problem's common frame, its stations in it (padded) and its initial guess in it, from the
    :class:`_Stations` ``given`` into the :class:`_Placed` ``placed``.

    A geodetic problem without an origin takes its stations' ECEF centroid on
    the ellipsoid (the first station where the centroid is at the earth's
    centre); a geodetic station ``(lat_rad, lon_rad, alt_m)`` is placed by
    exact geodesy, a local one ``(east_m, north_m, up_m)`` as given, with
    the local axes at it. So is a guess (where ``geodetic_guess``; NaN rows: none).
    """
    coordinates, counts, geodetic_stations, origin_given, guess_given, geodetic_guess = given
    origin, geodetic, origin_ecef, origin_rotation, enu, rotations, guess = placed
    origin[:], geodetic[:], enu[:], rotations[:], guess[:] = 0.0, False, 0.0, 0.0, guess_given
    first = 0
    for b in range(counts.size):
        count = counts[b]
        stations = coordinates[first:first + count]
        if geodetic_stations[b] and math.isnan(origin_given[b, 0]):
            origin[b, 0], origin[b, 1] = geodesy.centroid_on_ellipsoid_point(stations[:, 0].copy(),
                                                                             stations[:, 1].copy())
            geodetic[b] = True
        elif not math.isnan(origin_given[b, 0]):
            origin[b] = origin_given[b]
            geodetic[b] = True
        o = origin[b]
        origin_ecef[b, 0], origin_ecef[b, 1], origin_ecef[b, 2] = geodesy.geodetic_to_ecef_point(o[0], o[1], o[2])
        geodesy.ecef_to_enu_rotation_point(o[0], o[1], origin_rotation[b])
        if geodetic_guess[b] and not math.isnan(guess[b, 0]):
            x, y, z = geodesy.geodetic_to_ecef_point(guess[b, 0], guess[b, 1], guess[b, 2])
            guess[b, 0], guess[b, 1], guess[b, 2] = geodesy.ecef_to_enu_point(x, y, z, origin_ecef[b],
                                                                              origin_rotation[b])
        for i in range(count):
            c = stations[i]
            if geodetic_stations[b]:
                x, y, z = geodesy.geodetic_to_ecef_point(c[0], c[1], c[2])
                enu[b, i, 0], enu[b, i, 1], enu[b, i, 2] = geodesy.ecef_to_enu_point(x, y, z, origin_ecef[b],
                                                                                     origin_rotation[b])
                geodesy.rotation_from_point(c[0], c[1], origin_rotation[b], rotations[b, i])
            else:
                enu[b, i, 0], enu[b, i, 1], enu[b, i, 2] = c[0], c[1], c[2]
                local_axes_point(enu[b, i], geodetic[b], origin_ecef[b], origin_rotation[b], rotations[b, i])
        for i in range(count, enu.shape[1]):
            for r in range(3):
                rotations[b, i, r, r] = 1.0
        first += count


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pad_measurements(flat, padded):
    """The :class:`_FlatMeasurements` ``flat`` padded into the :class:`_Padded` ``padded`` (padding: kind
    ``PAD_KIND``, station 0, value 0, sigma NaN, indices -1), TOA values less each problem's earliest, and that
    reference (0 without TOA)."""
    counts, kinds, station_index, values, sigmas, bearing_index, source_index = flat
    kinds_out, station_out, values_out, sigmas_out, bearing_out, source_out, reference = padded
    kinds_out[:], station_out[:], values_out[:], sigmas_out[:] = _PAD_KIND_CODE, 0, 0.0, np.nan
    bearing_out[:], source_out[:], reference[:] = -1, -1, 0.0
    first = 0
    for b in range(counts.size):
        earliest = np.inf
        for m in range(counts[b]):
            j = first + m
            kinds_out[b, m], station_out[b, m] = kinds[j], station_index[j]
            values_out[b, m], sigmas_out[b, m] = values[j], sigmas[j]
            bearing_out[b, m], source_out[b, m] = bearing_index[j], source_index[j]
            if kinds[j] == TOA:
                earliest = min(earliest, values[j])
        if earliest < np.inf:
            reference[b] = earliest
            for m in range(counts[b]):
                if kinds_out[b, m] == TOA:
                    values_out[b, m] -= earliest
        first += counts[b]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _build_kernel(given, placed, flat, padded, altitude_m, masks, geometry):
    """:func:`_place`, :func:`_pad_measurements`, and the batch's ``masks`` and ``geometry`` from what they
    wrote (:func:`core.problem.batch_kernels.masks_kernel`, ``geometry_kernel``: every present measurement in
    use), in one call. The structures come as plain tuples (:mod:`core.kernel_data`)."""
    given, placed, flat, padded = _Stations(*given), _Placed(*placed), _FlatMeasurements(*flat), _Padded(*padded)
    _place(given, placed)
    _pad_measurements(flat, padded)
    masks_kernel(flat.counts, padded.kinds, np.zeros((0, 0), dtype=np.bool_), padded.sigmas, altitude_m, masks)
    geometry_kernel(masks[0][1], padded.kinds, padded.station_index, padded.values, padded.sigmas,
                    padded.bearing_index, placed.stations_enu_m, placed.rotations, geometry)


def build_problem_batch(
    station_counts,
    station_ids: Sequence[tuple[str, ...]],
    station_coordinates,
    geodetic_stations,
    origin,
    measurement_counts,
    kinds,
    station_index,
    values,
    sigmas,
    bearing_index,
    source_index,
    altitude_m,
    initial_guess,
    geodetic_guess,
) -> ProblemBatch:
    """:func:`core.problem.build.build_problem` for a batch of inputs that already pass its checks.

    Parameters
    ----------
    station_counts : ndarray of int, shape (B,)
        Stations of each problem (>= 1); their rows are consecutive below.
    station_ids : sequence of tuple of str, length B
    station_coordinates : ndarray, shape (S, 3)
        ``(lat_rad, lon_rad, alt_m)`` for geodetic stations, ``(east_m, north_m, up_m)`` for local ones;
        ``S = sum(station_counts)``.
    geodetic_stations : ndarray of bool, shape (B,)
    origin : ndarray, shape (B, 3)
        Given origin ``(lat_rad, lon_rad, alt_m)``; NaN rows where none was given.
    measurement_counts : ndarray of int, shape (B,)
        Scalar measurements of each problem (>= 1); rows consecutive below.
    kinds, station_index, values, sigmas, bearing_index, source_index : ndarray, shape (T,)
        As in :class:`~core.problem.frame.Problem`, except that TOA values are the raw
        seconds (the per-problem reference is subtracted here); ``station_index``
        counts within the problem.
    altitude_m : ndarray, shape (B,)
        NaN where unconstrained.
    initial_guess : ndarray, shape (B, 3)
        Geodetic ``(lat_rad, lon_rad, alt_m)`` or local ENU; NaN rows where none.
    geodetic_guess : ndarray of bool, shape (B,)

    Returns
    -------
    ProblemBatch
    """
    station_counts = np.asarray(station_counts, dtype=np.intp)
    measurement_counts = np.asarray(measurement_counts, dtype=np.intp)
    size = station_counts.size
    n, m = max([1, *station_counts.tolist()]), max([1, *measurement_counts.tolist()])
    altitude_m = np.ascontiguousarray(altitude_m, dtype=float).reshape(-1)
    placed = _Placed(np.empty((size, 3)), np.empty(size, dtype=bool), np.empty((size, 3)), np.empty((size, 3, 3)),
                     np.empty((size, n, 3)), np.empty((size, n, 3, 3)), np.empty((size, 3)))
    padded = _Padded(np.empty((size, m), dtype=np.int8), np.empty((size, m), dtype=np.intp), np.empty((size, m)),
                     np.empty((size, m)), np.empty((size, m), dtype=np.intp), np.empty((size, m), dtype=np.intp),
                     np.empty(size))
    masks, geometry = _Masks.room(size, m), _Geometry.room(size, m)
    _build_kernel(
        tuple(_Stations(np.ascontiguousarray(station_coordinates, dtype=float).reshape(-1, 3), station_counts,
                  np.asarray(geodetic_stations, dtype=bool), np.ascontiguousarray(origin, dtype=float).reshape(-1, 3),
                  np.ascontiguousarray(initial_guess, dtype=float).reshape(-1, 3),
                  np.asarray(geodetic_guess, dtype=bool))),
        tuple(placed),
        tuple(_FlatMeasurements(measurement_counts, np.asarray(kinds, dtype=np.int8), np.asarray(station_index, dtype=np.intp),
                          np.asarray(values, dtype=float), np.asarray(sigmas, dtype=float),
                          np.asarray(bearing_index, dtype=np.intp), np.asarray(source_index, dtype=np.intp))),
        tuple(padded), altitude_m, masks, geometry)

    built = ProblemBatch(
        station_ids=tuple(station_ids),
        origin=placed.origin,
        geodetic=placed.geodetic,
        n_stations=station_counts,
        stations_enu_m=placed.stations_enu_m,
        station_rotations=placed.rotations,
        n_measurements=measurement_counts,
        kinds=padded.kinds,
        station_index=padded.station_index,
        values=padded.values,
        sigmas=padded.sigmas,
        bearing_index=padded.bearing_index,
        source_index=padded.source_index,
        toa_reference_s=padded.toa_reference_s,
        altitude_m=altitude_m,
        initial_guess_enu_m=placed.guess_enu_m,
    )
    # The caches of frame_placements() and of the batch's masks and geometry, already computed.
    built.__dict__.update(_frame_placements=(placed.origin_ecef_m, placed.origin_rotation),
                          _masks=_Masks.of(masks), _geometry=_Geometry.of(geometry))
    return built
