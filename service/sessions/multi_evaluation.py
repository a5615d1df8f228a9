"""The multi-emitter evaluation: the association tracker on a scene of unlabelled bearings, scored with GOSPA
next to the pairwise-intersection + DBSCAN baseline on the same bearings.

``POST /v1/evaluations`` with ``{"multi_emitter": {...}}`` and ``passive-locator evaluate`` both answer with
:func:`multi_evaluation_body` (core's :func:`core.simulation.multi_emitter.evaluate_multi`); the route prices
it first (:func:`check_multi_evaluation`) and runs it watched, stopping between trials.
"""

from __future__ import annotations

import math
from dataclasses import replace

from service.schemas import sessions as session_schemas

#: Cost units (:mod:`service.limits`) per expected bearing of a trial: the tracker, the per-second scoring and
#: the baseline (a DBSCAN per epoch, most of it) took about 0.7 ms a bearing on the two-core bench machine
#: (variant 0, about 3,700 bearings, 2.7 s a trial), so the default ``max_evaluation_cost`` admits about five
#: full trials, within the default request deadline.
MULTI_EVALUATION_UNITS_PER_BEARING = 20


def multi_scene(spec: session_schemas.MultiEmitterEvaluationSpec):
    """The request's scene: :func:`core.simulation.multi_emitter.multi_emitter_scene` of its variant, over its
    duration."""
    from core.simulation.multi_emitter import multi_emitter_scene

    scene = multi_emitter_scene(spec.variant)
    return scene if spec.duration_s is None else replace(scene, duration_s=float(spec.duration_s))


def multi_evaluation_cost(spec: session_schemas.MultiEmitterEvaluationSpec) -> int:
    """``trials x expected bearings x`` :data:`MULTI_EVALUATION_UNITS_PER_BEARING`."""
    from core.simulation.multi_emitter import expected_bearings

    return math.ceil(spec.trials * expected_bearings(multi_scene(spec)) * MULTI_EVALUATION_UNITS_PER_BEARING)


def check_multi_evaluation(spec: session_schemas.MultiEmitterEvaluationSpec, limit: int) -> None:
    """422 ``over_limit`` (at ``multi_emitter.trials``) when the evaluation costs more than ``limit``."""
    from service.limits import over_limit

    cost = multi_evaluation_cost(spec)
    if cost > limit:
        raise over_limit("max_evaluation_cost", cost, limit, ["multi_emitter", "trials"],
                         f"{spec.trials} trials of the multi-emitter scene")


def _finite(value) -> float | None:
    return float(value) if math.isfinite(value) else None


def multi_evaluation_body(spec: session_schemas.MultiEmitterEvaluationSpec, should_stop=None) -> dict:
    """The response body (``MultiEmitterEvaluationResponse``); ``should_stop`` is asked between trials
    (:class:`core.parallel.Stopped` when it says stop)."""
    from core.simulation.multi_emitter import evaluate_multi

    scene = multi_scene(spec)
    result = evaluate_multi(scene, spec.trials, spec.seed, should_stop=should_stop)
    base = result.baseline_parts_m2
    return {
        "scene": result.scenario, "variant": spec.variant, "trials": spec.trials, "seed": spec.seed,
        "duration_s": float(scene.duration_s), "gospa_cutoff_m": float(scene.gospa_cutoff_m),
        "tracker": {"gospa_m": result.gospa_m, "localisation_m2": result.localisation_m2,
                    "missed_m2": result.missed_m2, "false_m2": result.false_m2,
                    "gospa_per_trial_m": [float(v) for v in result.gospa_per_trial]},
        "baseline": {"gospa_m": result.baseline_gospa_m, "localisation_m2": float(base[0]),
                     "missed_m2": float(base[1]), "false_m2": float(base[2]),
                     "gospa_per_trial_m": [float(v) for v in result.baseline_gospa_per_trial]},
        "gospa_over_baseline": _finite(result.gospa_m / result.baseline_gospa_m) if result.baseline_gospa_m else None,
        "emitters": [e.id for e in scene.emitters],
        "confirm_delay_s": [[_finite(v) for v in row] for row in result.confirm_delay_s.tolist()],
        "false_tracks": [int(v) for v in result.false_tracks],
        "identity_switches": [int(v) for v in result.identity_switches],
    }
