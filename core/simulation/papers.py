"""The five papers' scenarios, run at a given size, with each claim checked (``passive-locator reproduce``).

Each ``paper_NNN(size, ...)`` returns a :class:`PaperResult`: a table of
what we measure, the paper's own claim beside it, and :class:`Check` rows.
A check is *asserted* when the claim holds here at any size with a bar from
theory (the CRLB, sampling spread); a check that records a finding where the
paper's claim does not hold here (see ``tests/core/tracking/test_monte_carlo.py``)
is reported, not asserted. Scenarios come from
:mod:`core.simulation.scenarios` and :mod:`core.simulation.tracking`, the
definitions the tests use. Monte Carlo work runs through
:func:`core.parallel.run_chunks` (here, or on a Dask cluster with
``scheduler``), with one child seed per chunk.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from core.parallel import chunk_seeds, run_chunks
from core.simulation import scenarios as sc
from core.simulation.measurements import draw_noise, evaluate, trial_batch, true_values

#: Monte Carlo sizes: ``full`` is the papers' own where they state one.
SIZES = {
    "full": {"p000_trials": 1000, "p001_runs": 100, "p001_bound_runs": 50, "p002_grid_m": 500.0,
             "p002_trials": 1000, "p003_trials": 5000, "p004_trials": 500, "p004_sigmas_deg": (1.0, 3.0, 5.0, 10.0)},
    "quick": {"p000_trials": 300, "p001_runs": 10, "p001_bound_runs": 10, "p002_grid_m": 2000.0,
              "p002_trials": 300, "p003_trials": 1000, "p004_trials": 100, "p004_sigmas_deg": (1.0, 10.0)},
}


@dataclass
class Check:
    """One claim tested: what, what we measured, whether it holds, whether a failure fails the run."""

    claim: str
    measured: str
    holds: bool
    asserted: bool = True


@dataclass
class PaperResult:
    """One paper's reproduction.

    Attributes
    ----------
    paper : str
        ``"000"`` .. ``"004"``.
    title : str
    paper_claim : str
        What the paper says (its own numbers where it gives them).
    columns : list of str
    rows : list of list
        The table we measured.
    checks : list of Check
    curves : dict
        Plot data: ``{name: {"x": [...], "series": {label: [...]}, "xlabel", "ylabel", "log": bool}}``.
    notes : str
    """

    paper: str
    title: str
    paper_claim: str
    columns: list
    rows: list
    checks: list = field(default_factory=list)
    curves: dict = field(default_factory=dict)
    notes: str = ""

    @property
    def passed(self) -> bool:
        return all(c.holds for c in self.checks if c.asserted)


def _rmse_sd(errors_enu_m) -> float:
    """Relative sampling sd of a Monte Carlo RMSE from its own trials (delta method on the mean square)."""
    squared = np.sum(np.asarray(errors_enu_m) ** 2, axis=1)
    if squared.size < 2:
        return float("inf")
    return float(squared.std() / squared.mean() / (2.0 * np.sqrt(squared.size)))


def _bars(results: dict) -> dict:
    """Plot data: each labelled result's RMSE beside its bound (methods that never gave a fix are left out)."""
    kept = {label: r for label, r in results.items() if np.isfinite(r.rmse_m)}
    return {"bars": list(kept), "rmse_m": [float(r.rmse_m) for r in kept.values()],
            "bound_m": [float(r.crlb_rmse_m) for r in kept.values()], "ylabel": "RMSE (m)", "log": True}


def _fmt(value, digits: int = 1) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


# --- paper 000: EOVE ---------------------------------------------------------------------------------------


