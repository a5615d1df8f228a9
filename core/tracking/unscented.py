"""The unscented updates: step 3 of ``velocity_kinematic`` (:func:`polar_update`) and the joint UKF's
predict and update (:func:`joint_ukf_kernel`); motion in :mod:`core.tracking.motion`, linear algebra in
:mod:`core.tracking.linalg`.

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

from core.tracking.linalg import cholesky_into, symmetrized

PI = math.pi
TWO_PI = 2.0 * math.pi
#: Chi-square 99.9 % points for 2, 3 and 4 degrees of freedom: a normalised innovation squared above
#: them raises ``innovation_outlier``.
NIS_LIMIT = {2: 13.816, 3: 16.266, 4: 18.467}


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
    move ``p`` are evaluated (the others map to ``h(mean)``), in scalar
    arithmetic. The update itself is in whitened form: with the innovation
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
    (a00, a01, a02), (_, a11, a12), (_, _, a22) = cov[:3, :3].tolist()
    step1_position = None if pseudo is None else tuple(cov[offset:offset + 2, :3].ravel().tolist())
    transform = polar_transform(mean, (a00, a01, a02, a11, a12, a22), step1_position, pseudo, azimuth_rad,
                                elevation_rad, var_azimuth, var_elevation)
    # v = (covariance of the state with the innovation) L^-T, here as its transpose (m, n).
    columns = _FIVE[offset] if pseudo is not None else _THREE
    v_t = np.array(transform.to_innovation).dot(cov.take(columns, axis=0))
    if cross is not None:
        v_t[:, offset:] -= np.array(transform.from_angles).dot(cross.T)
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
    """The scalar part of :func:`polar_update` (``m = 3`` with a range, 2 without).

    Attributes
    ----------
    to_innovation : tuple of m rows
        ``(m, 5)`` with a range (columns: the state components ``x, y, z,
        vx_s, vy_s``), ``(m, 3)`` without (``x, y, z``): pre-multiplying
        those rows of the (symmetric) covariance gives ``L^-1`` times the
        innovation-state covariance.
    from_angles : tuple of m rows
        ``(m, 2)``: the same for the covariance of this epoch's ``(B, E)``
        errors with the step-1 errors (subtracted).
    whitened : tuple of m floats
        ``L^-1 innovation``.
    nis : float
    """

    to_innovation: tuple
    from_angles: tuple
    whitened: tuple
    nis: float


def polar_transform(mean, position_cov: tuple, step1_position: tuple | None, pseudo, azimuth_rad: float,
                    elevation_rad: float, var_azimuth: float, var_elevation: float) -> PolarTransform:
    """Sigma points, innovation and its whitening for :func:`polar_update`, in scalar arithmetic.

    Parameters
    ----------
    mean : list of floats
        Predicted state (``[:3]`` is the position).
    position_cov : tuple of 6 floats
        ``(xx, xy, xz, yy, yz, zz)`` of the position covariance.
    step1_position : tuple of 6 floats or None
        Covariance of the step-1 ``(vx, vy)`` with the position, row-major
        ``(vx x, vx y, vx z, vy x, vy y, vy z)``; None without a range.
    pseudo, azimuth_rad, elevation_rad, var_azimuth, var_elevation
        As :func:`polar_update`.

    Raises
    ------
    numpy.linalg.LinAlgError
        When the position or the innovation covariance is not positive definite.
    """
    spread = math.sqrt(6.0)
    weight = 1.0 / 12.0
    a00, a01, a02, a11, a12, a22 = position_cov
    if not a00 > 0.0:
        raise np.linalg.LinAlgError("position covariance is not positive definite")
    l00 = math.sqrt(a00)
    l10 = a01 / l00
    l20 = a02 / l00
    d11 = a11 - l10 * l10
    if not d11 > 0.0:
        raise np.linalg.LinAlgError("position covariance is not positive definite")
    l11 = math.sqrt(d11)
    l21 = (a12 - l20 * l10) / l11
    d22 = a22 - l20 * l20 - l21 * l21
    if not d22 > 0.0:
        raise np.linalg.LinAlgError("position covariance is not positive definite")
    l22 = math.sqrt(d22)
    i00 = 1.0 / l00
    i11 = 1.0 / l11
    i22 = 1.0 / l22
    i10 = -l10 * i00 * i11
    i21 = -l21 * i11 * i22
    i20 = -(l20 * i00 + l21 * i10) * i22

    x0, y0, z0 = mean[0], mean[1], mean[2]
    rho0 = math.sqrt(x0 * x0 + y0 * y0)
    r0 = math.sqrt(rho0 * rho0 + z0 * z0)
    azimuth0 = math.atan2(x0, y0)
    elevation0 = math.atan2(z0, rho0)
    sqrt = math.sqrt
    atan2 = math.atan2
    remainder = math.remainder
    # The six sigma points, unrolled: +-(spread L[:, j]). Those along L[:, 2] (z only) keep x0, y0, so
    # their horizontal range is rho0 and their azimuth deviation is zero. An azimuth deviation lies in
    # [-2 pi, 2 pi]; the wrap below equals remainder(., 2 pi) there (both are exact).
    cx, cy, cz = spread * l00, spread * l10, spread * l20
    x, y, z = x0 + cx, y0 + cy, z0 + cz
    rho = sqrt(x * x + y * y)
    r0_ = sqrt(rho * rho + z * z) - r0
    b0_ = atan2(x, y) - azimuth0
    e0_ = atan2(z, rho) - elevation0
    x, y, z = x0 - cx, y0 - cy, z0 - cz
    rho = sqrt(x * x + y * y)
    r3_ = sqrt(rho * rho + z * z) - r0
    b3_ = atan2(x, y) - azimuth0
    e3_ = atan2(z, rho) - elevation0
    xx0 = x0 * x0
    cy, cz = spread * l11, spread * l21
    y, z = y0 + cy, z0 + cz
    rho = sqrt(xx0 + y * y)
    r1_ = sqrt(rho * rho + z * z) - r0
    b1_ = atan2(x0, y) - azimuth0
    e1_ = atan2(z, rho) - elevation0
    y, z = y0 - cy, z0 - cz
    rho = sqrt(xx0 + y * y)
    r4_ = sqrt(rho * rho + z * z) - r0
    b4_ = atan2(x0, y) - azimuth0
    e4_ = atan2(z, rho) - elevation0
    cz = spread * l22
    rho2 = rho0 * rho0
    z = z0 + cz
    r2_ = sqrt(rho2 + z * z) - r0
    e2_ = atan2(z, rho0) - elevation0
    z = z0 - cz
    r5_ = sqrt(rho2 + z * z) - r0
    e5_ = atan2(z, rho0) - elevation0
    if not (-PI <= b0_ <= PI and -PI <= b3_ <= PI and -PI <= b1_ <= PI and -PI <= b4_ <= PI):
        b0_, b1_, b3_, b4_ = (remainder(b, TWO_PI) for b in (b0_, b1_, b3_, b4_))
    # The azimuth deviations of points 2 and 5 are zero: their terms are left out below.
    m0 = (r0_ + r1_ + r2_ + r3_ + r4_ + r5_) * weight
    m1 = (b0_ + b1_ + b3_ + b4_) * weight
    m2 = (e0_ + e1_ + e2_ + e3_ + e4_ + e5_) * weight
    s00 = (r0_ * r0_ + r1_ * r1_ + r2_ * r2_ + r3_ * r3_ + r4_ * r4_ + r5_ * r5_) * weight - m0 * m0
    s01 = (r0_ * b0_ + r1_ * b1_ + r3_ * b3_ + r4_ * b4_) * weight - m0 * m1
    s02 = (r0_ * e0_ + r1_ * e1_ + r2_ * e2_ + r3_ * e3_ + r4_ * e4_ + r5_ * e5_) * weight - m0 * m2
    s11 = (b0_ * b0_ + b1_ * b1_ + b3_ * b3_ + b4_ * b4_) * weight - m1 * m1 + var_azimuth
    s12 = (b0_ * e0_ + b1_ * e1_ + b3_ * e3_ + b4_ * e4_) * weight - m1 * m2
    s22 = (e0_ * e0_ + e1_ * e1_ + e2_ * e2_ + e3_ * e3_ + e4_ * e4_ + e5_ * e5_) * weight - m2 * m2 + var_elevation
    f = spread * weight
    d00, d01, d02 = f * (r0_ - r3_), f * (r1_ - r4_), f * (r2_ - r5_)
    d10, d11 = f * (b0_ - b3_), f * (b1_ - b4_)
    d20, d21, d22 = f * (e0_ - e3_), f * (e1_ - e4_), f * (e2_ - e5_)
    w00 = i00 * d00 + i10 * d01 + i20 * d02
    w01 = i00 * d10 + i10 * d11
    w02 = i00 * d20 + i10 * d21 + i20 * d22
    w10 = i11 * d01 + i21 * d02
    w11 = i11 * d11
    w12 = i11 * d21 + i21 * d22
    w20 = i22 * d02
    w21 = 0.0
    w22 = i22 * d22

    if pseudo is not None:
        range_m, d_vx, d_vy, d_az, d_el, _, (rr, rb, re, _, _, _), _ = pseudo
        a0, a1, a2, b0, b1, b2 = step1_position
        l0 = d_vx * a0 + d_vy * b0
        l1 = d_vx * a1 + d_vy * b1
        l2 = d_vx * a2 + d_vy * b2
        ell0 = l0 * i00
        ell1 = l0 * i10 + l1 * i11
        ell2 = l0 * i20 + l1 * i21 + l2 * i22
        s00 += rr - 2.0 * (d00 * ell0 + d01 * ell1 + d02 * ell2)
        s01 += rb - (d10 * ell0 + d11 * ell1)
        s02 += re - (d20 * ell0 + d21 * ell1 + d22 * ell2)
        n0 = range_m - r0 - m0
        n1 = remainder(azimuth_rad - azimuth0, TWO_PI) - m1
        n2 = elevation_rad - elevation0 - m2
        # Lower Cholesky factor of the innovation covariance and its inverse k.
        if not s00 > 0.0:
            raise np.linalg.LinAlgError("innovation covariance is not positive definite")
        c00 = sqrt(s00)
        c10 = s01 / c00
        c20 = s02 / c00
        e11 = s11 - c10 * c10
        if not e11 > 0.0:
            raise np.linalg.LinAlgError("innovation covariance is not positive definite")
        c11 = sqrt(e11)
        c21 = (s12 - c20 * c10) / c11
        e22 = s22 - c20 * c20 - c21 * c21
        if not e22 > 0.0:
            raise np.linalg.LinAlgError("innovation covariance is not positive definite")
        k00 = 1.0 / c00
        k11 = 1.0 / c11
        k22 = 1.0 / sqrt(e22)
        k10 = -c10 * k00 * k11
        k21 = -c21 * k11 * k22
        k20 = -(c20 * k00 + c21 * k10) * k22
        t0 = k00 * n0
        t1 = k10 * n0 + k11 * n1
        t2 = k20 * n0 + k21 * n1 + k22 * n2
        nis = t0 * t0 + t1 * t1 + t2 * t2
        whitened = (t0, t1, t2)
        # (state columns [p, vx_s, vy_s] -> innovation) @ k^T: the rows of W k^T.
        to_innovation = ((w00 * k00, w10 * k00, w20 * k00, -d_vx * k00, -d_vy * k00),
                         (w00 * k10 + w01 * k11, w10 * k10 + w11 * k11, w20 * k10 + w21 * k11, -d_vx * k10,
                          -d_vy * k10),
                         (w00 * k20 + w01 * k21 + w02 * k22, w10 * k20 + w11 * k21 + w12 * k22,
                          w20 * k20 + w21 * k21 + w22 * k22, -d_vx * k20, -d_vy * k20))
        from_angles = ((d_az * k00, d_el * k00), (d_az * k10 + k11, d_el * k10), (d_az * k20 + k21, d_el * k20 + k22))
    else:
        n1 = remainder(azimuth_rad - azimuth0, TWO_PI) - m1
        n2 = elevation_rad - elevation0 - m2
        if not s11 > 0.0:
            raise np.linalg.LinAlgError("innovation covariance is not positive definite")
        c11 = sqrt(s11)
        c21 = s12 / c11
        e22 = s22 - c21 * c21
        if not e22 > 0.0:
            raise np.linalg.LinAlgError("innovation covariance is not positive definite")
        k11 = 1.0 / c11
        k22 = 1.0 / sqrt(e22)
        k21 = -c21 * k11 * k22
        t1 = k11 * n1
        t2 = k21 * n1 + k22 * n2
        nis = t1 * t1 + t2 * t2
        whitened = (t1, t2)
        to_innovation = ((w01 * k11, w11 * k11, w21 * k11),
                         (w01 * k21 + w02 * k22, w11 * k21 + w12 * k22, w21 * k21 + w22 * k22))
        from_angles = ((k11, 0.0), (k21, k22))

    return PolarTransform(to_innovation, from_angles, whitened, nis)


_FIVE = {6: np.array([0, 1, 2, 6, 7])}
_THREE = np.array([0, 1, 2])


#: :func:`joint_ukf_kernel`'s outcome per state: updated; the predicted covariance, the innovation covariance
#: or the updated covariance not positive definite; the update not finite.
UPDATED, PREDICTED_NOT_PD, INNOVATION_NOT_PD, UPDATED_NOT_PD, NOT_FINITE = range(5)


@numba.njit(cache=True, nogil=True)
def _wrapped(angle_rad):
    """``angle_rad`` wrapped into ``[-pi, pi)``."""
    return (angle_rad + PI) % TWO_PI - PI


@numba.njit(cache=True, nogil=True)
def _joint_measurement(state, n_pulses, interval_s, use_toa, out):
    """``(B, E, c dS, Bdot)`` (without ``c dS`` unless ``use_toa``) of one joint state into ``out``.

    ``c dS = |p| - |p - v T| + n period_error_m - toa_noise_m`` with ``T = interval_s`` (the previous range
    from the current state; ``period_error_m`` only in an 8-component state).
    """
    x, y, z, vx, vy, vz = state[0], state[1], state[2], state[3], state[4], state[5]
    rho2 = x * x + y * y
    out[0] = math.atan2(x, y)
    out[1] = math.atan2(z, math.sqrt(rho2))
    rate = (y * vx - x * vy) / rho2
    if use_toa:
        qx, qy, qz = x - interval_s * vx, y - interval_s * vy, z - interval_s * vz
        change = math.sqrt(rho2 + z * z) - math.sqrt(qx * qx + qy * qy + qz * qz) - state[state.shape[0] - 1]
        if state.shape[0] == 8:
            change += n_pulses * state[6]
        out[2] = change
        out[3] = rate
    else:
        out[2] = rate


@numba.njit(cache=True, nogil=True)
def joint_ukf_kernel(means, covs, transition, noises, predict, n_pulses, interval_s, use_toa, measured, variances,
                     new_means, new_covs, nis, log_det, status):
    """Predict and update ``M`` joint UKF states (layout in :mod:`core.tracking.state`) with one epoch.

    Prediction ``mean <- F mean``, ``cov <- F cov F^T + Q`` (in place, exactly
    symmetric). Update: the ``2 F`` sigma points ``mean +- sqrt(F) L[:, j]``
    (``L L^T = cov``, weights ``1 / (2 F)``, see the module docstring), the
    measurement ``(B, E, [c dS,] Bdot)`` (:func:`_joint_measurement`; azimuth
    deviations wrapped), the innovation covariance ``S = M L_S L_S^T`` with
    the measurement noise, and the whitened update: with ``v = cov_xz L_S^-T``
    and ``t = L_S^-1 innovation``, the mean moves by ``v t``, the covariance
    loses ``v v^T`` (exactly symmetric), the NIS is ``|t|^2`` and ``log det S
    = 2 sum log diag L_S``.

    The last component (the reference TOA's noise) becomes the new TOA's
    noise, prior ``N(0, var_toa)``: with a usable TOA it enters the TOA row
    additively (its covariance with the TOA row is ``var_toa``), so its
    posterior is correlated with the rest; without, it is a fresh,
    independent noise.

    Parameters
    ----------
    means : ndarray, shape (M, F)
    covs : ndarray, shape (M, F, F)
        The states; with ``predict``, overwritten with the prediction.
    transition : ndarray, shape (F, F)
    noises : ndarray, shape (M, F, F)
        Each state's process noise (:func:`core.tracking.motion.transition`).
    predict : bool
        False: ``means``, ``covs`` are already predicted (``transition``, ``noises`` unused).
    n_pulses : int
    interval_s : float
        ``n_pulses`` times the period the TOA difference is referred to.
    use_toa : bool
        Whether the TOA row is used (3 measurement rows without).
    measured : ndarray, shape (4,)
        Azimuth (rad), elevation (rad), TOA difference less ``interval_s`` (m), azimuth rate (rad/s).
    variances : ndarray, shape (4,)
        Their noise variances (the TOA's is that of one TOA).
    new_means : ndarray, shape (M, F)
    new_covs : ndarray, shape (M, F, F)
    nis, log_det : ndarray, shape (M,)
    status : ndarray of int, shape (M,)
        Written: the updated states, the NIS (chi-square with 4, or 3, degrees of freedom when the model
        holds), ``log det S`` and the outcome (:data:`UPDATED` ... :data:`NOT_FINITE`; the outputs of a
        state are meaningful from :data:`UPDATED_NOT_PD` on).
    """
    count, f = means.shape
    rows = 4 if use_toa else 3
    spread = math.sqrt(f)
    weight = 1.0 / (2 * f)
    measured_rows = np.empty(rows)
    noise_rows = np.empty(rows)
    for r in range(rows):
        source = r if use_toa or r < 2 else 3
        measured_rows[r] = measured[source]
        noise_rows[r] = variances[source]
    var_toa = variances[2]
    work = np.empty((f, f))
    chol = np.empty((f, f))
    point = np.empty(f)
    z = np.empty(rows)
    centre = np.empty(rows)
    deviation = np.empty((rows, 2 * f))
    mean_deviation = np.empty(rows)
    innovation_cov = np.empty((rows, rows))
    innovation_chol = np.empty((rows, rows))
    v = np.empty((rows, f))
    t = np.empty(rows)
    innovation = np.empty(rows)
    for b in range(count):
        mean, cov, new_mean, new_cov = means[b], covs[b], new_means[b], new_covs[b]
        if predict:
            for i in range(f):
                total = 0.0
                for k in range(f):
                    total += transition[i, k] * mean[k]
                point[i] = total
                for j in range(f):
                    total = 0.0
                    for k in range(f):
                        total += transition[i, k] * cov[k, j]
                    work[i, j] = total
            for i in range(f):
                mean[i] = point[i]
                for j in range(i + 1):
                    total = noises[b, i, j]
                    for k in range(f):
                        total += work[i, k] * transition[j, k]
                    cov[i, j] = total
                    cov[j, i] = total
        if not cholesky_into(cov, chol):
            status[b] = PREDICTED_NOT_PD
            continue
        _joint_measurement(mean, n_pulses, interval_s, use_toa, centre)
        for j in range(2 * f):
            for i in range(f):
                offset = spread * chol[i, j % f]
                point[i] = mean[i] + offset if j < f else mean[i] - offset
            _joint_measurement(point, n_pulses, interval_s, use_toa, z)
            for r in range(rows):
                deviation[r, j] = z[r] - centre[r]
            deviation[0, j] = _wrapped(deviation[0, j])
        for r in range(rows):
            total = 0.0
            for j in range(2 * f):
                total += deviation[r, j]
            mean_deviation[r] = total * weight
            innovation[r] = measured_rows[r] - centre[r]
        innovation[0] = _wrapped(innovation[0])
        for r in range(rows):
            innovation[r] -= mean_deviation[r]
            for q in range(r + 1):
                total = 0.0
                for j in range(2 * f):
                    total += (deviation[r, j] - mean_deviation[r]) * (deviation[q, j] - mean_deviation[q])
                innovation_cov[r, q] = total * weight
                innovation_cov[q, r] = total * weight
            innovation_cov[r, r] += noise_rows[r]
            # Covariance of the state with row r: the symmetric points' differences along L.
            for i in range(f - 1):
                total = 0.0
                for j in range(i + 1):
                    total += chol[i, j] * (deviation[r, j] - deviation[r, j + f])
                v[r, i] = total * (spread * weight)
            v[r, f - 1] = var_toa if use_toa and r == 2 else 0.0
        if not cholesky_into(innovation_cov, innovation_chol):
            status[b] = INNOVATION_NOT_PD
            continue
        chi2 = 0.0
        half_log_det = 0.0
        for r in range(rows):
            pivot = innovation_chol[r, r]
            total = innovation[r]
            for q in range(r):
                total -= innovation_chol[r, q] * t[q]
            t[r] = total / pivot
            chi2 += t[r] * t[r]
            half_log_det += math.log(pivot)
            for i in range(f):
                total = v[r, i]
                for q in range(r):
                    total -= innovation_chol[r, q] * v[q, i]
                v[r, i] = total / pivot
        nis[b] = chi2
        log_det[b] = 2.0 * half_log_det
        finite = True
        for i in range(f):
            keep = i < f - 1
            total = mean[i] if keep else 0.0
            for r in range(rows):
                total += v[r, i] * t[r]
            new_mean[i] = total
            finite = finite and math.isfinite(total)
            for j in range(i + 1):
                total = cov[i, j] if keep else (var_toa if j == i else 0.0)
                for r in range(rows):
                    total -= v[r, i] * v[r, j]
                new_cov[i, j] = total
                new_cov[j, i] = total
                finite = finite and math.isfinite(total)
        if not finite:
            status[b] = NOT_FINITE
        elif not cholesky_into(new_cov, chol):
            status[b] = UPDATED_NOT_PD
        else:
            status[b] = UPDATED


def compile_kernels() -> None:
    """Compile (or load from numba's on-disk cache) this module's kernels and the Cholesky they call, with
    the argument types the filters pass (see :func:`core.linalg.compile_kernels`)."""
    cholesky_into(np.eye(2), np.empty((2, 2)))
    f = 8
    mean = np.array([[1.2e5, 1.0e5, 8.0e3, -300.0, 100.0, 2.0, 0.0, 0.0]])
    cov = np.diag([1e6, 1e6, 1e6, 1e2, 1e2, 1e2, 1e-2, 9.0])[None]
    joint_ukf_kernel(mean, cov, np.eye(f), np.zeros((1, f, f)), True, 1000, 1.0, True, np.zeros(4), np.ones(4),
                     np.empty((1, f)), np.empty((1, f, f)), np.empty(1), np.empty(1), np.empty(1, dtype=np.int64))
