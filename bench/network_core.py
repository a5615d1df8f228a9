"""The network tracker next to Stone Soup's unscented Kalman filter on the same reports.

:class:`ReportModel` is a Stone Soup measurement model whose ``h(x)`` is core's
(:func:`core.measurements.predict`, the one coding of the measurement model) for one report, TOAs differenced
against the report's reference TOA with the differences' full covariance, as core eliminates the emission
time (:func:`core.tracking.network.report_rows`): the two filters see the same numbers and differ only in
the filter. Stone Soup orders its state ``[e, ve, n, vn, u, vu]``; :data:`TO_STONESOUP` permutes ours.

Used by ``tests/core/tracking/test_network_stonesoup.py`` (accuracy) and by the bench row
:func:`network_step_row` (one report step in core against Stone Soup's unscented predict and update of the
same report).
"""

from __future__ import annotations

import datetime
import functools
import math
import time

import numpy as np

from core.measurements import AZIMUTH, ELEVATION, TOA, predict
from core.tracking.network import NetworkConfig, Report, Track, advance_track, report_rows

#: Our state ``[e, n, u, ve, vn, vu]`` indexed into Stone Soup's ``[e, ve, n, vn, u, vu]`` order.
TO_STONESOUP = np.array([0, 3, 1, 4, 2, 5])
EPOCH = datetime.datetime(2026, 1, 1)


def _stonesoup():
    from stonesoup.models.measurement.nonlinear import _AngleNonLinearGaussianMeasurement
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
    from stonesoup.predictor.kalman import UnscentedKalmanPredictor
    from stonesoup.types.angle import Bearing, Elevation
    from stonesoup.types.array import StateVector, StateVectors
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import GaussianState
    from stonesoup.updater.kalman import UnscentedKalmanUpdater
    return locals()


@functools.cache
def _report_model_class():
    """Stone Soup's measurement model of one report, its ``h`` core's (built once: Stone Soup's classes declare
    their fields as ``Property``)."""
    ss = _stonesoup()
    from stonesoup.base import Property

    class ReportModel(ss["_AngleNonLinearGaussianMeasurement"]):
        report: Report = Property(doc="The report (stations, rotations, kinds)")
        used: np.ndarray = Property(doc="Its measurements in row order")
        reference: int = Property(doc="Its reference TOA (-1: none)")
        typed: list = Property(doc="Each row's Stone Soup type (Bearing, Elevation or float)")

        @property
        def ndim_meas(self):
            return len(self.used)

        def _typed_vector(self):
            return ss["StateVector"](self.typed)

        def _function(self, state, noise=False, **kwargs):
            positions = np.asarray(state.state_vector, dtype=float)[(0, 2, 4), :].T
            report = self.report
            values, _ = predict(positions, np.zeros(len(positions)), report.stations_enu_m, report.rotations,
                                report.kinds)
            out = values[:, self.used]
            if self.reference >= 0:
                out = np.where(report.kinds[self.used] == TOA, out - values[:, [self.reference]], out)
            if isinstance(noise, bool) and noise:
                noise = self.rvs(num_samples=len(positions), **kwargs)
            elif isinstance(noise, bool):
                noise = 0.0
            return ss["StateVectors"](out.T) + noise

    return ReportModel


def report_model(report: Report):
    """A Stone Soup measurement model of one report (core's ``h``) and its measured vector.

    Returns
    -------
    model : stonesoup measurement model
    measured : StateVector
        The report's values in the model's rows (TOA differences in metres).
    """
    ss = _stonesoup()
    rows = report_rows(report)
    used = rows.rows
    kinds = report.kinds[used]
    typed = [ss["Bearing"](0.0) if k == AZIMUTH else ss["Elevation"](0.0) if k == ELEVATION else 0.0
             for k in kinds.tolist()]
    noise = np.diag(rows.variances[used])
    if rows.toa_reference >= 0:
        toa = kinds == TOA
        noise[np.ix_(toa, toa)] += rows.variances[rows.toa_reference]
    model = _report_model_class()(ndim_state=6, mapping=(0, 2, 4), noise_covar=noise, report=report, used=used,
                                  reference=rows.toa_reference, typed=typed)
    measured = ss["StateVector"]([typed[i] + rows.values[m] if kinds[i] != TOA else rows.values[m]
                                  for i, m in enumerate(used.tolist())])
    return model, measured