def paper_000(size: str = "full", seed: int = 2000, scheduler: Any = None, progress=None) -> PaperResult:
    """EOVE against OVE, 3D PLE and WS3D on paper 000's two stations above the target's meridian."""
    from core.estimators import solve

    trials = SIZES[size]["p000_trials"]
    scenes = {"N=2": sc.paper_000(), "N=4 (2 looks each)": sc.paper_000(looks=2),
              "st-1 moved, azimuth only": sc.paper_000(moved_azimuth_only=True)}
    methods = {"N=2": ["eove", "ove", "ple3d", "ws3d", "ml"], "N=4 (2 looks each)": ["eove", "ove", "ml"],
               "st-1 moved, azimuth only": ["eove", "ml"]}
    rows, results = [], {}
    for k, (label, scene) in enumerate(scenes.items()):
        problem = scene.template()
        target = scene.target_enu_m(problem)
        results[label] = evaluate(problem, target, methods[label], trials, seed + k, scheduler=scheduler)
        for method, r in results[label].items():
            rows.append([label, method, _fmt(r.rmse_m), _fmt(r.crlb_rmse_m), _fmt(r.efficiency, 3), r.failures])
    checks = []
    for label in ("N=2", "st-1 moved, azimuth only"):
        scene = scenes[label]
        r = results[label]["eove"]
        predicted = float(np.sqrt(np.trace(solve(scene.problem(), "eove").covariance_enu_m2)))
        sd = _rmse_sd(r.errors_enu_m)
        checks.append(Check(f"EOVE locates ({label}): no failure, RMSE within 15 % of its first-order prediction",
                            f"{r.failures} failures, RMSE {r.rmse_m:.0f} m / predicted {predicted:.0f} m = "
                            f"{r.rmse_m / predicted:.3f}",
                            r.failures == 0 and abs(r.rmse_m / predicted - 1) < 0.15))
        checks.append(Check(f"EOVE does not beat the CRLB ({label}) beyond 3.5 sampling sd",
                            f"RMSE / CRLB {r.rmse_m / r.crlb_rmse_m:.3f} (sd {sd:.3f})",
                            r.rmse_m > r.crlb_rmse_m * (1 - 3.5 * sd)))
    for method in ("ple3d", "ws3d"):
        r = results["N=2"][method]
        checks.append(Check(f"{method} cannot locate above the straight station track (N=2)",
                            f"{r.failures} of {trials} trials refused (collinear ground track)",
                            r.failures >= 0.95 * trials))
    ove2 = results["N=2"]["ove"]
    checks.append(Check("OVE cannot locate with N=2", f"{ove2.failures} of {trials} refused",
                        ove2.failures == trials))
    eove4, ove4 = results["N=4 (2 looks each)"]["eove"], results["N=4 (2 looks each)"]["ove"]
    checks.append(Check("EOVE is more accurate than OVE with N=4",
                        f"EOVE {eove4.rmse_m:.0f} m, OVE {_fmt(ove4.rmse_m, 0)} m ({ove4.failures} failures)",
                        not np.isfinite(ove4.rmse_m) or eove4.rmse_m < ove4.rmse_m))
    return PaperResult(
        "000", "Extended orthogonal vector estimator (EOVE), 3D bearing-only",
        "Target 108.9E 34.5N 8 km, stations 108.9E 34.2N 0.4 km and 108.9E 34.9N 1 km, 2 deg on both angles: "
        "EOVE locates from two stations; 3D PLE and WS3D cannot (the target is above the stations' track); OVE "
        "needs three lines of sight and is less accurate than EOVE at N = 4; EOVE still locates with station 1 "
        "moved to 108.8E giving the azimuth only.",
        ["scene", "method", "RMSE (m)", "sqrt tr CRLB (m)", "MSE / tr CRLB", "failures"], rows, checks,
        {"p000_rmse": _bars({f"{label}: {m}": r for label, by in results.items() for m, r in by.items()})},
        notes=f"{trials} trials per scene, seeds {seed}..{seed + 2}.")


# --- paper 001: session filter ------------------------------------------------------------------------------


#: The paper-001 filters compared: label -> (model, config changes).
P001_FILTERS = {"velocity_kinematic (paper)": ("velocity_kinematic", {}),
                "direct joint UKF, prior 150+-50 km (paper's baseline)": ("joint_ukf", {"joint_initial_range": "prior"})}


