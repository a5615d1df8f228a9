"""Small dense linear algebra, the one module for it: stacks of tiny matrices and the filters' factors.

LAPACK through ``np.linalg`` pays a fixed cost per matrix (tens of
microseconds for an ``8 x 3`` SVD), which dominates when the matrices are
tiny and there are thousands of them, and rounds a matrix differently with
rows of zero padding. :func:`jacobi_svd` computes the same factorisation in
one compiled kernel (numba) that costs a few microseconds per matrix, alone
or in a stack, with the same bits either way.

The session filters' Cholesky factor, triangular inverse, linear prediction,
whitened Kalman update, covariance repair and symmetrisation
(:func:`cholesky_into`, :func:`lower_inverse_into`, :func:`linear_predict_into`,
:func:`whiten_into`, :func:`whitened_update_into`, :func:`cholesky_repaired`,
:func:`repaired_block`, :func:`symmetrized`) are here too: compiled where a
filter kernel calls them, each sum added in index order.
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: Column pairs whose cosine is at most this are taken as orthogonal.
JACOBI_TOLERANCE = 1e-15
#: Sweeps over all column pairs at most (convergence is quadratic: 5-6 suffice for 3 or 4 columns).
JACOBI_MAX_SWEEPS = 30
#: Matrices a kernel factorises side by side (:func:`svd_in_place`): 4 take ~0.65 of the time 4 alone do.
SVD_LANES = 4
#: Smallest eigenvalue kept, relative to the largest, of a repaired correlation matrix.
EIGENVALUE_FLOOR = 1e-12


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
def _lane_dot(x, lane, i, y, j, start, stop):
    """``sum_r x[lane, i, r] y[lane, j, r]`` over ``start <= r < stop``, added in order."""
    total = x[lane, i, start] * y[lane, j, start]
    for r in range(start + 1, stop):
        total += x[lane, i, r] * y[lane, j, r]
    return total


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _reflect_lane(reflector, beta, m, lane, first, stop, start, rows):
    """Rows ``first <= j < stop`` of ``m[lane]`` reflected over entries ``start <= r < rows``:
    ``m[lane, j] -= beta (reflector[lane] . m[lane, j]) reflector[lane]``."""
    for j in range(first, stop):
        total = reflector[lane, start] * m[lane, j, start]
        for r in range(start + 1, rows):
            total += reflector[lane, r] * m[lane, j, r]
        scale = beta * total
        for r in range(start, rows):
            m[lane, j, r] -= scale * reflector[lane, r]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def svd_in_place(x, y, s, v, projected, reflector, norms):
    """:func:`jacobi_svd` of ``L`` matrices side by side, each given as its columns ``x[lane]`` ``(C, R)`` with
    sides ``y[lane]`` ``(K, R)`` (both overwritten), into ``s`` ``(L, C)``, ``v`` ``(L, C, C)`` and
    ``projected`` ``(L, C, K)``; ``reflector`` ``(L, R)`` and ``norms`` ``(L, C)`` are work space. Compiled;
    callable from other kernels.

    Each matrix gets the bits it gets alone (a matrix whose sweep rotates nothing is left as it is by the
    later sweeps another one needs). Stepping a few together lets the processor overlap their rotations,
    each a chain of dependent divisions and square roots: one 9 x 3 matrix alone is latency-bound.
    """
    lanes, width, rows = x.shape
    kinds = y.shape[1]
    depth = rows
    if rows > width:
        for k in range(width):
            for lane in range(lanes):
                norm = np.sqrt(_lane_dot(x, lane, k, x, k, k, rows))
                alpha = -np.copysign(norm, x[lane, k, k])
                reflector[lane, k] = x[lane, k, k] - alpha
                length2 = reflector[lane, k] * reflector[lane, k]
                for r in range(k + 1, rows):
                    reflector[lane, r] = x[lane, k, r]
                    length2 += reflector[lane, r] * reflector[lane, r]
                beta = 2.0 / length2 if length2 > 0 else 0.0
                _reflect_lane(reflector, beta, x, lane, k + 1, width, k, rows)
                _reflect_lane(reflector, beta, y, lane, 0, kinds, k, rows)
                x[lane, k, k] = alpha
                for r in range(k + 1, rows):
                    x[lane, k, r] = 0.0
        depth = width
    for lane in range(lanes):
        for i in range(width):
            for j in range(width):
                v[lane, i, j] = 1.0 if i == j else 0.0
            norms[lane, i] = _lane_dot(x, lane, i, x, i, 0, depth)
    for _ in range(JACOBI_MAX_SWEEPS):
        rotated = False
        for p in range(width - 1):
            for q in range(p + 1, width):
                for lane in range(lanes):
                    gamma = _lane_dot(x, lane, p, x, q, 0, depth)
                    if not abs(gamma) > JACOBI_TOLERANCE * np.sqrt(norms[lane, p] * norms[lane, q]):
                        continue
                    rotated = True
                    cos, sin = _rotation(norms[lane, p], norms[lane, q], gamma)
                    for r in range(depth):
                        xp, xq = x[lane, p, r], x[lane, q, r]
                        x[lane, p, r] = cos * xp - sin * xq
                        x[lane, q, r] = sin * xp + cos * xq
                    for i in range(width):
                        vp, vq = v[lane, i, p], v[lane, i, q]
                        v[lane, i, p] = cos * vp - sin * vq
                        v[lane, i, q] = sin * vp + cos * vq
                    norms[lane, p] = _lane_dot(x, lane, p, x, p, 0, depth)
                    norms[lane, q] = _lane_dot(x, lane, q, x, q, 0, depth)
        if not rotated:
            break
    for lane in range(lanes):
        for i in range(width):
            s[lane, i] = np.sqrt(norms[lane, i])
            for k in range(kinds):
                projected[lane, i, k] = _lane_dot(x, lane, i, y, k, 0, depth)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _jacobi_svd_kernel(columns, sides):
    """:func:`jacobi_svd` of ``(B, C, R)`` column stacks (copied, then worked in place, ``SVD_LANES`` at a
    time) with ``(B, K, R)`` sides."""
    count, width, rows = columns.shape
    kinds = sides.shape[1]
    s = np.empty((count, width))
    v = np.empty((count, width, width))
    projected = np.empty((count, width, kinds))
    x = np.empty((SVD_LANES, width, rows))
    y = np.empty((SVD_LANES, kinds, rows))
    reflector = np.empty((SVD_LANES, rows))
    norms = np.empty((SVD_LANES, width))
    for first in range(0, count, SVD_LANES):
        stop = min(first + SVD_LANES, count)
        lanes = stop - first
        x[:lanes] = columns[first:stop]
        y[:lanes] = sides[first:stop]
        svd_in_place(x[:lanes], y[:lanes], s[first:stop], v[first:stop], projected[first:stop], reflector, norms)
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


def solve_2x2(matrix, right):
    """Solutions ``(B, 2, ...)`` of 2x2 systems ``(B, 2, 2)`` (a singular one gives inf or NaN, not an exception)."""
    a, b, c, d = matrix[:, 0, 0], matrix[:, 0, 1], matrix[:, 1, 0], matrix[:, 1, 1]
    extra = (slice(None),) + (None,) * (np.ndim(right) - 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse_det = 1.0 / (a * d - b * c)
        x0 = (d[extra] * right[:, 0] - b[extra] * right[:, 1]) * inverse_det[extra]
        x1 = (a[extra] * right[:, 1] - c[extra] * right[:, 0]) * inverse_det[extra]
    return np.stack([x0, x1], axis=1)


def inverse_2x2(matrix):
    """Inverses ``(B, 2, 2)`` of 2x2 matrices."""
    return solve_2x2(matrix, np.broadcast_to(np.eye(2), matrix.shape))


def gram_eigenvalues_2x2(rows) -> np.ndarray:
    """Eigenvalues ``(B, 2)``, ascending, of ``sum_k x_k x_k^T`` for rows ``(B, K, 2)`` (in closed form, summed
    in order by :func:`row_sums`)."""
    a, c = row_sums(rows[..., 0] ** 2), row_sums(rows[..., 1] ** 2)
    b = row_sums(rows[..., 0] * rows[..., 1])
    mean, radius = 0.5 * (a + c), np.hypot(0.5 * (a - c), b)
    return np.stack([mean - radius, mean + radius], axis=-1)


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


# The session filters' factors: Cholesky, triangular inverse, repair, symmetrisation.


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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def linear_predict_into(mean, cov, transition, noise, point, work):
    """A Gaussian through a linear motion model, in place: ``mean <- F mean``, ``cov <- F cov F^T + Q`` (the
    lower triangle computed, then mirrored, so the result stays exactly symmetric). ``mean`` ``(n,)``,
    ``cov``, ``transition``, ``noise`` ``(n, n)``; ``point`` ``(n,)`` and ``work`` ``(n, n)`` are scratch."""
    f = mean.shape[0]
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
            total = noise[i, j]
            for k in range(f):
                total += work[i, k] * transition[j, k]
            cov[i, j] = total
            cov[j, i] = total


@numba.njit(cache=True, nogil=True, error_model="numpy")
def whiten_into(factor, innovation, cross, rows, whitened):
    """Whiten an innovation and its cross-covariance by the innovation covariance's lower Cholesky factor
    ``L``: ``whitened = L^-1 innovation`` and ``cross <- L^-1 cross`` in place, by forward substitution in
    index order. The Kalman update is then ``mean += cross^T whitened``, ``cov -= cross^T cross``.

    Parameters
    ----------
    factor : ndarray, shape (R, R)
        ``L`` (its first ``rows`` rows and columns are used).
    innovation : ndarray, shape (R,)
    cross : ndarray, shape (R, F)
        The state-measurement cross-covariance, transposed; overwritten.
    rows : int
    whitened : ndarray, shape (R,)
        Written.

    Returns
    -------
    chi2 : float
        ``innovation^T S^-1 innovation`` (the NIS).
    half_log_det : float
        ``log det(S) / 2``.
    """
    chi2 = 0.0
    half_log_det = 0.0
    f = cross.shape[1]
    for r in range(rows):
        pivot = factor[r, r]
        total = innovation[r]
        for q in range(r):
            total -= factor[r, q] * whitened[q]
        whitened[r] = total / pivot
        chi2 += whitened[r] * whitened[r]
        half_log_det += math.log(pivot)
        for i in range(f):
            total = cross[r, i]
            for q in range(r):
                total -= factor[r, q] * cross[q, i]
            cross[r, i] = total / pivot
    return chi2, half_log_det


@numba.njit(cache=True, nogil=True, error_model="numpy")
def whitened_update_into(mean, cov, cross, whitened, new_mean, new_cov):
    """The Kalman update from :func:`whiten_into`'s outputs: ``new_mean = mean + cross^T whitened`` and
    ``new_cov = cov - cross^T cross`` (its lower triangle computed from ``cov``'s, then mirrored, so it is
    exactly symmetric); each sum added in index order. ``new_mean``, ``new_cov`` may be ``mean``, ``cov``.

    Parameters
    ----------
    mean : ndarray, shape (F,)
    cov : ndarray, shape (F, F)
    cross : ndarray, shape (R, F)
        ``L^-1`` times the state-measurement cross-covariance, transposed.
    whitened : ndarray, shape (R,)
        ``L^-1 innovation``.
    new_mean : ndarray, shape (F,)
    new_cov : ndarray, shape (F, F)
        Written.

    Returns
    -------
    bool
        Whether every written entry is finite.
    """
    rows = whitened.shape[0]
    finite = True
    for i in range(mean.shape[0]):
        total = mean[i]
        for r in range(rows):
            total += cross[r, i] * whitened[r]
        new_mean[i] = total
        finite = finite and math.isfinite(total)
        for j in range(i + 1):
            total = cov[i, j]
            for r in range(rows):
                total -= cross[r, i] * cross[r, j]
            new_cov[i, j] = total
            new_cov[j, i] = total
            finite = finite and math.isfinite(total)
    return finite


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
    values, vectors = np.linalg.eigh(symmetrized(correlation))
    floor = EIGENVALUE_FLOOR * max(float(values[-1]), 1.0)
    for _ in range(8):
        fixed = (vectors * np.maximum(values, floor)) @ vectors.T
        fixed = symmetrized(fixed) * np.outer(scale, scale)
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
