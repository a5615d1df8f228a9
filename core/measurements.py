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


class MeasurementModel:
    """The measurement model of B measurement sets: ``h(p, b)`` and its Jacobian in one fused pass.

    The stations and rotations are held component-first, ``(3, B, M)`` and
    ``(3, 3, B, M)``: element-wise arithmetic on whole ``(B, M)`` planes is
    several times faster than ``einsum`` or ``matmul`` over ``(B, M, 3, 3)``
    blocks of 3x3 matrices. Every estimator, the CRLB and the finisher
    evaluate the model through this class (or :func:`predict`, which wraps it).

    Parameters
    ----------
    stations_enu_m : ndarray, shape (B, M, 3)
        Station of each measurement, common frame.
    rotations : ndarray, shape (B, M, 3, 3)
        Station ENU <- common ENU.
    kinds : ndarray of int, shape (B, M)
        :class:`Kind` codes.
    """

    def __init__(self, stations_enu_m, rotations, kinds):
        self.stations = np.ascontiguousarray(np.moveaxis(np.asarray(stations_enu_m, dtype=float), -1, 0))
        self.rotations = np.ascontiguousarray(np.moveaxis(np.asarray(rotations, dtype=float), (-2, -1), (0, 1)))
        kinds = np.asarray(kinds)
        self.kinds = kinds
        self.is_az = kinds == Kind.AZIMUTH
        self.is_el = kinds == Kind.ELEVATION
        self.is_angle = self.is_az | self.is_el
        self.is_toa = (kinds == Kind.TOA).astype(float)
        self.ranged = not bool(np.all(self.is_angle))

    def take(self, rows) -> "MeasurementModel":
        """The model of the sets ``rows``."""
        out = object.__new__(MeasurementModel)
        out.stations = self.stations[:, rows]
        out.rotations = self.rotations[:, :, rows]
        for name in ("kinds", "is_az", "is_el", "is_angle", "is_toa"):
            setattr(out, name, getattr(self, name)[rows])
        out.ranged = not bool(np.all(out.is_angle))
        return out

    def predict(self, positions_enu_m, bias_m):
        """Predicted measurements ``(B, M)`` and their Jacobian ``(B, 4, M)``.

        Parameters
        ----------
        positions_enu_m : ndarray, shape (B, 3)
        bias_m : ndarray, shape (B,)
            TOA emission-time offset times c; ignored for other kinds.

        Returns
        -------
        predicted : ndarray, shape (B, M)
            Radians for angles, metres for range and TOA pseudo-range.
        jacobian : ndarray, shape (B, 4, M)
            Derivatives w.r.t. ``(east, north, up, bias)`` of the common frame.
        """
        s, rot = self.stations, self.rotations
        dx = positions_enu_m[:, 0, None] - s[0]
        dy = positions_enu_m[:, 1, None] - s[1]
        dz = positions_enu_m[:, 2, None] - s[2]
        e = rot[0, 0] * dx + rot[0, 1] * dy + rot[0, 2] * dz
        n = rot[1, 0] * dx + rot[1, 1] * dy + rot[1, 2] * dz
        u = rot[2, 0] * dx + rot[2, 1] * dy + rot[2, 2] * dz
        rho2 = np.maximum(e * e + n * n, MIN_HORIZONTAL_DISTANCE_M**2)
        rho = np.sqrt(rho2)
        r2 = rho2 + u * u
        is_az, is_el = self.is_az, self.is_el
        elevation = np.arctan2(u, rho)
        elevation_factor = u / (r2 * rho)
        if self.ranged:
            r = np.sqrt(r2)
            inv_r = 1.0 / r
            far = np.where(is_el, elevation, r + np.asarray(bias_m)[:, None] * self.is_toa)
            ge_far = np.where(is_el, -e * elevation_factor, e * inv_r)
            gn_far = np.where(is_el, -n * elevation_factor, n * inv_r)
            gu_far = np.where(is_el, rho / r2, u * inv_r)
        else:
            far, ge_far, gn_far, gu_far = elevation, -e * elevation_factor, -n * elevation_factor, rho / r2
        predicted = np.where(is_az, np.arctan2(e, n), far)
        ge = np.where(is_az, n / rho2, ge_far)
        gn = np.where(is_az, -e / rho2, gn_far)
        gu = np.where(is_az, 0.0, gu_far)
        jacobian = np.empty((e.shape[0], 4, e.shape[1]))
        jacobian[:, 0] = ge * rot[0, 0] + gn * rot[1, 0] + gu * rot[2, 0]
        jacobian[:, 1] = ge * rot[0, 1] + gn * rot[1, 1] + gu * rot[2, 1]
        jacobian[:, 2] = ge * rot[0, 2] + gn * rot[1, 2] + gu * rot[2, 2]
        jacobian[:, 3] = self.is_toa
        return predicted, jacobian

    def residuals(self, measured, predicted):
        """Measured minus predicted ``(B, M)``, angle residuals wrapped to (-pi, pi]."""
        raw = measured - predicted
        if not self.ranged:
            return wrap_to_pi(raw)
        return np.where(self.is_angle, wrap_to_pi(raw), raw)


def predict(position_enu_m, bias_m, stations_enu_m, rotations, kinds):
    """Predicted measurements and their Jacobian, for any leading axes.

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
    position_enu_m = np.asarray(position_enu_m, dtype=float)
    stations_enu_m = np.asarray(stations_enu_m, dtype=float)
    lead = np.broadcast_shapes(position_enu_m.shape[:-1], np.shape(bias_m), stations_enu_m.shape[:-2],
                               np.shape(rotations)[:-3], np.shape(kinds)[:-1])
    m = stations_enu_m.shape[-2]
    model = MeasurementModel(np.broadcast_to(stations_enu_m, (*lead, m, 3)).reshape(-1, m, 3),
                             np.broadcast_to(rotations, (*lead, m, 3, 3)).reshape(-1, m, 3, 3),
                             np.broadcast_to(kinds, (*lead, m)).reshape(-1, m))
    predicted, jacobian = model.predict(np.broadcast_to(position_enu_m, (*lead, 3)).reshape(-1, 3),
                                        np.broadcast_to(bias_m, lead).reshape(-1))
    return predicted.reshape(*lead, m), np.swapaxes(jacobian, -1, -2).reshape(*lead, m, 4)


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
