"""Tracks started from the bearings no track took, across three or more stations, ghosts rejected.

:func:`start_tracks` takes the start pool (the latest unassigned bearings of each station) and returns the
tracks it starts and the pool without their bearings: pairs crossed, triples gated, each candidate fitted
and scored (:func:`find_candidates`), the candidates that share no bearing chosen by set packing
(:func:`select_candidates`). The rules are described in :mod:`core.tracking.association`, which calls this
module after each scan; this module never imports it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from core.angles import line_of_sight_enu, station_to_common, wrap_to_pi
from core.measurements import AZIMUTH, ELEVATION, predict
from core.tracking.association_types import (
    COARSE_SIGMAS,
    AssociationConfig,
    MultiTrack,
    Observation,
    frequency_ok,
)
from core.tracking.network_kernel import STATE_SIZE
from core.tracking.network_types import Track
from core.tracking.network_update import chi2_point, velocity_prior
from core.tracking.state import frozen_array

#: A pair of bearings whose lines of sight are closer to parallel than this (rad) is not crossed.
MIN_CROSSING_ANGLE_RAD = math.radians(2.0)
#: Gauss-Newton iterations of a candidate's fit (each from the pair crossing, which is within a few
#: standard deviations of the optimum).
FIT_ITERATIONS = 6


class Candidate(NamedTuple):
    """A possible emitter: the pool bearings it explains, its fitted position and score.

    Attributes
    ----------
    members : tuple of int
        Pool indices, one per station.
    position_enu_m : ndarray, shape (3,)
    covariance_enu_m2 : ndarray, shape (3, 3)
        Inverse Fisher information of the fit.
    chi2 : float
    score : float
        Log likelihood ratio against "all false" (:mod:`core.tracking.association`).
    """

    members: tuple[int, ...]
    position_enu_m: np.ndarray
    covariance_enu_m2: np.ndarray
    chi2: float
    score: float


class _Pool(NamedTuple):
    """The pool's bearings as arrays ``(P, ...)``: two rows (azimuth, elevation) each."""

    station: np.ndarray       # (P,) int, station index
    positions: np.ndarray     # (P, 3)
    rotations: np.ndarray     # (P, 3, 3)
    values: np.ndarray        # (P, 2) azimuth, elevation (0 when not measured)
    sigmas: np.ndarray        # (P, 2)
    directions: np.ndarray    # (P, 3) line of sight, common frame
    frequency: np.ndarray     # (P,)
    has_elevation: np.ndarray  # (P,) bool


def _pool_arrays(pool: Sequence[Observation], config: AssociationConfig) -> _Pool:
    names = {}
    station = np.empty(len(pool), dtype=np.int64)
    positions = np.empty((len(pool), 3))
    rotations = np.empty((len(pool), 3, 3))
    values = np.zeros((len(pool), 2))
    sigmas = np.full((len(pool), 2), config.network.azimuth_only_elevation_sigma_rad)
    has_elevation = np.zeros(len(pool), dtype=bool)
    for k, obs in enumerate(pool):
        report = obs.report
        station[k] = names.setdefault(obs.station_id, len(names))
        positions[k] = report.stations_enu_m[0]
        rotations[k] = report.rotations[0]
        for kind, value, sigma in zip(report.kinds.tolist(), report.values.tolist(), report.sigmas.tolist()):
            column = 0 if kind == AZIMUTH else 1
            values[k, column], sigmas[k, column] = value, sigma
            has_elevation[k] |= kind == ELEVATION
    directions = station_to_common(line_of_sight_enu(values[:, 0], values[:, 1]), rotations)
    frequency = np.array([obs.frequency_hz for obs in pool], dtype=float)
    return _Pool(station, positions, rotations, values, sigmas, directions, frequency, has_elevation)


