"""The session filters' small dense linear algebra: Cholesky factor, inverse Cholesky, repair, symmetrise."""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dpotrf as _potrf

#: Smallest eigenvalue kept, relative to the largest, of a repaired correlation matrix.
EIGENVALUE_FLOOR = 1e-12


def cholesky_lower(matrix):
    """Lower Cholesky factor of a symmetric matrix (only its lower triangle is read), or None when it is
    not positive definite.

    LAPACK ``dpotrf`` called directly: ``np.linalg.cholesky`` spends some
    2 us per call around the same routine, which matters at a few tens of
    microseconds per filter step (unlike ``dtrtrs``, see
    :func:`inverse_cholesky`, it stays single-threaded at these sizes: two
    processes calling it on two cores take 0.8 us each). It does not look
    for NaN: check finiteness separately.
    """
    factor, info = _potrf(matrix, lower=1)
    return factor if info == 0 else None


def inverse_cholesky(matrix: list) -> list:
    """``L^-1`` for the lower Cholesky factor ``L`` of a small symmetric positive definite matrix, in scalar
    arithmetic (rows of a lower-triangular matrix, as lists).

    For the innovation covariances (3 x 3, 4 x 4) of the unscented updates: the
    whitening ``L^-1`` then goes into one matrix product. Not LAPACK ``dtrtrs``:
    the OpenBLAS that scipy ships runs it multithreaded even at 4 x 4, and two
    processes doing so on two cores took some 700 us per call instead of 2.

    Raises
    ------
    numpy.linalg.LinAlgError
        When ``matrix`` is not (numerically) positive definite.
    """
    m = len(matrix)
    if m == 4:
        return _inverse_cholesky4(matrix)
    factor = [[0.0] * m for _ in range(m)]
    for j in range(m):
        row_j = factor[j]
        pivot = matrix[j][j] - sum(x * x for x in row_j[:j])
        if not pivot > 0.0:
            raise np.linalg.LinAlgError("innovation covariance is not positive definite")
        row_j[j] = math.sqrt(pivot)
        for i in range(j + 1, m):
            row_i = factor[i]
            row_i[j] = (matrix[i][j] - sum(a * b for a, b in zip(row_i[:j], row_j[:j]))) / row_j[j]
    inverse = [[0.0] * m for _ in range(m)]
    for i in range(m):
        inverse[i][i] = 1.0 / factor[i][i]
        for j in range(i):
            inverse[i][j] = -sum(factor[i][k] * inverse[k][j] for k in range(j, i)) * inverse[i][i]
    return inverse


def _inverse_cholesky4(matrix: list) -> list:
    """:func:`inverse_cholesky` unrolled for 4 x 4 (the joint UKF's every epoch)."""
    (a00, _, _, _), (a10, a11, _, _), (a20, a21, a22, _), (a30, a31, a32, a33) = matrix
    if not a00 > 0.0:
        raise np.linalg.LinAlgError("innovation covariance is not positive definite")
    l00 = math.sqrt(a00)
    l10, l20, l30 = a10 / l00, a20 / l00, a30 / l00
    d = a11 - l10 * l10
    if not d > 0.0:
        raise np.linalg.LinAlgError("innovation covariance is not positive definite")
    l11 = math.sqrt(d)
    l21 = (a21 - l20 * l10) / l11
    l31 = (a31 - l30 * l10) / l11
    d = a22 - l20 * l20 - l21 * l21
    if not d > 0.0:
        raise np.linalg.LinAlgError("innovation covariance is not positive definite")
    l22 = math.sqrt(d)
    l32 = (a32 - l30 * l20 - l31 * l21) / l22
    d = a33 - l30 * l30 - l31 * l31 - l32 * l32
    if not d > 0.0:
        raise np.linalg.LinAlgError("innovation covariance is not positive definite")
    k00, k11, k22, k33 = 1.0 / l00, 1.0 / l11, 1.0 / l22, 1.0 / math.sqrt(d)
    k10 = -l10 * k00 * k11
    k21 = -l21 * k11 * k22
    k20 = -(l20 * k00 + l21 * k10) * k22
    k32 = -l32 * k22 * k33
    k31 = -(l31 * k11 + l32 * k21) * k33
    k30 = -(l30 * k00 + l31 * k10 + l32 * k20) * k33
    return [[k00, 0.0, 0.0, 0.0], [k10, k11, 0.0, 0.0], [k20, k21, k22, 0.0], [k30, k31, k32, k33]]


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


def symmetrized(cov):
    """``(cov + cov^T) / 2``, a new C-ordered array."""
    out = np.add(cov, cov.T, order="C")
    out *= 0.5
    return out
