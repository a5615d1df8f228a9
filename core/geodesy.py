"""WGS84 geodesy: geodetic <-> ECEF <-> ENU, and the rotations between frames.

The conversions are our own. pymap3d's and pyproj's inverse loses accuracy
with altitude (about 1e-6 m at 100 km and tens of metres at 20,000 km in a
round trip), so :func:`ecef_to_geodetic` is a converged iteration, exact to
round-off at any altitude; the forward conversion is the closed form (the one
pymap3d evaluates, and the tests check against it). Each point conversion is
one compiled scalar function (:func:`geodetic_to_ecef_point`,
:func:`ecef_to_geodetic_point`, :func:`ecef_to_enu_rotation_point`), which the array functions here loop over
and compiled kernels elsewhere (the ML iteration's altitude constraint) call
directly: one implementation for one point and for a million.

Angles are radians; lengths metres. All array functions broadcast over leading axes.
"""

from __future__ import annotations

import math

import numba
import numpy as np

WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)
#: Rounds of Bowring's iteration in :func:`ecef_to_geodetic_point` (cubically convergent).
BOWRING_ROUNDS = 5


@numba.njit(cache=True, nogil=True, error_model="numpy")
def geodetic_to_ecef_point(lat_rad, lon_rad, alt_m):
    """One point's ECEF ``(x, y, z)`` (m) from geodetic coordinates (compiled; callable from kernels)."""
    sin_lat, cos_lat = math.sin(lat_rad), math.cos(lat_rad)
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    horizontal = (n + alt_m) * cos_lat
    return (horizontal * math.cos(lon_rad), horizontal * math.sin(lon_rad),
            (n * (1.0 - WGS84_E2) + alt_m) * sin_lat)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def ecef_to_geodetic_point(x, y, z):
    """One point's ``(lat_rad, lon_rad, alt_m)`` from ECEF (compiled; see :func:`ecef_to_geodetic`)."""
    lon = math.atan2(y, x)
    p = math.hypot(x, y)
    beta = math.atan2(z, (1.0 - WGS84_F) * p)
    lat = 0.0
    for _ in range(BOWRING_ROUNDS):
        sin_b, cos_b = math.sin(beta), math.cos(beta)
        lat = math.atan2(z + WGS84_EP2 * WGS84_B_M * sin_b ** 3, p - WGS84_E2 * WGS84_A_M * cos_b ** 3)
        beta = math.atan2((1.0 - WGS84_F) * math.sin(lat), math.cos(lat))
    sin_lat, cos_lat = math.sin(lat), math.cos(lat)
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    return lat, lon, p * cos_lat + (z + WGS84_E2 * n * sin_lat) * sin_lat - n


@numba.njit(cache=True, nogil=True, error_model="numpy")
def ecef_to_enu_rotation_point(lat_rad, lon_rad, out):
    """Write into ``out`` ``(3, 3)`` the rotation ECEF -> east/north/up at one point (compiled; see
    :func:`ecef_to_enu_rotation`)."""
    sp, cp, sl, cl = math.sin(lat_rad), math.cos(lat_rad), math.sin(lon_rad), math.cos(lon_rad)
    out[0, 0], out[0, 1], out[0, 2] = -sl, cl, 0.0
    out[1, 0], out[1, 1], out[1, 2] = -sp * cl, -sp * sl, cp
    out[2, 0], out[2, 1], out[2, 2] = cp * cl, cp * sl, sp