class StoneSoupFilter:
    """Stone Soup's ``UnscentedKalmanPredictor`` and ``UnscentedKalmanUpdater`` (its default unscented
    parameters) on the constant-velocity model of a :class:`NetworkConfig` (``ConstantVelocity`` per axis
    with ``noise_diff_coeff = accel_sigma_mps2**2``, ``vertical_accel_sigma_mps2**2`` on the up axis when
    set: the same white acceleration)."""

    def __init__(self, config: NetworkConfig, mean_enu, covariance_enu, time_s: float):
        ss = self.ss = _stonesoup()
        q = config.accel_sigma_mps2 ** 2
        vertical = q if config.vertical_accel_sigma_mps2 is None else config.vertical_accel_sigma_mps2 ** 2
        self.transition = ss["CombinedLinearGaussianTransitionModel"](
            [ss["ConstantVelocity"](q), ss["ConstantVelocity"](q), ss["ConstantVelocity"](vertical)])
        self.predictor = ss["UnscentedKalmanPredictor"](self.transition)
        self.updater = ss["UnscentedKalmanUpdater"](measurement_model=None)
        index = TO_STONESOUP
        self.state = ss["GaussianState"](ss["StateVector"](np.asarray(mean_enu)[index]),
                                         np.asarray(covariance_enu)[np.ix_(index, index)],
                                         timestamp=EPOCH + datetime.timedelta(seconds=time_s))

    def step(self, report: Report) -> None:
        """Predict to the report and update with it."""
        ss = self.ss
        model, measured = report_model(report)
        timestamp = EPOCH + datetime.timedelta(seconds=report.time_s)
        prediction = self.predictor.predict(self.state, timestamp=timestamp)
        detection = ss["Detection"](measured, timestamp=timestamp, measurement_model=model)
        self.state = self.updater.update(ss["SingleHypothesis"](prediction, detection))

    @property
    def mean_enu(self) -> np.ndarray:
        out = np.empty(6)
        out[TO_STONESOUP] = np.asarray(self.state.state_vector, dtype=float).ravel()
        return out

    @property
    def covariance_enu(self) -> np.ndarray:
        out = np.empty((6, 6))
        out[np.ix_(TO_STONESOUP, TO_STONESOUP)] = np.asarray(self.state.covar, dtype=float)
        return out


def _steady_track(config: NetworkConfig, reports) -> tuple[Track, list]:
    """A track after the DF scene's first 200 reports (one Gaussian by then), and the reports after them."""
    track = None
    for report in reports[:200]:
        track, _ = advance_track(track, report, config)
    return track, reports[200:]


