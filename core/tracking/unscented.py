"""The unscented updates: step 3 of ``velocity_kinematic`` (:func:`polar_update`) here, the joint UKF's
predict and update in :mod:`core.tracking.joint_kernel`; motion in :mod:`core.tracking.motion`, linear algebra
in :mod:`core.linalg`.

The unscented transform uses ``kappa = 0``, ``alpha = 1``, ``beta = 0``:
``2 n`` points ``mean +- sqrt(n) L[:, j]`` (``L L^T = P``), each of weight
``1 / (2 n)`` (the third-degree spherical cubature rule). Every weight is
positive, so the transformed covariance is positive semi-definite by
construction, which a negative centre weight (``kappa = 3 - n``) would not
guarantee for ``n > 3``.

The motion model is linear, so the prediction is done in closed form; the
unscented transform of a linear map is exactly that.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from core.angles import wrap_point
from core.linalg import cholesky_into, lower_inverse_into, symmetrized
from core.measurements import AZIMUTH, ELEVATION, RANGE, measure_point
from core.tracking.kernel_types import OBSERVER_AXES, OBSERVER_ENU_M

PI = math.pi
TWO_PI = 2.0 * math.pi
#: Chi-square 99.9 % points for 2, 3 and 4 degrees of freedom: a normalised innovation squared above
#: them raises ``innovation_outlier``.
NIS_LIMIT = {2: 13.816, 3: 16.266, 4: 18.467}


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _polar(east_m, north_m, up_m):
    """Range, azimuth and elevation of a point seen from the observer (:func:`core.measurements.measure_point`)."""
    return (measure_point(east_m, north_m, up_m, 0.0, OBSERVER_ENU_M, OBSERVER_AXES, 0, RANGE)[0],
            measure_point(east_m, north_m, up_m, 0.0, OBSERVER_ENU_M, OBSERVER_AXES, 0, AZIMUTH)[0],
            measure_point(east_m, north_m, up_m, 0.0, OBSERVER_ENU_M, OBSERVER_AXES, 0, ELEVATION)[0])


def polar_update(mean, cov, offset: int, cross, pseudo, azimuth_rad: float, elevation_rad: float,
                 var_azimuth: float, var_elevation: float):
    """Unscented update of ``[p, v]`` with the pseudo-measurement ``(r_hat, B, E)`` (or ``(B, E)``).

    The state is ``[p, v, s]`` with ``s`` the step-1 state (from ``offset``);
    the covariance is the joint covariance of both filters' errors. The
    pseudo-measurement is ``h(p) + M e``: ``h`` the range and angles of the
    position and ``e = [e_s, n_B, n_E, n_Bdot]`` the step-1 error and this
    epoch's measurement errors, ``M`` the Jacobian of step 2. Successive
    pseudo-ranges share the slowly changing step-1 velocity error; the joint
    covariance carries that correlation, and the update is a Schmidt
    "consider" update: ``[p, v]`` gets the optimal gain, ``s`` is not
    changed (step 1 stays independent of step 3, as in the paper) and the
    cross-covariance follows the gain used.

    The transform is the ``2 n``-point unscented transform of ``[p, v]``
    (``n = 6``, ``kappa = 0``) for ``h``, with the part of ``M e`` correlated
    with the state carried along the sigma points and the rest added in
    closed form, so every linear part is exact. Only the six sigma points that
    move ``p`` are evaluated (the others map to ``h(mean)``), in a compiled
    kernel (:func:`polar_transform`). The update itself is in whitened form: with the innovation
    covariance ``S = L L^T``, ``v = cov_xz L^-T`` and ``t = L^-1 innovation``,
    ``[p, v]`` moves by ``v[:6] t``, the covariance loses ``v[:6] v^T`` in the
    rows of ``[p, v]`` and its transpose in their columns
    (:func:`consider_downdate`), and the NIS is ``|t|^2``.

    Parameters
    ----------
    mean : list of 6 + K floats
    cov : ndarray, shape (6 + K, 6 + K)
        Predicted joint state and covariance.
    offset : int
        Start of the step-1 block (6).
    cross : ndarray, shape (K, 2) or None
        Step-1 error covariance with this epoch's azimuth and elevation errors.
    pseudo : RangePseudoMeasurement or None
        None for an angles-only update.
    azimuth_rad, elevation_rad : float
        Measured angles.
    var_azimuth, var_elevation : float
        Their variances (rad^2).

    Returns
    -------
    mean : list of 6 + K floats
    cov : ndarray, shape (6 + K, 6 + K)
        New; exactly symmetric.
    nis : float
        Normalised innovation squared (chi-square with 3 or 2 degrees of
        freedom when the model holds).

    Raises
    ------
    numpy.linalg.LinAlgError
        When the position block of ``cov`` is not positive definite.
    """
    transform = polar_transform(mean, cov[:3, :3], None if pseudo is None else cov[offset:offset + 2, :3], pseudo,
                                azimuth_rad, elevation_rad, var_azimuth, var_elevation)
    # v = (covariance of the state with the innovation) L^-T, here as its transpose (m, n).
    columns = _FIVE[offset] if pseudo is not None else _THREE
    v_t = transform.to_innovation.dot(cov.take(columns, axis=0))
    if cross is not None:
        v_t[:, offset:] -= transform.from_angles.dot(cross.T)
    new_mean = list(mean)
    for i, change in enumerate(np.dot(transform.whitened, v_t[:, :6]).tolist()):
        new_mean[i] += change
    return new_mean, consider_downdate(cov, v_t), transform.nis


def consider_downdate(cov, v_t):
    """``cov`` less the Schmidt update of its first six components: ``v_pv v^T`` in their rows, the transpose
    in their columns (``v = v_t^T``, ``v_pv`` its first six rows, the rest ``v_s``). A new, exactly
    symmetric array.

    That is ``v_pv v_pv^T + v_pv v_s^T + v_s v_pv^T``, the symmetric part of ``(v_pv + 2 v_s) v_pv^T`` (each
    padded with zeros): one product, then one symmetrisation, which is needed anyway because ``cov`` is
    symmetric only to rounding.
    """
    n = cov.shape[0]
    masks = _MASKS.get(n)
    if masks is None:
        masks = _MASKS[n] = (np.array([1.0] * 6 + [2.0] * (n - 6)), np.array([1.0] * 6 + [0.0] * (n - 6)))
    doubled, head = masks
    new_cov = cov - (v_t * doubled).T.dot(v_t * head)
    return symmetrized(new_cov)


_MASKS: dict = {}


class PolarTransform(NamedTuple):
    """The sigma-point part of :func:`polar_update` (``m = 3`` with a range, 2 without).

    Attributes
    ----------
    to_innovation : ndarray, shape (m, 5) or (m, 3)
        Columns: the state components ``x, y, z, vx_s, vy_s`` with a range,
        ``x, y, z`` without: pre-multiplying those rows of the (symmetric)
        covariance gives ``L^-1`` times the innovation-state covariance.
    from_angles : ndarray, shape (m, 2)
        The same for the covariance of this epoch's ``(B, E)`` errors with the
        step-1 errors (subtracted).
    whitened : ndarray, shape (m,)
        ``L^-1 innovation``.
    nis : float
    """

    to_innovation: np.ndarray
    from_angles: np.ndarray
    whitened: np.ndarray
    nis: float


def polar_transform(mean, position_cov, step1_position, pseudo, azimuth_rad: float, elevation_rad: float,
                    var_azimuth: float, var_elevation: float) -> PolarTransform:
    """Sigma points, innovation and its whitening for :func:`polar_update` (:func:`_polar_kernel`).

    Parameters
    ----------
    mean : list of floats
        Predicted state (``[:3]`` is the position).
    position_cov : ndarray, shape (3, 3)
        The position covariance.
    step1_position : ndarray, shape (2, 3), or None
        Covariance of the step-1 ``(vx, vy)`` with the position; None without a range.
    pseudo, azimuth_rad, elevation_rad, var_azimuth, var_elevation
        As :func:`polar_update`.

    Raises
    ------
    numpy.linalg.LinAlgError
        When the position or the innovation covariance is not positive definite.
    """
    rows = 2 if pseudo is None else 3
    to_innovation, from_angles, whitened = np.empty((rows, 5)), np.empty((rows, 2)), np.empty(rows)
    if pseudo is None:
        range_terms, step1_position = np.zeros(8), np.zeros((2, 3))
    else:
        range_m, d_vx, d_vy, d_az, d_el, _, (rr, rb, re, _, _, _), _ = pseudo
        range_terms = np.array((range_m, d_vx, d_vy, d_az, d_el, rr, rb, re))
    status, nis = _polar_kernel(np.array(mean[:3]), np.array(position_cov), np.array(step1_position), range_terms,
                                pseudo is not None, azimuth_rad, elevation_rad, var_azimuth, var_elevation,
                                to_innovation, from_angles, whitened)
    if status:
        raise np.linalg.LinAlgError(("position", "innovation")[status - 1] + " covariance is not positive definite")
    return PolarTransform(to_innovation if pseudo is not None else to_innovation[:, :3], from_angles, whitened, nis)


class PolarAngles(NamedTuple):
    """This epoch's measured angles and their noise.

    Attributes
    ----------
    azimuth_rad, elevation_rad : float
    var_azimuth, var_elevation : float
        Variances (rad^2).
    """

    azimuth_rad: float
    elevation_rad: float
    var_azimuth: float
    var_elevation: float


class RangeTerms(NamedTuple):
    """The range pseudo-measurement's terms (:class:`core.tracking.kinematic.RangePseudoMeasurement`) that
    :func:`_polar_kernel` uses: its value, its sensitivities to the step-1 velocity errors (s) and to this
    epoch's angle errors (m/rad), and the ``(range, B, E)`` covariance's first row (m^2, m rad, m rad).
    """

    range_m: float
    d_vx: float
    d_vy: float
    d_azimuth: float
    d_elevation: float
    var_range: float
    cov_range_azimuth: float
    cov_range_elevation: float


class PositionPrior(NamedTuple):
    """The predicted position as :func:`_polar_kernel` uses it.

    Attributes
    ----------
    position : ndarray, shape (3,)
        ENU (m).
    position_cov : ndarray, shape (3, 3)
    step1_position : ndarray, shape (2, 3)
        Covariance of the step-1 ``(vx, vy)`` with the position (zero without a range).
    """

    position: np.ndarray
    position_cov: np.ndarray
    step1_position: np.ndarray


class PolarOutputs(NamedTuple):
    """:class:`PolarTransform`'s arrays, written by :func:`_polar_kernel`: ``to_innovation`` ``(m, 5)``,
    ``from_angles`` ``(m, 2)`` and ``whitened`` ``(m,)``."""

    to_innovation: np.ndarray
    from_angles: np.ndarray
    whitened: np.ndarray


class PolarMoments(NamedTuple):
    """The sigma points' statistics of ``(r, B, E)`` (rows 0, 1, 2) about the values at the mean.

    Attributes
    ----------
    centre : tuple of 3 floats
        ``(r, B, E)`` at the mean.
    mean_deviation : ndarray, shape (3,)
    s : ndarray, shape (3, 3)
        Their covariance (the innovation covariance once the noise is added).
    d : ndarray, shape (3, 3)
        ``d[m, c]``: the symmetric points' difference of row ``m`` along ``L[:, c]``, weighted.
    """

    centre: tuple
    mean_deviation: np.ndarray
    s: np.ndarray
    d: np.ndarray


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _polar_moments(position, chol):
    """:class:`PolarMoments` of the six sigma points ``p +- sqrt(6) L[:, c]`` of the position (``L`` is
    ``chol``); points along ``L[:, 1]`` and ``L[:, 2]`` keep ``x`` (and ``y``) exactly, so their azimuth
    deviations are exactly zero, as they should be."""
    spread = math.sqrt(6.0)
    weight = 1.0 / 12.0
    factor = spread * weight
    x0, y0, z0 = position[0], position[1], position[2]
    r0, azimuth0, elevation0 = _polar(x0, y0, z0)
    deviation = np.empty((3, 6))
    for j in range(6):
        c = j % 3
        sign = 1.0 if j < 3 else -1.0
        r, azimuth, elevation = _polar(x0 + sign * (spread * chol[0, c]), y0 + sign * (spread * chol[1, c]),
                                       z0 + sign * (spread * chol[2, c]))
        deviation[0, j] = r - r0
        azimuth -= azimuth0
        deviation[1, j] = azimuth if -PI <= azimuth <= PI else wrap_point(azimuth)
        deviation[2, j] = elevation - elevation0
    mean_deviation = np.empty(3)
    s = np.empty((3, 3))
    d = np.empty((3, 3))
    for m in range(3):
        total = 0.0
        for j in range(6):
            total += deviation[m, j]
        mean_deviation[m] = total * weight
        for c in range(3):
            d[m, c] = factor * (deviation[m, c] - deviation[m, c + 3])
    for m in range(3):
        for q in range(m + 1):
            total = 0.0
            for j in range(6):
                total += deviation[m, j] * deviation[q, j]
            s[m, q] = total * weight - mean_deviation[m] * mean_deviation[q]
            s[q, m] = s[m, q]
    return PolarMoments((r0, azimuth0, elevation0), mean_deviation, s, d)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _add_range_noise(moments, range_terms, step1_position, inverse):
    """The range row's error correlated with the state (through the step-1 velocity, ``step1_position``)
    taken out of the points' covariance and its own ``(range, B, E)`` covariance added, in ``moments.s``."""
    s, d = moments.s, moments.d
    ell = np.empty(3)
    for a in range(3):
        total = 0.0
        for k in range(a + 1):
            total += (range_terms.d_vx * step1_position[0, k] + range_terms.d_vy * step1_position[1, k]) * inverse[a, k]
        ell[a] = total
    noise = (range_terms.var_range, range_terms.cov_range_azimuth, range_terms.cov_range_elevation)
    for m in range(3):
        total = 0.0
        for k in range(3):
            total += d[m, k] * ell[k]
        s[0, m] += noise[m] - (2.0 if m == 0 else 1.0) * total
        s[m, 0] = s[0, m]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _polar_update(prior, range_terms, with_range, angles, out):
    """:func:`_polar_kernel` with its inputs named: ``prior`` a :class:`PositionPrior`, ``range_terms`` a
    :class:`RangeTerms` (used ``with_range``), ``angles`` a :class:`PolarAngles`; ``out`` a
    :class:`PolarOutputs`."""
    to_innovation, from_angles, whitened = out.to_innovation, out.from_angles, out.whitened
    chol, inverse = np.empty((3, 3)), np.empty((3, 3))
    if not cholesky_into(prior.position_cov, chol):
        return 1, 0.0
    lower_inverse_into(chol, inverse)
    moments = _polar_moments(prior.position, chol)
    r0, azimuth0, elevation0 = moments.centre
    mean_deviation, s, d = moments.mean_deviation, moments.s, moments.d
    s[1, 1] += angles.var_azimuth
    s[2, 2] += angles.var_elevation
    # w[a, m]: the covariance of position component a with row m, times L^-T.
    w = np.empty((3, 3))
    for a in range(3):
        for m in range(3):
            total = 0.0
            for k in range(a, 3):
                total += inverse[k, a] * d[m, k]
            w[a, m] = total
    innovation = np.empty(3)
    innovation[0] = range_terms.range_m - r0 - mean_deviation[0]
    innovation[1] = wrap_point(angles.azimuth_rad - azimuth0) - mean_deviation[1]
    innovation[2] = angles.elevation_rad - elevation0 - mean_deviation[2]
    if with_range:
        _add_range_noise(moments, range_terms, prior.step1_position, inverse)
    first = 0 if with_range else 1
    rows = 3 - first
    innovation_chol, k = np.empty((rows, rows)), np.empty((rows, rows))
    if not cholesky_into(s[first:, first:], innovation_chol):
        return 2, 0.0
    lower_inverse_into(innovation_chol, k)
    nis = 0.0
    for i in range(rows):
        total = 0.0
        for q in range(i + 1):
            total += k[i, q] * innovation[first + q]
        whitened[i] = total
        nis += total * total
        for a in range(3):
            total = 0.0
            for q in range(i + 1):
                total += w[a, first + q] * k[i, q]
            to_innovation[i, a] = total
        if with_range:
            to_innovation[i, 3] = -range_terms.d_vx * k[i, 0]
            to_innovation[i, 4] = -range_terms.d_vy * k[i, 0]
            from_angles[i, 0] = range_terms.d_azimuth * k[i, 0] + k[i, 1]
            from_angles[i, 1] = range_terms.d_elevation * k[i, 0] + k[i, 2]
        else:
            from_angles[i, 0] = k[i, 0]
            from_angles[i, 1] = k[i, 1]
    return 0, nis


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _polar_kernel(position, position_cov, step1_position, range_terms, with_range, azimuth_rad, elevation_rad,
                  var_azimuth, var_elevation, to_innovation, from_angles, whitened):
    """:func:`polar_transform`: writes its three arrays and returns ``(status, nis)``, status 0, or 1 (2) when
    the position (innovation) covariance is not positive definite.

    The six sigma points of the position map to deviations of ``(r, B, E)`` (:func:`_polar_moments`).
    ``range_terms`` ``(8,)`` holds a :class:`RangeTerms`' fields: the part of the pseudo-range's error
    correlated with the state (through the step-1 velocity, ``step1_position``) is carried along the points'
    differences, the rest added to the innovation covariance in closed form (:func:`_add_range_noise`). Flat
    at this boundary because numba types a named-tuple argument in Python, which costs more than the update.
    """
    terms = RangeTerms(range_terms[0], range_terms[1], range_terms[2], range_terms[3], range_terms[4],
                       range_terms[5], range_terms[6], range_terms[7])
    return _polar_update(PositionPrior(position, position_cov, step1_position), terms, with_range,
                         PolarAngles(azimuth_rad, elevation_rad, var_azimuth, var_elevation),
                         PolarOutputs(to_innovation, from_angles, whitened))