def paper_001(size: str = "full", seed: int = 1000, scheduler: Any = None, progress=None) -> PaperResult:
    """The velocity-vector method against the direct joint UKF on paper 001's emitter, and the default filter
    against the posterior CRLB."""
    from core.simulation.emitter import paper_001_scenario
    from core.simulation.tracking import PAPER_ACCEL_SIGMA_MPS2, against_bound, paper_config, run_monte_carlo

    runs = SIZES[size]["p001_runs"]
    scenario = paper_001_scenario()
    results = {}
    for label, (model, changes) in P001_FILTERS.items():
        for known in (True, False):
            results[label, known] = run_monte_carlo(paper_config(model, known, **changes), scenario, runs, seed,
                                                    scheduler=scheduler)
    rows = []
    for (label, known), mc in results.items():
        tail = _tail_percent(mc)
        rows.append([label, "known" if known else "unknown", _fmt(tail, 2), _fmt(mc.convergence_time_s(5.0), 0),
                     _fmt(mc.rmse_percent()[50], 2), _fmt(mc.rmse_percent()[-1], 2)])
    velocity, direct = list(P001_FILTERS)
    checks = []
    for known in (True, False):
        tail = _tail_percent(results[velocity, known])
        checks.append(Check(f"velocity method within 3 % of range over the last 50 s ({'known' if known else 'unknown'}"
                            " period)", f"{tail:.2f} %", tail < 3.0))
    t_known = results[velocity, True].convergence_time_s(5.0)
    t_unknown = results[velocity, False].convergence_time_s(5.0)
    checks.append(Check("a known period converges at least as fast as an unknown one (velocity method, to 5 %)",
                        f"{t_known:.0f} s known, {t_unknown:.0f} s unknown", t_known <= t_unknown))
    for known in (True, False):
        mc = results[velocity, known]
        final = np.nanmax(np.abs(mc.errors[:, -1]) / mc.sigmas[:, -1])
        checks.append(Check(f"no velocity-method run diverges ({'known' if known else 'unknown'} period): every "
                            "final error inside 5 sigma", f"largest {final:.2f} sigma", bool(final <= 5.0)))
    for known in (True, False):
        tv, td = results[velocity, known].convergence_time_s(5.0), results[direct, known].convergence_time_s(5.0)
        checks.append(Check(f"paper: the velocity method converges faster than the direct joint UKF "
                            f"({'known' if known else 'unknown'} period)",
                            f"{tv:.0f} s vs {td:.0f} s: {'holds' if tv < td else 'does not hold here'} (depends on the "
                            "direct filter's range prior; tests/core/tracking/test_monte_carlo.py)", tv < td,
                            asserted=False))

    bound_runs = SIZES[size]["p001_bound_runs"]
    q = PAPER_ACCEL_SIGMA_MPS2
    config = paper_config("joint_ukf", True, accel_sigma_mps2=q)
    against = against_bound(config, paper_001_scenario(accel_sigma_mps2=q), bound_runs, seed, scheduler=scheduler)
    ratio = against.ratio(slice(-50, None))
    ceiling = 1.1 if size == "full" else 1.3
    checks.append(Check(f"default session filter (joint_ukf) near the PCRB over the last 50 s (q = {q} m/s^2, "
                        f"{bound_runs} runs): 0.8 < RMSE / PCRB <= {ceiling}", f"{ratio:.3f}",
                        0.8 < ratio <= ceiling))
    bound_percent = 100.0 * float(np.sqrt(against.bound_m2[-1]) / against.ranges_m[:, -1].mean())
    checks.append(Check("the PCRB after 200 s is about 0.9 % of range at q = 0.05 m/s^2 (ALGORITHMS.md 10)",
                        f"{bound_percent:.2f} %", 0.7 <= bound_percent <= 1.1))
    times = [float(t) for t in results[velocity, True].times_s]
    curves = {
        "p001_rmse": {"x": times, "xlabel": "time (s)", "ylabel": "position RMSE (% of range)", "log": True,
                      "series": {f"{label}, {'known' if known else 'unknown'}": [float(v) for v in mc.rmse_percent()]
                                 for (label, known), mc in results.items()}},
        "p001_pcrb": {"x": [float(t) for t in against.times_s], "xlabel": "time (s)", "ylabel": "position (m)",
                      "log": True,
                      "series": {"joint_ukf RMSE": [float(v) for v in against.rmse_m()],
                                 "sqrt tr PCRB": [float(v) for v in np.sqrt(against.bound_m2)]}},
    }
    return PaperResult(
        "001", "Moving emitter from one fixed observer: velocity vector, range from the azimuth rate",
        "Tr = 1 ms, N = 1000, emitter from (120, 100, 8) km at (-300, 100, 2) m/s, 5 mrad angles, 0.2 mrad/s "
        "azimuth rate, 10 ns TOA, 100 runs: the velocity method converges faster than the direct joint UKF and "
        "near the bound; a known period converges faster than an unknown one.",
        ["filter", "period", "RMSE last 50 s (% range)", "to 5 % (s)", "RMSE at 50 s (%)", "RMSE at 200 s (%)"],
        rows, checks, curves,
        notes=f"{runs} runs per filter (seeds {seed} + r), constant velocity as in the paper; the PCRB check uses "
              f"{bound_runs} truths drawn with q = {q} m/s^2.")