def start_tracks(tracks: list[MultiTrack], pool: list[Observation], next_id: int, time_s: float,
                 config: AssociationConfig) -> tuple[list[MultiTrack], list[Observation], int, list[str]]:
    """Start tracks from the pool (rules in :mod:`core.tracking.association`).

    Parameters
    ----------
    tracks : list of MultiTrack
        The live tracks; the new ones are appended to this list.
    pool : list of Observation
        Unassigned bearings of the last ``init_window_s``; the latest scan of each station is used.
    next_id : int
        The number of the next track id.
    time_s : float
        Time of the scan just processed.
    config : AssociationConfig

    Returns
    -------
    tracks : list of MultiTrack
    pool : list of Observation
        Without the bearings the new tracks took.
    next_id : int
    new_ids : list of str
    """
    latest = {}
    for obs in pool:
        latest[obs.station_id] = max(latest.get(obs.station_id, -math.inf), obs.time_s)
    usable = [o for o in pool if o.time_s == latest[o.station_id]]
    if len(latest) < config.init_min_stations:
        return tracks, pool, next_id, []
    candidates = find_candidates(usable, config)
    chosen, rivals = select_candidates(candidates, len(usable)), []
    if config.init_ambiguity_margin > 0.0:
        rivals = rival_candidates(candidates, chosen, len(usable), config.init_ambiguity_margin,
                                  config.gate_probability)
    started = chosen + rivals
    ids = [f"t{next_id + k}" for k in range(len(started))]
    next_id += len(started)
    give_up = _give_up_llr(_pool_arrays(usable, config), config) if rivals else None
    for k, cand in enumerate(started):
        shared = {ids[n]: float(sum(give_up[m] for m in set(cand.members).intersection(other.members)))
                  for n, other in enumerate(started) if n != k and set(cand.members).intersection(other.members)}
        tracks.append(_new_track(ids[k], cand, [usable[m] for m in cand.members], config, shared))
    consumed = {id(usable[m]) for cand in started for m in cand.members}
    return tracks, [o for o in pool if id(o) not in consumed], next_id, ids


def select_candidates(candidates: Sequence[Candidate], size: int) -> list[Candidate]:
    """The candidates that share no bearing with the largest total score: the S-D assignment problem as a
    set packing, ``max sum score_k x_k`` over binary ``x`` with every bearing in at most one chosen candidate,
    solved exactly (:func:`set_packing`). A greedy pick by score is not enough: where stations see two
    emitters nearly in line, a ghost that borrows one bearing of each can out-score either real emitter and
    would block both.

    Parameters
    ----------
    candidates : sequence of Candidate
        Scores positive.
    size : int
        Number of bearings (pool indices ``0 .. size-1``).

    Returns
    -------
    list of Candidate
        In descending score.
    """
    chosen = set_packing(np.array([c.score for c in candidates]), [c.members for c in candidates], size)
    return sorted((candidates[k] for k in chosen), key=lambda c: -c.score)


def rival_candidates(candidates: Sequence[Candidate], chosen: Sequence[Candidate], size: int, margin: float,
                     gate_probability: float) -> list[Candidate]:
    """The candidates of each best packing without one of ``chosen`` (the best packing) that scores less than
    ``margin`` below it: where a missed detection makes a ghost and an emitter about equally likely, both
    start and the next scans decide (:func:`core.tracking.rival_starts.decide_rivals`). A candidate whose
    position agrees with that of a chosen one it shares a bearing with (within the ``gate_probability``
    chi-square point of their summed covariances) is the same emitter from other bearings and is left out:
    the chosen one's track refines it, and a choice between the two by their scores would be noise.

    Returns
    -------
    list of Candidate
        Not in ``chosen``, in descending score.
    """
    if not chosen:
        return []
    scores = np.array([c.score for c in candidates])
    members = [c.members for c in candidates]
    best = float(sum(c.score for c in chosen))
    index = {c.members: k for k, c in enumerate(candidates)}
    picked = [index[c.members] for c in chosen]
    out: set[int] = set()
    for k in picked:
        value, others = best_without(scores, members, size, k)
        if best - value < margin:
            out.update(n for n in others if n not in picked)
    gate = chi2_point(gate_probability, 3)
    distinct = [k for k in out if not any(set(candidates[k].members).intersection(c.members)
                                          and _distance2(candidates[k], c) <= gate for c in chosen)]
    return sorted((candidates[k] for k in distinct), key=lambda c: -c.score)


def _distance2(a: Candidate, b: Candidate) -> float:
    """Squared Mahalanobis distance of two candidates' positions (their covariances summed)."""
    difference = a.position_enu_m - b.position_enu_m
    return float(difference @ np.linalg.solve(a.covariance_enu_m2 + b.covariance_enu_m2, difference))


