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

import math
from enum import IntEnum

import numba
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


#: Kind codes as plain ints (for compiled code, and because comparing an array with an IntEnum member goes
#: through the enum machinery).
AZIMUTH, ELEVATION, RANGE, TOA = (int(k) for k in Kind)
#: Each kind's name as the API and the warnings spell it, by code.
KIND_NAMES = tuple(k.name.lower() for k in Kind)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def seen_from_station(east_m, north_m, up_m, stations_enu_m, rotations, m):
    """A common-frame point in station ``m``'s own ENU: ``R_m (p - s_m)`` of stations ``(M, 3)`` and their
    rotations ``(M, 3, 3)`` (compiled; indexed in place, no per-station views)."""
    dx, dy, dz = east_m - stations_enu_m[m, 0], north_m - stations_enu_m[m, 1], up_m - stations_enu_m[m, 2]
    return (rotations[m, 0, 0] * dx + rotations[m, 0, 1] * dy + rotations[m, 0, 2] * dz,
            rotations[m, 1, 0] * dx + rotations[m, 1, 1] * dy + rotations[m, 1, 2] * dz,
            rotations[m, 2, 0] * dx + rotations[m, 2, 1] * dy + rotations[m, 2, 2] * dz)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def ahead_point(east_m, north_m, up_m, stations_enu_m, rotations, m, azimuth_rad, elevation_rad):
    """How far a common-frame point lies ahead of station ``m`` along its line of sight (m; negative:
    behind it), with the point's east and north in the station's ENU; ``elevation_rad`` NaN for an
    azimuth-only bearing (the horizontal direction alone)."""
    e, n, u = seen_from_station(east_m, north_m, up_m, stations_enu_m, rotations, m)
    has_elevation = not math.isnan(elevation_rad)
    cos_el = math.cos(elevation_rad) if has_elevation else 1.0
    ahead = cos_el * math.sin(azimuth_rad) * e + cos_el * math.cos(azimuth_rad) * n
    if has_elevation:
        ahead += math.sin(elevation_rad) * u
    return ahead, e, n


@numba.njit(cache=True, nogil=True, error_model="numpy")
def measure_point(east_m, north_m, up_m, bias_m, stations_enu_m, rotations, m, kind):
    """One measurement's prediction and its Jacobian w.r.t. ``(east, north, up, bias)`` of the common frame.

    Compiled; the one coding of ``h(p)`` that :class:`MeasurementModel` and the ML iteration's kernel
    evaluate.

    Parameters
    ----------
    east_m, north_m, up_m : float
        Target in the common frame.
    bias_m : float
        TOA emission-time offset times c (used by TOA only).
    stations_enu_m : ndarray, shape (M, 3)
    rotations : ndarray, shape (M, 3, 3)
        Station ENU <- common ENU.
    m : int
        Which station (row of ``stations_enu_m`` and ``rotations``) takes the measurement.
    kind : int
        :class:`Kind` code.

    Returns
    -------
    predicted, d_east, d_north, d_up, d_bias : float
    """
    e, n, u = seen_from_station(east_m, north_m, up_m, stations_enu_m, rotations, m)
    rho2 = max(e * e + n * n, MIN_HORIZONTAL_DISTANCE_M ** 2)
    rho = math.sqrt(rho2)
    r2 = rho2 + u * u
    d_bias = 0.0
    if kind == AZIMUTH:
        predicted, ge, gn, gu = math.atan2(e, n), n / rho2, -e / rho2, 0.0
    elif kind == ELEVATION:
        factor = u / (r2 * rho)
        predicted, ge, gn, gu = math.atan2(u, rho), -e * factor, -n * factor, rho / r2
    else:
        r = math.sqrt(r2)
        predicted, ge, gn, gu = r, e / r, n / r, u / r
        if kind == TOA:
            predicted += bias_m
            d_bias = 1.0
    return (predicted,
            ge * rotations[m, 0, 0] + gn * rotations[m, 1, 0] + gu * rotations[m, 2, 0],
            ge * rotations[m, 0, 1] + gn * rotations[m, 1, 1] + gu * rotations[m, 2, 1],
            ge * rotations[m, 0, 2] + gn * rotations[m, 1, 2] + gu * rotations[m, 2, 2],
            d_bias)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _predict_kernel(positions_enu_m, bias_m, stations_enu_m, rotations, kinds):
    size, width = kinds.shape
    predicted = np.empty((size, width))
    jacobian = np.empty((size, 4, width))
    for b in range(size):
        east, north, up = positions_enu_m[b, 0], positions_enu_m[b, 1], positions_enu_m[b, 2]
        stations, turns = stations_enu_m[b], rotations[b]
        for m in range(width):
            predicted[b, m], jacobian[b, 0, m], jacobian[b, 1, m], jacobian[b, 2, m], jacobian[b, 3, m] = \
                measure_point(east, north, up, bias_m[b], stations, turns, m, kinds[b, m])
    return predicted, jacobian


