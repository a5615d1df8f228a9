"""The small symmetric eigen-decomposition (``core.linalg.symmetric_eigen_in_place``) against LAPACK."""

from __future__ import annotations

import numpy as np
import pytest

from core.linalg import symmetric_eigen_in_place


def _decompose(matrix):
    a, v = np.array(matrix, dtype=float), np.empty(np.shape(matrix))
    symmetric_eigen_in_place(a, v)
    return np.diag(a).copy(), v


@pytest.mark.parametrize("width", [2, 3, 4])
def test_eigenpairs_reconstruct_the_matrix_and_equal_lapacks_values(width):
    rng = np.random.default_rng(40 + width)
    for _ in range(500):
        q, _ = np.linalg.qr(rng.standard_normal((width, width)))
        values = 10.0 ** rng.uniform(-12, 0, width) * 10.0 ** rng.uniform(-4, 8) * rng.choice([-1.0, 1.0], width)
        matrix = q @ np.diag(values) @ q.T
        matrix = 0.5 * (matrix + matrix.T)
        got, vectors = _decompose(matrix)
        scale = np.abs(matrix).max()
        assert np.abs(np.sort(got) - np.linalg.eigvalsh(matrix)).max() <= 1e-14 * scale
        assert np.abs(vectors.T @ vectors - np.eye(width)).max() <= 1e-14
        assert np.abs(vectors @ np.diag(got) @ vectors.T - matrix).max() <= 1e-14 * scale


def test_diagonal_and_zero_matrices_are_left_as_they_are():
    for matrix in (np.diag([3.0, -1.0, 2.0]), np.zeros((3, 3)), np.eye(4)):
        got, vectors = _decompose(matrix)
        assert np.array_equal(got, np.diag(matrix))
        assert np.array_equal(vectors, np.eye(len(matrix)))
