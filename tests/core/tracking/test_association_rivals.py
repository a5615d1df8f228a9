"""Rival starts: a ghost pairing and the emitters it borrows bearings from start side by side as tentative
tracks, and their cumulative scores decide which are confirmed."""

import itertools
import json
import math
from dataclasses import replace

import numpy as np
import pytest

from core.errors import InvalidInput
from core.simulation.multi_emitter import multi_emitter_scene, simulate_multi, truth_at
from core.simulation.network import START_TIME_S
from core.tracking.association import (
    AssociationConfig,
    AssociationState,
    MultiTrack,
    apply_observations,
    current_tracks,
    new_association_state,
)
from core.tracking.network import Track
from core.tracking.rival_starts import RIVALS_MAX_GROUP, _best_hypothesis, decide_rivals
from core.tracking.state import frozen_array

CONFIG = multi_emitter_scene(0).config


def rival(track_id, east_m, score, rivals, started_s=START_TIME_S) -> MultiTrack:
    """A tentative track at ``east_m`` (known to 30 m), ``confirm_window`` hits behind it."""
    mean = np.array([east_m, 0.0, 100.0, 0.0, 0.0, 0.0])
    cov = np.diag([900.0, 900.0, 900.0, 1.0, 1.0, 1.0])
    track = Track(track_id, "tentative", START_TIME_S + 2.0, frozen_array(mean), frozen_array(cov), 4, (), "single",
                  frozen_array([1.0]), frozen_array(mean[None]), frozen_array(cov[None]))
    return MultiTrack(track, math.nan, 0, (True,) * CONFIG.confirm_window, START_TIME_S + 2.0, False, started_s,
                      score=score, rivals=rivals)


def ghost_pair(real_score, ghost_score):
    """Emitters r1, r2 and the ghosts g1, g2 of their swapped pairing: each ghost shares bearings with both
    emitters (a conflict of 20: they cannot all be emitters), the pairs are apart."""
    conflict = 20.0
    return [rival("r1", 0.0, real_score, {"g1": conflict, "g2": conflict}),
            rival("r2", 5e3, real_score, {"g1": conflict, "g2": conflict}),
            rival("g1", 2e3, ghost_score, {"r1": conflict, "r2": conflict}),
            rival("g2", 3e3, ghost_score, {"r1": conflict, "r2": conflict})]


def test_rivals_wait_while_their_scores_are_close_then_the_better_pair_is_confirmed():
    now = START_TIME_S + 2.0
    # The pairs 2 apart (< init_ambiguity_margin): nothing is decided yet.
    close = decide_rivals(ghost_pair(30.0, 29.0), now, CONFIG)
    assert [t.confirmed for t in close] == [False] * 4
    # init_decision_s after the start the better pair is confirmed anyway and the ghosts end.
    late = decide_rivals(ghost_pair(30.0, 29.0), START_TIME_S + CONFIG.init_decision_s, CONFIG)
    assert [(t.id, t.confirmed) for t in late] == [("r1", True), ("r2", True)]
    # Apart by more than the margin: decided at once.
    apart = decide_rivals(ghost_pair(30.0, 30.0 - CONFIG.init_ambiguity_margin - 1.0), now, CONFIG)
    assert [(t.id, t.confirmed) for t in apart] == [("r1", True), ("r2", True)]
    # A lone ghost that out-scores each emitter still loses to the pair.
    tracks = ghost_pair(30.0, 15.0)
    tracks[2] = replace(tracks[2], score=38.0)
    assert [t.id for t in decide_rivals(tracks, now, CONFIG)] == ["r1", "r2"]


def test_two_emitters_that_shared_a_starting_bearing_are_both_confirmed():
    # The conflict (one shared bearing) is less than either score: both are emitters, decided at once.
    now = START_TIME_S + 2.0
    tracks = [rival("a", 0.0, 30.0, {"b": 10.0}), rival("b", 4e3, 29.5, {"a": 10.0})]
    assert [(t.id, t.confirmed) for t in decide_rivals(tracks, now, CONFIG)] == [("a", True), ("b", True)]
    # Not before every station has scanned since their start.
    early = START_TIME_S + 2.0 + 0.5 * CONFIG.init_window_s
    tracks = [replace(t, started_s=START_TIME_S + 2.0) for t in tracks]
    assert not any(t.confirmed for t in decide_rivals(tracks, early, CONFIG))