@numba.njit(cache=True, nogil=True, error_model="numpy")
def enu_to_ecef_point(east_m, north_m, up_m, origin_ecef_m, rotation):
    """One ENU point of the frame at ``origin_ecef_m`` ``(3,)`` with ECEF -> ENU ``rotation`` ``(3, 3)``, in
    ECEF (compiled; see :func:`enu_to_ecef`)."""
    return (origin_ecef_m[0] + rotation[0, 0] * east_m + rotation[1, 0] * north_m + rotation[2, 0] * up_m,
            origin_ecef_m[1] + rotation[0, 1] * east_m + rotation[1, 1] * north_m + rotation[2, 1] * up_m,
            origin_ecef_m[2] + rotation[0, 2] * east_m + rotation[1, 2] * north_m + rotation[2, 2] * up_m)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def ecef_to_enu_point(x_m, y_m, z_m, origin_ecef_m, rotation):
    """One ECEF point in the ENU frame at ``origin_ecef_m`` with ECEF -> ENU ``rotation`` (compiled; see
    :func:`ecef_to_enu`)."""
    dx, dy, dz = x_m - origin_ecef_m[0], y_m - origin_ecef_m[1], z_m - origin_ecef_m[2]
    return (rotation[0, 0] * dx + rotation[0, 1] * dy + rotation[0, 2] * dz,
            rotation[1, 0] * dx + rotation[1, 1] * dy + rotation[1, 2] * dz,
            rotation[2, 0] * dx + rotation[2, 1] * dy + rotation[2, 2] * dz)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def covariance_enu_to_ecef_point(covariance_enu_m2, rotation, out):
    """Write into ``out`` ``(3, 3)`` an ENU covariance ``(3, 3)`` of the frame with ECEF -> ENU ``rotation``,
    in ECEF: ``R^T C R`` (compiled; see :func:`covariance_enu_to_ecef`)."""
    for i in range(3):
        for j in range(3):
            total = 0.0
            for k in range(3):
                total += rotation[k, i] * (covariance_enu_m2[k, 0] * rotation[0, j] + covariance_enu_m2[k, 1]
                                           * rotation[1, j] + covariance_enu_m2[k, 2] * rotation[2, j])
            out[i, j] = total


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _covariances_to_ecef_many(covariance_enu_m2, rotations):
    out = np.empty_like(covariance_enu_m2)
    shared = rotations.shape[0] == 1
    for i in range(covariance_enu_m2.shape[0]):
        covariance_enu_to_ecef_point(covariance_enu_m2[i], rotations[0 if shared else i], out[i])
    return out


def covariance_enu_to_ecef(covariance_enu_m2, rotation):
    """ENU covariances in ECEF, ``R^T C R``.

    Parameters
    ----------
    covariance_enu_m2 : ndarray, shape (..., 3, 3)
    rotation : ndarray, shape (3, 3) or (..., 3, 3)
        ECEF -> ENU of each covariance's frame (:func:`ecef_to_enu_rotation`).

    Returns
    -------
    ndarray, shape (..., 3, 3)
    """
    covariance = np.asarray(covariance_enu_m2, dtype=float)
    rotations = np.ascontiguousarray(np.asarray(rotation, dtype=float).reshape(-1, 3, 3))
    return _covariances_to_ecef_many(np.ascontiguousarray(covariance).reshape(-1, 3, 3),
                                     rotations).reshape(covariance.shape)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _between_frames_many(points, origin_ecef_m, rotations, to_ecef):
    out = np.empty_like(points)
    shared = origin_ecef_m.shape[0] == 1
    for i in range(points.shape[0]):
        k = 0 if shared else i
        p, o, r = points[i], origin_ecef_m[k], rotations[k]
        if to_ecef:
            out[i, 0], out[i, 1], out[i, 2] = enu_to_ecef_point(p[0], p[1], p[2], o, r)
        else:
            out[i, 0], out[i, 1], out[i, 2] = ecef_to_enu_point(p[0], p[1], p[2], o, r)
    return out