def _tail_percent(mc) -> float:
    errors = mc.position_errors_m[:, -51:]
    return 100.0 * float(np.sqrt(np.mean(errors**2)) / mc.ranges_m[:, -51:].mean())


# --- paper 002: line-of-sight intersection ------------------------------------------------------------------


def efficient_gain(problem, target_enu_m) -> np.ndarray:
    """The efficient linear map ``(3, M)`` from measurement noise to position error at the target (CRLB H^T R^-1)."""
    from core.crlb import information_at
    from core.measurements import predict

    s = problem.station_index
    _, jac = predict(np.asarray(target_enu_m)[None], np.zeros(1), problem.stations_enu_m[s][None],
                     problem.station_rotations[s][None], problem.kinds[None])
    crlb = information_at(problem, target_enu_m).covariance_enu_m2[0]
    return crlb @ jac[0, :, :3].T / problem.sigmas**2


def paper_002_point(problem, target_enu_m, trials: int, seed) -> tuple[float, float, float]:
    """One grid point of paper 002: ``(control-variate efficiency, plain MSE / tr CRLB, its sampling sd)``.

    The control variate is the efficient linear estimator ``G n`` on the same noise ``n``
    (``E|G n|^2 = tr CRLB`` exactly): ``1 + mean(|e|^2 - |G n|^2) / tr CRLB`` has the expectation of the
    plain ratio and a far smaller spread.
    """
    from core.crlb import information_at
    from core.estimators import solve_many

    noise = draw_noise(np.random.default_rng(seed), problem.sigmas, size=trials)
    ((rows, fixes),) = solve_many(trial_batch(problem, true_values(problem, target_enu_m) + noise),
                                  "los_intersection", None)
    if not hasattr(fixes, "ok") or not fixes.ok.all():
        return float("nan"), float("nan"), float("nan")
    crlb = information_at(problem, target_enu_m).covariance_enu_m2[0]
    trace = float(np.trace(crlb))
    squared = np.sum((fixes.position_enu_m - target_enu_m) ** 2, axis=1)
    linear = np.sum((noise @ efficient_gain(problem, target_enu_m).T) ** 2, axis=1)
    return (1.0 + float(np.mean(squared - linear)) / trace, float(np.mean(squared)) / trace,
            float(np.sqrt(2.0 * np.trace(crlb @ crlb) / trials)) / trace)


def paper_002(size: str = "full", seed: int = 2002, scheduler: Any = None, progress=None) -> PaperResult:
    """Common-perpendicular LOS intersection over paper 002's grid, MSE against the CRLB."""
    step = SIZES[size]["p002_grid_m"]
    trials = SIZES[size]["p002_trials"]
    problem = sc.paper_002_problem()
    axis = np.arange(0.0, 10_000.0 + 1.0, step)
    targets = [np.array([e, n, sc.PAPER_002_TARGET_HEIGHT_M]) for n in axis for e in axis]
    seeds = chunk_seeds(seed, len(targets))
    out = np.array(run_chunks(paper_002_point, [(problem, t, trials, s) for t, s in zip(targets, seeds)],
                              scheduler=scheduler, progress=progress))
    stations = problem.stations_enu_m
    nearest = np.array([np.min(np.hypot(*(stations[:, :2] - t[:2]).T)) for t in targets])
    away = nearest > 1_000.0
    cv, plain, sd = out.T
    rows = [[f"{len(targets)} points, {step / 1e3:g} km grid", int(away.sum()), _fmt(np.nanmin(cv[away]), 3),
             _fmt(np.nanmax(cv[away]), 3), _fmt(np.nanmean(plain[away]), 3), _fmt(np.nanmin(plain[away]), 3),
             _fmt(np.nanmax(plain[away]), 3), _fmt(np.nanmax(cv[~away]), 3) if (~away).any() else "-"]]
    checks = [
        Check("MSE / tr CRLB in 0.9 .. 1.1 at every grid point more than 1 km from a sensor (control variate)",
              f"{np.nanmin(cv[away]):.3f} .. {np.nanmax(cv[away]):.3f} over {int(away.sum())} points",
              bool(np.all((cv[away] > 0.9) & (cv[away] < 1.1)))),
        Check("the plain ratio agrees within 4 sampling sd at every such point, and on average within 5 %",
              f"largest |ratio - 1| / sd {np.nanmax(np.abs(plain[away] - 1) / sd[away]):.2f}, mean "
              f"{np.nanmean(plain[away]):.3f}",
              bool(np.all(np.abs(plain[away] - 1) < 4 * sd[away]) and abs(np.nanmean(plain[away]) - 1) < 0.05)),
    ]
    grid = cv.reshape(axis.size, axis.size)
    half_km = step / 2e3
    curves = {"p002_efficiency": {"grid": grid.tolist(), "extent_km": [-half_km, 10.0 + half_km, -half_km, 10.0 + half_km],
                                  "label": "MSE / tr CRLB (control variate)",
                                  "stations_km": (stations[:, :2] / 1e3).tolist()}}
    return PaperResult(
        "002", "Target location by intersection of lines of sight (common perpendicular), netted sensors",
        "Sensors at (0,0,0), (10,0,0), (5,10,0) km, 10 mrad on both angles, target 0.5 km up over x, y in "
        "[0, 10] km on a 0.5 km grid, 1000 Monte Carlo runs per point: MSE / tr(CRLB) stays in 0.9 .. 1.1.",
        ["grid", "points > 1 km from a sensor", "min eff.", "max eff.", "mean plain", "min plain", "max plain",
         "max eff. within 1 km"], rows, checks, curves,
        notes=f"{trials} trials per point; efficiency estimated with the efficient linear estimator as a "
              "control variate (same expectation as MSE / tr CRLB, spread below 1 %); points within 1 km of a "
              "sensor (where the linearisation of the bearing model breaks down) are shown, not asserted.")