def network_step_row(repeats: int = 9, steps: int = 400):
    """Bench row: one report step in core (6-state UKF, one bearing: azimuth and elevation) next to Stone
    Soup's unscented predict and update of the same report, in turns, ``repeats`` rounds (medians)."""
    from bench.rows import Row, committed, unavailable
    from core.simulation.network import df_network_scene, simulate_network

    number, what, target = 9, "one network report step in core (6-state UKF, one bearing)", \
        "<= 0.1x Stone Soup and <= 100 us"
    if not committed("core/tracking/network.py"):
        return unavailable(number, what, target, "core/tracking/network.py has not landed in git yet")
    try:
        _stonesoup()
    except ImportError:
        return unavailable(number, what, target, "stonesoup is not installed (pip install -e '.[dev]')")
    scene = df_network_scene()
    run = simulate_network(scene, np.random.default_rng(1))
    reports = sorted((p.report for p in run.posted), key=lambda r: r.order_key)
    track, rest = _steady_track(scene.config, reports)
    rest = rest[:steps]
    assert track.stage == "single"

    def core_round():
        t = time.perf_counter()
        state = track
        for report in rest:
            state, _ = advance_track(state, report, scene.config)
        return (time.perf_counter() - t) / len(rest)

    def stonesoup_round():
        ukf = StoneSoupFilter(scene.config, track.mean_enu, track.covariance_enu, track.time_s)
        t = time.perf_counter()
        for report in rest:
            ukf.step(report)
        return (time.perf_counter() - t) / len(rest)

    core_round(), stonesoup_round()  # compile and warm
    core_s, stonesoup_s = [], []
    for _ in range(repeats):
        core_s.append(core_round())
        stonesoup_s.append(stonesoup_round())
    ratios = [c / s for c, s in zip(core_s, stonesoup_s)]
    core_us, stonesoup_us, ratio = np.median(core_s) * 1e6, np.median(stonesoup_s) * 1e6, float(np.median(ratios))
    met = ratio <= 0.1 and core_us <= 100.0
    verdict = "met" if met else f"missed: {ratio:.3f}x, {core_us:.0f} us"
    return Row(number, what, f"{core_us:,.1f} us per report", f"Stone Soup UKF predict+update {stonesoup_us:,.0f} us",
               f"{ratio:.3f}x Stone Soup, median of {repeats} rounds", target, verdict,
               [f"core.tracking.network.advance_track over {len(rest)} reports of the DF-network scene (each one "
                "station's azimuth and elevation), from the track its first 200 reports made (one Gaussian); Stone "
                "Soup's UnscentedKalmanPredictor + UnscentedKalmanUpdater on the same reports from the same state, "
                "its measurement model core's h(x) (bench/network_core.py); the two in turns, per-round ratios "
                + ", ".join(f"{r:.3f}" for r in ratios) + ". The core step includes building the report's rows, "
                "the immutable track and its status; the compiled kernel is the predict and the update."])


def stonesoup_accuracy(scene, trials: int, seed: int, start_after_s: float | None = None):
    """Position RMSE after ``scene.converged_after_s`` of core's tracker and of Stone Soup's UKF on the same
    reports (time order), over the same epochs.

    Stone Soup has no start of its own for a line of sight: it starts from core's estimate (mean and
    covariance, the moments of the start's Gaussian sum while there is one) at the first report at or after
    ``start_after_s`` from the scene's start, or, with ``start_after_s`` None, right after the first report
    (the moments of the line-of-sight sum: what one Gaussian can hold of that start).

    Returns
    -------
    core_rmse_m, stonesoup_rmse_m : float
    """
    from core.simulation.network import START_TIME_S, simulate_network

    core_sq, ss_sq = [], []
    for r in range(trials):
        run = simulate_network(scene, np.random.default_rng(seed + r))
        reports = sorted((p.report for p in run.posted), key=lambda rep: rep.order_key)
        track, ukf = None, None
        for report in reports:
            track, _ = advance_track(track, report, scene.config)
            if ukf is not None:
                ukf.step(report)
            elif start_after_s is None or report.time_s >= START_TIME_S + start_after_s:
                ukf = StoneSoupFilter(scene.config, track.mean_enu, track.covariance_enu, track.time_s)
            if report.time_s >= START_TIME_S + scene.converged_after_s:
                truth = run.truth_at(report.time_s)
                core_sq.append(float(np.sum((track.mean_enu[:3] - truth[:3]) ** 2)))
                ss_sq.append(float(np.sum((ukf.mean_enu[:3] - truth[:3]) ** 2)))
    return math.sqrt(np.mean(core_sq)), math.sqrt(np.mean(ss_sq))
