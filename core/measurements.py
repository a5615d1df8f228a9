"""Measurement models and their analytic Jacobians (ALGORITHMS.md section 2).

A station ``s`` (common ENU frame, metres) with rotation ``R_s`` (station ENU
<- common ENU) sees the target ``p`` at ``d = R_s (p - s) = (e, n, u)``.

Times of arrival are handled as pseudo-ranges: ``c * (toa - toa_reference)``
in metres against the model ``r + b`` with ``b = c * (t0 - toa_reference)``
the unknown emission-time offset in metres. This keeps the normal equations
in one unit and free of the large absolute epoch.

Every function broadcasts over leading axes, so one call serves a single
problem ``(M,)`` or a batch ``(B, M)``.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

from core.angles import wrap_to_pi

SPEED_OF_LIGHT_MPS = 299_792_458.0

#: Below this horizontal distance (m) the azimuth of the target is undefined.
MIN_HORIZONTAL_DISTANCE_M = 1e-6


class Kind(IntEnum):
    """What a scalar measurement observes."""

    AZIMUTH = 0
    ELEVATION = 1
    RANGE = 2
    TOA = 3



def relative_position(position_enu_m, stations_enu_m, rotations):
    """Target position in each station's own ENU frame.

    Parameters
    ----------
    position_enu_m : ndarray, shape (..., 3)
        Target in the common frame.
    stations_enu_m : ndarray, shape (..., M, 3)
        Station of each measurement in the common frame.
    rotations : ndarray, shape (..., M, 3, 3)
        Station ENU <- common ENU.

    Returns
    -------
    ndarray, shape (..., M, 3)
    """
    delta = np.asarray(position_enu_m)[..., None, :] - stations_enu_m
    return np.einsum("...ij,...j->...i", rotations, delta)


def predict(position_enu_m, bias_m, stations_enu_m, rotations, kinds):
    """Predicted measurements and their Jacobian.

    Parameters
    ----------
    position_enu_m : ndarray, shape (..., 3)
    bias_m : ndarray, shape (...)
        TOA emission-time offset times c; ignored for other kinds.
    stations_enu_m : ndarray, shape (..., M, 3)
    rotations : ndarray, shape (..., M, 3, 3)
    kinds : ndarray of int, shape (..., M)
        :class:`Kind` codes.

    Returns
    -------
    predicted : ndarray, shape (..., M)
        Radians for angles, metres for range and TOA pseudo-range.
    jacobian : ndarray, shape (..., M, 4)
        Derivatives w.r.t. ``(east, north, up, bias)`` of the common frame.
    """
    d = relative_position(position_enu_m, stations_enu_m, rotations)
    e, n, u = d[..., 0], d[..., 1], d[..., 2]
    rho2 = np.maximum(e * e + n * n, MIN_HORIZONTAL_DISTANCE_M**2)
    rho = np.sqrt(rho2)
    r2 = rho2 + u * u
    r = np.sqrt(r2)
    zero = np.zeros_like(e)

    is_az = kinds == Kind.AZIMUTH
    is_el = kinds == Kind.ELEVATION
    is_toa = kinds == Kind.TOA
    predicted = np.where(is_az, np.arctan2(e, n), np.where(is_el, np.arctan2(u, rho), r))
    predicted = predicted + np.where(is_toa, np.asarray(bias_m)[..., None], 0.0)

    grad_az = np.stack([n / rho2, -e / rho2, zero], axis=-1)
    grad_el = np.stack([-e * u / (r2 * rho), -n * u / (r2 * rho), rho / r2], axis=-1)
    grad_r = d / r[..., None]
    grad_d = np.where(is_az[..., None], grad_az, np.where(is_el[..., None], grad_el, grad_r))
    grad_p = np.einsum("...i,...ij->...j", grad_d, rotations)
    jacobian = np.concatenate([grad_p, is_toa[..., None].astype(float)], axis=-1)
    return predicted, jacobian


def residuals(measured, predicted, kinds):
    """Measured minus predicted, with angle residuals wrapped to (-pi, pi].

    Shapes broadcast: ``(..., M)``.
    """
    raw = np.asarray(measured) - predicted
    is_angle = (kinds == Kind.AZIMUTH) | (kinds == Kind.ELEVATION)
    return np.where(is_angle, wrap_to_pi(raw), raw)


def azimuth_rate(position_enu_m, velocity_enu_mps):
    """Rate of change of the azimuth of a moving target seen from a fixed station at the origin, and its
    Jacobian (ALGORITHMS.md sections 2 and 6).

    ``Bdot = (n v_e - e v_n) / rho^2`` with ``(e, n, u)`` the position and
    ``rho^2 = e^2 + n^2`` (floored like :func:`predict`'s azimuth).

    Parameters
    ----------
    position_enu_m : ndarray, shape (..., 3)
        Target relative to the station, in the station's ENU.
    velocity_enu_mps : ndarray, shape (..., 3)
        Target velocity relative to the station.

    Returns
    -------
    rate_rad_s : ndarray, shape (...)
    jacobian : ndarray, shape (..., 6)
        Derivatives w.r.t. ``(e, n, u, v_e, v_n, v_u)``.
    """
    p = np.asarray(position_enu_m, dtype=float)
    v = np.asarray(velocity_enu_mps, dtype=float)
    e, n = p[..., 0], p[..., 1]
    ve, vn = v[..., 0], v[..., 1]
    rho2 = np.maximum(e * e + n * n, MIN_HORIZONTAL_DISTANCE_M**2)
    rate = (n * ve - e * vn) / rho2
    zero = np.zeros_like(rate)
    jacobian = np.stack([(-vn - 2.0 * e * rate) / rho2, (ve - 2.0 * n * rate) / rho2, zero,
                         n / rho2, -e / rho2, zero], axis=-1)
    return rate, jacobian
