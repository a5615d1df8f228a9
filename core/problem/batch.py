"""Many localisation problems at once, padded to common sizes.

A :class:`ProblemBatch` holds B problems, each in its own common frame, with
stations padded to N and measurements to M. Padding is marked by
``n_stations`` and ``n_measurements`` (and :attr:`ProblemBatch.valid`); it
never carries weight. The batched ML estimator and its closed-form start work
on a batch; :meth:`ProblemBatch.problem` gives one :class:`~core.problem.frame.Problem`
back for the per-problem code paths.

A batch is built from the callers' flat inputs by
:func:`core.problem.batch_build.build_problem_batch`, or padded from built
problems by :meth:`ProblemBatch.from_problems`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from typing import NamedTuple, Sequence

import numpy as np

from core.kernel_data import Frames, Measurements
from core.measurements import AZIMUTH, ELEVATION, Kind
from core.problem.batch_kernels import geometry_kernel, masks_kernel, model_kernel
from core.problem.frame import CommonFrame, GeodeticPoint, Problem, frame_placements, onto_altitude

#: Kind written into measurement padding (any kind works: padding has zero weight).
PAD_KIND = Kind.RANGE
_PAD_KIND_CODE = int(PAD_KIND)


class _Masks(NamedTuple):
    """What :func:`masks_kernel` returns, by name (shapes in :class:`ProblemBatch`'s properties)."""

    present: np.ndarray
    valid: np.ndarray
    has_toa: np.ndarray
    constrained: np.ndarray
    lacks_sigma: np.ndarray
    kind_counts: np.ndarray
    dof: np.ndarray

    @staticmethod
    def room(size: int, width: int) -> tuple:
        """The arrays :func:`masks_kernel` writes, for ``size`` problems of ``width`` measurement rows."""
        return (np.empty((2, size, width), dtype=np.bool_), np.empty((3, size), dtype=np.bool_),
                np.empty((size, 4), dtype=np.int64), np.empty(size, dtype=np.int64))

    @classmethod
    def of(cls, computed) -> "_Masks":
        """The masks of :func:`masks_kernel`'s outputs ``computed``, read-only (views of frozen arrays are too)."""
        measured, facts, kind_counts, dof = map(_frozen, computed)
        return cls(*measured, *facts, kind_counts, dof)


class _Geometry(NamedTuple):
    """What :func:`geometry_kernel` returns, by name."""

    model_values: np.ndarray
    weights: np.ndarray
    measurement_stations_enu_m: np.ndarray
    measurement_rotations: np.ndarray
    is_line: np.ndarray
    elevation_rad: np.ndarray
    sigma_elevation_rad: np.ndarray

    @staticmethod
    def room(size: int, width: int) -> tuple:
        """The arrays :func:`geometry_kernel` writes, for ``size`` problems of ``width`` measurement rows."""
        return (np.empty((4, size, width)), np.empty((size, width, 3)), np.empty((size, width, 3, 3)),
                np.empty((size, width), dtype=np.bool_))

    @classmethod
    def of(cls, computed) -> "_Geometry":
        """The geometry of :func:`geometry_kernel`'s outputs ``computed``, read-only."""
        planes, stations, rotations, is_line = map(_frozen, computed)
        model_values, weights, elevation, sigma_elevation = planes  # views of a frozen array are read-only too
        return cls(model_values, weights, stations, rotations, is_line, elevation, sigma_elevation)


def _frozen(array: np.ndarray) -> np.ndarray:
    """``array``, read-only: a batch computes its masks once and hands the same array to every caller."""
    array.setflags(write=False)
    return array


class MeasurementRows(NamedTuple):
    """One problem's measurements in use (:meth:`ProblemBatch.rows_in_use`), ``(M_b,)`` each, in request order;
    ``station_index`` counts within the problem, ``source_index`` is the request's measurement index."""

    kinds: np.ndarray
    station_index: np.ndarray
    values: np.ndarray
    sigmas: np.ndarray
    bearing_index: np.ndarray
    source_index: np.ndarray


@dataclass(frozen=True)
class ProblemBatch:
    """B problems padded to N stations and M measurements.

    Attributes
    ----------
    station_ids : tuple of tuple of str, length B
    origin : ndarray, shape (B, 3)
        Each frame's origin ``(lat_rad, lon_rad, alt_m)``; zeros for a flat plane.
    geodetic : ndarray of bool, shape (B,)
        Whether the frame touches the earth (``CommonFrame.is_geodetic``).
    n_stations : ndarray of int, shape (B,)
    stations_enu_m : ndarray, shape (B, N, 3)
    station_rotations : ndarray, shape (B, N, 3, 3)
        Station ENU <- common ENU; the identity on padding.
    n_measurements : ndarray of int, shape (B,)
    kinds : ndarray of int8, shape (B, M)
    station_index : ndarray of int, shape (B, M)
    values : ndarray, shape (B, M)
        Problem units (rad, m, s after ``toa_reference_s``); 0 on padding.
    sigmas : ndarray, shape (B, M)
        Problem units; NaN where not given and on padding.
    bearing_index, source_index : ndarray of int, shape (B, M)
        As in :class:`~core.problem.frame.Problem`; -1 on padding.
    toa_reference_s : ndarray, shape (B,)
    altitude_m : ndarray, shape (B,)
        Known target altitude; NaN where unconstrained.
    initial_guess_enu_m : ndarray, shape (B, 3)
        NaN rows where none was given.
    used : ndarray of bool, shape (B, M), or None
        Measurements the estimator may use (None: every one). An unused
        measurement is still reported (its residual at the fix) but carries
        no weight and enters no verdict: see :meth:`with_used`.
    """

    station_ids: tuple[tuple[str, ...], ...]
    origin: np.ndarray
    geodetic: np.ndarray
    n_stations: np.ndarray
    stations_enu_m: np.ndarray
    station_rotations: np.ndarray
    n_measurements: np.ndarray
    kinds: np.ndarray
    station_index: np.ndarray
    values: np.ndarray
    sigmas: np.ndarray
    bearing_index: np.ndarray
    source_index: np.ndarray
    toa_reference_s: np.ndarray
    altitude_m: np.ndarray
    initial_guess_enu_m: np.ndarray
    used: np.ndarray | None = None

    @property
    def size(self) -> int:
        return int(self.n_measurements.size)

    @cached_property
    def _masks(self) -> _Masks:
        """The masks and counts derived from the batch's own (:func:`masks_kernel`): computed together on
        first use, read-only."""
        used = np.zeros((0, 0), dtype=np.bool_) if self.used is None else np.ascontiguousarray(self.used)
        c = np.ascontiguousarray
        out = _Masks.room(*self.kinds.shape)
        masks_kernel(c(self.n_measurements, dtype=np.intp), c(self.kinds, dtype=np.int8), used,
                     c(self.sigmas, dtype=float), c(self.altitude_m, dtype=float), out)
        return _Masks.of(out)

    @cached_property
    def _geometry(self) -> _Geometry:
        """The model values, weights, measurement stations and lines of sight (:func:`geometry_kernel`):
        computed together on first use (a batch that is only split into parts never needs them), read-only."""
        c = np.ascontiguousarray
        out = _Geometry.room(*self.kinds.shape)
        geometry_kernel(self.valid, c(self.kinds, dtype=np.int8), c(self.station_index, dtype=np.intp),
                        c(self.values, dtype=float), c(self.sigmas, dtype=float), c(self.bearing_index, dtype=np.intp),
                        c(self.stations_enu_m, dtype=float), c(self.station_rotations, dtype=float), out)
        return _Geometry.of(out)

    @cached_property
    def kernel_measurements(self) -> Measurements:
        """The measurements as the compiled kernels take them (:class:`core.kernel_data.Measurements`; the
        batch's own arrays in the kernels' dtypes, C-contiguous): made once."""
        c = np.ascontiguousarray
        geometry = self._geometry
        return Measurements(c(self.kinds, dtype=np.int64), c(self.n_measurements, dtype=np.int64), self.valid,
                            c(self.values, dtype=float), c(self.sigmas, dtype=float), geometry.model_values,
                            geometry.weights, geometry.measurement_stations_enu_m, geometry.measurement_rotations,
                            geometry.is_line, geometry.elevation_rad, geometry.sigma_elevation_rad,
                            c(self.source_index, dtype=np.int64))

    @cached_property
    def kernel_frames(self) -> Frames:
        """Each problem's frame and constraint as the compiled kernels take them
        (:class:`core.kernel_data.Frames`): made once."""
        c = np.ascontiguousarray
        origin_ecef, origin_rotation = self.frame_placements()
        return Frames(c(self.altitude_m, dtype=float), self.has_toa, c(self.geodetic, dtype=np.bool_),
                      c(origin_ecef, dtype=float), c(origin_rotation, dtype=float))

    @property
    def present(self) -> np.ndarray:
        """``(B, M)``: True on real measurements, False on padding."""
        return self._masks.present

    @property
    def valid(self) -> np.ndarray:
        """``(B, M)``: True on the measurements an estimator uses (real and not set aside by :meth:`with_used`)."""
        return self._masks.valid

    def with_used(self, used) -> "ProblemBatch":
        """The same problems with only ``used`` ``(B, M)`` (and present) measurements in the fit."""
        return replace(self, used=self.present & np.asarray(used, dtype=bool))

    @property
    def constrained(self) -> np.ndarray:
        """``(B,)``: a known altitude is given."""
        return self._masks.constrained

    @property
    def has_toa(self) -> np.ndarray:
        """``(B,)``: some measurement is a TOA (so the emission offset is a free parameter)."""
        return self._masks.has_toa

    @property
    def lacks_sigma(self) -> np.ndarray:
        """``(B,)``: some measurement in use has no sigma."""
        return self._masks.lacks_sigma

    @property
    def kind_counts(self) -> np.ndarray:
        """``(B, 4)`` int: how many measurements of each kind (column ``Kind``) are in use."""
        return self._masks.kind_counts

    @property
    def dof(self) -> np.ndarray:
        """``(B,)`` int: degrees of freedom of a fit to the measurements in use with a stated sigma (their count
        less the position's free coordinates and a TOA offset)."""
        return self._masks.dof

    def model_values(self) -> np.ndarray:
        """Values ``(B, M)`` in model units (TOA as pseudo-range metres; computed once, read-only)."""
        return self._geometry.model_values

    def weights(self, sigmas=None) -> np.ndarray:
        """``1 / sigma^2`` ``(B, M)`` in model units; 0 on padding and where no sigma is known.

        Parameters
        ----------
        sigmas : ndarray, shape (B, M), optional
            Replacement sigmas in problem units (default ``self.sigmas``: those weights are computed once and
            read-only).
        """
        if sigmas is None:
            return self._geometry.weights
        return self._model_values_weights(sigmas)[1]

    def _model_values_weights(self, sigmas) -> tuple[np.ndarray, np.ndarray]:
        return model_kernel(np.ascontiguousarray(self.kinds, dtype=np.int8), np.ascontiguousarray(self.values),
                             np.ascontiguousarray(sigmas, dtype=float), np.ascontiguousarray(self.valid))

    def onto_altitude(self, positions_enu_m, rows=None) -> np.ndarray:
        """Positions moved onto their problem's known altitude (unconstrained problems' unchanged).

        Parameters
        ----------
        positions_enu_m : ndarray, shape (R, 3)
        rows : ndarray of int, shape (R,), optional
            The problem of each position (default: position ``b`` is problem ``b``).

        Returns
        -------
        ndarray, shape (R, 3)
        """
        rows = np.arange(self.size) if rows is None else np.asarray(rows, dtype=np.intp)
        out = np.array(positions_enu_m, dtype=float, copy=True)
        chosen = np.flatnonzero(self.constrained[rows])
        if chosen.size:
            b = rows[chosen]
            out[chosen] = onto_altitude(out[chosen], self.altitude_m[b], self.origin[b], self.geodetic[b])
        return out

    def frame_placements(self) -> tuple[np.ndarray, np.ndarray]:
        """Each frame's origin in ECEF ``(B, 3)`` and its ECEF -> ENU rotation ``(B, 3, 3)``
        (:func:`core.problem.frame.frame_placements`, computed once)."""
        return self._frame_placements

    @cached_property
    def _frame_placements(self):
        return frame_placements(self.origin)

    def measurement_stations(self) -> tuple[np.ndarray, np.ndarray]:
        """Station position ``(B, M, 3)`` and rotation ``(B, M, 3, 3)`` of every measurement (computed once)."""
        return self._geometry.measurement_stations_enu_m, self._geometry.measurement_rotations

    def lines_of_sight(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bearings as lines of sight, one per azimuth row (computed once).

        Returns
        -------
        is_line : ndarray of bool, shape (B, M)
            True on the azimuth row of each bearing.
        elevation_rad, sigma_elevation_rad : ndarray, shape (B, M)
            The bearing's elevation and its sigma on its azimuth row; NaN
            for an azimuth-only bearing and off azimuth rows.
        """
        geometry = self._geometry
        return geometry.is_line, geometry.elevation_rad, geometry.sigma_elevation_rad

    def by_bearing(self, values, kind: int, fill=np.nan) -> np.ndarray:
        """Per-measurement values ``(B, M)`` of the ``kind`` rows (azimuth or elevation) laid out per bearing.

        Returns
        -------
        ndarray, shape (B, K)
            Column ``k`` is bearing ``k`` of each problem (request order);
            ``fill`` where a problem has no such bearing or row. ``K`` is the
            largest bearing count in the batch.
        """
        values = np.asarray(values)
        b, m, k = self._bearing_rows[kind]
        out = np.full((self.size, self._bearing_width), fill, dtype=np.result_type(values.dtype, np.asarray(fill)))
        out[b, k] = values[b, m]
        return out

    @cached_property
    def _bearing_width(self) -> int:
        return int(self.bearing_index.max(initial=-1)) + 1

    @cached_property
    def _bearing_rows(self) -> dict:
        out = {}
        for kind in (AZIMUTH, ELEVATION):
            b, m = np.nonzero(self.valid & (self.kinds == kind))
            out[kind] = b, m, self.bearing_index[b, m]
        return out

    def frame(self, b: int) -> CommonFrame:
        """The common frame of problem ``b``."""
        if not self.geodetic[b]:
            return CommonFrame(None)
        lat, lon, alt = (float(v) for v in self.origin[b])
        return CommonFrame(GeodeticPoint(lat, lon, alt))

    def rows_in_use(self, b: int) -> MeasurementRows:
        """Problem ``b``'s measurements in use, unpadded (copies: a caller may change them)."""
        m = np.flatnonzero(self.valid[b])
        return MeasurementRows(self.kinds[b, m], self.station_index[b, m], self.values[b, m], self.sigmas[b, m],
                               self.bearing_index[b, m], self.source_index[b, m])

    def problem(self, b: int) -> Problem:
        """Problem ``b`` on its own: no padding, and only the measurements in use."""
        n = int(self.n_stations[b])
        rows = self.rows_in_use(b)
        altitude = float(self.altitude_m[b])
        guess = self.initial_guess_enu_m[b]
        bearing = rows.bearing_index
        lines = bearing >= 0
        bearing[lines] = np.unique(bearing[lines], return_inverse=True)[1]
        return Problem(
            frame=self.frame(b),
            station_ids=self.station_ids[b],
            stations_enu_m=self.stations_enu_m[b, :n].copy(),
            station_rotations=self.station_rotations[b, :n].copy(),
            kinds=rows.kinds,
            station_index=rows.station_index,
            values=rows.values,
            sigmas=rows.sigmas,
            bearing_index=bearing,
            source_index=rows.source_index,
            toa_reference_s=float(self.toa_reference_s[b]),
            altitude_m=None if np.isnan(altitude) else altitude,
            initial_guess_enu_m=None if np.isnan(guess[0]) else guess.copy(),
        )

    def leave_one_out(self, rows, used, suspicion, count: int) -> tuple[np.ndarray, np.ndarray]:
        """The subsets of problems ``rows`` that each leave out one request measurement (a bearing's azimuth
        and elevation together), for the ``count`` most suspect ones of each problem.

        Parameters
        ----------
        rows : ndarray of int, shape (R,)
        used : ndarray of bool, shape (B, M)
            The measurements in the fit now (candidates are among them).
        suspicion : ndarray, shape (B, M)
            Larger first (say ``|studentized residual|``); NaN counts as the largest.
        count : int

        Returns
        -------
        owners : ndarray of int, shape (C,)
            The problem of each subset, in the order of ``rows``.
        dropped : ndarray of bool, shape (C, M)
            The measurements each subset leaves out.
        """
        rows = np.asarray(rows, dtype=np.intp)
        in_use = used[rows]
        order = np.argsort(np.where(in_use, -np.nan_to_num(suspicion[rows], nan=np.inf), np.inf), axis=1,
                           kind="stable")
        sources = np.take_along_axis(self.source_index[rows], order, axis=1)
        # Walked row by row, most suspect first: each source's first measurement in use is its candidate.
        flat = np.flatnonzero(np.take_along_axis(in_use, order, axis=1))
        row = flat // sources.shape[1]
        _, first = np.unique(row * (int(self.source_index.max(initial=0)) + 1) + sources.ravel()[flat],
                             return_index=True)
        flat, row = flat[np.sort(first)], row[np.sort(first)]
        rank = np.arange(row.size) - np.searchsorted(row, row)
        flat, row = flat[rank < count], row[rank < count]
        owners, chosen = rows[row], sources.ravel()[flat]
        return owners, used[owners] & (self.source_index[owners] == chosen[:, None])

    def take(self, indices) -> "ProblemBatch":
        """The sub-batch of ``indices``, padding trimmed to its own largest problem."""
        idx = np.asarray(indices, dtype=np.intp)
        n = int(self.n_stations[idx].max(initial=1))
        m = int(self.n_measurements[idx].max(initial=1))
        return ProblemBatch(
            station_ids=tuple(map(self.station_ids.__getitem__, idx.tolist())),
            origin=self.origin[idx],
            geodetic=self.geodetic[idx],
            n_stations=self.n_stations[idx],
            stations_enu_m=self.stations_enu_m[idx, :n],
            station_rotations=self.station_rotations[idx, :n],
            n_measurements=self.n_measurements[idx],
            kinds=self.kinds[idx, :m],
            station_index=self.station_index[idx, :m],
            values=self.values[idx, :m],
            sigmas=self.sigmas[idx, :m],
            bearing_index=self.bearing_index[idx, :m],
            source_index=self.source_index[idx, :m],
            toa_reference_s=self.toa_reference_s[idx],
            altitude_m=self.altitude_m[idx],
            initial_guess_enu_m=self.initial_guess_enu_m[idx],
            used=None if self.used is None else self.used[idx, :m],
        )

    @classmethod
    def concatenate(cls, parts: Sequence["ProblemBatch"]) -> "ProblemBatch":
        """One batch of the problems of ``parts``, in order, padded to the widest."""
        if len(parts) == 1:
            return parts[0]
        n = max(p.stations_enu_m.shape[1] for p in parts)
        m = max(p.kinds.shape[1] for p in parts)

        def widened(name, width, fill):
            arrays = []
            for p in parts:
                a = getattr(p, name)
                extra = width - a.shape[1]
                if extra:
                    pad = np.broadcast_to(np.asarray(fill, dtype=a.dtype), (a.shape[0], extra, *a.shape[2:]))
                    a = np.concatenate([a, pad], axis=1)
                arrays.append(a)
            return np.concatenate(arrays)

        def joined(name):
            return np.concatenate([getattr(p, name) for p in parts])

        def widened_used():
            masks = [p.valid for p in parts]
            return np.concatenate([np.pad(v, ((0, 0), (0, m - v.shape[1]))) for v in masks])

        return cls(
            station_ids=tuple(ids for p in parts for ids in p.station_ids),
            origin=joined("origin"),
            geodetic=joined("geodetic"),
            n_stations=joined("n_stations"),
            stations_enu_m=widened("stations_enu_m", n, 0.0),
            station_rotations=widened("station_rotations", n, np.eye(3)),
            n_measurements=joined("n_measurements"),
            kinds=widened("kinds", m, PAD_KIND),
            station_index=widened("station_index", m, 0),
            values=widened("values", m, 0.0),
            sigmas=widened("sigmas", m, np.nan),
            bearing_index=widened("bearing_index", m, -1),
            source_index=widened("source_index", m, -1),
            toa_reference_s=joined("toa_reference_s"),
            altitude_m=joined("altitude_m"),
            initial_guess_enu_m=joined("initial_guess_enu_m"),
            used=None if all(p.used is None for p in parts) else widened_used(),
        )

    @classmethod
    def from_problems(cls, problems: Sequence[Problem]) -> "ProblemBatch":
        """Pad built problems into one batch (inverse of :meth:`problem`)."""
        if len(problems) == 1:
            return cls._from_one(problems[0])
        n_stations = np.array([p.stations_enu_m.shape[0] for p in problems], dtype=np.intp)
        n_measurements = np.array([p.kinds.size for p in problems], dtype=np.intp)
        by_station, by_measurement = _scatter(n_stations), _scatter(n_measurements)
        stations = _pad(np.concatenate([p.stations_enu_m for p in problems]), by_station, 0.0)
        rotations = _pad(np.concatenate([p.station_rotations for p in problems]), by_station, 0.0)
        rotations[~(np.arange(rotations.shape[1]) < n_stations[:, None])] = np.eye(3)

        def measured(name, fill):
            return _pad(np.concatenate([getattr(p, name) for p in problems]), by_measurement, fill)

        frames = [p.frame for p in problems]
        return cls(
            station_ids=tuple(p.station_ids for p in problems),
            origin=np.array([f.origin_array() for f in frames]).reshape(-1, 3),
            geodetic=np.array([f.is_geodetic for f in frames], dtype=bool),
            n_stations=n_stations,
            stations_enu_m=stations,
            station_rotations=rotations,
            n_measurements=n_measurements,
            kinds=measured("kinds", PAD_KIND).astype(np.int8),
            station_index=measured("station_index", 0).astype(np.intp),
            values=measured("values", 0.0),
            sigmas=measured("sigmas", np.nan),
            bearing_index=measured("bearing_index", -1).astype(np.intp),
            source_index=measured("source_index", -1).astype(np.intp),
            toa_reference_s=np.array([p.toa_reference_s for p in problems], dtype=float),
            altitude_m=np.array([np.nan if p.altitude_m is None else p.altitude_m for p in problems], dtype=float),
            initial_guess_enu_m=np.array([np.full(3, np.nan) if p.initial_guess_enu_m is None
                                          else p.initial_guess_enu_m for p in problems], dtype=float).reshape(-1, 3),
        )


    @classmethod
    def _from_one(cls, p: Problem) -> "ProblemBatch":
        guess = np.full(3, np.nan) if p.initial_guess_enu_m is None else p.initial_guess_enu_m
        return cls(
            station_ids=(p.station_ids,),
            origin=p.frame.origin_array()[None],
            geodetic=np.array([p.frame.is_geodetic]),
            n_stations=np.array([p.stations_enu_m.shape[0]], dtype=np.intp),
            stations_enu_m=p.stations_enu_m[None],
            station_rotations=p.station_rotations[None],
            n_measurements=np.array([p.kinds.size], dtype=np.intp),
            kinds=p.kinds.astype(np.int8, copy=False)[None],
            station_index=p.station_index.astype(np.intp, copy=False)[None],
            values=p.values[None],
            sigmas=p.sigmas[None],
            bearing_index=p.bearing_index.astype(np.intp, copy=False)[None],
            source_index=p.source_index.astype(np.intp, copy=False)[None],
            toa_reference_s=np.array([p.toa_reference_s], dtype=float),
            altitude_m=np.array([np.nan if p.altitude_m is None else p.altitude_m], dtype=float),
            initial_guess_enu_m=np.asarray(guess, dtype=float).reshape(1, 3),
        )


def _scatter(counts) -> tuple[np.ndarray, np.ndarray, int]:
    """Where the rows of a flat array ``(sum(counts), ...)`` go in ``(B, width, ...)``: row and column
    indices, ``B`` and ``width = max(counts)`` (at least 1)."""
    counts = np.asarray(counts, dtype=np.intp)
    rows = np.repeat(np.arange(counts.size), counts)
    starts = np.cumsum(counts) - counts
    return rows, np.arange(rows.size) - starts[rows], counts.size, max(int(counts.max(initial=1)), 1)


def _pad(flat, scatter, fill):
    """Scatter rows of a flat array ``(sum(counts), ...)`` into ``(B, max(counts), ...)`` (``scatter``:
    :func:`_scatter` of the counts)."""
    flat = np.asarray(flat)
    rows, cols, size, width = scatter
    out = np.full((size, width, *flat.shape[1:]), fill, dtype=flat.dtype)
    out[rows, cols] = flat
    return out


def size_groups(n_measurements, n_stations=None) -> list[np.ndarray]:
    """Indices grouped so that padding stays under 2x: by the power of two at or above each size.

    Parameters
    ----------
    n_measurements : ndarray of int, shape (B,)
    n_stations : ndarray of int, shape (B,), optional

    Returns
    -------
    list of ndarray of int
        Each group in input order; groups by increasing size.
    """
    if len(n_measurements) <= 1:
        return [np.arange(len(n_measurements))] if len(n_measurements) else []
    sizes = np.maximum(np.asarray(n_measurements, dtype=np.intp), 1)
    if n_stations is not None:
        sizes = np.maximum(sizes, np.asarray(n_stations, dtype=np.intp))
    bucket = np.ceil(np.log2(sizes)).astype(np.intp)
    if bucket.size and bucket.min() == bucket.max():
        return [np.arange(bucket.size)]
    return [np.flatnonzero(bucket == k) for k in np.unique(bucket)]
