"""One localisation problem in its exact common ENU frame: the points, the frame and the problem record.

:class:`CommonFrame` is the tangent plane every estimator works in (ALGORITHMS.md
section 1): at the given origin, else at the stations' centroid on the
ellipsoid (:func:`frame_placements`). Station positions and lines of sight
are rotated into it exactly, with no flat-earth shortcut. A ``local`` problem
without an origin is a flat plane with no earth under it: every station
shares the plane's axes. :class:`Problem` is one problem in that frame, the
record every estimator reads.

This module sits below :mod:`core.problem.build` (which checks and builds a single
problem), :mod:`core.problem.batch` (many at once, handing one back as a
:class:`Problem`) and :mod:`core.problem.batch_build`, so none of them
imports another back.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numba
import numpy as np

from core import geodesy
from core.angles import line_of_sight_enu
from core.measurements import SPEED_OF_LIGHT_MPS, Kind


@dataclass(frozen=True)
class GeodeticPoint:
    """WGS84 position: radians and metres above the ellipsoid."""

    lat_rad: float
    lon_rad: float
    alt_m: float


@dataclass(frozen=True)
class LocalPoint:
    """East/north/up metres in a tangent plane."""

    east_m: float
    north_m: float
    up_m: float


@dataclass(frozen=True)
class CommonFrame:
    """The tangent frame every estimator works in.

    Parameters
    ----------
    origin : GeodeticPoint or None
        Where the frame touches the earth; None for a flat local plane.
    """

    origin: GeodeticPoint | None

    @property
    def is_geodetic(self) -> bool:
        return self.origin is not None

    @property
    def ecef_to_enu_rotation(self) -> np.ndarray:
        """Rotation ``(3, 3)``: ECEF vectors to the frame's ENU axes."""
        return geodesy.ecef_to_enu_rotation(self.origin.lat_rad, self.origin.lon_rad)

    def to_ecef(self, position_enu_m):
        """Frame ENU ``(..., 3)`` to ECEF ``(..., 3)``."""
        o = self.origin
        return geodesy.enu_to_ecef(position_enu_m, o.lat_rad, o.lon_rad, o.alt_m)

    @cached_property
    def placement(self) -> tuple[np.ndarray, np.ndarray]:
        """The origin's ECEF position ``(3,)`` and ECEF -> ENU rotation ``(3, 3)`` (:func:`frame_placements`;
        those of zero latitude and longitude for a flat plane, where nothing reads them), made once per frame."""
        return frame_placements(self.origin_array())

    def to_geodetic(self, position_enu_m):
        """Frame ENU ``(..., 3)`` to ``(lat_rad, lon_rad, alt_m)``."""
        p = np.asarray(position_enu_m, dtype=float)
        if p.shape == (3,):  # one point: the same compiled steps, on the frame's placement made once
            return tuple(np.float64(v) for v in _enu_to_geodetic_point(p, *self.placement))
        return geodesy.ecef_to_geodetic(self.to_ecef(p))

    def from_geodetic(self, lat_rad, lon_rad, alt_m):
        """Geodetic to frame ENU ``(..., 3)``."""
        o = self.origin
        return geodesy.geodetic_to_enu(lat_rad, lon_rad, alt_m, o.lat_rad, o.lon_rad, o.alt_m)

    def covariance_to_ecef(self, covariance_enu_m2):
        """Rotate covariances ``(..., 3, 3)`` from the frame's ENU to ECEF."""
        return geodesy.covariance_enu_to_ecef(covariance_enu_m2, self.ecef_to_enu_rotation)

    def origin_array(self) -> np.ndarray:
        """``(lat_rad, lon_rad, alt_m)`` of the origin, zeros for a flat plane."""
        o = self.origin
        return np.zeros(3) if o is None else np.array([o.lat_rad, o.lon_rad, o.alt_m])

    def local_axes(self, position_enu_m):
        """Local east/north/up unit vectors at points; see :func:`local_axes`."""
        p = np.asarray(position_enu_m, dtype=float)
        if p.shape == (3,):  # one point: the same compiled steps, on the frame's placement made once
            axes = np.empty((3, 3))
            local_axes_point(p, self.is_geodetic, *self.placement, axes)
            return axes
        return local_axes(p, self.origin_array(), self.is_geodetic)

    def onto_altitude(self, position_enu_m, altitude_m):
        """Points moved onto a constant altitude; see :func:`onto_altitude`."""
        p = np.asarray(position_enu_m, dtype=float)
        return onto_altitude(p, altitude_m, self.origin_array(), self.is_geodetic)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _enu_to_geodetic_point(position_enu_m, origin_ecef_m, origin_rotation):
    x, y, z = geodesy.enu_to_ecef_point(position_enu_m[0], position_enu_m[1], position_enu_m[2], origin_ecef_m,
                                        origin_rotation)
    return geodesy.ecef_to_geodetic_point(x, y, z)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def onto_altitude_point(position_enu_m, altitude_m, geodetic, origin_ecef_m, origin_rotation):
    """:func:`onto_altitude` of one point ``(3,)``, in place (compiled; callable from kernels).

    ``origin_ecef_m`` ``(3,)`` and ``origin_rotation`` ``(3, 3)`` place the frame (:func:`frame_placements`).
    """
    if not geodetic:
        position_enu_m[2] = altitude_m
        return
    lat, lon, _ = _enu_to_geodetic_point(position_enu_m, origin_ecef_m, origin_rotation)
    x, y, z = geodesy.geodetic_to_ecef_point(lat, lon, altitude_m)
    position_enu_m[0], position_enu_m[1], position_enu_m[2] = geodesy.ecef_to_enu_point(x, y, z, origin_ecef_m,
                                                                                         origin_rotation)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def local_axes_point(position_enu_m, geodetic, origin_ecef_m, origin_rotation, axes):
    """:func:`local_axes` of one point into ``axes`` ``(3, 3)`` (compiled)."""
    if not geodetic:
        for i in range(3):
            for j in range(3):
                axes[i, j] = 1.0 if i == j else 0.0
        return
    lat, lon, _ = _enu_to_geodetic_point(position_enu_m, origin_ecef_m, origin_rotation)
    geodesy.rotation_from_point(lat, lon, origin_rotation, axes)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _onto_altitude_many(positions_enu_m, altitude_m, geodetic, origin_ecef_m, origin_rotation):
    out = positions_enu_m.copy()
    for i in range(out.shape[0]):
        onto_altitude_point(out[i], altitude_m[i], geodetic[i], origin_ecef_m[i], origin_rotation[i])
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _local_axes_many(positions_enu_m, geodetic, origin_ecef_m, origin_rotation):
    out = np.empty((positions_enu_m.shape[0], 3, 3))
    for i in range(out.shape[0]):
        local_axes_point(positions_enu_m[i], geodetic[i], origin_ecef_m[i], origin_rotation[i], out[i])
    return out


