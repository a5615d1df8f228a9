"""Small dense linear algebra over stacks of matrices, vectorised over the stack.

LAPACK through ``np.linalg`` pays a fixed cost per matrix (tens of
microseconds for an ``8 x 3`` SVD), which dominates when the matrices are
tiny and there are thousands of them. :func:`jacobi_svd` computes the same
factorisation by one-sided Jacobi rotations applied to every matrix of the
stack at once, element-wise over the stack axes.
"""

from __future__ import annotations

import numpy as np

#: Column pairs whose cosine is at most this are taken as orthogonal.
JACOBI_TOLERANCE = 1e-15
#: Sweeps over all column pairs at most (convergence is quadratic: 5-6 suffice for 3 or 4 columns).
JACOBI_MAX_SWEEPS = 30


def jacobi_svd(a):
    """Singular value decomposition of a stack of matrices with few columns, ``a = (u s) v^T``.

    One-sided Jacobi (Hestenes): column pairs are rotated until every pair is
    orthogonal; the column norms are then the singular values, accurate to
    a few ulps of the largest (as LAPACK's). A matrix whose columns are
    already orthogonal is left exactly as it is, so a matrix's result does
    not depend on the others in the stack; zero rows (padding) change
    nothing. The singular values are not sorted.

    Parameters
    ----------
    a : ndarray, shape (..., R, C)
        Any R (fewer rows than columns is allowed); C small (the cost is
        quadratic in C).

    Returns
    -------
    scaled_u : ndarray, shape (..., R, C)
        ``a v``: left singular vectors times their singular values.
    s : ndarray, shape (..., C)
        Singular values, in the order of the columns of ``v`` (C of them even
        when R < C: the extra ones are 0 to rounding).
    v : ndarray, shape (..., C, C)
        Right singular vectors as columns (orthonormal).
    """
    a = np.asarray(a, dtype=float)
    width = a.shape[-1]
    stack = a.shape[:-2]
    columns = list(np.moveaxis(a, (-1, -2), (0, 1)).copy())
    v = [[np.full(stack, float(i == j)) for j in range(width)] for i in range(width)]
    norms = [np.sum(x * x, axis=0) for x in columns]
    pairs = [(p, q) for p in range(width - 1) for q in range(p + 1, width)]
    with np.errstate(over="ignore"):  # a vanishing cosine overflows zeta to inf, which rightly gives t = 0
        _sweep(columns, v, norms, pairs)
    scaled_u = np.moveaxis(np.stack(columns), (0, 1), (-1, -2))
    v_matrix = np.moveaxis(np.array(v), (0, 1), (-2, -1))
    return scaled_u, np.sqrt(np.stack(norms, axis=-1)), v_matrix


def _sweep(columns, v, norms, pairs):
    """Rotate column pairs in place until all are orthogonal (or ``JACOBI_MAX_SWEEPS``)."""
    for _ in range(JACOBI_MAX_SWEEPS):
        rotated = False
        for p, q in pairs:
            xp, xq = columns[p], columns[q]
            gamma = np.sum(xp * xq, axis=0)
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
            norms[p] = np.sum(columns[p] * columns[p], axis=0)
            norms[q] = np.sum(columns[q] * columns[q], axis=0)
        if not rotated:
            return
