"""The session filters' small dense linear algebra: Cholesky factor, triangular inverse, repair, symmetrise."""

from __future__ import annotations

import numba
import numpy as np

#: Smallest eigenvalue kept, relative to the largest, of a repaired correlation matrix.
EIGENVALUE_FLOOR = 1e-12


def cholesky_lower(matrix):
    """Lower Cholesky factor of a symmetric matrix (only its lower triangle is read), or None when it is
    not positive definite (a NaN in the lower triangle counts as not positive definite).

    Parameters
    ----------
    matrix : ndarray, shape (n, n)

    Returns
    -------
    ndarray, shape (n, n), or None
        Lower triangular (the upper triangle is zero).
    """
    factor = np.empty((matrix.shape[0], matrix.shape[0]))
    return factor if cholesky_into(np.array(matrix, dtype=float), factor) else None


@numba.njit(cache=True, nogil=True, error_model="numpy")
def cholesky_into(matrix, factor):
    """Write the lower Cholesky factor of ``matrix`` into ``factor`` (both ``(n, n)``; the upper triangle
    zeroed); False, with ``factor`` partly written, when ``matrix`` is not positive definite.

    The one Cholesky of the session filters, compiled: called from Python by :func:`cholesky_lower` and
    inside the joint UKF's kernel. Column by column, each sum added in index order.
    """
    n = matrix.shape[0]
    for j in range(n):
        pivot = matrix[j, j]
        for k in range(j):
            pivot -= factor[j, k] * factor[j, k]
        if not pivot > 0.0:
            return False
        diagonal = np.sqrt(pivot)
        factor[j, j] = diagonal
        for i in range(j):
            factor[i, j] = 0.0
        for i in range(j + 1, n):
            total = matrix[i, j]
            for k in range(j):
                total -= factor[i, k] * factor[j, k]
            factor[i, j] = total / diagonal
    return True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def lower_inverse_into(factor, inverse):
    """Write the inverse of the lower-triangular ``factor`` (``(n, n)``, its diagonal nonzero) into
    ``inverse`` (the upper triangle zeroed); row by row, each sum added in index order."""
    n = factor.shape[0]
    for i in range(n):
        inverse[i, i] = 1.0 / factor[i, i]
        for j in range(i):
            total = 0.0
            for k in range(j, i):
                total += factor[i, k] * inverse[k, j]
            inverse[i, j] = -total * inverse[i, i]
        for j in range(i + 1, n):
            inverse[i, j] = 0.0


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