def _between_frames(points_m, origin_lat_rad, origin_lon_rad, origin_alt_m, to_ecef: bool):
    """:func:`enu_to_ecef_point` (``to_ecef``) or :func:`ecef_to_enu_point` over broadcast points and origins
    (one origin for all points is not repeated)."""
    points = np.asarray(points_m, dtype=float)
    origin_ecef = geodetic_to_ecef(origin_lat_rad, origin_lon_rad, origin_alt_m)
    rotation = ecef_to_enu_rotation(origin_lat_rad, origin_lon_rad)
    shape = np.broadcast_shapes(points.shape[:-1], origin_ecef.shape[:-1])
    if points.shape[:-1] != shape:
        points = np.broadcast_to(points, shape + (3,))
    if origin_ecef.ndim > 1 and origin_ecef.shape[:-1] != shape:
        origin_ecef = np.broadcast_to(origin_ecef, shape + (3,))
        rotation = np.broadcast_to(rotation, shape + (3, 3))
    return _between_frames_many(np.ascontiguousarray(points).reshape(-1, 3),
                                np.ascontiguousarray(origin_ecef).reshape(-1, 3),
                                np.ascontiguousarray(rotation).reshape(-1, 3, 3), to_ecef).reshape(shape + (3,))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _rotations_many(lat_rad, lon_rad):
    out = np.empty((lat_rad.size, 3, 3))
    for i in range(lat_rad.size):
        ecef_to_enu_rotation_point(lat_rad[i], lon_rad[i], out[i])
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _to_ecef_many(lat_rad, lon_rad, alt_m):
    out = np.empty((lat_rad.size, 3))
    for i in range(lat_rad.size):
        out[i, 0], out[i, 1], out[i, 2] = geodetic_to_ecef_point(lat_rad[i], lon_rad[i], alt_m[i])
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _to_geodetic_many(position_ecef_m):
    out = np.empty((3, position_ecef_m.shape[0]))
    for i in range(position_ecef_m.shape[0]):
        out[0, i], out[1, i], out[2, i] = ecef_to_geodetic_point(
            position_ecef_m[i, 0], position_ecef_m[i, 1], position_ecef_m[i, 2])
    return out


def geodetic_to_ecef(lat_rad, lon_rad, alt_m):
    """Geodetic coordinates to Earth-centred Earth-fixed.

    Parameters
    ----------
    lat_rad, lon_rad : ndarray, shape (...)
        Geodetic latitude and longitude.
    alt_m : ndarray, shape (...)
        Height above the WGS84 ellipsoid.

    Returns
    -------
    ndarray, shape (..., 3)
        ECEF position in metres.
    """
    lat, lon, alt = np.broadcast_arrays(np.asarray(lat_rad, dtype=float), np.asarray(lon_rad, dtype=float),
                                        np.asarray(alt_m, dtype=float))
    return _to_ecef_many(np.ascontiguousarray(lat).ravel(), np.ascontiguousarray(lon).ravel(),
                         np.ascontiguousarray(alt).ravel()).reshape(lat.shape + (3,))


def ecef_to_geodetic(position_ecef_m):
    """ECEF to geodetic, exact to round-off from the geocentre to GEO and beyond.

    Bowring's parametric-latitude iteration, converged (it is cubically
    convergent; :data:`BOWRING_ROUNDS` = 5 rounds reach round-off everywhere outside the ellipsoid's
    evolute, i.e. farther than ~43 km from the geocentre).

    Parameters
    ----------
    position_ecef_m : ndarray, shape (..., 3)

    Returns
    -------
    lat_rad, lon_rad, alt_m : ndarray, shape (...)
    """
    p_ecef = np.asarray(position_ecef_m, dtype=float)
    lat, lon, alt = _to_geodetic_many(np.ascontiguousarray(p_ecef.reshape(-1, 3)))
    shape = p_ecef.shape[:-1]
    return lat.reshape(shape)[()], lon.reshape(shape)[()], alt.reshape(shape)[()]


def ecef_to_enu_rotation(lat_rad, lon_rad):
    """Rotation matrices taking ECEF vectors to east/north/up at a point.

    Parameters
    ----------
    lat_rad, lon_rad : ndarray, shape (...)

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``R`` with ``v_enu = R @ v_ecef``; its transpose goes back. A
        covariance moves as ``C_enu = R C_ecef R^T``.
    """
    lat, lon = np.broadcast_arrays(np.asarray(lat_rad, dtype=float), np.asarray(lon_rad, dtype=float))
    return _rotations_many(np.ascontiguousarray(lat).ravel(), np.ascontiguousarray(lon).ravel()).reshape(
        lat.shape + (3, 3))