def set_packing(scores: np.ndarray, members: Sequence[Sequence[int]], size: int) -> list[int]:
    """The items that share no resource with the largest total score: ``max sum score_k x_k`` over binary
    ``x`` with every resource (``0 .. size-1``) in at most one chosen item's ``members``, solved exactly
    (:func:`scipy.optimize.milp`; a greedy pick by score when HiGHS gives no solution). ``scores`` ``(K,)``;
    an item scoring 0 or less is never chosen. Returns the chosen indices."""
    if len(scores) == 1:
        return [0] if scores[0] > 0.0 else []
    return best_without(scores, members, size, -1)[1]


def best_without(scores: np.ndarray, members: Sequence[Sequence[int]], size: int,
                 excluded: int) -> tuple[float, list[int]]:
    """:func:`set_packing` without item ``excluded`` (-1: none): the total score and the chosen indices."""
    if not len(scores):
        return 0.0, []
    from scipy.optimize import Bounds, LinearConstraint, milp
    from scipy.sparse import coo_matrix

    scores = np.asarray(scores, dtype=float)
    rows = [m for group in members for m in group]
    cols = [k for k, group in enumerate(members) for _ in group]
    usage = LinearConstraint(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(max(size, 1), len(scores))),
                             -np.inf, 1.0)
    upper = (scores > 0.0).astype(float)
    if excluded >= 0:
        upper[excluded] = 0.0
    result = milp(-scores, constraints=usage, integrality=np.ones(len(scores)), bounds=Bounds(0.0, upper))
    if result.x is None:  # no solution within HiGHS's limits: the greedy pick
        chosen, used = [], set()
        for k in np.argsort(-scores, kind="stable").tolist():
            if upper[k] > 0.0 and not used.intersection(members[k]):
                used.update(members[k])
                chosen.append(k)
    else:
        chosen = np.flatnonzero(result.x > 0.5).tolist()
    return float(scores[chosen].sum()), chosen


def _new_track(track_id, cand: Candidate, members, config, rivals=None) -> MultiTrack:
    time_s = max(o.time_s for o in members)
    mean = np.zeros(STATE_SIZE)
    mean[:3] = cand.position_enu_m
    cov = np.zeros((STATE_SIZE, STATE_SIZE))
    cov[:3, :3] = cand.covariance_enu_m2
    cov[3:, 3:] = velocity_prior(config.network)
    nearest = float(min(np.linalg.norm(o.report.stations_enu_m[0] - cand.position_enu_m) for o in members))
    track = Track(track_id, "tentative", time_s, frozen_array(mean), frozen_array(cov), len(members), (), "single",
                  frozen_array([1.0]), frozen_array(mean[None]), frozen_array(cov[None]), 0, False, nearest)
    frequencies = [o.frequency_hz for o in members if math.isfinite(o.frequency_hz)]
    frequency = float(np.mean(frequencies)) if frequencies else math.nan
    return MultiTrack(track, frequency, len(frequencies), (True,) * min(len(members), config.confirm_window),
                      time_s, False, time_s, score=float(cand.score), rivals=rivals or {})


def find_candidates(pool: Sequence[Observation], config: AssociationConfig) -> list[Candidate]:
    """Candidate emitters from bearings of at least ``init_min_stations`` stations (:mod:`core.tracking.association`).

    Parameters
    ----------
    pool : sequence of Observation
        At most one scan per station.

    Returns
    -------
    list of Candidate
        Each passing its chi-square test with a positive score; candidates may share bearings.
    """
    if len(pool) < 3:
        return []
    arrays = _pool_arrays(pool, config)
    triples = _triples(arrays, config)
    if not triples.size:
        return []
    positions, covariances, chi2_values, ok = _fit(arrays, triples, _best_crossings(arrays, triples))
    gate = chi2_point(config.init_gate_probability, 3)
    keep = ok & (chi2_values <= gate)
    out: dict[frozenset, Candidate] = {}
    stations = np.unique(arrays.station)
    grown: list[frozenset] = []
    for t in np.flatnonzero(keep):
        triple = [int(m) for m in triples[t]]
        position, cov = positions[t], covariances[t]
        _add_candidate(out, arrays, triple, position, cov, float(chi2_values[t]), len(stations), config)
        # The triple extended with every further station's best-fitting bearing, kept beside the triple: the
        # set packing decides (a bearing of another emitter may pass the gate of a triple on its own). A triple
        # inside a set already extended (an emitter seen by S stations has S-choose-3 triples) extends to it.
        if any(extended.issuperset(triple) for extended in grown):
            continue
        members = list(triple)
        known = arrays.frequency[members][np.isfinite(arrays.frequency[members])]
        frequency = float(known.mean()) if known.size else math.nan
        for s in stations:
            if s in arrays.station[members]:
                continue
            best = _best_addition(arrays, s, position, cov, frequency, config)
            if best >= 0:
                members.append(best)
        if len(members) > 3:
            p, c, x2, good = _fit(arrays, np.array([members]), position[None])
            if good[0] and x2[0] <= chi2_point(config.init_gate_probability, 2 * len(members) - 3):
                _add_candidate(out, arrays, members, p[0], c[0], float(x2[0]), len(stations), config)
                grown.append(frozenset(members))
    return list(out.values())


