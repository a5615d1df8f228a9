"""The interpolated CEP50/SEP50 (the default) equal the reference quadrature to the stated 5e-5 relative."""

from __future__ import annotations

import numpy as np
import pytest

from core.error_summary import error_summary

#: What ``core.error_summary`` promises for the interpolated radii against ``exact=True`` (measured: 1.5e-5).
TOLERANCE = 5e-5


def _rotation(rng):
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    return q * np.sign(np.diag(r))


def _shapes() -> np.ndarray:
    """Covariances over a grid of eigenvalue ratios (log and linear, down to 0), rotated, at several scales."""
    rng = np.random.default_rng(2024)
    ratios = np.unique(np.concatenate([[0.0, 1e-14, 1e-9, 1e-6, 1e-4, 1e-3], np.linspace(0.0, 1.0, 23),
                                       np.logspace(-3, 0, 19)]))
    covariances = []
    for a in ratios:
        for b in ratios[ratios <= a]:
            scale = 10.0 ** rng.uniform(-4, 8)
            lam = scale * np.array([1.0, a, b])
            rot = _rotation(rng)
            covariances.append(rot @ np.diag(lam) @ rot.T)
            covariances.append(np.diag(rng.permutation(lam)))  # axis-aligned, in any order
    return np.array(covariances)


DEGENERATE = {
    "zero": np.zeros((3, 3)),
    "rank-1 vertical": np.diag([0.0, 0.0, 4.0]),
    "rank-1 horizontal": np.diag([0.0, 9.0, 0.0]),
    "rank-1 oblique": np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]),
    "rank-2 horizontal": np.diag([4.0, 1.0, 0.0]),
    "rank-2 tilted": (lambda u, v: np.outer(u, u) + 0.3 * np.outer(v, v))(np.array([1.0, 1.0, 0.5]),
                                                                       np.array([-1.0, 1.0, 0.0])),
    "round": 25.0 * np.eye(3),
    "horizontal round, vertical zero": np.diag([2.0, 2.0, 0.0]),
    "tiny": 1e-20 * np.eye(3),
    "huge": 1e16 * np.diag([1.0, 0.5, 0.1]),
}


def _relative(fast, exact):
    return np.abs(fast - exact) / np.maximum(np.abs(exact), 1e-300)


def test_fast_radii_equal_the_quadrature_over_a_grid_of_shapes():
    covariances = _shapes()
    fast, exact = error_summary(covariances), error_summary(covariances, exact=True)
    assert _relative(fast.cep50_m, exact.cep50_m).max() <= TOLERANCE
    assert _relative(fast.sep50_m, exact.sep50_m).max() <= TOLERANCE
    for name in ("vertical_sigma_m", "gdop_m", "ellipse_semi_major_m", "ellipse_semi_minor_m",
                 "ellipse_orientation_rad"):
        assert np.array_equal(getattr(fast, name), getattr(exact, name)), name


@pytest.mark.parametrize("name", DEGENERATE)
def test_fast_radii_of_degenerate_covariances(name):
    cov = DEGENERATE[name]
    fast, exact = error_summary(cov), error_summary(cov, exact=True)
    for field in ("cep50_m", "sep50_m"):
        got, expected = getattr(fast, field)[0], getattr(exact, field)[0]
        assert np.isfinite(got) and got >= 0.0
        if expected == 0.0:
            assert got == 0.0
        else:
            assert got == pytest.approx(expected, rel=TOLERANCE)


def test_round_line_and_zero_fall_on_table_nodes():
    for cov in (np.eye(3), np.diag([0.0, 1.0, 0.0]), np.zeros((3, 3))):
        fast, exact = error_summary(cov), error_summary(cov, exact=True)
        assert fast.cep50_m[0] == pytest.approx(exact.cep50_m[0], rel=1e-13, abs=0.0)
        assert fast.sep50_m[0] == pytest.approx(exact.sep50_m[0], rel=1e-13, abs=0.0)


def test_batched_equals_one_by_one():
    covariances = _shapes()[:200]
    batch = error_summary(covariances)
    for i in range(0, 200, 7):
        one = error_summary(covariances[i])
        assert one.cep50_m[0] == pytest.approx(batch.cep50_m[i], rel=1e-12)
        assert one.sep50_m[0] == pytest.approx(batch.sep50_m[i], rel=1e-12)


@pytest.mark.parametrize("cov", [np.full((3, 3), np.nan), np.diag([np.inf, 1.0, 1.0])], ids=["nan", "inf"])
def test_a_covariance_that_is_not_finite_has_nan_radii(cov):
    for exact in (False, True):
        summary = error_summary(cov, exact=exact)
        assert np.isnan(summary.cep50_m[0]) and np.isnan(summary.sep50_m[0])