@numba.njit(cache=True, nogil=True, error_model="numpy")
def toa_offset_point(east_m, north_m, up_m, stations_enu_m, kinds, values, weights):
    """One problem's weighted-mean TOA emission offset ``b`` (m) at a position: the ``b`` that fits its
    TOA pseudo-ranges best there (0 without TOA; compiled).

    Parameters
    ----------
    east_m, north_m, up_m : float
    stations_enu_m : ndarray, shape (M, 3)
    kinds : ndarray of int, shape (M,)
    values, weights : ndarray, shape (M,)
        Model units (TOA pseudo-range metres); zero weight on padding.
    """
    total = offset = 0.0
    for m in range(kinds.size):
        if kinds[m] == TOA and weights[m] > 0.0:
            distance = math.sqrt((east_m - stations_enu_m[m, 0]) ** 2 + (north_m - stations_enu_m[m, 1]) ** 2
                                 + (up_m - stations_enu_m[m, 2]) ** 2)
            total += weights[m]
            offset += weights[m] * (values[m] - distance)
    return offset / total if total > 0.0 else 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _toa_offsets(positions_enu_m, stations_enu_m, kinds, values, weights):
    out = np.empty(kinds.shape[0])
    for b in range(out.size):
        out[b] = toa_offset_point(positions_enu_m[b, 0], positions_enu_m[b, 1], positions_enu_m[b, 2],
                                  stations_enu_m[b], kinds[b], values[b], weights[b])
    return out


def toa_offsets(positions_enu_m, stations_enu_m, kinds, values, weights):
    """:func:`toa_offset_point` of B problems ``(B,)``: positions ``(B, 3)``, measurement stations
    ``(B, M, 3)``, kinds, values and weights ``(B, M)``."""
    return _toa_offsets(np.ascontiguousarray(positions_enu_m, dtype=float),
                        np.ascontiguousarray(stations_enu_m, dtype=float), np.ascontiguousarray(kinds, dtype=np.int64),
                        np.ascontiguousarray(values, dtype=float), np.ascontiguousarray(weights, dtype=float))


class MeasurementModel:
    """The measurement model of B measurement sets: ``h(p, b)`` and its Jacobian.

    Every estimator, the CRLB and the finisher evaluate the model through
    this class (or :func:`predict`, which wraps it); all of them run
    :func:`measure_point`, compiled, once per measurement.

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
        self.stations = np.ascontiguousarray(stations_enu_m, dtype=float)
        self.rotations = np.ascontiguousarray(rotations, dtype=float)
        self.kinds = np.ascontiguousarray(kinds, dtype=np.int64)
        self.is_angle = (self.kinds == Kind.AZIMUTH) | (self.kinds == Kind.ELEVATION)

    def take(self, rows) -> "MeasurementModel":
        """The model of the sets ``rows``."""
        return MeasurementModel(self.stations[rows], self.rotations[rows], self.kinds[rows])

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
        size = self.kinds.shape[0]
        positions = np.ascontiguousarray(np.broadcast_to(np.asarray(positions_enu_m, dtype=float), (size, 3)))
        bias = np.ascontiguousarray(np.broadcast_to(np.asarray(bias_m, dtype=float), (size,)))
        return _predict_kernel(positions, bias, self.stations, self.rotations, self.kinds)

    def residuals(self, measured, predicted):
        """Measured minus predicted ``(B, M)``, angle residuals wrapped to (-pi, pi]."""
        raw = measured - predicted
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


def toa_spacing_s(sent_s):
    """The float64 spacing of TOAs as sent (seconds since the client's epoch; any shape): the finest time they can
    carry (at 1.7e9 s, 2.4e-7 s or 71 m). Above a TOA's sigma, the data are coarser than the client says."""
    return np.spacing(np.abs(sent_s))


def residuals(measured, predicted, kinds):
    """Measured minus predicted, with angle residuals wrapped to (-pi, pi].

    Shapes broadcast: ``(..., M)``.
    """
    raw = np.asarray(measured) - predicted
    is_angle = (kinds == Kind.AZIMUTH) | (kinds == Kind.ELEVATION)
    return np.where(is_angle, wrap_to_pi(raw), raw)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def azimuth_rate_point(east_m, north_m, v_east_mps, v_north_mps):
    """One target's azimuth rate seen from a fixed station and its derivatives (compiled; see
    :func:`azimuth_rate`).

    Returns
    -------
    rate_rad_s, d_east, d_north, d_v_east, d_v_north : float
    """
    rho2 = max(east_m * east_m + north_m * north_m, MIN_HORIZONTAL_DISTANCE_M ** 2)
    rate = (north_m * v_east_mps - east_m * v_north_mps) / rho2
    return (rate, (-v_north_mps - 2.0 * east_m * rate) / rho2, (v_east_mps - 2.0 * north_m * rate) / rho2,
            north_m / rho2, -east_m / rho2)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _azimuth_rates(positions_enu_m, velocities_enu_mps):
    size = positions_enu_m.shape[0]
    rate, jacobian = np.empty(size), np.zeros((size, 6))
    for i in range(size):
        rate[i], jacobian[i, 0], jacobian[i, 1], jacobian[i, 3], jacobian[i, 4] = azimuth_rate_point(
            positions_enu_m[i, 0], positions_enu_m[i, 1], velocities_enu_mps[i, 0], velocities_enu_mps[i, 1])
    return rate, jacobian


def azimuth_rate(position_enu_m, velocity_enu_mps):
    """Rate of change of the azimuth of a moving target seen from a fixed station at the origin, and its
    Jacobian (ALGORITHMS.md sections 2 and 6).

    ``Bdot = (n v_e - e v_n) / rho^2`` with ``(e, n, u)`` the position and
    ``rho^2 = e^2 + n^2`` (floored like :func:`predict`'s azimuth); :func:`azimuth_rate_point` per target.

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
    p, v = np.broadcast_arrays(np.asarray(position_enu_m, dtype=float), np.asarray(velocity_enu_mps, dtype=float))
    shape = p.shape[:-1]
    rate, jacobian = _azimuth_rates(np.ascontiguousarray(p).reshape(-1, 3), np.ascontiguousarray(v).reshape(-1, 3))
    return rate.reshape(shape)[()], jacobian.reshape(shape + (6,))
