"""Small dense linear algebra over stacks of matrices, vectorised over the stack.

LAPACK through ``np.linalg`` pays a fixed cost per matrix (tens of
microseconds for an ``8 x 3`` SVD), which dominates when the matrices are
tiny and there are thousands of them. :func:`jacobi_svd` computes the same
factorisation with element-wise arithmetic over the whole stack at once.
"""

from __future__ import annotations

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
    largest (as LAPACK's). Each matrix's arithmetic is its own (element-wise
    over the stack, a pair already orthogonal is not rotated), so a matrix's
    result does not depend on the others in the stack; zero rows (padding)
    change nothing.

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
    columns = list(np.moveaxis(a, (-1, -2), (0, 1)).copy())
    sides = [] if rhs is None else list(np.moveaxis(np.asarray(rhs, dtype=float), (-1, -2), (0, 1)).copy())
    if rows > width:
        _householder(columns, sides)
        columns = [x[:width] for x in columns]
        sides = [y[:width] for y in sides]
    v = [[np.full(stack, float(i == j)) for j in range(width)] for i in range(width)]
    norms = [row_dot(x, x) for x in columns]
    pairs = [(p, q) for p in range(width - 1) for q in range(p + 1, width)]
    with np.errstate(over="ignore"):  # a vanishing cosine overflows zeta to inf, which rightly gives t = 0
        _sweep(columns, v, norms, pairs)
    s = np.sqrt(np.stack(norms, axis=-1))
    v_matrix = np.moveaxis(np.array(v), (0, 1), (-2, -1))
    if rhs is None:
        return s, v_matrix, None
    projected = np.array([[row_dot(x, y) for y in sides] for x in columns])
    return s, v_matrix, np.moveaxis(projected, (0, 1), (-2, -1))


def row_dot(x, y):
    """``sum_r x[r] y[r]`` over the leading axis, added in row order.

    ``np.sum`` adds a lone contiguous vector pairwise but the columns of a
    stack one row at a time, so a matrix would round differently alone and
    in a stack, and differently again with zero rows of padding; added in
    row order, the bits are the same in every case.
    """
    total = x[0] * y[0]
    for r in range(1, x.shape[0]):
        total += x[r] * y[r]
    return total


def _householder(columns, sides):
    """Reduce column planes ``(R, ...)`` in place to upper-triangular form, applying the reflections to ``sides``."""
    for k in range(len(columns)):
        x = columns[k][k:]
        norm = np.sqrt(row_dot(x, x))
        alpha = -np.copysign(norm, x[0])
        reflector = x.copy()
        reflector[0] -= alpha
        length2 = row_dot(reflector, reflector)
        beta = np.where(length2 > 0, 2.0 / np.where(length2 > 0, length2, 1.0), 0.0)
        for other in columns[k + 1:] + sides:
            part = other[k:]
            part -= (beta * row_dot(reflector, part)) * reflector
        x[0] = alpha
        x[1:] = 0.0


def _sweep(columns, v, norms, pairs):
    """Rotate column pairs in place until all are orthogonal (or ``JACOBI_MAX_SWEEPS``)."""
    for _ in range(JACOBI_MAX_SWEEPS):
        rotated = False
        for p, q in pairs:
            xp, xq = columns[p], columns[q]
            gamma = row_dot(xp, xq)
            rotate = np.abs(gamma) > JACOBI_TOLERANCE * np.sqrt(norms[p] * norms[q])
            if not np.any(rotate):
                continue
            rotated = True
            zeta = (norms[q] - norms[p]) / (2.0 * np.where(rotate, gamma, 1.0))
            t = np.where(rotate, np.copysign(1.0, zeta) / (np.abs(zeta) + np.hypot(1.0, zeta)), 0.0)
            cos = 1.0 / np.sqrt(1.0 + t * t)
            sin = cos * t
            columns[p], columns[q] = cos * xp - sin * xq, sin * xp + cos * xq
            for row in v:
                vp, vq = row[p], row[q]
                row[p], row[q] = cos * vp - sin * vq, sin * vp + cos * vq
            norms[p] = row_dot(columns[p], columns[p])
            norms[q] = row_dot(columns[q], columns[q])
        if not rotated:
            return


def last_dot(x, y):
    """``sum_i x[..., i] y[..., i]`` over the (short) last axis, added in order; broadcasts.

    ``np.einsum`` picks its inner loop by shape, so it can round a matrix
    differently alone and in a stack; this cannot.
    """
    x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
    total = x[..., 0] * y[..., 0]
    for i in range(1, x.shape[-1]):
        total = total + x[..., i] * y[..., i]
    return total


def matvec(m, x):
    """``m @ x`` for stacks of small matrices ``(..., I, J)`` and vectors ``(..., J)``, bit-stable as :func:`last_dot`."""
    return last_dot(m, np.asarray(x)[..., None, :])