_FIVE = {6: np.array([0, 1, 2, 6, 7])}
_THREE = np.array([0, 1, 2])


def compile_kernels() -> None:
    """Compile (or load from numba's on-disk cache) this module's kernels and the Cholesky they call, with
    the argument types the filters pass (called by :func:`core.kernels.compile_kernels`)."""
    cholesky_into(np.eye(2), np.empty((2, 2)))
    for pseudo in (None, (1.5e5, 1.0, 1.0, 1.0, 1.0, 0.0, (1e6, 0.0, 0.0, 0.0, 0.0, 0.0), 0.01)):
        polar_transform([1.2e5, 1.0e5, 8.0e3], np.eye(3) * 1e6, np.zeros((2, 3)), pseudo, 0.87, 0.04, 1e-5, 1e-5)
    f = 8
    mean = np.array([[1.2e5, 1.0e5, 8.0e3, -300.0, 100.0, 2.0, 0.0, 0.0]])
    cov = np.diag([1e6, 1e6, 1e6, 1e2, 1e2, 1e2, 1e-2, 9.0])[None]
    from core.tracking.joint_kernel import joint_ukf_kernel
    from core.tracking.motion import transitions
    from core.tracking.range_mixture import moments
    from core.tracking.state import frozen_array

    phi, noises = transitions(f, (3,), True, 1.0, (1.0,))
    joint_ukf_kernel(mean, cov, phi, noises, True, 1000, 1.0, True, np.zeros(4), np.ones(4), np.empty((1, f)),
                     np.empty((1, f, f)), np.empty(1), np.empty(1), np.empty(1, dtype=np.int64))
    for arrays in ((np.ones(1), mean, cov), tuple(frozen_array(a) for a in (np.ones(1), mean, cov))):
        moments(*arrays)