def ecef_to_enu(position_ecef_m, origin_lat_rad, origin_lon_rad, origin_alt_m):
    """ECEF points to ENU coordinates in the tangent frame at an origin.

    Parameters
    ----------
    position_ecef_m : ndarray, shape (..., 3)
    origin_lat_rad, origin_lon_rad, origin_alt_m : float or ndarray, shape (...)

    Returns
    -------
    ndarray, shape (..., 3)
    """
    return _between_frames(position_ecef_m, origin_lat_rad, origin_lon_rad, origin_alt_m, to_ecef=False)


def enu_to_ecef(position_enu_m, origin_lat_rad, origin_lon_rad, origin_alt_m):
    """ENU coordinates at an origin back to ECEF; the inverse of :func:`ecef_to_enu`."""
    return _between_frames(position_enu_m, origin_lat_rad, origin_lon_rad, origin_alt_m, to_ecef=True)


def enu_to_ecef_placed(position_enu_m, origin_ecef_m, rotation):
    """:func:`enu_to_ecef` for frames already placed (as :func:`core.problem.frame.frame_placements` places them).

    Parameters
    ----------
    position_enu_m : ndarray, shape (B, 3)
    origin_ecef_m : ndarray, shape (B, 3)
    rotation : ndarray, shape (B, 3, 3)
        ECEF -> ENU at each origin.

    Returns
    -------
    ndarray, shape (B, 3)
    """
    return _between_frames_many(np.ascontiguousarray(position_enu_m, dtype=float),
                                np.ascontiguousarray(origin_ecef_m, dtype=float),
                                np.ascontiguousarray(rotation, dtype=float), True)


def geodetic_to_enu(lat_rad, lon_rad, alt_m, origin_lat_rad, origin_lon_rad, origin_alt_m):
    """Geodetic points to ENU at an origin. Returns shape (..., 3)."""
    return ecef_to_enu(geodetic_to_ecef(lat_rad, lon_rad, alt_m), origin_lat_rad, origin_lon_rad, origin_alt_m)


def enu_to_geodetic(position_enu_m, origin_lat_rad, origin_lon_rad, origin_alt_m):
    """ENU at an origin to geodetic. Returns ``(lat_rad, lon_rad, alt_m)``."""
    return ecef_to_geodetic(enu_to_ecef(position_enu_m, origin_lat_rad, origin_lon_rad, origin_alt_m))


