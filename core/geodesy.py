"""WGS84 geodesy: geodetic <-> ECEF <-> ENU, and the rotations between frames.

The forward conversion comes from pymap3d. Its inverse (and pyproj's) loses
accuracy with altitude (about 1e-6 m at 100 km and tens of metres at
20,000 km in a round trip), so :func:`ecef_to_geodetic` is our own iteration,
exact to round-off at any altitude. ENU rotation matrices are not offered by
either library in the batched form the estimators need, so they are here too.

Angles are radians; lengths metres. All functions broadcast over leading axes.
"""

from __future__ import annotations

import numpy as np
import pymap3d

WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)
_ELLIPSOID = pymap3d.Ellipsoid.from_name("wgs84")


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
    x, y, z = pymap3d.geodetic2ecef(
        np.asarray(lat_rad, dtype=float),
        np.asarray(lon_rad, dtype=float),
        np.asarray(alt_m, dtype=float),
        ell=_ELLIPSOID,
        deg=False,
    )
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(position_ecef_m):
    """ECEF to geodetic, exact to round-off from the geocentre to GEO and beyond.

    Bowring's parametric-latitude iteration, converged (it is cubically
    convergent; five rounds reach round-off everywhere outside the ellipsoid's
    evolute, i.e. farther than ~43 km from the geocentre).

    Parameters
    ----------
    position_ecef_m : ndarray, shape (..., 3)

    Returns
    -------
    lat_rad, lon_rad, alt_m : ndarray, shape (...)
    """
    p_ecef = np.asarray(position_ecef_m, dtype=float)
    x, y, z = p_ecef[..., 0], p_ecef[..., 1], p_ecef[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    beta = np.arctan2(z, (1.0 - WGS84_F) * p)
    for _ in range(5):
        sin_b, cos_b = np.sin(beta), np.cos(beta)
        lat = np.arctan2(z + WGS84_EP2 * WGS84_B_M * sin_b**3, p - WGS84_E2 * WGS84_A_M * cos_b**3)
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
    sin_lat, cos_lat = np.sin(lat), np.cos(lat)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    alt = p * cos_lat + (z + WGS84_E2 * n * sin_lat) * sin_lat - n
    return lat, lon, alt


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
    lat = np.asarray(lat_rad, dtype=float)
    lon = np.asarray(lon_rad, dtype=float)
    sp, cp, sl, cl = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    zero = np.zeros_like(sp * sl)
    rows = [
        [-sl + zero, cl + zero, zero],
        [-sp * cl, -sp * sl, cp + zero],
        [cp * cl, cp * sl, sp + zero],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


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
    origin_ecef = geodetic_to_ecef(origin_lat_rad, origin_lon_rad, origin_alt_m)
    rotation = ecef_to_enu_rotation(origin_lat_rad, origin_lon_rad)
    delta = np.asarray(position_ecef_m, dtype=float) - origin_ecef
    return np.einsum("...ij,...j->...i", rotation, delta)


def enu_to_ecef(position_enu_m, origin_lat_rad, origin_lon_rad, origin_alt_m):
    """ENU coordinates at an origin back to ECEF; the inverse of :func:`ecef_to_enu`."""
    origin_ecef = geodetic_to_ecef(origin_lat_rad, origin_lon_rad, origin_alt_m)
    rotation = ecef_to_enu_rotation(origin_lat_rad, origin_lon_rad)
    return origin_ecef + np.einsum("...ji,...j->...i", rotation, np.asarray(position_enu_m, dtype=float))


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
    centroid = geodetic_to_ecef(lat_rad, lon_rad, np.zeros_like(np.asarray(lat_rad, dtype=float))).mean(axis=0)
    if np.linalg.norm(centroid) < 1.0:
        centroid = geodetic_to_ecef(np.asarray(lat_rad)[0], np.asarray(lon_rad)[0], 0.0)
    lat, lon, _ = ecef_to_geodetic(centroid)
    return float(lat), float(lon)
