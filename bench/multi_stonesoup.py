"""A Stone Soup global-nearest-neighbour tracker on the multi-emitter scene's unlabelled bearings (a yardstick, bench row 13).

The association tracker (:mod:`core.tracking.association`) and this one see the same bearings and are scored
by the same epochs and GOSPA (:func:`core.simulation.multi_emitter.run_multi_trial`). The choices, made to
compare the association and the filter and nothing else:

- **filter**: Stone Soup's ``UnscentedKalmanPredictor`` and ``UnscentedKalmanUpdater`` (default unscented
  parameters) on the scene's constant-velocity model (``ConstantVelocity`` per axis, the tracker's horizontal
  and vertical intensities), each bearing a ``Detection`` whose measurement model is core's ``h`` for its
  station (:func:`bench.network_core.report_model`: azimuth and elevation in the station's frame, angles
  wrapped as Stone Soup's ``Bearing`` and ``Elevation``);
- **association**: ``GNNWith2DAssignment`` over a ``DistanceHypothesiser`` with the ``Mahalanobis`` measure
  and ``missed_distance`` the square root of the tracker's chi-square gate point (``gate_probability`` on two
  degrees of freedom), one scan (one station's bearings at one time) at a time; the frequency channel is
  used as the association tracker uses it: each channel's tracks and bearings are associated apart;
- **starts**: Stone Soup has none for bearings-only sensors (``MultiMeasurementInitiator`` needs an
  invertible measurement model), so tracks start exactly as the association tracker's do: the bearings no
  track took go to the same pool and :func:`core.tracking.track_start.start_tracks` starts them (its fit and
  covariance, velocity zero with the tracker's prior), the best packing only (``init_ambiguity_margin`` 0:
  the rival starts of an ambiguous packing are decided by the association tracker's scores,
  :mod:`core.tracking.rival_starts`, which a GNN tracker does not keep);
- **management**: the association tracker's rules (M of N confirmation, tentative tracks deleted when they
  can no longer confirm, a confirmed track without a hit for ``coast_after_s`` not reported, ended after
  ``end_after_s``).
"""

from __future__ import annotations

import datetime
import itertools
import math
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from bench.network_core import EPOCH, TO_STONESOUP, report_model
from core.tracking.association_types import AssociationConfig, frequency_ok
from core.tracking.network_update import chi2_point
from core.tracking.track_start import start_tracks


class Estimate(NamedTuple):
    """A reported track: what :func:`core.simulation.multi_emitter.run_multi_trial` scores."""

    id: str
    mean_enu: np.ndarray


class _Managed:
    """A Stone Soup track and the association tracker's bookkeeping of it."""

    def __init__(self, track, track_id: str, frequency_hz: float, hits: tuple, time_s: float):
        self.track, self.id, self.frequency_hz, self.hits = track, track_id, frequency_hz, hits
        self.last_hit_s, self.confirmed = time_s, False