def frame_placements(origin):
    """Where frames sit on the earth: each origin's ECEF position and its ECEF -> ENU rotation.

    Parameters
    ----------
    origin : ndarray, shape (..., 3)
        Each frame's ``(lat_rad, lon_rad, alt_m)`` (NaN for a flat plane: the results are then unused).

    Returns
    -------
    origin_ecef_m : ndarray, shape (..., 3)
    rotation : ndarray, shape (..., 3, 3)
    """
    origin = np.asarray(origin, dtype=float)
    return (geodesy.geodetic_to_ecef(origin[..., 0], origin[..., 1], origin[..., 2]),
            geodesy.ecef_to_enu_rotation(origin[..., 0], origin[..., 1]))


def _flat_points(position_enu_m, origin, geodetic, *more):
    """Broadcast point arguments and flatten them for the compiled loops: (shape, flat arrays...)."""
    position = np.asarray(position_enu_m, dtype=float)
    origin = np.asarray(origin, dtype=float)
    shape = np.broadcast_shapes(position.shape[:-1], origin.shape[:-1], np.shape(geodetic),
                                *(np.shape(m) for m in more))
    flat = [np.ascontiguousarray(np.broadcast_to(position, shape + (3,))).reshape(-1, 3),
            np.ascontiguousarray(np.broadcast_to(origin, shape + (3,))).reshape(-1, 3),
            np.ascontiguousarray(np.broadcast_to(np.asarray(geodetic, dtype=np.bool_), shape)).ravel()]
    flat += [np.ascontiguousarray(np.broadcast_to(np.asarray(m, dtype=float), shape)).ravel() for m in more]
    return shape, flat


