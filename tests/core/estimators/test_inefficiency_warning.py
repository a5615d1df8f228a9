"""A closed form whose own covariance is far above the bound says so."""

from __future__ import annotations

import numpy as np

from core.estimators import solve
from core.estimators.finish import INEFFICIENCY_RATIO
from core.simulation.scenarios import generic_3d, paper_000


def _flags(problem, method):
    fix = solve(problem, method)
    ratio = np.trace(fix.covariance_enu_m2) / np.trace(fix.crlb_enu_m2)
    return ratio, "inefficient_method" in {w.code for w in fix.warnings}


def test_ove_in_paper_000_meridian_geometry_is_flagged():
    """Paper 000's N = 4 scene: OVE's normals all lie in the meridian plane (degenerate without noise)."""
    problem = paper_000(looks=2).problem(np.random.default_rng(1))
    ratio, flagged = _flags(problem, "ove")
    assert ratio > INEFFICIENCY_RATIO and flagged


def test_efficient_closed_forms_are_not_flagged():
    problem = generic_3d().problem(np.random.default_rng(1))
    for method in ("eove", "weighted_eove"):
        ratio, flagged = _flags(problem, method)
        assert ratio < INEFFICIENCY_RATIO and not flagged, method