class StoneSoupGnn:
    """The yardstick tracker (module docstring), a ``tracker`` for
    :func:`core.simulation.multi_emitter.run_multi_trial`."""

    def __init__(self, config: AssociationConfig):
        from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
        from stonesoup.hypothesiser.distance import DistanceHypothesiser
        from stonesoup.measures import Mahalanobis
        from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
        from stonesoup.predictor.kalman import UnscentedKalmanPredictor
        from stonesoup.types.detection import Detection
        from stonesoup.types.state import GaussianState
        from stonesoup.types.track import Track
        from stonesoup.updater.kalman import UnscentedKalmanUpdater

        self._types = Detection, GaussianState, Track
        self.config = config
        network = config.network
        q = network.accel_sigma_mps2 ** 2
        vertical = q if network.vertical_accel_sigma_mps2 is None else network.vertical_accel_sigma_mps2 ** 2
        transition = CombinedLinearGaussianTransitionModel([ConstantVelocity(q), ConstantVelocity(q),
                                                            ConstantVelocity(vertical)])
        self.predictor = UnscentedKalmanPredictor(transition)
        self.updater = UnscentedKalmanUpdater(measurement_model=None)
        gate = math.sqrt(chi2_point(config.gate_probability, 2))
        self.associator = GNNWith2DAssignment(DistanceHypothesiser(self.predictor, self.updater, Mahalanobis(),
                                                                   missed_distance=gate))
        self.tracks: list[_Managed] = []
        self.pool: list = []
        self.next_id = 1
        self.first_s: float | None = None

    def __call__(self, observations, time_s: float) -> list[Estimate]:
        ordered = sorted(observations, key=lambda o: (o.time_s, o.station_id, o.report.seq))
        for _, scan in itertools.groupby(ordered, key=lambda o: (o.time_s, o.station_id)):
            self._scan(list(scan))
        timestamp = EPOCH + datetime.timedelta(seconds=time_s)
        out = []
        for managed in self.tracks:
            if managed.confirmed and time_s - managed.last_hit_s <= self.config.coast_after_s:
                state = self.predictor.predict(managed.track.state, timestamp=timestamp)
                mean = np.empty(6)
                mean[TO_STONESOUP] = np.asarray(state.state_vector, dtype=float).ravel()
                out.append(Estimate(managed.id, mean))
        return out

    def _scan(self, scan) -> None:
        Detection, _, _ = self._types
        config = self.config
        time_s = scan[0].time_s
        self.first_s = time_s if self.first_s is None else self.first_s
        self.tracks = [t for t in self.tracks if time_s - t.last_hit_s <= config.end_after_s]
        timestamp = EPOCH + datetime.timedelta(seconds=time_s)
        detections = {}
        for obs in scan:
            model, measured = report_model(obs.report)
            detections[Detection(measured, timestamp=timestamp, measurement_model=model)] = obs
        taken, hypotheses = set(), {}
        for frequency in dict.fromkeys(o.frequency_hz for o in scan):
            channel = {d for d, o in detections.items() if o.frequency_hz == frequency
                       or (math.isnan(frequency) and math.isnan(o.frequency_hz))}
            tracks = {t.track: t for t in self.tracks if t.track not in hypotheses
                      and frequency_ok(t.frequency_hz, frequency, config)}
            if tracks:
                for track, hypothesis in self.associator.associate(set(tracks), channel, timestamp).items():
                    hypotheses[track] = hypothesis
                    if hypothesis:
                        taken.add(hypothesis.measurement)
        kept = []
        for managed in self.tracks:
            hypothesis = hypotheses.get(managed.track)
            hit = bool(hypothesis)
            managed.hits = (managed.hits + (hit,))[-config.confirm_window:]
            if hit:
                managed.track.append(self.updater.update(hypothesis))
                managed.last_hit_s = time_s
                managed.confirmed = managed.confirmed or managed.hits.count(True) >= config.confirm_hits
            elif not managed.confirmed and (managed.hits.count(False)
                                            > config.confirm_window - config.confirm_hits):
                continue
            kept.append(managed)
        self.tracks = kept
        unassigned = [o for d, o in detections.items() if d not in taken]
        self.pool = [o for o in self.pool if o.time_s > time_s - config.init_window_s] + unassigned
        if unassigned and time_s - self.first_s >= config.init_window_s:
            started, self.pool, self.next_id, _ = start_tracks([], self.pool, self.next_id, time_s,
                                                               replace(config, init_ambiguity_margin=0.0))
            for new in started:
                self.tracks.append(self._from_start(new))

    def _from_start(self, new) -> _Managed:
        _, GaussianState, Track = self._types
        mean, cov = np.asarray(new.track.mean_enu), np.asarray(new.track.covariance_enu)
        state = GaussianState(mean[TO_STONESOUP][:, None], cov[np.ix_(TO_STONESOUP, TO_STONESOUP)],
                              timestamp=EPOCH + datetime.timedelta(seconds=new.track.time_s))
        return _Managed(Track([state]), new.id, new.frequency_hz, new.hits, new.track.time_s)


def stonesoup_gospa(scenario, trials: int, seed: int) -> np.ndarray:
    """Mean GOSPA per trial ``(trials,)`` of :class:`StoneSoupGnn` on the runs
    :func:`core.simulation.multi_emitter.evaluate_multi` draws for the same seeds."""
    from core.simulation.multi_emitter import run_multi_trial, simulate_multi

    return np.array([run_multi_trial(scenario, simulate_multi(scenario, np.random.default_rng(seed + r)),
                                     tracker=StoneSoupGnn(scenario.config))["gospa"].mean()
                     for r in range(trials)])


def stonesoup_gospa_row(variants=tuple(range(8)), trials: int = 1, seed: int = 40):
    """Bench row 13: mean GOSPA of the association tracker against this Stone Soup GNN tracker on the same runs
    of every variant of :func:`core.simulation.multi_emitter.multi_emitter_scene` (paired: each run's GOSPA the
    mean over its epochs, both trackers on the same bearings)."""
    from bench.rows import Row
    from core.simulation.multi_emitter import evaluate_multi, multi_emitter_scene

    ours, theirs = [], []
    for variant in variants:
        scene = multi_emitter_scene(variant)
        ours.extend(evaluate_multi(scene, trials, seed).gospa_per_trial.tolist())
        theirs.extend(stonesoup_gospa(scene, trials, seed).tolist())
    ours, theirs = np.array(ours), np.array(theirs)
    wins = int(np.sum(ours <= theirs))
    return Row(13, f"multi-emitter scene, variants {variants[0]}-{variants[-1]}, {trials} run(s) each, seed {seed}: "
                   "mean GOSPA of the confirmed tracks",
               f"{ours.mean():.1f} m (median {np.median(ours):.1f} m)",
               f"Stone Soup GNN {theirs.mean():.1f} m (median {np.median(theirs):.1f} m)",
               f"{ours.mean() / theirs.mean():.2f}x", "<= 1x Stone Soup GNN",
               "met" if ours.mean() <= theirs.mean() else "missed",
               notes=[f"per run, ours / Stone Soup (m): "
                      + ", ".join(f"{a:.0f}/{b:.0f}" for a, b in zip(ours, theirs))
                      + f"; ours lower or equal on {wins} of {len(ours)} runs"])