def _add_candidate(out: dict, arrays: _Pool, members, position, cov, chi2_value: float, stations: int,
                   config) -> None:
    key = frozenset(members)
    if key in out:
        return
    score = _score(arrays, members, cov, chi2_value, stations, config)
    if score > 0.0 and _in_range(arrays, members, position, config):
        out[key] = Candidate(tuple(int(m) for m in members), position, cov, chi2_value, score)


def _frequency_compatible(arrays: _Pool, a, b, config) -> np.ndarray:
    difference = np.abs(arrays.frequency[a] - arrays.frequency[b])
    return ~(difference > config.frequency_tolerance_hz)


def _crossings(arrays: _Pool, a: np.ndarray, b: np.ndarray):
    """Midpoints ``(K, 3)`` of the closest approach of the lines of sight of bearings ``a`` and ``b``, and
    the ranges ``(K,)`` along each (least squares on ``p_a + r_a u_a = p_b + r_b u_b``)."""
    ua, ub = arrays.directions[a], arrays.directions[b]
    pa, pb = arrays.positions[a], arrays.positions[b]
    d = pb - pa
    uu = np.einsum("ki,ki->k", ua, ub)
    da, db = np.einsum("ki,ki->k", d, ua), np.einsum("ki,ki->k", d, ub)
    det = 1.0 - uu * uu
    with np.errstate(divide="ignore", invalid="ignore"):
        ra = (da - uu * db) / det
        rb = (uu * da - db) / det
    return 0.5 * (pa + ra[:, None] * ua + pb + rb[:, None] * ub), ra, rb


def _best_crossings(arrays: _Pool, triples: np.ndarray) -> np.ndarray:
    """Each triple's starting point ``(K, 3)``: the crossing of its pair of lines of sight closest to
    perpendicular."""
    pairs = ((0, 1), (0, 2), (1, 2))
    sines = np.stack([np.linalg.norm(np.cross(arrays.directions[triples[:, i]], arrays.directions[triples[:, j]]),
                                     axis=1) for i, j in pairs], axis=1)
    best = np.argmax(sines, axis=1)
    first = np.array([pairs[b][0] for b in best])
    second = np.array([pairs[b][1] for b in best])
    rows = np.arange(triples.shape[0])
    return _crossings(arrays, triples[rows, first], triples[rows, second])[0]