# --- paper 003: angle and range ------------------------------------------------------------------------------


def paper_003(size: str = "full", seed: int = 3003, scheduler: Any = None, progress=None) -> PaperResult:
    """Angle + range (coarse then fine) against angles alone on paper 003's two aircraft, gaussian and uniform."""
    trials = SIZES[size]["p003_trials"]
    with_ranges = sc.paper_003_problem()
    angles_only = sc.paper_003_problem(with_ranges=False)
    target = with_ranges.frame.from_geodetic(*sc.PAPER_003_TARGET)
    rows, found = [], {}
    paper = {"angle_range": "219 / 277 / 289 (456)", "ml": "596 / 370 / 564 (~900)"}
    for noise in ("gaussian", "uniform"):
        for label, problem, method in (("angle + range", with_ranges, "angle_range"),
                                       ("angles only", angles_only, "ml")):
            r = evaluate(problem, target, [method], trials, seed, noise, scheduler=scheduler)[method]
            found[noise, method] = r
            rows.append([label, method, noise, " / ".join(_fmt(v, 0) for v in r.rmse_enu_m), _fmt(r.rmse_m, 0),
                         _fmt(r.crlb_rmse_m, 0), paper[method], r.failures])
    g = found["gaussian", "angle_range"]
    sd = _rmse_sd(g.errors_enu_m)
    checks = [
        Check("angle + range reaches the CRLB (gaussian): RMSE within 10 % of sqrt tr CRLB",
              f"RMSE / CRLB {g.rmse_m / g.crlb_rmse_m:.3f} (sd {sd:.3f})", abs(g.rmse_m / g.crlb_rmse_m - 1) < 0.10),
    ]
    for noise in ("gaussian", "uniform"):
        ar, ml = found[noise, "angle_range"], found[noise, "ml"]
        checks.append(Check(f"the ranges cut the error about in half ({noise}): RMSE angle+range <= 0.6 x angles only",
                            f"{ar.rmse_m:.0f} m vs {ml.rmse_m:.0f} m ({ar.rmse_m / ml.rmse_m:.2f})",
                            ar.rmse_m <= 0.6 * ml.rmse_m))
    u = found["uniform", "angle_range"]
    checks.append(Check("uniform noise of the same sigma gives an RMSE within 10 % of the gaussian one",
                        f"{u.rmse_m:.0f} m vs {g.rmse_m:.0f} m ({u.rmse_m / g.rmse_m:.3f})",
                        abs(u.rmse_m / g.rmse_m - 1) < 0.10))
    checks.append(Check("paper's table: angle + range total RMSE 456 m",
                        f"{g.rmse_m:.0f} m gaussian, {u.rmse_m:.0f} m uniform; the CRLB is {g.crlb_rmse_m:.0f} m, so "
                        "no unbiased estimator reaches the paper's figure with these sigmas: read it as a trend",
                        g.rmse_m <= 1.25 * 456.0, asserted=False))
    return PaperResult(
        "003", "Dual-aircraft cooperative location with angle and distance (coarse + Gauss-Newton fine)",
        "1 deg angles, 250 m ranges, ~50 km baseline and range: angle-only x/y/z RMSE 596 / 370 / 564 m, "
        "angle + range 219 / 277 / 289 m (total 456 m): the ranges cut the error about in half.",
        ["measurements", "method", "noise", "RMSE e / n / u (m)", "RMSE (m)", "sqrt tr CRLB (m)",
         "paper x / y / z (m)", "failures"], rows, checks,
        {"p003_rmse": _bars({f"{m} ({n})": r for (n, m), r in found.items()})},
        notes=f"{trials} trials per row, seed {seed}. Axes here are east / north / up, the paper's x / y / z are its "
              "own frame: compare totals and the trend, not axis by axis.")


