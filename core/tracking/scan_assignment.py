"""One scan of unlabelled bearings against the tracks: gate, assign (JPDA or GNN), update.

:func:`assign_scan` takes one station's bearings of one time and the live tracks, and returns the tracks
after it and the bearings no track took (they go to the start pool, :mod:`core.tracking.track_start`). The gate, the
likelihood ratios and both assignment methods are described in :mod:`core.tracking.association`, which calls
this module once per scan; each track's update is the network tracker's
(:func:`core.tracking.network_update.advance_track`). This module never imports
:mod:`core.tracking.association`.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment

from core.angles import wrap_to_pi
from core.measurements import AZIMUTH, predict
from core.tracking.association_types import (
    COARSE_SIGMAS,
    AssociationConfig,
    MultiTrack,
    Observation,
    frequency_ok,
    under_test,
)
from core.tracking.network import NetworkState, predict_tracks
from core.tracking.network_kernel import STATE_SIZE, UPDATED, network_ukf_pairs
from core.tracking.network_types import Report
from core.tracking.network_update import (
    advance_track,
    chi2_point,
    predicted_moments,
    report_rows,
    updated_track,
)
from core.tracking.state import frozen_array

#: With this many tracks or more, a scan's pairs are screened (:func:`_coarse_gate`) before the exact gate;
#: with fewer, the screen costs more than the exact gate it saves.
COARSE_FROM_TRACKS = 8


class ScanGate(NamedTuple):
    """One scan's gate (:func:`scan_gate`): the costs, and the update each gated pair would make.

    Attributes
    ----------
    cost : ndarray, shape (T, B)
        ``-log`` likelihood ratio of each pair (track's bearing against a false one); ``inf`` outside the gate.
    nis : ndarray, shape (T, B)
    rows : list of ReportRows
        Each bearing's :func:`core.tracking.network_update.report_rows` (None for one no track may take).
    predicted : dict
        Track index -> its mean ``(6,)`` and covariance ``(6, 6)`` predicted to the scan's time.
    updates : dict
        ``(track, bearing)`` -> the kernel's updated mean, covariance, NIS, ``log det S`` and status, with the
        network tracker's ``linearisation_passes``: the update :func:`core.tracking.network_update.advance_track`
        would make, reused for a gated pair (:func:`core.tracking.network_update.updated_track`).
    """

    cost: np.ndarray
    nis: np.ndarray
    rows: list
    predicted: dict
    updates: dict


def gate_costs(tracks: Sequence[MultiTrack], scan: Sequence[Observation], config: AssociationConfig):
    """The association costs of one scan's bearings against the tracks (JPDA and GNN).

    Returns
    -------
    cost : ndarray, shape (T, B)
        ``-log`` likelihood ratio of each pair (track's bearing against a false one); ``inf`` outside the gate.
    nis : ndarray, shape (T, B)
    """
    gate = scan_gate(tracks, scan, config)
    return gate.cost, gate.nis


def scan_gate(tracks: Sequence[MultiTrack], scan: Sequence[Observation], config: AssociationConfig) -> ScanGate:
    """The gate of one scan's bearings against the tracks: costs, NIS and each gated pair's update
    (:class:`ScanGate`). Each track is predicted once per scan, and the pairs the coarse screen leaves are
    updated in one kernel call."""
    count, size = len(tracks), len(scan)
    cost = np.full((count, size), np.inf)
    nis_out = np.full((count, size), np.inf)
    out = ScanGate(cost, nis_out, [None] * size, {}, {})
    if not count or not size:
        return out
    time_s = scan[0].time_s
    if count >= COARSE_FROM_TRACKS:
        near = _coarse_gate(tracks, scan, config)
    else:
        near = np.array([[frequency_ok(t.frequency_hz, o.frequency_hz, config) for o in scan] for t in tracks])
    needed = np.flatnonzero(near.any(axis=1))
    if not needed.size:
        return out
    all_means, all_covs = predicted_moments([tracks[i].track for i in needed.tolist()], time_s, config.network)
    for k, i in enumerate(needed.tolist()):
        out.predicted[i] = (all_means[k], all_covs[k])
    passes = config.network.linearisation_passes
    log_pd_over_lambda = math.log(config.detection_probability / config.false_density_per_rad2)
    pair_local, pair_bearing = np.nonzero(near[needed])
    # One kernel call per group of bearings that share their station, frame and kinds (a scan is one
    # station's: one group, unless some bearings lack an elevation).
    groups: dict[tuple, list[int]] = {}
    for j in np.unique(pair_bearing).tolist():
        report = scan[j].report
        out.rows[j] = report_rows(report)
        key = (report.kinds.tobytes(), report.stations_enu_m.tobytes(), report.rotations.tobytes())
        groups.setdefault(key, []).append(j)
    for members in groups.values():
        first = scan[members[0]].report
        rows = out.rows[members[0]]
        at = np.full(size, -1)
        at[members] = np.arange(len(members))
        picked = at[pair_bearing] >= 0
        local, bearings = pair_local[picked], pair_bearing[picked]
        values = np.array([out.rows[j].values for j in members])[at[bearings]]
        variances = np.array([out.rows[j].variances for j in members])[at[bearings]]
        count_pairs = local.size
        new_means, new_covs = np.empty((count_pairs, STATE_SIZE)), np.empty((count_pairs, STATE_SIZE, STATE_SIZE))
        nis, log_det = np.empty(count_pairs), np.empty(count_pairs)
        status = np.empty(count_pairs, dtype=np.int64)
        network_ukf_pairs(all_means, all_covs, local.astype(np.int64), first.stations_enu_m, first.rotations,
                          first.kinds, values, variances, rows.rows, passes, new_means, new_covs, nis, log_det,
                          status)
        dof = rows.rows.size
        gated = (status == UPDATED) & (nis <= chi2_point(config.gate_probability, dof))
        costs = 0.5 * (nis + log_det + dof * math.log(2.0 * math.pi)) - log_pd_over_lambda
        for k in np.flatnonzero(gated).tolist():
            i, j = int(needed[local[k]]), int(bearings[k])
            nis_out[i, j] = nis[k]
            cost[i, j] = costs[k]
            out.updates[i, j] = (new_means[k], new_covs[k], float(nis[k]), float(log_det[k]), int(status[k]))
    return out


def _coarse_gate(tracks: Sequence[MultiTrack], scan: Sequence[Observation], config: AssociationConfig) -> np.ndarray:
    """Pairs ``(T, B)`` that may pass the gate: frequencies compatible and the bearing's azimuth within
    :data:`COARSE_SIGMAS` of the track's azimuth from the scan's station, with an upper bound of its standard
    deviation (the root of the position covariance's trace, grown by the velocity's over the interval, over
    the range, with the bearing's own). The exact test on the pairs left is the gate itself."""
    station, rotation = scan[0].report.stations_enu_m[0], scan[0].report.rotations[0]
    means = np.array([t.track.mean_enu for t in tracks])
    covs = np.array([t.track.covariance_enu for t in tracks])
    dt = np.abs(scan[0].time_s - np.array([t.track.time_s for t in tracks]))
    positions = means[:, :3] + means[:, 3:] * dt[:, None]
    spread_m = (np.sqrt(np.trace(covs[:, :3, :3], axis1=1, axis2=2))
                + dt * np.sqrt(np.trace(covs[:, 3:, 3:], axis1=1, axis2=2))
                + 3.0 * config.network.accel_sigma_mps2 * dt ** 1.5)
    seen, _ = predict(positions, 0.0, station[None], rotation[None], np.array([AZIMUTH]))
    distances = np.linalg.norm(positions - station, axis=1)
    azimuths = np.array([o.report.values[o.report.kinds == AZIMUTH][0] for o in scan])
    sigmas = np.array([o.report.sigmas[o.report.kinds == AZIMUTH][0] for o in scan])
    with np.errstate(divide="ignore", invalid="ignore"):
        angular = np.where(distances > spread_m, spread_m / distances, np.inf)
    window = COARSE_SIGMAS * np.hypot(angular[:, None], sigmas[None, :])
    near = np.abs(wrap_to_pi(azimuths[None, :] - seen[:, 0][:, None])) < window
    frequencies = np.array([t.frequency_hz for t in tracks])
    near &= ~(np.abs(frequencies[:, None] - np.array([o.frequency_hz for o in scan])[None, :])
              > config.frequency_tolerance_hz)
    return near


def assign_scan(tracks: list[MultiTrack], scan: Sequence[Observation],
                config: AssociationConfig) -> tuple[list[MultiTrack], list[Observation]]:
    """Associate one scan's bearings with the tracks (JPDA or GNN, ``config.method``) and update the tracks.

    Parameters
    ----------
    tracks : list of MultiTrack
        The live tracks, length T.
    scan : sequence of Observation
        One station's bearings of one time, length B >= 1.
    config : AssociationConfig

    Returns
    -------
    tracks : list of MultiTrack
        The tracks after the scan, in order, without the tentative ones that can no longer confirm.
    unassigned : list of Observation
        The bearings left for track starts.
    """
    if not tracks:
        return [], list(scan)
    gate = scan_gate(tracks, scan, config)
    # Rival tentative tracks are alternative explanations of the same bearings, not emitters beside each
    # other: they stay out of the joint assignment and are scored on their own (:func:`_test_rivals`).
    testing = under_test(tracks)
    joint = gate._replace(cost=gate.cost.copy()) if testing else gate
    joint.cost[testing] = np.inf
    if config.method == "jpda":
        out, claimed = _scan_jpda(tracks, scan, joint, config)
        free = claimed < 0.5
    else:
        out, free = _scan_gnn(tracks, scan, joint, config)
    if testing:
        out, free = _test_rivals(tracks, scan, gate, testing, out, free, config)
    return [t for t in out if t is not None], [o for j, o in enumerate(scan) if free[j]]


def _scan_gnn(tracks, scan, gate: ScanGate, config):
    """Global nearest neighbour: the tracks after the scan (None: deleted) and which bearings are left
    ``(B,)``."""
    time_s = scan[0].time_s
    cost = gate.cost
    pairs = {}
    usable = np.minimum(np.where(np.isfinite(cost), cost, 0.0), 0.0)
    if usable.any():
        rows, cols = linear_sum_assignment(usable)
        pairs = {int(i): int(j) for i, j in zip(rows, cols) if cost[i, j] < 0.0}
    unsure = (ambiguous_tracks(pairs, cost, config.ambiguity_margin) if pairs and config.ambiguity_margin > 0.0
              else set())
    out = [_after_scan(t, None if pairs.get(i) is None else scan[pairs[i]], time_s, config, i in unsure,
                       _update_of(gate, i, pairs.get(i)))
           for i, t in enumerate(tracks)]
    free = np.ones(len(scan), dtype=bool)
    free[list(pairs.values())] = False
    return out, free


def _test_rivals(tracks, scan, gate: ScanGate, testing, out, free, config):
    """Each rival tentative track (:func:`core.tracking.association_types.under_test`) takes its best gated bearing of
    those the other tracks left, rivals alike (each is one hypothesis about them), and adds that bearing's log
    likelihood ratio, or ``log(1 - P_D)`` when none gates, to its score; two rivals that took one bearing add
    to their conflict what the one that fits it less would lose by missing it. They are not confirmed here
    (:func:`core.tracking.rival_starts.decide_rivals` does); the bearings they take leave the start pool."""
    time_s = scan[0].time_s
    left = free.copy()
    missed = math.log1p(-config.detection_probability)
    took = {}
    for i in testing:
        t = tracks[i]
        cost = np.where(free, gate.cost[i], np.inf)
        j = int(np.argmin(cost))
        hit = bool(np.isfinite(cost[j]))
        out[i] = _after_scan(t, scan[j] if hit else None, time_s, config,
                             update=_update_of(gate, i, j if hit else None), may_confirm=False)
        if out[i] is not None:
            out[i] = replace(out[i], score=t.score + (-float(cost[j]) if hit else missed))
            if hit:
                left[j] = False
                took[t.id] = (j, -float(cost[j]))
    for i in testing:
        if out[i] is None or out[i].id not in took:
            continue
        j, llr = took[out[i].id]
        shared = {other: max(0.0, min(llr, took[other][1]) - missed) for other in out[i].rivals
                  if other in took and took[other][0] == j}
        if shared:
            out[i] = replace(out[i], rivals={other: loss + shared.get(other, 0.0)
                                             for other, loss in out[i].rivals.items()})
    return out, left


#: Largest number of tracks in one JPDA cluster whose joint events are enumerated; larger ones fall back to
#: the GNN assignment.
JPDA_MAX_CLUSTER = 6
#: A JPDA hypothesis (a bearing, or none) less probable than this is dropped.
JPDA_NEGLIGIBLE = 1e-3


def jpda_weights(likelihood: np.ndarray, missed: float) -> tuple[np.ndarray, np.ndarray]:
    """Association probabilities of one scan: ``beta (T, B)`` and ``beta_0 (T,)`` (no bearing), by enumerating
    the feasible joint events of each cluster of tracks that share gated bearings. ``likelihood`` is each
    pair's ``P_D N / lambda`` (0 outside the gate); a track left without a bearing weighs ``missed``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    count, size = likelihood.shape
    beta, beta0 = np.zeros((count, size)), np.ones(count)
    gated = likelihood > 0.0
    rows, cols = np.nonzero(gated)
    if not rows.size:
        return beta, beta0
    # A track whose gated bearings no other track gates is a cluster of its own: its bearings or none, in
    # closed form, for all such tracks at once (the common case: emitters apart).
    shared = gated.sum(axis=0) > 1
    alone = gated.any(axis=1) & ~(gated & shared[None, :]).any(axis=1)
    total = missed + likelihood[alone].sum(axis=1)
    beta[alone], beta0[alone] = likelihood[alone] / total[:, None], missed / total
    if alone.sum() == np.unique(rows).size:
        return beta, beta0
    # Clusters: the connected parts of the graph of tracks and bearings joined by their gates.
    graph = coo_matrix((np.ones(rows.size), (rows, count + cols)), shape=(count + size, count + size))
    labels = connected_components(graph, directed=False)[1][:count]
    for label in np.unique(labels[np.unique(rows[~alone[rows]])]).tolist():
        order = np.flatnonzero(labels == label).tolist()
        if len(order) > JPDA_MAX_CLUSTER:
            picked_tracks, picked = linear_sum_assignment(-np.log(np.where(gated[order], likelihood[order], 1e-300)))
            for r, c in zip(picked_tracks, picked):
                if gated[order[r], c]:
                    beta[order[r], c], beta0[order[r]] = 1.0, 0.0
            continue
        acc, acc0, total = _joint_events(order, gated, likelihood, missed)
        beta[order] = acc[order] / total
        beta0[order] = acc0[order] / total
    return beta, beta0


def _joint_events(order: list, gated: np.ndarray, likelihood: np.ndarray, missed: float):
    """Sum over the feasible joint events of the tracks ``order`` (each takes one gated bearing no other
    takes, or none) of their weights, per track and bearing: ``(T, B)``, per track for no bearing ``(T,)``,
    and in all."""
    count, size = likelihood.shape
    acc, acc0, total = np.zeros((count, size)), np.zeros(count), 0.0
    stack = [(0, frozenset(), 1.0, ())]
    while stack:
        position, used, weight, picks = stack.pop()
        if position == len(order):
            total += weight
            for i, j in picks:
                if j < 0:
                    acc0[i] += weight
                else:
                    acc[i, j] += weight
            continue
        i = order[position]
        stack.append((position + 1, used, weight * missed, picks + ((i, -1),)))
        for j in np.flatnonzero(gated[i]).tolist():
            if j not in used:
                stack.append((position + 1, used | {j}, weight * likelihood[i, j], picks + ((i, j),)))
    return acc, acc0, total


def _scan_jpda(tracks, scan, gate: ScanGate, config):
    """JPDA in place of GNN: each track updated with every gated bearing of the scan and left as predicted,
    the hypotheses merged by their association probabilities (the Gaussian sum's moments; for a linear model
    this is the PDA update); a hit when the track's bearing probability is above one half. Returns the tracks
    after the scan (None: deleted) and each bearing's probability of belonging to a track ``(B,)`` (below one
    half: it goes to the start pool)."""
    time_s = scan[0].time_s
    cost = gate.cost
    likelihood = np.where(np.isfinite(cost), np.exp(-np.where(np.isfinite(cost), cost, 0.0)), 0.0)
    beta, beta0 = jpda_weights(likelihood, 1.0 - config.detection_probability)
    out = []
    for i, t in enumerate(tracks):
        # Hypotheses below JPDA_NEGLIGIBLE are dropped (the rest renormalised): an isolated track with one
        # bearing deep in its gate is then updated as GNN would, at GNN's cost.
        options = np.flatnonzero(beta[i] > JPDA_NEGLIGIBLE).tolist()
        keep_missed = beta0[i] > JPDA_NEGLIGIBLE
        if not options or t.track.stage == "imm" or (len(options) == 1 and not keep_missed):
            best = int(np.argmax(beta[i])) if options else -1
            hit = bool(options) and beta[i, best] > 0.5
            out.append(_after_scan(t, scan[best] if hit else None, time_s, config,
                                   update=_update_of(gate, i, best if hit else None)))
            continue
        weights, means, covs, updated = [], [], [], []
        if keep_missed:
            if i in gate.predicted:
                weights, means, covs = [beta0[i]], [gate.predicted[i][0]], [gate.predicted[i][1]]
            else:
                predicted = predict_tracks(NetworkState(tracks=(t.track,)), time_s, config.network)[0]
                weights, means, covs = [beta0[i]], [predicted.mean_enu], [predicted.covariance_enu]
        for j in options:
            track = _updated(t, scan[j], _update_of(gate, i, j), config)
            weights.append(beta[i, j])
            means.append(track.mean_enu)
            covs.append(track.covariance_enu)
            updated.append(track)
        weights = np.array(weights) / np.sum(weights)
        mean = np.einsum("k,ki->i", weights, np.array(means))
        spread = np.array(means) - mean
        cov = np.einsum("k,kij->ij", weights, np.array(covs)) + np.einsum("k,ki,kj->ij", weights, spread, spread)
        cov = 0.5 * (cov + cov.T)
        best = int(np.argmax(weights[1:] if keep_missed else weights))
        merged = replace(updated[best], mean_enu=frozen_array(mean), covariance_enu=frozen_array(cov),
                         weights=frozen_array([1.0]), means=frozen_array(mean[None]),
                         covariances=frozen_array(cov[None]))
        hit = 1.0 - beta0[i] > 0.5
        hits = (t.hits + (bool(hit),))[-config.confirm_window:]
        if not hit and not t.confirmed and hits.count(False) > config.confirm_window - config.confirm_hits:
            out.append(None)
            continue
        confirmed = t.confirmed or hits.count(True) >= config.confirm_hits
        out.append(replace(t, track=merged, hits=hits, last_hit_s=time_s if hit else t.last_hit_s,
                           confirmed=confirmed, confirmed_s=time_s if confirmed and not t.confirmed else t.confirmed_s))
    return out, beta.sum(axis=0)


def ambiguous_tracks(pairs: dict, cost: np.ndarray, margin: float) -> set:
    """Tracks whose assigned bearing is not decisively theirs: another track could take it (swapping bearings
    with it, or taking it while left without one) at a cost less than ``margin`` above the assignment's."""
    out = set()
    for i, j in pairs.items():
        for k in np.flatnonzero(np.isfinite(cost[:, j])).tolist():
            if k == i:
                continue
            other = pairs.get(k)
            if other is None:
                worse = cost[k, j] - cost[i, j]
            elif np.isfinite(cost[i, other]):
                worse = cost[k, j] + cost[i, other] - cost[i, j] - cost[k, other]
            else:
                continue
            if worse < margin:
                out.update((i, k))
    return out


def _update_of(gate: ScanGate | None, track: int, bearing: int | None):
    """The gate's update of a pair, with what :func:`core.tracking.network_update.updated_track` needs; None
    when the pair has none."""
    if gate is None or bearing is None or (track, bearing) not in gate.updates:
        return None
    return gate.rows[bearing], gate.predicted[track], gate.updates[track, bearing]


def _updated(track: MultiTrack, obs: Observation, update, config: AssociationConfig):
    """The filter of ``track`` after ``obs``: the gate's update when it has one for a ``single``-stage track
    (the same kernel call :func:`core.tracking.network_update.advance_track` would make), else that function."""
    if update is not None and track.track.stage == "single" and not config.network.imm_accel_sigmas_mps2:
        rows, (mean, cov), (new_mean, new_cov, nis, log_det, status) = update
        return updated_track(track.track, obs.report, rows, mean, cov, new_mean, new_cov, nis, log_det, status,
                             config.network, track.id)
    return advance_track(track.track, _labelled(obs.report, track.id), config.network)[0]


def _after_scan(track: MultiTrack, obs: Observation | None, time_s: float, config: AssociationConfig,
                unsure: bool = False, update=None, may_confirm: bool = True):
    """A track after one scan (None: deleted as a tentative track that can no longer confirm). With ``unsure``
    the bearing counts as a hit but does not update the track (:func:`ambiguous_tracks`). ``update`` is the
    gate's for the pair (:func:`_update_of`), if any. Without ``may_confirm`` a tentative track stays
    tentative."""
    hits = (track.hits + (obs is not None,))[-config.confirm_window:]
    if obs is None:
        if not track.confirmed and hits.count(False) > config.confirm_window - config.confirm_hits:
            return None
        return replace(track, hits=hits)
    confirmed = track.confirmed or (may_confirm and hits.count(True) >= config.confirm_hits)
    confirmed_s = time_s if confirmed and not track.confirmed else track.confirmed_s
    if unsure:
        return replace(track, hits=hits, last_hit_s=time_s, confirmed=confirmed, confirmed_s=confirmed_s)
    updated = _updated(track, obs, update, config)
    frequency, count = track.frequency_hz, track.frequency_count
    if math.isfinite(obs.frequency_hz):
        count += 1
        frequency = obs.frequency_hz if not math.isfinite(frequency) else (
            frequency + (obs.frequency_hz - frequency) / count)
    return replace(track, track=updated, frequency_hz=frequency, frequency_count=count, hits=hits, last_hit_s=time_s,
                   confirmed=confirmed, confirmed_s=confirmed_s)


def _labelled(report: Report, track_id: str) -> Report:
    """The report as its track's (``emitter_id`` set): a shallow copy, its arrays read-only and shared."""
    out = copy.copy(report)
    object.__setattr__(out, "emitter_id", track_id)
    return out


__all__ = [
    "COARSE_FROM_TRACKS",
    "JPDA_MAX_CLUSTER",
    "JPDA_NEGLIGIBLE",
    "ScanGate",
    "ambiguous_tracks",
    "assign_scan",
    "gate_costs",
    "jpda_weights",
    "scan_gate",
]