def _triples(arrays: _Pool, config) -> np.ndarray:
    """Triples ``(K, 3)`` of pool indices of three stations whose third bearing lies near the first two's
    crossing (coarse azimuth window, frequencies compatible), each set once."""
    stations = np.unique(arrays.station)
    by_station = {int(s): np.flatnonzero(arrays.station == s) for s in stations}
    out = []
    for sa, sb in itertools.combinations(stations.tolist(), 2):
        a, b = np.meshgrid(by_station[sa], by_station[sb], indexing="ij")
        a, b = a.ravel(), b.ravel()
        a, b = a[_frequency_compatible(arrays, a, b, config)], b[_frequency_compatible(arrays, a, b, config)]
        if not a.size:
            continue
        crossing_angle = np.arccos(np.clip(np.abs(np.einsum("ki,ki->k", arrays.directions[a], arrays.directions[b])),
                                           0.0, 1.0))
        points, ra, rb = _crossings(arrays, a, b)
        good = ((crossing_angle > MIN_CROSSING_ANGLE_RAD) & (ra > config.range_min_m) & (rb > config.range_min_m)
                & (ra < config.range_max_m) & (rb < config.range_max_m))
        a, b, points, ra, rb = a[good], b[good], points[good], ra[good], rb[good]
        if not a.size:
            continue
        # Angular uncertainty of the crossing as seen from a third station: both bearings' sigmas at their
        # ranges, over the sine of the crossing angle (a loose bound; the fit's chi-square decides).
        spread_m = np.hypot(ra * arrays.sigmas[a, 0], rb * arrays.sigmas[b, 0]) / np.sin(crossing_angle[good])
        for sc in stations.tolist():
            if sc in (sa, sb):
                continue
            c = by_station[sc]
            station = arrays.positions[c[0]]
            rotation = arrays.rotations[c[0]]
            seen, _ = predict(points, 0.0, station[None], rotation[None], np.array([AZIMUTH]))
            distance = np.linalg.norm(points - station, axis=1)
            window = COARSE_SIGMAS * np.hypot(arrays.sigmas[c, 0][None, :], (spread_m / distance)[:, None])
            near = np.abs(wrap_to_pi(arrays.values[c, 0][None, :] - seen[:, 0][:, None])) < window
            near &= _frequency_compatible(arrays, a[:, None], c[None, :], config)
            near &= _frequency_compatible(arrays, b[:, None], c[None, :], config)
            k, l = np.nonzero(near)
            if k.size:
                out.append(np.stack([a[k], b[k], c[l]], axis=1))
    if not out:
        return np.zeros((0, 3), dtype=np.int64)
    # Each triple is reached from each of its pairs (a near-collinear pair crosses far from the emitter, so
    # the well-conditioned pairs must be tried too): one copy each.
    triples = np.concatenate(out)
    _, first = np.unique(np.sort(triples, axis=1), axis=0, return_index=True)
    return triples[np.sort(first)]


def _fit(arrays: _Pool, members: np.ndarray, start: np.ndarray):
    """Gauss-Newton maximum-likelihood positions of ``K`` candidates of ``n`` bearings each.

    Parameters
    ----------
    members : ndarray of int, shape (K, n)
    start : ndarray, shape (K, 3)

    Returns
    -------
    positions : ndarray, shape (K, 3)
    covariances : ndarray, shape (K, 3, 3)
        Inverse Fisher information at the fit.
    chi2 : ndarray, shape (K,)
    ok : ndarray of bool, shape (K,)
    """
    count, n = members.shape
    stations = np.repeat(arrays.positions[members], 2, axis=1)              # (K, 2n, 3)
    rotations = np.repeat(arrays.rotations[members], 2, axis=1)             # (K, 2n, 3, 3)
    kinds = np.tile(np.array([AZIMUTH, ELEVATION]), (count, n))             # (K, 2n)
    measured = arrays.values[members].reshape(count, 2 * n)
    weights = 1.0 / arrays.sigmas[members].reshape(count, 2 * n) ** 2
    is_azimuth = kinds == AZIMUTH
    position = np.array(start, dtype=float)
    ok = np.all(np.isfinite(position), axis=1)
    position[~ok] = 0.0
    info = np.tile(np.eye(3), (count, 1, 1))
    for _ in range(FIT_ITERATIONS + 1):
        value, jacobian = predict(position, 0.0, stations, rotations, kinds)
        residual = measured - value
        residual = np.where(is_azimuth, wrap_to_pi(residual), residual)
        h = jacobian[..., :3]
        info = np.einsum("kmi,km,kmj->kij", h, weights, h)
        gradient = np.einsum("kmi,km,km->ki", h, weights, residual)
        step = np.einsum("kij,kj->ki", _inverses(info), gradient)
        ok &= np.all(np.isfinite(step), axis=1)
        position = position + np.where(ok[:, None], step, 0.0)
    chi2_values = np.einsum("km,km,km->k", residual, weights, residual)
    covariances = _inverses(info)
    ok &= np.all(np.isfinite(position), axis=1) & np.all(np.isfinite(covariances), axis=(1, 2))
    ok &= np.linalg.eigvalsh(np.where(ok[:, None, None], covariances, np.eye(3)))[:, 0] > 0.0
    return position, covariances, chi2_values, ok


