"""Constant-velocity prediction, covariance repair and the unscented update of step 3.

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

import numpy as np
from scipy.linalg.lapack import dpotrf as _potrf

TWO_PI = 2.0 * math.pi
#: Chi-square 99.9 % points for 2, 3 and 4 degrees of freedom: a normalised innovation squared above
#: them raises ``innovation_outlier``.
NIS_LIMIT = {2: 13.816, 3: 16.266, 4: 18.467}
#: Smallest eigenvalue kept, relative to the largest, of a repaired correlation matrix.
EIGENVALUE_FLOOR = 1e-12


def transition(n: int, velocity_blocks: tuple[int, ...], moves_position: bool, dt_s: float, accel_psd: float,
               separate_block: int | None = None):
    """Transition matrix and process noise of a constant-velocity state, memoised.

    ``[0:3]`` (if ``moves_position``) is a position advanced by the velocity
    ``[3:6]``; every 3-component velocity block starting at an index in
    ``velocity_blocks`` takes the same white acceleration (so their noises are
    fully correlated); the block at ``separate_block``, if any, takes an
    acceleration of the same intensity but modelled as independent; other
    components are constant. The noise is the exact discretisation
    ``q [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` per axis.

    Parameters
    ----------
    n : int
        State size.
    velocity_blocks : tuple of int
    moves_position : bool
    dt_s : float
    accel_psd : float
        Power spectral density of the acceleration noise (m^2/s^3).
    separate_block : int, optional

    Returns
    -------
    transition : ndarray, shape (n, n)
    noise : ndarray, shape (n, n)
        Read-only; shared between calls with equal arguments.
    """
    key = (n, velocity_blocks, moves_position, dt_s, accel_psd, separate_block)
    found = _TRANSITIONS.get(key)
    if found is None:
        phi = np.eye(n)
        if moves_position:
            phi[(0, 1, 2), (3, 4, 5)] = dt_s
        noise = np.zeros((n, n))
        for i in range(3):
            for first in velocity_blocks:
                for second in velocity_blocks:
                    noise[first + i, second + i] = accel_psd * dt_s
                if moves_position:
                    noise[i, first + i] = noise[first + i, i] = accel_psd * dt_s * dt_s / 2.0
            if moves_position:
                noise[i, i] = accel_psd * dt_s**3 / 3.0
            if separate_block is not None:
                noise[separate_block + i, separate_block + i] = accel_psd * dt_s
        phi.flags.writeable = False
        noise.flags.writeable = False
        if len(_TRANSITIONS) >= 256:
            _TRANSITIONS.clear()
        found = _TRANSITIONS[key] = (phi, noise)
    return found


_TRANSITIONS: dict = {}


def constant_velocity_predict(mean, cov, dt_s: float, accel_psd: float, velocity_blocks: tuple[int, ...],
                              moves_position: bool, separate_block: int | None = None):
    """Propagate a state and covariance over ``dt_s`` (see :func:`transition`).

    Parameters
    ----------
    mean : ndarray, shape (n,)
    cov : ndarray, shape (n, n)
    dt_s, accel_psd : float
    velocity_blocks : tuple of int
    moves_position : bool
    separate_block : int, optional

    Returns
    -------
    mean, cov : ndarray, shapes (n,), (n, n)
    """
    phi, noise = transition(mean.shape[0], velocity_blocks, moves_position, dt_s, accel_psd, separate_block)
    predicted = phi.dot(cov).dot(phi.T)
    predicted += noise
    return phi.dot(mean), predicted


def cholesky_lower(matrix):
    """Lower Cholesky factor of a symmetric matrix (only its lower triangle is read), or None when it is
    not positive definite.

    LAPACK ``dpotrf`` called directly: ``np.linalg.cholesky`` spends some
    2 us per call around the same routine, which matters at a few tens of
    microseconds per filter step. It does not look for NaN: check finiteness
    separately.
    """
    factor, info = _potrf(matrix, lower=1)
    return factor if info == 0 else None


def cholesky_repaired(cov):
    """Cholesky factor of a covariance, repairing it when it is not positive definite.

    The repair works on the correlation matrix (so it is blind to units):
    its eigenvalues are floored at ``EIGENVALUE_FLOOR`` times the largest.

    Parameters
    ----------
    cov : ndarray, shape (n, n)
        Symmetric.

    Returns
    -------
    chol : ndarray, shape (n, n)
        Lower-triangular factor of the returned covariance.
    cov : ndarray, shape (n, n)
        ``cov`` itself, or its repaired version.
    repaired : bool
    """
    factor = cholesky_lower(cov)
    if factor is not None:
        return factor, cov, False
    return _repair(cov)


def repaired_block(cov, size: int):
    """``cov`` with its leading ``size x size`` block made positive definite if it is not.

    Returns
    -------
    cov : ndarray, shape (n, n)
    repaired : bool
    """
    if cholesky_lower(cov[:size, :size]) is not None:
        return cov, False
    _, block, _ = _repair(cov[:size, :size])
    cov = cov.copy()
    old_scale = np.sqrt(np.maximum(np.diag(cov)[:size], 1e-300))
    new_scale = np.sqrt(np.diag(block))
    cov[:size, size:] *= (new_scale / old_scale)[:, None]
    cov[size:, :size] = cov[:size, size:].T
    cov[:size, :size] = block
    return cov, True


def _repair(cov):
    scale = np.sqrt(np.abs(np.diag(cov)))
    scale[~(scale > 0.0)] = 1.0
    correlation = cov / np.outer(scale, scale)
    values, vectors = np.linalg.eigh(0.5 * (correlation + correlation.T))
    floor = EIGENVALUE_FLOOR * max(float(values[-1]), 1.0)
    for _ in range(8):
        fixed = (vectors * np.maximum(values, floor)) @ vectors.T
        fixed = 0.5 * (fixed + fixed.T) * np.outer(scale, scale)
        factor = cholesky_lower(fixed)
        if factor is not None:
            return factor, fixed, True
        floor *= 100.0
    raise FloatingPointError("covariance could not be repaired")


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
    arithmetic.

    Parameters
    ----------
    mean : ndarray, shape (6 + K,)
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
    mean : ndarray, shape (6 + K,)
    cov : ndarray, shape (6 + K, 6 + K)
    nis : float
        Normalised innovation squared (chi-square with 3 or 2 degrees of
        freedom when the model holds).

    Raises
    ------
    numpy.linalg.LinAlgError
        When the position block of ``cov`` is not positive definite.
    """
    spread = math.sqrt(6.0)
    weight = 1.0 / 12.0
    (a00, a01, a02), (_, a11, a12), (_, _, a22) = cov[:3, :3].tolist()
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

    x0, y0, z0 = mean[:3].tolist()
    rho0 = math.sqrt(x0 * x0 + y0 * y0)
    r0 = math.sqrt(rho0 * rho0 + z0 * z0)
    azimuth0 = math.atan2(x0, y0)
    elevation0 = math.atan2(z0, rho0)
    sqrt = math.sqrt
    atan2 = math.atan2
    remainder = math.remainder
    ranges = []
    azimuths = []
    elevations = []
    for cx, cy, cz in ((spread * l00, spread * l10, spread * l20), (0.0, spread * l11, spread * l21),
                       (0.0, 0.0, spread * l22), (-spread * l00, -spread * l10, -spread * l20),
                       (0.0, -spread * l11, -spread * l21), (0.0, 0.0, -spread * l22)):
        x = x0 + cx
        y = y0 + cy
        z = z0 + cz
        rho = sqrt(x * x + y * y)
        ranges.append(sqrt(rho * rho + z * z) - r0)
        azimuths.append(remainder(atan2(x, y) - azimuth0, TWO_PI))
        elevations.append(atan2(z, rho) - elevation0)
    r0_, r1_, r2_, r3_, r4_, r5_ = ranges
    b0_, b1_, b2_, b3_, b4_, b5_ = azimuths
    e0_, e1_, e2_, e3_, e4_, e5_ = elevations
    m0 = (r0_ + r1_ + r2_ + r3_ + r4_ + r5_) * weight
    m1 = (b0_ + b1_ + b2_ + b3_ + b4_ + b5_) * weight
    m2 = (e0_ + e1_ + e2_ + e3_ + e4_ + e5_) * weight
    s00 = (r0_ * r0_ + r1_ * r1_ + r2_ * r2_ + r3_ * r3_ + r4_ * r4_ + r5_ * r5_) * weight - m0 * m0
    s01 = (r0_ * b0_ + r1_ * b1_ + r2_ * b2_ + r3_ * b3_ + r4_ * b4_ + r5_ * b5_) * weight - m0 * m1
    s02 = (r0_ * e0_ + r1_ * e1_ + r2_ * e2_ + r3_ * e3_ + r4_ * e4_ + r5_ * e5_) * weight - m0 * m2
    s11 = (b0_ * b0_ + b1_ * b1_ + b2_ * b2_ + b3_ * b3_ + b4_ * b4_ + b5_ * b5_) * weight - m1 * m1 + var_azimuth
    s12 = (b0_ * e0_ + b1_ * e1_ + b2_ * e2_ + b3_ * e3_ + b4_ * e4_ + b5_ * e5_) * weight - m1 * m2
    s22 = (e0_ * e0_ + e1_ * e1_ + e2_ * e2_ + e3_ * e3_ + e4_ * e4_ + e5_ * e5_) * weight - m2 * m2 + var_elevation
    f = spread * weight
    d00, d01, d02 = f * (r0_ - r3_), f * (r1_ - r4_), f * (r2_ - r5_)
    d10, d11, d12 = f * (b0_ - b3_), f * (b1_ - b4_), f * (b2_ - b5_)
    d20, d21, d22 = f * (e0_ - e3_), f * (e1_ - e4_), f * (e2_ - e5_)
    w00 = i00 * d00 + i10 * d01 + i20 * d02
    w01 = i00 * d10 + i10 * d11 + i20 * d12
    w02 = i00 * d20 + i10 * d21 + i20 * d22
    w10 = i11 * d01 + i21 * d02
    w11 = i11 * d11 + i21 * d12
    w12 = i11 * d21 + i21 * d22
    w20 = i22 * d02
    w21 = i22 * d12
    w22 = i22 * d22

    if pseudo is not None:
        d_vx, d_vy = pseudo.d_vx, pseudo.d_vy
        rr, rb, re, _, _, _ = pseudo.covariance
        (a0, a1, a2), (b0, b1, b2) = cov[offset:offset + 2, :3].tolist()
        l0 = d_vx * a0 + d_vy * b0
        l1 = d_vx * a1 + d_vy * b1
        l2 = d_vx * a2 + d_vy * b2
        ell0 = l0 * i00
        ell1 = l0 * i10 + l1 * i11
        ell2 = l0 * i20 + l1 * i21 + l2 * i22
        s00 += rr - 2.0 * (d00 * ell0 + d01 * ell1 + d02 * ell2)
        s01 += rb - (d10 * ell0 + d11 * ell1 + d12 * ell2)
        s02 += re - (d20 * ell0 + d21 * ell1 + d22 * ell2)
        n0 = pseudo.range_m - r0 - m0
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
        to_innovation = np.array(((w00 * k00, w00 * k10 + w01 * k11, w00 * k20 + w01 * k21 + w02 * k22),
                                  (w10 * k00, w10 * k10 + w11 * k11, w10 * k20 + w11 * k21 + w12 * k22),
                                  (w20 * k00, w20 * k10 + w21 * k11, w20 * k20 + w21 * k21 + w22 * k22),
                                  (-d_vx * k00, -d_vx * k10, -d_vx * k20),
                                  (-d_vy * k00, -d_vy * k10, -d_vy * k20)))
        columns = _FIVE[offset]
        if cross is not None:
            d_az, d_el = pseudo.d_azimuth, pseudo.d_elevation
            from_angles = np.array(((d_az * k00, d_az * k10 + k11, d_az * k20 + k21),
                                    (d_el * k00, d_el * k10, d_el * k20 + k22)))
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
        to_innovation = np.array(((w01 * k11, w01 * k21 + w02 * k22), (w11 * k11, w11 * k21 + w12 * k22),
                                  (w21 * k11, w21 * k21 + w22 * k22)))
        columns = _THREE
        if cross is not None:
            from_angles = np.array(((k11, k21), (0.0, k22)))

    # v = (covariance of the state with the innovation) k^T, so that the gain is v[:6] k and
    # the covariance loses v[:6] v^T in rows [p, v] (and its transpose in the columns).
    v = cov.take(columns, axis=1).dot(to_innovation)
    if cross is not None:
        v[offset:] -= cross.dot(from_angles)
    head = v[:6]
    new_mean = mean.copy()
    new_mean[:6] += head.dot(whitened)
    loss = v.dot(head.T)
    loss[:6] *= 0.5
    new_cov = cov.copy()
    new_cov[:, :6] -= loss
    new_cov[:6] -= loss.T
    return new_mean, new_cov, nis


_FIVE = {6: np.array([0, 1, 2, 6, 7])}
_THREE = np.array([0, 1, 2])