# --- paper 004: Taylor WLS with bearing errors ---------------------------------------------------------------


def paper_004(size: str = "full", seed: int = 4000, scheduler: Any = None, progress=None) -> PaperResult:
    """Taylor-series WLS against TLS and CTLS on paper 004's moving sensor, over the bearing sigma."""
    trials = SIZES[size]["p004_trials"]
    rows, checks = [], []
    ratios = {}
    methods = ["taylor_wls", "tls", "ctls"]
    for k, sigma_deg in enumerate(SIZES[size]["p004_sigmas_deg"]):
        scene = sc.paper_004(sigma_deg)
        problem = scene.template()
        results = evaluate(problem, scene.target_enu_m(problem), methods, trials, seed + k, scheduler=scheduler)
        for method, r in results.items():
            rows.append([f"{sigma_deg:g}", method, _fmt(r.rmse_m, 0), _fmt(r.crlb_rmse_m, 0), _fmt(r.efficiency, 3),
                         r.failures])
        t = results["taylor_wls"]
        sd = _rmse_sd(t.errors_enu_m)
        bar = max(0.10, 3.5 * sd)
        ratios[sigma_deg] = t.rmse_m / t.crlb_rmse_m
        checks.append(Check(f"Taylor WLS is efficient at {sigma_deg:g} deg: RMSE within {100 * bar:.0f} % of the CRLB",
                            f"RMSE / CRLB {t.rmse_m / t.crlb_rmse_m:.3f}", t.failures == 0
                            and abs(t.rmse_m / t.crlb_rmse_m - 1) < bar))
        for other in ("tls", "ctls"):
            o = results[other]
            checks.append(Check(f"Taylor WLS at least as accurate as {other} at {sigma_deg:g} deg (within 3.5 "
                                "sampling sd)", f"{t.rmse_m:.0f} m vs {_fmt(o.rmse_m, 0)} m",
                                not np.isfinite(o.rmse_m) or t.rmse_m <= o.rmse_m * (1 + 3.5 * sd)))
    return PaperResult(
        "004", "Bearing-error estimation by iterative Taylor-series WLS (patent)",
        "One sensor on y = -0.2 x + 14 km, x = 15 .. 30 km every 0.1 km (151 bearings), target (30, 35) km, "
        "sigma 1 .. 10 deg: the Taylor WLS with the bearing-error term is more accurate than TLS and CTLS and "
        "estimates each bearing's error.",
        ["sigma (deg)", "method", "RMSE (m)", "sqrt tr CRLB (m)", "MSE / tr CRLB", "failures"], rows, checks,
        {"p004_efficiency": {"x": list(ratios), "xlabel": "bearing sigma (deg)", "ylabel": "RMSE / sqrt tr CRLB",
                             "log": False, "series": {"taylor_wls": list(ratios.values())}}},
        notes=f"{trials} trials per sigma, seeds {seed} + k; ctls is the Newton variant. On this geometry all three "
              "reach the CRLB, so the patent's accuracy ranking shows only as 'not worse'; its bearing-error "
              "estimates are checked in tests/core/estimators/test_paper004.py.")


PAPERS: dict[str, Callable[..., PaperResult]] = {"000": paper_000, "001": paper_001, "002": paper_002,
                                                 "003": paper_003, "004": paper_004}


def reproduce(size: str = "full", scheduler: Any = None, papers=None,
              progress: Callable[[str], None] | None = None) -> list[PaperResult]:
    """Every paper (or those named in ``papers``) at ``size`` (``"full"`` or ``"quick"``)."""
    out = []
    for name in papers or PAPERS:
        if progress is not None:
            progress(name)
        out.append(PAPERS[name](size, scheduler=scheduler))
    return out