def local_axes(position_enu_m, origin, geodetic):
    """Local east/north/up unit vectors at points, in their frames' coordinates.

    Parameters
    ----------
    position_enu_m : ndarray, shape (..., 3)
    origin : ndarray, shape (..., 3)
        Each frame's ``(lat_rad, lon_rad, alt_m)``.
    geodetic : bool or ndarray of bool, shape (...)
        False for a flat plane (axes are the identity there).

    Returns
    -------
    ndarray, shape (..., 3, 3)
        Rows east, north, up at each point (point ENU <- frame ENU).
    """
    shape, (position, origin, geodetic) = _flat_points(position_enu_m, origin, geodetic)
    origin_ecef, rotation = frame_placements(origin)
    return _local_axes_many(position, geodetic, origin_ecef, rotation).reshape(shape + (3, 3))


def onto_altitude(position_enu_m, altitude_m, origin, geodetic):
    """Move points along their local vertical onto a constant altitude.

    Parameters
    ----------
    position_enu_m : ndarray, shape (..., 3)
    altitude_m : float or ndarray, shape (...)
        Geodetic altitude, or the ``up`` coordinate in a flat plane.
    origin, geodetic
        As in :func:`local_axes`.

    Returns
    -------
    ndarray, shape (..., 3)
    """
    shape, (position, origin, geodetic, altitude) = _flat_points(position_enu_m, origin, geodetic, altitude_m)
    origin_ecef, rotation = frame_placements(origin)
    return _onto_altitude_many(position, altitude, geodetic, origin_ecef, rotation).reshape(shape + (3,))


@dataclass(frozen=True)
class Problem:
    """One localisation problem in its common frame.

    Attributes
    ----------
    frame : CommonFrame
    station_ids : tuple of str, length N
    stations_enu_m : ndarray, shape (N, 3)
        Station positions in the common frame.
    station_rotations : ndarray, shape (N, 3, 3)
        Station ENU <- common ENU (identity in a flat plane).
    kinds : ndarray of int, shape (M,)
        :class:`~core.measurements.Kind` of each scalar measurement.
    station_index : ndarray of int, shape (M,)
    values : ndarray, shape (M,)
        Radians for angles, metres for ranges, seconds after
        ``toa_reference_s`` for TOA.
    sigmas : ndarray, shape (M,)
        Same units; NaN where the caller gave no sigma.
    bearing_index : ndarray of int, shape (M,)
        Which line of sight an angle belongs to (``-1`` for range and TOA).
    source_index : ndarray of int, shape (M,)
        Index of the caller's measurement this scalar came from (a bearing
        gives an azimuth and possibly an elevation).
    toa_reference_s : float
        Subtracted from every TOA before any arithmetic.
    altitude_m : float or None
        Known target altitude (geodetic, or ``up`` in a flat plane).
    initial_guess_enu_m : ndarray, shape (3,), or None
    """

    frame: CommonFrame
    station_ids: tuple[str, ...]
    stations_enu_m: np.ndarray
    station_rotations: np.ndarray
    kinds: np.ndarray
    station_index: np.ndarray
    values: np.ndarray
    sigmas: np.ndarray
    bearing_index: np.ndarray
    source_index: np.ndarray
    toa_reference_s: float = 0.0
    altitude_m: float | None = None
    initial_guess_enu_m: np.ndarray | None = None

    @property
    def n_measurements(self) -> int:
        return int(self.kinds.size)

    @property
    def has_toa(self) -> bool:
        return bool(np.any(self.kinds == Kind.TOA))

    def count(self, kind: Kind) -> int:
        return int(np.count_nonzero(self.kinds == kind))

    def unit_scale(self) -> np.ndarray:
        """Factor ``(M,)`` from problem units to model units (TOA seconds -> metres)."""
        return np.where(self.kinds == Kind.TOA, SPEED_OF_LIGHT_MPS, 1.0)

    def model_values(self) -> np.ndarray:
        """Values ``(M,)`` in the units of :func:`core.measurements.predict`."""
        return self.values * self.unit_scale()

    def model_sigmas(self) -> np.ndarray:
        """Sigmas ``(M,)`` in the units of :func:`core.measurements.predict`."""
        return self.sigmas * self.unit_scale()

    def lines_of_sight(self) -> "LinesOfSight":
        """The bearings of this problem grouped per line of sight."""
        return LinesOfSight.from_problem(self)

    def with_values(self, values) -> "Problem":
        """A copy with other measured values (problem units: rad, m, s after the TOA reference)."""
        return replace(self, values=np.asarray(values, dtype=float))

    def with_sigmas(self, sigmas) -> "Problem":
        """A copy with other measurement sigmas (same units as ``sigmas``)."""
        return replace(self, sigmas=np.asarray(sigmas, dtype=float))


