"""Rival tentative tracks decided on their cumulative scores (:func:`decide_rivals`).

:func:`core.tracking.track_start.start_tracks` starts, beside the best packing of an ambiguous start, the
candidates of the packings that score almost as well, as rivals; :mod:`core.tracking.scan_assignment` scores
each scan's bearing for them; this module decides, after each scan, which rivals are confirmed and which end.
The rules are described in :mod:`core.tracking.association`, which calls this module after each scan; this
module never imports it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from core.tracking.association_types import AssociationConfig, MultiTrack, under_test

#: Largest group of rival tracks whose joint hypotheses are all enumerated; a larger one is packed greedily.
RIVALS_MAX_GROUP = 12


def decide_rivals(tracks: list[MultiTrack], time_s: float, config: AssociationConfig) -> list[MultiTrack]:
    """Confirm rival tentative tracks on their cumulative scores, and end the rivals that lost.

    The tentative tracks with a live rival (:func:`core.tracking.association_types.under_test`) fall into
    groups (rivals of rivals); a group's joint hypotheses are its subsets, each scored by its tracks' scores
    (:attr:`MultiTrack.score`) less what every pair of rivals in it would lose to be two emitters
    (:attr:`MultiTrack.rivals`). A track is confirmed when it is in the best subset, has ``confirm_hits`` of its
    last ``confirm_window`` scans, ``init_window_s`` has passed since its start (every station has scanned
    since: a score of fewer scans weighs the stations unevenly), and the best subset without it scores at
    least ``init_ambiguity_margin`` less, or ``init_decision_s`` has passed since its start. Its rivals outside
    the best subset then end.

    Parameters
    ----------
    tracks : list of MultiTrack
        The live tracks after a scan.
    time_s : float
    config : AssociationConfig

    Returns
    -------
    list of MultiTrack
        In order, without the ended rivals.
    """
    testing = under_test(tracks)
    if not testing:
        return tracks
    out = list(tracks)
    gone: set[int] = set()
    for group in _rival_groups(tracks, testing):
        ids = {tracks[k].id: n for n, k in enumerate(group)}
        scores = np.array([tracks[k].score for k in group])
        scores = np.where(np.isfinite(scores), scores, 0.0)
        rival = np.zeros((len(group), len(group)), dtype=bool)
        conflict = np.zeros((len(group), len(group)))
        for n, k in enumerate(group):
            for other, loss in tracks[k].rivals.items():
                if other in ids:
                    rival[n, ids[other]] = rival[ids[other], n] = True
                    conflict[n, ids[other]] = conflict[ids[other], n] = max(conflict[n, ids[other]], loss)
        value, best = _best_hypothesis(scores, conflict, np.ones(len(group), dtype=bool))
        for n in sorted(np.flatnonzero(best).tolist(), key=lambda n: -scores[n]):
            track = tracks[group[n]]
            if track.hits.count(True) < config.confirm_hits or time_s - track.started_s < config.init_window_s:
                continue
            if (time_s - track.started_s < config.init_decision_s
                    and value - _best_hypothesis(scores, conflict, np.arange(len(group)) != n)[0]
                    < config.init_ambiguity_margin):
                continue
            out[group[n]] = replace(track, confirmed=True, confirmed_s=time_s)
            gone.update(group[m] for m in np.flatnonzero(rival[n] & ~best).tolist())
    return [t for k, t in enumerate(out) if k not in gone]


def _rival_groups(tracks: Sequence[MultiTrack], testing: list[int]) -> list[list[int]]:
    """The connected groups of ``testing`` (track indices) joined by their live rivalries."""
    group_of = {tracks[k].id: n for n, k in enumerate(testing)}
    parent = list(range(len(testing)))

    def root(n):
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = parent[n]
        return n

    for n, k in enumerate(testing):
        for other in tracks[k].rivals:
            if other in group_of:
                parent[root(n)] = root(group_of[other])
    groups: dict[int, list[int]] = {}
    for n, k in enumerate(testing):
        groups.setdefault(root(n), []).append(k)
    return list(groups.values())


def _best_hypothesis(scores: np.ndarray, conflict: np.ndarray, allowed: np.ndarray) -> tuple[float, np.ndarray]:
    """The subset of the ``allowed`` tracks ``(n,)`` with the largest sum of ``scores`` less the ``conflict``
    ``(n, n)`` of each pair in it: its value and mask ``(n,)``. Every subset is tried up to
    :data:`RIVALS_MAX_GROUP` candidate tracks; beyond, tracks are added greedily by score while they gain."""
    mask = np.zeros(scores.size, dtype=bool)
    index = np.flatnonzero(allowed & (scores > 0.0))
    if index.size > RIVALS_MAX_GROUP:
        for k in index[np.argsort(-scores[index], kind="stable")].tolist():
            if scores[k] - conflict[k, mask].sum() > 0.0:
                mask[k] = True
    elif index.size:
        subsets = ((np.arange(2 ** index.size)[:, None] >> np.arange(index.size)[None, :]) & 1).astype(float)
        inner = conflict[np.ix_(index, index)]
        values = subsets @ scores[index] - 0.5 * np.einsum("ki,ij,kj->k", subsets, inner, subsets)
        mask[index[subsets[int(np.argmax(values))] > 0.5]] = True
    upper = np.triu(conflict, 1)
    return float(scores[mask].sum() - upper[np.ix_(mask, mask)].sum()), mask


__all__ = ["RIVALS_MAX_GROUP", "decide_rivals"]