def test_a_ghost_pairing_that_ties_the_emitters_at_the_start_is_not_confirmed():
    # Variant 1, seed 10: e1 and e2 (one frequency) each lie near the line between two opposite stations, and
    # a station misses e1 in the first scan, so the swapped pairing scores as well as the real one at the start.
    scene = multi_emitter_scene(1)
    run = simulate_multi(scene, np.random.default_rng(10))
    state = new_association_state()
    for second in range(1, 31):
        now = START_TIME_S + second
        batch = [o for o in run.observations if (second == 1 or now - 1.0 < o.time_s) and o.time_s <= now]
        state = apply_observations(state, batch, scene.config).state
        confirmed = [t for t in current_tracks(state, now, scene.config) if t.status == "confirmed"]
        ids, truths = truth_at(scene, now)
        distances = np.linalg.norm(np.array([t.mean_enu[:2] for t in confirmed]).reshape(-1, 1, 2)
                                   - truths[None, :, :2], axis=-1)
        # No confirmed track away from every emitter, at any second.
        assert np.all(distances.min(axis=1, initial=np.inf) < 1000.0), (second, distances)
    # By 30 s each emitter on the air has a confirmed track.
    assert np.all(distances.min(axis=0) < 1000.0), ids


def test_states_written_before_rivals_were_kept_still_load():
    scene = multi_emitter_scene(0)
    run = simulate_multi(scene, np.random.default_rng(2))
    state = apply_observations(new_association_state(), [o for o in run.observations
                                                         if o.time_s < START_TIME_S + 5.0], scene.config).state
    data = json.loads(json.dumps(state.to_dict()))
    assert data["tracks"] and all("rivals" in t and "score" in t for t in data["tracks"])
    data["format"] = 1
    for t in data["tracks"]:
        del t["rivals"], t["score"]
    old = AssociationState.from_dict(data)
    assert all(t.rivals == {} and math.isnan(t.score) for t in old.tracks)
    rest = [o for o in run.observations if START_TIME_S + 5.0 <= o.time_s < START_TIME_S + 10.0]
    after = apply_observations(old, rest, scene.config).state
    assert [t.id for t in after.tracks if t.confirmed] == [t.id for t in state.tracks if t.confirmed]


def test_rival_settings_are_validated():
    for bad in ({"init_ambiguity_margin": -1.0}, {"init_ambiguity_margin": math.inf}, {"init_decision_s": 0.0}):
        with pytest.raises(InvalidInput) as error:
            AssociationConfig(**bad)
        assert error.value.loc == (next(iter(bad)),)


def _brute_force_best(scores: np.ndarray, conflict: np.ndarray) -> float:
    """The best joint hypothesis's value by enumerating every subset (independent of the module's arithmetic)."""
    best = 0.0
    for size in range(1, scores.size + 1):
        for subset in itertools.combinations(range(scores.size), size):
            value = sum(scores[k] for k in subset) - sum(conflict[i, j] for i, j in itertools.combinations(subset, 2))
            best = max(best, value)
    return best


@pytest.mark.parametrize("seed", range(20))
def test_the_best_joint_hypothesis_is_the_best_subset(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 9))
    scores = rng.normal(5.0, 5.0, n)
    conflict = np.triu(rng.exponential(4.0, (n, n)) * (rng.random((n, n)) < 0.5), 1)
    conflict = conflict + conflict.T
    value, mask = _best_hypothesis(scores, conflict, np.ones(n, dtype=bool))
    assert value == pytest.approx(_brute_force_best(scores, conflict), abs=1e-9)
    assert value == pytest.approx(scores[mask].sum() - np.triu(conflict, 1)[np.ix_(mask, mask)].sum(), abs=1e-9)


def test_a_group_too_large_to_enumerate_is_packed_greedily_into_a_consistent_hypothesis():
    """Past RIVALS_MAX_GROUP candidates every subset is not tried: the pick is greedy by score, and no track whose
    conflicts with those already picked outweigh its score joins (two rivals of 20 never both)."""
    n = RIVALS_MAX_GROUP + 4
    scores = np.linspace(10.0, 5.0, n)
    conflict = np.zeros((n, n))
    for k in range(0, n, 2):  # pairs (0, 1), (2, 3), ...: rivals that cannot both be emitters
        conflict[k, k + 1] = conflict[k + 1, k] = 20.0
    value, mask = _best_hypothesis(scores, conflict, np.ones(n, dtype=bool))
    assert mask.tolist() == [k % 2 == 0 for k in range(n)]
    assert value == pytest.approx(scores[::2].sum())
