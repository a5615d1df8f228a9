"""Small dense linear algebra over stacks of matrices, vectorised over the stack.

LAPACK through ``np.linalg`` pays a fixed cost per matrix (tens of
microseconds for an ``8 x 3`` SVD), which dominates when the matrices are
tiny and there are thousands of them, and rounds a matrix differently with
rows of zero padding. :func:`jacobi_svd` computes the same factorisation in
one compiled kernel (numba) that costs a few microseconds per matrix, alone
or in a stack, with the same bits either way.
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: Column pairs whose cosine is at most this are taken as orthogonal.
JACOBI_TOLERANCE = 1e-15
#: Sweeps over all column pairs at most (convergence is quadratic: 5-6 suffice for 3 or 4 columns).
JACOBI_MAX_SWEEPS = 30


def jacobi_svd(a, rhs=None):
    """Singular values and right singular vectors of a stack of matrices with few columns.

    A tall matrix is first reduced to its ``C x C`` triangle by Householder
    reflections (which also carry ``rhs`` along); the triangle's columns are
    then rotated pairwise until orthogonal (one-sided Jacobi, Hestenes), and
    their norms are the singular values, accurate to a few ulps of the
    largest (as LAPACK's). Each matrix is factorised on its own by one
    compiled kernel (sums added in row order), so its result does not
    depend on the others in the stack, and zero rows (padding) change
    nothing: a problem gives the same bits alone and in any batch.

    Parameters
    ----------
    a : ndarray, shape (..., R, C)
        Any R (fewer rows than columns is allowed); C small (the cost is
        quadratic in C).
    rhs : ndarray, shape (..., R, K), optional
        Right-hand sides to project.

    Returns
    -------
    s : ndarray, shape (..., C)
        Singular values, in the order of the columns of ``v``, not sorted (C
        of them even when R < C: the extra ones are 0 to rounding).
    v : ndarray, shape (..., C, C)
        Right singular vectors as columns (orthonormal).
    projected : ndarray, shape (..., C, K), or None
        ``(a v)^T rhs``, i.e. ``s`` times the left singular vectors' components of ``rhs``;
        the least-squares solution of ``a x = rhs`` is ``v (projected / s^2)``.
    """
    a = np.asarray(a, dtype=float)
    rows, width = a.shape[-2:]
    stack = a.shape[:-2]
    columns = np.ascontiguousarray(np.swapaxes(a.reshape((-1, rows, width)), -1, -2))
    if rhs is None:
        sides = np.zeros((columns.shape[0], 0, rows))
    else:
        rhs = np.asarray(rhs, dtype=float)
        sides = np.ascontiguousarray(np.swapaxes(rhs.reshape((-1, rows, rhs.shape[-1])), -1, -2))
    s, v, projected = _jacobi_svd_kernel(columns, sides)
    s, v = s.reshape(stack + (width,)), v.reshape(stack + (width, width))
    if rhs is None:
        return s, v, None
    return s, v, projected.reshape(stack + (width, sides.shape[1]))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row_dot(x, i, y, j, start, stop):
    """``sum_r x[i, r] y[j, r]`` over ``start <= r < stop``, added in order."""
    total = x[i, start] * y[j, start]
    for r in range(start + 1, stop):
        total += x[i, r] * y[j, r]
    return total


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _rotation(alpha, beta, gamma):
    """Cosine and sine of the Jacobi rotation that zeroes the off-diagonal ``gamma`` of ``[[alpha, gamma],
    [gamma, beta]]`` (the smaller of the two angles)."""
    zeta = (beta - alpha) / (2.0 * gamma)
    t = math.copysign(1.0, zeta) / (abs(zeta) + math.hypot(1.0, zeta))
    cos = 1.0 / math.sqrt(1.0 + t * t)
    return cos, cos * t


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _rotate_columns(m, p, q, cos, sin):
    for i in range(m.shape[0]):
        mp, mq = m[i, p], m[i, q]
        m[i, p] = cos * mp - sin * mq
        m[i, q] = sin * mp + cos * mq


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _rotate_rows(m, p, q, cos, sin, count):
    """Rows ``p`` and ``q`` of ``m``, their first ``count`` entries."""
    for r in range(count):
        mp, mq = m[p, r], m[q, r]
        m[p, r] = cos * mp - sin * mq
        m[q, r] = sin * mp + cos * mq


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _reflect_rows(reflector, beta, m, first, stop, start, rows):
    """Rows ``first <= j < stop`` of ``m`` reflected over entries ``start <= r < rows``:
    ``m[j] -= beta (reflector . m[j]) reflector``."""
    for j in range(first, stop):
        total = reflector[start] * m[j, start]
        for r in range(start + 1, rows):
            total += reflector[r] * m[j, r]
        scale = beta * total
        for r in range(start, rows):
            m[j, r] -= scale * reflector[r]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def svd_in_place(x, y, s, v, projected, reflector, norms):
    """:func:`jacobi_svd` of one matrix, given as its columns ``x`` ``(C, R)`` with sides ``y`` ``(K, R)``
    (both overwritten), into ``s`` ``(C,)``, ``v`` ``(C, C)`` and ``projected`` ``(C, K)``; ``reflector``
    ``(R,)`` and ``norms`` ``(C,)`` are work space. Compiled; callable from other kernels."""
    width, rows = x.shape
    kinds = y.shape[0]
    depth = rows
    if rows > width:
        for k in range(width):
            norm = np.sqrt(_row_dot(x, k, x, k, k, rows))
            alpha = -np.copysign(norm, x[k, k])
            reflector[k] = x[k, k] - alpha
            length2 = reflector[k] * reflector[k]
            for r in range(k + 1, rows):
                reflector[r] = x[k, r]
                length2 += reflector[r] * reflector[r]
            beta = 2.0 / length2 if length2 > 0 else 0.0
            _reflect_rows(reflector, beta, x, k + 1, width, k, rows)
            _reflect_rows(reflector, beta, y, 0, kinds, k, rows)
            x[k, k] = alpha
            for r in range(k + 1, rows):
                x[k, r] = 0.0
        depth = width
    for i in range(width):
        for j in range(width):
            v[i, j] = 1.0 if i == j else 0.0
        norms[i] = _row_dot(x, i, x, i, 0, depth)
    for _ in range(JACOBI_MAX_SWEEPS):
        rotated = False
        for p in range(width - 1):
            for q in range(p + 1, width):
                gamma = _row_dot(x, p, x, q, 0, depth)
                if not abs(gamma) > JACOBI_TOLERANCE * np.sqrt(norms[p] * norms[q]):
                    continue
                rotated = True
                cos, sin = _rotation(norms[p], norms[q], gamma)
                _rotate_rows(x, p, q, cos, sin, depth)
                _rotate_columns(v, p, q, cos, sin)
                norms[p] = _row_dot(x, p, x, p, 0, depth)
                norms[q] = _row_dot(x, q, x, q, 0, depth)
        if not rotated:
            break
    for i in range(width):
        s[i] = np.sqrt(norms[i])
        for k in range(kinds):
            projected[i, k] = _row_dot(x, i, y, k, 0, depth)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _jacobi_svd_kernel(columns, sides):
    """:func:`jacobi_svd` of ``(B, C, R)`` column stacks (copied, then worked in place) with ``(B, K, R)`` sides."""
    count, width, rows = columns.shape
    kinds = sides.shape[1]
    s = np.empty((count, width))
    v = np.empty((count, width, width))
    projected = np.empty((count, width, kinds))
    x = np.empty((width, rows))
    y = np.empty((kinds, rows))
    reflector = np.empty(rows)
    norms = np.empty(width)
    for b in range(count):
        x[:, :] = columns[b]
        y[:, :] = sides[b]
        svd_in_place(x, y, s[b], v[b], projected[b], reflector, norms)
    return s, v, projected


def row_sums(x):
    """Sums ``(...)`` over the last axis of ``(..., M)``, added in order (compiled).

    ``np.sum`` (and ``einsum``) add a row of eight or more pairwise, so zero padding at its end changes
    the rounding: a problem's chi-square would then differ in its last bits alone and in a batch.
    """
    x = np.asarray(x, dtype=float)
    return _row_sums(np.ascontiguousarray(x).reshape(math.prod(x.shape[:-1]), x.shape[-1])).reshape(x.shape[:-1])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row_sums(x):
    out = np.zeros(x.shape[0])
    if x.shape[1] == 0:
        return out
    for b in range(x.shape[0]):
        total = x[b, 0]
        for m in range(1, x.shape[1]):
            total += x[b, m]
        out[b] = total
    return out


def weighted_gram(a, weights):
    """``a W a^T`` ``(B, P, P)`` of ``(B, P, M)`` rows and ``(B, M)`` weights, summed over ``M`` in order
    (compiled; unlike ``matmul``, bit for bit the same with zero-weight padding at the end)."""
    return _weighted_gram(np.ascontiguousarray(a, dtype=float), np.ascontiguousarray(weights, dtype=float))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _weighted_gram(a, weights):
    out = np.empty((a.shape[0], a.shape[1], a.shape[1]))
    for b in range(a.shape[0]):
        gram_point(a[b], weights[b], out[b])
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def gram_point(a, weights, out):
    """``a W a^T`` ``(P, P)`` of rows ``a`` ``(P, M)``, summed over ``M`` in order (compiled; one problem's
    :func:`weighted_gram`)."""
    rows, width = a.shape
    for i in range(rows):
        for j in range(i + 1):
            total = 0.0
            for m in range(width):
                total += a[i, m] * weights[m] * a[j, m]
            out[i, j] = out[j, i] = total


def last_dot(x, y):
    """``sum_i x[..., i] y[..., i]`` over the last axis, added in order (:func:`row_sums`); broadcasts.

    ``np.einsum`` picks its inner loop by shape, so it can round a matrix
    differently alone and in a stack; this cannot.
    """
    return row_sums(np.asarray(x, dtype=float) * np.asarray(y, dtype=float))


def matvec(m, x):
    """``m @ x`` for stacks of small matrices ``(..., I, J)`` and vectors ``(..., J)``, bit-stable as :func:`last_dot`."""
    return last_dot(m, np.asarray(x)[..., None, :])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def symmetric_eigen_in_place(a, v):
    """Eigen-decomposition of one small symmetric matrix ``a`` ``(C, C)`` by cyclic Jacobi rotations.

    On return ``a``'s diagonal holds the eigenvalues (unsorted, the off-diagonal is rounding) and ``v``
    ``(C, C)`` the eigenvectors as columns, in the same order; the eigenvalues are accurate to a few ulps
    of the largest, as LAPACK's. A diagonal matrix is left as it is. Compiled; callable from other kernels.
    """
    width = a.shape[0]
    for i in range(width):
        for j in range(width):
            v[i, j] = 1.0 if i == j else 0.0
    for _ in range(JACOBI_MAX_SWEEPS):
        rotated = False
        for p in range(width - 1):
            for q in range(p + 1, width):
                apq = a[p, q]
                if not abs(apq) > JACOBI_TOLERANCE * math.sqrt(abs(a[p, p] * a[q, q])) or apq == 0.0:
                    continue
                rotated = True
                cos, sin = _rotation(a[p, p], a[q, q], apq)
                _rotate_columns(a, p, q, cos, sin)
                _rotate_rows(a, p, q, cos, sin, width)
                _rotate_columns(v, p, q, cos, sin)
        if not rotated:
            break
