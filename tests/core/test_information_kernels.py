"""The compiled information pieces of ``core.crlb`` (used by every fix's finisher, the CRLB endpoint and the
coverage maps) against brute-force numpy formulas: the normal matrix, its Jacobi-scaled inverse, the robust
sandwich and the reference sigma, with and without frozen parameters and rotated axes."""

from __future__ import annotations

import numpy as np
import pytest

from core.crlb import (OBSERVABILITY_THRESHOLD, invert_information, normal_matrix, reference_sigma_m,
                       sandwich_covariance)


def _random_rotations(rng, size):
    q, r = np.linalg.qr(rng.standard_normal((size, 3, 3)))
    return q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[:, None, :]


def _case(seed, size=200, width=7):
    rng = np.random.default_rng(seed)
    jacobian = rng.standard_normal((size, 4, width)) * 10.0 ** rng.uniform(-6, 0, (size, 4, 1))
    weights = 10.0 ** rng.uniform(-2, 8, (size, width))
    weights[:, -2:] = 0.0  # padding
    free = np.ones((size, 4), dtype=bool)
    free[: size // 2, 2] = False
    free[::3, 3] = False
    axes = _random_rotations(rng, size)
    return jacobian, weights, axes, free


def _brute_force(jacobian, weights, axes, free):
    local = jacobian.copy()
    local[:, :3] = axes @ jacobian[:, :3]
    local *= free[:, :, None]
    information = np.einsum("bim,bm,bjm->bij", local, weights, local) + np.eye(4) * ~free[:, None, :]
    return local, information


@pytest.mark.parametrize("rotated", [False, True])
def test_normal_matrix_and_inverse_equal_the_numpy_formulas(rotated):
    jacobian, weights, axes, free = _case(7 + rotated)
    axes = axes if rotated else None
    information, local = normal_matrix(jacobian, weights, axes, free)
    expected_local, expected = _brute_force(jacobian, weights, np.eye(3) if axes is None else axes, free)
    size = np.linalg.norm(jacobian, axis=1, keepdims=True)  # a rotated row can cancel: compare to its norm
    assert np.all(np.abs(local - expected_local) <= 1e-14 * size)
    diag = np.sqrt(np.einsum("bii->bi", expected))
    assert np.all(np.abs(information - expected) <= 1e-13 * diag[:, :, None] * diag[:, None, :])

    inverted = invert_information(information, axes, free)
    inverse = np.linalg.inv(expected) * (free[:, :, None] & free[:, None, :])
    smallest = np.linalg.eigvalsh(expected / diag[:, :, None] / diag[:, None, :])[:, 0]
    assert np.allclose(inverted.min_eigenvalue, smallest, rtol=1e-9, atol=1e-14)
    observable = smallest > OBSERVABILITY_THRESHOLD
    assert np.array_equal(inverted.observable, observable) and observable.any()
    # Two inverses of the Jacobi-scaled matrix (norm about 1, inverse's norm 1 / lambda_min) agree to rounding
    # times its condition number, relative to the inverse: |delta| <= c eps / lambda_min^2.
    scale = diag[:, :, None] * diag[:, None, :]
    tolerance = 1e-13 / smallest[:, None, None] ** 2
    ok = observable
    assert np.all(np.abs((inverted.covariance_params - inverse) * scale)[ok] <= tolerance[ok])
    block = inverse[:, :3, :3] if axes is None else np.swapaxes(axes, -1, -2) @ inverse[:, :3, :3] @ axes
    conditioned = smallest > 1e-4
    assert conditioned.sum() > 20
    for b in np.flatnonzero(conditioned):
        assert np.allclose(inverted.covariance_enu_m2[b], block[b], rtol=0.0, atol=1e-10 * np.abs(block[b]).max())
    assert np.array_equal(inverted.covariance_enu_m2, np.swapaxes(inverted.covariance_enu_m2, -1, -2))


def test_an_unobservable_problem_is_said_so_and_not_inverted():
    jacobian = np.zeros((1, 4, 3))
    jacobian[0, 0] = [1.0, 2.0, 3.0]  # only east is seen
    weights = np.ones((1, 3))
    free = np.array([[True, True, True, False]])
    inverted = invert_information(normal_matrix(jacobian, weights, None, free)[0], None, free)
    assert not inverted.observable[0] and inverted.min_eigenvalue[0] == 0.0
    assert np.all(np.isfinite(inverted.covariance_enu_m2))


def test_non_finite_information_is_unobservable_not_an_error():
    information = np.eye(4)[None].copy()
    information[0, 1, 1] = np.inf
    inverted = invert_information(information, None, np.ones((1, 4), dtype=bool))
    assert not inverted.observable[0] and inverted.min_eigenvalue[0] == 0.0


def test_sandwich_with_the_inverse_variances_is_the_inverse_information():
    jacobian, weights, axes, free = _case(11)
    information, _ = normal_matrix(jacobian, weights, axes, free)
    inverted = invert_information(information, axes, free)
    sandwich = sandwich_covariance(jacobian, weights, weights, axes, free)
    ok = inverted.min_eigenvalue > 1e-6
    assert np.allclose(sandwich[ok], inverted.covariance_enu_m2[ok], rtol=1e-6,
                       atol=1e-9 * np.abs(inverted.covariance_enu_m2[ok]).max())


def test_sandwich_equals_the_numpy_formula_with_other_weights():
    jacobian, weights, axes, free = _case(12)
    factor = np.random.default_rng(3).uniform(0.05, 1.0, weights.shape)
    local, bread = _brute_force(jacobian, weights * factor, axes, free)
    meat = np.einsum("bim,bm,bjm->bij", local, weights * factor**2, local)
    inverse = np.linalg.inv(bread) * (free[:, :, None] & free[:, None, :])
    expected = np.swapaxes(axes, -1, -2) @ (inverse @ meat @ inverse)[:, :3, :3] @ axes
    got = sandwich_covariance(jacobian, weights * factor, weights * factor**2, axes, free)
    diag = np.sqrt(np.einsum("bii->bi", bread))
    good = np.linalg.eigvalsh(bread / diag[:, :, None] / diag[:, None, :])[:, 0] > 1e-6
    for b in np.flatnonzero(good):
        assert np.allclose(got[b], expected[b], rtol=1e-6, atol=1e-8 * np.abs(expected[b]).max()), b


def test_reference_sigma_is_the_information_mean_of_the_metres_equivalent_sigmas():
    jacobian, weights, _, _ = _case(13)
    information = weights * np.sum(jacobian[:, :3] ** 2, axis=1)
    usable = information > 0
    expected = np.sqrt(np.count_nonzero(usable, axis=-1) / np.sum(np.where(usable, information, 0.0), axis=-1))
    assert np.allclose(reference_sigma_m(jacobian, weights), expected, rtol=1e-13)
    assert np.isnan(reference_sigma_m(np.zeros((1, 4, 2)), np.ones((1, 2)))[0])
