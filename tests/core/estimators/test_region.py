"""The widening that makes a stated 99 % region hold a fix's error model (:mod:`core.estimators.region`): a
curved error's and a two-solution mixture's, checked against draws independent of those the widening uses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from core.estimators.ambiguity import mixture_covariance, mixture_region
from core.estimators.region import PROMISED_COVERAGE, holding, normal_draws
from core.estimators.unscented_fix import quadratic_offsets, second_moment


def _banana(curvature_m):
    """One fix's sigma points (three directions at sqrt(3) sigmas): a 3 km axis along the first, a 2 m one
    along the second, and ``curvature_m`` of offset off the long axis per squared sigma of slide along it."""
    root3 = np.sqrt(3.0)
    offsets = np.array([[3e3 * root3, 3.0 * curvature_m, 0.0], [-3e3 * root3, 3.0 * curvature_m, 0.0],
                        [0.0, 2.0 * root3, 0.0], [0.0, -2.0 * root3, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    return np.zeros(6, dtype=np.intp), offsets


def test_a_curved_error_s_region_is_widened_across_the_curve_until_it_holds():
    """Under the sigma points' second-order model (sampled independently of the draws the widening uses), the
    second moment's 99 % region leaves out the draws that slide far (about 5 %); the widened one holds 99 % of
    them, widening only across the curve."""
    owners, offsets = _banana(25.0)
    spread = second_moment(1, owners, offsets)
    held, widened = holding(spread, *quadratic_offsets(1, owners, offsets))
    assert widened[0]
    assert held[0, 0, 0] == pytest.approx(spread[0, 0, 0]) and held[0, 1, 1] > 2.0 * spread[0, 1, 1]
    noise = np.random.default_rng(3).standard_normal((200_000, 3))
    linear, curved = (offsets[0::2] - offsets[1::2]) / (2 * np.sqrt(3.0)), (offsets[0::2] + offsets[1::2]) / 6.0
    model = noise @ linear + noise**2 @ curved
    level = chi2.ppf(PROMISED_COVERAGE, 2)

    def inside(covariance):
        precision = np.linalg.pinv(covariance, rcond=1e-9, hermitian=True)
        return np.mean(np.einsum("ni,ij,nj->n", model, precision, model) <= level)

    assert inside(spread[0]) < 0.97
    assert inside(held[0]) == pytest.approx(PROMISED_COVERAGE, abs=0.002)


def test_a_gaussian_error_s_covariance_is_left_as_it_is():
    """A linear model (no curvature) is exactly the covariance's Gaussian: no widening."""
    owners, offsets = _banana(0.0)
    spread = second_moment(1, owners, offsets)
    held, widened = holding(spread, *quadratic_offsets(1, owners, offsets))
    assert not widened[0] and np.array_equal(held, spread)


@pytest.mark.parametrize("probability", [0.02, 0.05, 0.1])
def test_a_rival_more_likely_than_one_in_a_hundred_lies_inside_the_region(probability):
    """The mixture's second moment reaches ``sqrt(w)`` of the way to the rival; its widened region reaches
    the rival itself, and holds 99 % of the mixture (sampled independently)."""
    fix, rival = np.zeros(3), np.array([3e3, -1e3, 0.0])
    own, other = np.diag([100.0, 400.0, 0.0]), np.diag([900.0, 25.0, 0.0])
    mixed = mixture_covariance(fix, own, rival, other, probability)
    held = mixture_region(fix, own, rival, other, probability)
    level = chi2.ppf(PROMISED_COVERAGE, 2)
    precision = np.linalg.pinv(held, rcond=1e-9, hermitian=True)
    assert rival @ np.linalg.pinv(mixed, rcond=1e-9, hermitian=True) @ rival > level
    assert rival @ precision @ rival <= level
    rng = np.random.default_rng(8)
    count = 200_000
    second = rng.random(count) < probability
    samples = np.where(second[:, None], rng.multivariate_normal(rival, other, count),
                       rng.multivariate_normal(fix, own, count))
    covered = np.mean(np.einsum("ni,ij,nj->n", samples, precision, samples) <= level)
    assert covered >= PROMISED_COVERAGE - 0.002


def test_the_draws_are_a_standard_normal():
    draws = normal_draws(4)
    assert draws.shape[1] == 4 and not draws.flags.writeable
    assert np.allclose(draws.mean(axis=0), 0.0, atol=0.01) and np.allclose(draws.std(axis=0), 1.0, atol=0.01)