def _inverses(matrices: np.ndarray) -> np.ndarray:
    """Inverses ``(K, 3, 3)`` of symmetric matrices, NaN where one is singular (lines of sight that are
    parallel or meet at a station)."""
    try:
        return np.linalg.inv(matrices)
    except np.linalg.LinAlgError:
        out = np.full(matrices.shape, np.nan)
        for k, matrix in enumerate(matrices):
            try:
                out[k] = np.linalg.inv(matrix)
            except np.linalg.LinAlgError:
                pass
        return out


def _best_addition(arrays: _Pool, station: int, position, cov, frequency: float, config) -> int:
    """The pool index of ``station``'s bearing that best fits a candidate (NIS at the fit, the fit's
    covariance propagated), -1 when none passes the gate."""
    index = np.flatnonzero(arrays.station == station)
    kinds = np.array([AZIMUTH, ELEVATION])
    value, jacobian = predict(position, 0.0, arrays.positions[index[0]][None].repeat(2, 0),
                              arrays.rotations[index[0]][None].repeat(2, 0), kinds)
    h = jacobian[:, :3]
    base = h @ cov @ h.T
    best, best_nis = -1, chi2_point(config.init_gate_probability, 2)
    for k in index.tolist():
        if not frequency_ok(arrays.frequency[k], frequency, config):
            continue
        residual = arrays.values[k] - value
        residual[0] = wrap_to_pi(residual[0])
        nis = float(residual @ np.linalg.solve(base + np.diag(arrays.sigmas[k] ** 2), residual))
        if nis < best_nis:
            best, best_nis = k, nis
    return best


def _score(arrays: _Pool, members, cov, chi2_value: float, stations: int, config) -> float:
    """Log likelihood ratio of "one emitter made these bearings, the other stations missed it" against "these
    bearings are false" (Laplace approximation over the uniform prior on the surveillance volume): per
    bearing ``log(P_D / lambda)`` less its Gaussian normaliser, ``-chi2 / 2`` at the fit, ``log(1 - P_D)`` per
    station that saw nothing, ``log det(2 pi P) / 2 - log V`` for the position integrated out."""
    n = len(members)
    sign, log_det = np.linalg.slogdet(2.0 * math.pi * np.asarray(cov))
    if sign <= 0:
        return -math.inf
    return float(_exact_llr(arrays, members, config).sum() - 0.5 * chi2_value
                 + (stations - n) * math.log1p(-config.detection_probability) + 0.5 * log_det
                 - math.log(config.surveillance_volume_m3))


def _exact_llr(arrays: _Pool, members, config) -> np.ndarray:
    """Log likelihood ratio ``(n,)`` of each bearing of ``members`` against a false one where it fits exactly:
    ``log(P_D / lambda)`` less its Gaussian normaliser."""
    sigmas = arrays.sigmas[members]
    normaliser = 0.5 * np.log(2.0 * math.pi * sigmas[:, 0] ** 2) + np.where(
        arrays.has_elevation[members], 0.5 * np.log(2.0 * math.pi * sigmas[:, 1] ** 2), 0.0)
    return math.log(config.detection_probability / config.false_density_per_rad2) - normaliser


def _give_up_llr(arrays: _Pool, config) -> np.ndarray:
    """What a candidate loses ``(P,)`` by leaving each pool bearing to another (counting it missed instead): its
    expected log likelihood ratio at a fit (the residual's chi-square at its mean, one per measured angle) less
    ``log(1 - P_D)``."""
    everyone = np.arange(arrays.station.size)
    return (_exact_llr(arrays, everyone, config) - 0.5 * (1.0 + arrays.has_elevation)
            - math.log1p(-config.detection_probability))


def _in_range(arrays: _Pool, members, position, config) -> bool:
    distances = np.linalg.norm(arrays.positions[members] - position, axis=1)
    return bool(np.all((distances > config.range_min_m) & (distances < config.range_max_m)))


__all__ = ["FIT_ITERATIONS", "MIN_CROSSING_ANGLE_RAD", "Candidate", "best_without", "find_candidates",
           "rival_candidates", "select_candidates", "set_packing", "start_tracks"]