@dataclass(frozen=True)
class LinesOfSight:
    """Bearings as lines of sight, in request order.

    Attributes
    ----------
    station_index : ndarray of int, shape (K,)
    origins_enu_m : ndarray, shape (K, 3)
        Station position of each line, common frame.
    rotations : ndarray, shape (K, 3, 3)
        Station ENU <- common ENU.
    azimuth_rad, elevation_rad : ndarray, shape (K,)
        Elevation NaN for an azimuth-only bearing.
    sigma_azimuth_rad, sigma_elevation_rad : ndarray, shape (K,)
        NaN where not given.
    azimuth_row, elevation_row : ndarray of int, shape (K,)
        Index of the scalar measurement in the problem (``-1`` if absent).
    """

    station_index: np.ndarray
    origins_enu_m: np.ndarray
    rotations: np.ndarray
    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    sigma_azimuth_rad: np.ndarray
    sigma_elevation_rad: np.ndarray
    azimuth_row: np.ndarray
    elevation_row: np.ndarray

    @classmethod
    def from_problem(cls, problem: Problem) -> "LinesOfSight":
        n_los = int(problem.bearing_index.max()) + 1 if problem.bearing_index.size else 0
        az_row = np.full(n_los, -1)
        el_row = np.full(n_los, -1)
        for row, (kind, los) in enumerate(zip(problem.kinds, problem.bearing_index)):
            if kind == Kind.AZIMUTH:
                az_row[los] = row
            elif kind == Kind.ELEVATION:
                el_row[los] = row
        lines = az_row >= 0  # an elevation without its azimuth (set aside) is no line of sight
        az_row, el_row = az_row[lines], el_row[lines]
        station = problem.station_index[az_row]
        has_el = el_row >= 0
        el_values = np.where(has_el, problem.values[el_row], np.nan)
        el_sigmas = np.where(has_el, problem.sigmas[el_row], np.nan)
        return cls(
            station_index=station,
            origins_enu_m=problem.stations_enu_m[station],
            rotations=problem.station_rotations[station],
            azimuth_rad=problem.values[az_row],
            elevation_rad=el_values,
            sigma_azimuth_rad=problem.sigmas[az_row],
            sigma_elevation_rad=el_sigmas,
            azimuth_row=az_row,
            elevation_row=el_row,
        )

    @property
    def count(self) -> int:
        return int(self.station_index.size)

    @property
    def has_elevation(self) -> np.ndarray:
        return ~np.isnan(self.elevation_rad)

    def directions_enu(self) -> np.ndarray:
        """Unit line-of-sight vectors ``(K, 3)`` in the common frame (azimuth-only: horizontal)."""
        el = np.where(self.has_elevation, self.elevation_rad, 0.0)
        local = line_of_sight_enu(self.azimuth_rad, el)
        return np.einsum("kji,kj->ki", self.rotations, local)
