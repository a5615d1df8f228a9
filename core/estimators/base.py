"""The one interface every estimator implements, and the registry.

An estimator is a function ``estimate(batch, options) -> Estimates`` over a
whole :class:`~core.problem.batch.ProblemBatch`, registered under its API name with
:func:`register`. Its :class:`EstimatorSpec` adds the finisher:
``spec.solve_batch(batch, options) -> FixBatch``. One problem is a batch of
one (:func:`core.estimators.solve`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from core.errors import InvalidInput
from core.estimators.finish import finish
from core.estimators.result import Estimates, FixBatch
from core.measurements import Kind
from core.problem.batch import ProblemBatch

#: Every measurement kind.
ALL_KINDS = frozenset(Kind)
#: The kinds of a bearing.
ANGLES = frozenset((Kind.AZIMUTH, Kind.ELEVATION))
#: Azimuths alone.
AZIMUTHS = frozenset((Kind.AZIMUTH,))


@dataclass(frozen=True)
class SolveOptions:
    """Options shared by the estimators.

    Attributes
    ----------
    max_iterations : int
    tolerance_m : float
        Iterations stop when the position step is below this.
    variant : str or None
        Method-specific variant (e.g. ``"projected"`` or ``"newton"`` for CTLS).
    outliers : {"report", "exclude"}
        ``"exclude"``: fault detection and exclusion as GNSS receivers do it
        (:func:`core.estimators.exclude_outliers`); ``"report"`` only warns.
    absolute_sigma : bool
        False scales each covariance by the fit's ``sigma_scale^2`` (as scipy's ``curve_fit``).
    loss : str
        One of :data:`core.estimators.loss.LOSSES` (scipy's names): the ML iteration's loss.
    loss_scale : float
        The loss's scale in sigmas (scipy's ``f_scale`` on whitened residuals).
    """

    max_iterations: int = 50
    tolerance_m: float = 1e-3
    variant: str | None = None
    outliers: str = "report"
    absolute_sigma: bool = True
    loss: str = "linear"
    loss_scale: float = 1.0


Estimator = Callable[[ProblemBatch, SolveOptions], Estimates]


@dataclass(frozen=True)
class EstimatorSpec:
    """A registered estimator.

    Attributes
    ----------
    name : str
        The API's ``method`` value.
    estimate : Estimator
        Positions (and what else the method knows) for a batch.
    summary : str
    needs_sigmas : bool
        False when the method can estimate missing bearing sigmas.
    variants : tuple of str
        Accepted ``options.variant`` values (the first is the default); empty when none.
    uses : frozenset of Kind
        The measurement kinds the method uses; the others are reported, not judged.
    robust : bool
        True when the method minimises ``options.loss`` (the others take only ``"linear"``).
    """

    name: str
    estimate: Estimator
    summary: str
    needs_sigmas: bool = True
    variants: tuple[str, ...] = ()
    uses: frozenset = ALL_KINDS
    robust: bool = False

    def solve_batch(self, batch: ProblemBatch, options: SolveOptions, excluded=None) -> FixBatch:
        """Fixes of every problem of ``batch`` (a problem that cannot be solved carries its error).

        Measurements of kinds the method does not use are set aside first; ``excluded`` ``(B, M)``
        names those outlier exclusion removed (already out of ``batch.valid``).
        """
        if self.uses != ALL_KINDS:
            batch = batch.with_used(batch.valid & np.isin(batch.kinds, list(self.uses)))
        return finish(batch, self.name, self.estimate(batch, options), excluded=excluded)


REGISTRY: dict[str, EstimatorSpec] = {}


def register(name: str, summary: str, needs_sigmas: bool = True, variants: tuple[str, ...] = (),
             uses: frozenset = None, robust: bool = False):
    """Decorator adding a batch estimator to :data:`REGISTRY` under its API name."""

    def add(estimate: Estimator) -> Estimator:
        if name in REGISTRY:
            raise RuntimeError(f"estimator {name!r} registered twice")
        REGISTRY[name] = EstimatorSpec(name, estimate, summary, needs_sigmas, variants,
                                       ALL_KINDS if uses is None else frozenset(uses), robust)
        return estimate

    return add


def get_estimator(name: str) -> EstimatorSpec:
    try:
        return REGISTRY[name]
    except KeyError:
        raise InvalidInput(f"unknown method {name!r}; known: {', '.join(sorted(REGISTRY))}", ("method",)) from None
