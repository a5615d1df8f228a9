"""Angle helpers. Radians everywhere in the core."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, error_model="numpy")
def wrap_point(angle_rad):
    """One angle wrapped to (-pi, pi] (compiled; the one coding that :func:`wrap_to_pi` and the kernels use).

    Inside ``[0, 2 pi)`` the remainder ``%`` would return its operand exactly, so it is only taken outside."""
    shifted = angle_rad + math.pi
    wrapped = (shifted if 0.0 <= shifted < 2.0 * math.pi else shifted % (2.0 * math.pi)) - math.pi
    return math.pi if wrapped == -math.pi else wrapped


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _wrap_many(angles_rad):
    out = np.empty_like(angles_rad)
    for i in range(angles_rad.size):
        out[i] = wrap_point(angles_rad[i])
    return out


def wrap_to_pi(angle_rad):
    """Wrap angles to the half-open interval (-pi, pi] (:func:`wrap_point` on each).

    Parameters
    ----------
    angle_rad : float or ndarray
        Angles in radians, any shape.

    Returns
    -------
    float or ndarray
        Same shape, wrapped.
    """
    angles = np.asarray(angle_rad, dtype=float)
    wrapped = _wrap_many(np.ascontiguousarray(angles).ravel()).reshape(angles.shape)
    return wrapped if wrapped.ndim else float(wrapped)


def line_of_sight_enu(azimuth_rad, elevation_rad):
    """Unit line-of-sight vectors in a station's ENU frame.

    Parameters
    ----------
    azimuth_rad : ndarray, shape (...)
        Compass azimuth, clockwise from north.
    elevation_rad : ndarray, shape (...)
        Elevation above the station's horizontal plane.

    Returns
    -------
    ndarray, shape (..., 3)
        ``[cos(el) sin(az), cos(el) cos(az), sin(el)]``.
    """
    az = np.asarray(azimuth_rad, dtype=float)
    el = np.asarray(elevation_rad, dtype=float)
    cos_el = np.cos(el)
    return np.stack([cos_el * np.sin(az), cos_el * np.cos(az), np.sin(el)], axis=-1)


def line_of_sight_derivatives(azimuth_rad, elevation_rad):
    """Unit lines of sight in a station's ENU frame and their derivatives by azimuth and elevation.

    Parameters
    ----------
    azimuth_rad, elevation_rad : ndarray, shape (...)
        As in :func:`line_of_sight_enu`.

    Returns
    -------
    direction, d_azimuth, d_elevation : ndarray, shape (..., 3)
        ``u`` (as :func:`line_of_sight_enu`), ``du/daz`` and ``du/del`` (per radian).
    """
    az = np.asarray(azimuth_rad, dtype=float)
    el = np.asarray(elevation_rad, dtype=float)
    sin_az, cos_az, sin_el, cos_el = np.sin(az), np.cos(az), np.sin(el), np.cos(el)
    direction = np.stack([cos_el * sin_az, cos_el * cos_az, sin_el], axis=-1)
    d_azimuth = np.stack([cos_el * cos_az, -cos_el * sin_az, np.zeros_like(sin_az)], axis=-1)
    d_elevation = np.stack([-sin_el * sin_az, -sin_el * cos_az, cos_el], axis=-1)
    return direction, d_azimuth, d_elevation


def station_to_common(vectors, rotations):
    """Vectors ``(..., 3)`` in each station's ENU rotated into the common frame: ``R^T v``.

    Parameters
    ----------
    vectors : ndarray, shape (..., 3)
    rotations : ndarray, shape (..., 3, 3)
        Station ENU <- common ENU.
    """
    return (vectors[..., 0, None] * rotations[..., 0, :] + vectors[..., 1, None] * rotations[..., 1, :]
            + vectors[..., 2, None] * rotations[..., 2, :])