def enu_to_enu_rotation(from_lat_rad, from_lon_rad, to_lat_rad, to_lon_rad):
    """Rotation taking vectors from one tangent frame's ENU axes to another's.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``R_to @ R_from^T``: station ENU -> ECEF -> common ENU when ``from``
        is the station and ``to`` the common reference.
    """
    r_from = ecef_to_enu_rotation(from_lat_rad, from_lon_rad)
    r_to = ecef_to_enu_rotation(to_lat_rad, to_lon_rad)
    return r_to @ np.swapaxes(r_from, -1, -2)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def rotation_from_point(lat_rad, lon_rad, origin_rotation, out):
    """Into ``out`` ``(3, 3)``: the rotation from the common ENU frame (ECEF -> ENU ``origin_rotation``) to the
    tangent frame at ``(lat_rad, lon_rad)``, ``R(lat, lon) R_origin^T`` (compiled)."""
    ecef_to_enu_rotation_point(lat_rad, lon_rad, out)
    for i in range(3):
        a, b, c = out[i, 0], out[i, 1], out[i, 2]
        for j in range(3):
            out[i, j] = a * origin_rotation[j, 0] + b * origin_rotation[j, 1] + c * origin_rotation[j, 2]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def covariance_to_point(covariance_enu_m2, lat_rad, lon_rad, origin_rotation, turn, out):
    """Into ``out`` ``(3, 3)``: a covariance ``(3, 3)`` in the common frame's ENU axes (ECEF -> ENU
    ``origin_rotation``) re-expressed in the east/north/up axes at ``(lat_rad, lon_rad)``, ``T C T^T`` with
    ``T`` :func:`rotation_from_point` (written into ``turn`` ``(3, 3)``; compiled).

    The two frames' axes differ by the meridian convergence and the earth's curvature between their
    points: over a few hundred kilometres the vertical variance moves by a few percent.
    """
    rotation_from_point(lat_rad, lon_rad, origin_rotation, turn)
    for i in range(3):
        for j in range(i + 1):
            total = 0.0
            for k in range(3):
                total += turn[i, k] * (covariance_enu_m2[k, 0] * turn[j, 0] + covariance_enu_m2[k, 1] * turn[j, 1]
                                       + covariance_enu_m2[k, 2] * turn[j, 2])
            out[i, j] = out[j, i] = total


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _covariances_to_points(covariance_enu_m2, lat_rad, lon_rad, origin_rotation):
    out, turn = np.empty_like(covariance_enu_m2), np.empty((3, 3))
    for i in range(covariance_enu_m2.shape[0]):
        covariance_to_point(covariance_enu_m2[i], lat_rad[i], lon_rad[i], origin_rotation, turn, out[i])
    return out


def covariances_to_points(covariance_enu_m2, lat_rad, lon_rad, origin_rotation):
    """Covariances in one common frame's ENU axes, each in the east/north/up axes at its own point
    (:func:`covariance_to_point`).

    Parameters
    ----------
    covariance_enu_m2 : ndarray, shape (N, 3, 3)
    lat_rad, lon_rad : ndarray, shape (N,)
        Each covariance's point.
    origin_rotation : ndarray, shape (3, 3)
        The common frame's ECEF -> ENU rotation (:func:`ecef_to_enu_rotation` at its origin).

    Returns
    -------
    ndarray, shape (N, 3, 3)
    """
    covariance = np.ascontiguousarray(covariance_enu_m2, dtype=float).reshape(-1, 3, 3)
    return _covariances_to_points(covariance, np.ascontiguousarray(lat_rad, dtype=float).reshape(-1),
                                  np.ascontiguousarray(lon_rad, dtype=float).reshape(-1),
                                  np.ascontiguousarray(origin_rotation, dtype=float))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def centroid_on_ellipsoid_point(lat_rad, lon_rad):
    """:func:`centroid_on_ellipsoid` of points ``(N,)`` (compiled; callable from kernels)."""
    x = y = z = 0.0
    for i in range(lat_rad.size):
        px, py, pz = geodetic_to_ecef_point(lat_rad[i], lon_rad[i], 0.0)
        x, y, z = x + px, y + py, z + pz
    x, y, z = x / lat_rad.size, y / lat_rad.size, z / lat_rad.size
    if math.sqrt(x * x + y * y + z * z) < 1.0:
        x, y, z = geodetic_to_ecef_point(lat_rad[0], lon_rad[0], 0.0)
    lat, lon, _ = ecef_to_geodetic_point(x, y, z)
    return lat, lon


def centroid_on_ellipsoid(lat_rad, lon_rad):
    """Geodetic (lat, lon) of the ECEF centroid of points, projected to the ellipsoid.

    Well defined across the antimeridian, unlike averaging longitudes.

    Parameters
    ----------
    lat_rad, lon_rad : ndarray, shape (N,)

    Returns
    -------
    lat_rad, lon_rad : float
    """
    lat, lon = centroid_on_ellipsoid_point(np.ascontiguousarray(lat_rad, dtype=float).reshape(-1),
                                           np.ascontiguousarray(lon_rad, dtype=float).reshape(-1))
    return float(lat), float(lon)
