"""Reports of the command-line tools: Markdown, JSON and PNG plots (matplotlib, Agg backend).

``passive-locator evaluate`` writes ``evaluation.md``, ``evaluation.json``
and ``rmse.png`` (fix methods, the paper-001 session filter, or the network tracker); ``passive-locator reproduce`` writes ``papers.md``,
``papers.json`` and one PNG per figure. matplotlib is imported only when a
plot is drawn (the service itself never needs it).
"""

from __future__ import annotations

import json
import math
import pathlib
import sys
import time

import numpy as np


class ProgressBar:
    """A one-line progress bar on stderr, ``progress(done, total)`` style (what core.parallel calls).

    A dozen lines instead of a dependency (tqdm): the CLI needs only done/total and an elapsed time.
    On a stream that is not a terminal it writes a line per tenth of the work instead of redrawing.
    """

    def __init__(self, label: str, stream=None, width: int = 30):
        self.label, self.stream, self.width = label, stream or sys.stderr, width
        self.start = time.monotonic()
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._shown = -1

    def __call__(self, done: int, total: int) -> None:
        fraction = done / total if total else 1.0
        tenth = int(10 * fraction)
        if not self.tty and tenth == self._shown and done != total:
            return
        self._shown = tenth
        filled = int(self.width * fraction)
        line = (f"{self.label} [{'#' * filled}{'.' * (self.width - filled)}] {done}/{total} "
                f"{time.monotonic() - self.start:.1f} s")
        self.stream.write(("\r" + line) if self.tty else line + "\n")
        if self.tty and done == total:
            self.stream.write("\n")
        self.stream.flush()


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise RuntimeError("PNG plots need matplotlib: pip install 'passive-locator[reports]'") from None

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def markdown_table(columns, rows) -> str:
    lines = ["| " + " | ".join(str(c) for c in columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(str(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def _plain(value):
    """JSON-able: arrays to lists, non-finite floats to None."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


# --- evaluate ---------------------------------------------------------------------------------------------


def write_evaluation(body: dict, directory: pathlib.Path, title: str) -> list[pathlib.Path]:
    """A fix evaluation's report (``body`` as POST /v1/evaluations answers) in ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    methods = body["methods"]
    rows = [[name, _num(m["rmse_m"]), _num(m["crlb_rmse_m"]), _num(m["efficiency"], 3), _num(m["nees_mean"], 2),
             " / ".join(_num(v) for v in (m["bias_enu_m"] or [None] * 3)), m["failures"], m.get("excluded_trials", 0)]
            for name, m in methods.items()]
    text = [f"# Evaluation: {title}", "",
            f"{body['trials']} trials, seed {body['seed']}, noise {body['noise']}"
            + (f", outliers {body['options']['outliers']}" if "options" in body else "") + ".", "",
            markdown_table(["method", "RMSE (m)", "sqrt tr CRLB (m)", "MSE / tr CRLB", "mean NEES (3 if honest)",
                            "bias e / n / u (m)", "failures", "trials with exclusions"], rows), "",
            "![RMSE against the bound](rmse.png)", ""]
    paths = [directory / "evaluation.md", directory / "evaluation.json", directory / "rmse.png"]
    paths[0].write_text("\n".join(text))
    paths[1].write_text(json.dumps(_plain(body), indent=2, sort_keys=True) + "\n")
    _bar_plot(paths[2], list(methods), [m["rmse_m"] for m in methods.values()],
              [m["crlb_rmse_m"] for m in methods.values()], "RMSE (m)", title)
    return paths


def write_tracking_evaluation(result, config, runs: int, seed: int, directory: pathlib.Path,
                              title: str, every_s: float = 10.0) -> list[pathlib.Path]:
    """A session-filter evaluation's report (:class:`core.simulation.tracking.AgainstBound`) in ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    times = np.asarray(result.times_s)
    rmse = result.rmse_m()
    bound = np.sqrt(result.bound_m2)
    ranges = result.ranges_m.mean(axis=0)
    nees = np.nanmean(result.nees, axis=0) if np.isfinite(result.nees).any() else np.full(times.size, np.nan)
    picked = [i for i in range(times.size) if i == times.size - 1 or
              math.floor((times[i] - times[0]) / every_s) != math.floor((times[i - 1] - times[0]) / every_s)
              or i == 0]
    rows = [[_num(times[i], 0), _num(rmse[i]), _num(bound[i]), _num(rmse[i] / bound[i], 3),
             _num(100 * rmse[i] / ranges[i], 2), _num(nees[i], 2)] for i in picked]
    last = slice(-min(50, times.size), None)
    body = {"model": config.model, "period_known": config.period_known, "runs": runs, "seed": seed,
            "ratio_last_50": result.ratio(last),
            "epochs": {"time_s": times, "rmse_m": rmse, "pcrb_rmse_m": bound, "mean_range_m": ranges,
                       "position_nees_mean": nees}}
    text = [f"# Session-filter evaluation: {title}", "",
            f"{config.model}, period {'known' if config.period_known else 'unknown'}, {runs} runs (seeds {seed} + r); "
            f"RMSE over the last {min(50, times.size)} epochs / PCRB: {body['ratio_last_50']:.3f}.", "",
            markdown_table(["time (s)", "RMSE (m)", "sqrt tr PCRB (m)", "RMSE / PCRB", "RMSE (% range)",
                            "position NEES (3 if honest)"], rows), "", "![RMSE against the PCRB](rmse.png)", ""]
    paths = [directory / "evaluation.md", directory / "evaluation.json", directory / "rmse.png"]
    paths[0].write_text("\n".join(text))
    paths[1].write_text(json.dumps(_plain(body), indent=2, sort_keys=True) + "\n")
    _line_plot(paths[2], times, {f"{config.model} RMSE": rmse, "sqrt tr PCRB": bound}, "time (s)",
               "position error (m)", title, log=True)
    return paths


def write_network_evaluation(body: dict, directory: pathlib.Path, title: str,
                             every_s: float = 10.0) -> list[pathlib.Path]:
    """A network-tracker evaluation's report (``body`` as ``POST /v1/evaluations`` answers a ``network`` request)
    in ``directory``: per-epoch RMSE and NEES beside the posterior CRLB."""
    directory.mkdir(parents=True, exist_ok=True)
    epochs = body["epochs"]
    times = np.asarray(epochs["time_s"])
    rmse = np.array([np.nan if v is None else v for v in epochs["rmse_position_m"]], dtype=float)
    bound = np.array([np.nan if v is None else v for v in epochs["pcrb_position_m"]], dtype=float)
    picked = [i for i in range(times.size) if i in (0, times.size - 1)
              or math.floor((times[i] - times[0]) / every_s) != math.floor((times[i - 1] - times[0]) / every_s)]
    rows = [[_num(times[i] - times[0], 0), _num(rmse[i]), _num(bound[i]),
             _num(rmse[i] / bound[i] if np.isfinite(bound[i]) else None, 3), _num(epochs["nees_position"][i], 2),
             _num(epochs["confirmed_fraction"][i], 2)] for i in picked]
    low, high = body["nees_interval_99"]
    text = [f"# Network-tracker evaluation: {title}", "",
            f"Scene {body['scene']}, {body['trials']} trials (seeds {body['seed']} + r). From "
            f"{body['converged_after_s']:g} s after the start: position RMSE / PCRB "
            f"{_num(body['rmse_over_pcrb'], 3)}, mean position NEES {_num(body['nees_after'], 2)} (99 % interval "
            f"of a per-epoch mean: {low:.2f} to {high:.2f}); {body['late_reports']} reports late.", "",
            markdown_table(["time after start (s)", "RMSE (m)", "sqrt tr PCRB (m)", "RMSE / PCRB",
                            "position NEES (3 if honest)", "confirmed fraction"], rows), "",
            "![RMSE against the PCRB](rmse.png)", ""]
    paths = [directory / "evaluation.md", directory / "evaluation.json", directory / "rmse.png"]
    paths[0].write_text("\n".join(text))
    paths[1].write_text(json.dumps(_plain(body), indent=2, sort_keys=True) + "\n")
    _line_plot(paths[2], times - times[0], {"network tracker RMSE": rmse, "sqrt tr PCRB": bound},
               "time after start (s)", "position error (m)", title, log=True)
    return paths


def write_multi_evaluation(body: dict, directory: pathlib.Path, title: str) -> list[pathlib.Path]:
    """A multi-emitter evaluation's report (``body`` as ``POST /v1/evaluations`` answers a ``multi_emitter``
    request) in ``directory``: GOSPA and its parts for the tracker and the baseline, and per run the
    confirmation delays, false confirmed tracks and identity switches."""
    directory.mkdir(parents=True, exist_ok=True)
    parts = [[name, _num(p["gospa_m"]), _num(p["localisation_m2"], 0), _num(p["missed_m2"], 0), _num(p["false_m2"], 0)]
             for name, p in (("tracker", body["tracker"]), ("intersections + DBSCAN", body["baseline"]))]
    runs = [[str(body["seed"] + r), _num(body["tracker"]["gospa_per_trial_m"][r]),
             _num(body["baseline"]["gospa_per_trial_m"][r]),
             ", ".join(f"{e} {_num(d)}" for e, d in zip(body["emitters"], body["confirm_delay_s"][r])),
             str(body["false_tracks"][r]), str(body["identity_switches"][r])] for r in range(body["trials"])]
    text = [f"# Multi-emitter evaluation: {title}", "",
            f"Scene {body['scene']} variant {body['variant']}, {body['duration_s']:g} s, {body['trials']} trials "
            f"(seeds {body['seed']} + r); GOSPA with c = {body['gospa_cutoff_m']:g} m, p = 2, on east-north, "
            f"once a second. Tracker / baseline: {_num(body['gospa_over_baseline'], 3)}.", "",
            markdown_table(["", "mean GOSPA (m)", "localisation (m^2)", "missed (m^2)", "false (m^2)"], parts), "",
            markdown_table(["seed", "tracker GOSPA (m)", "baseline GOSPA (m)", "confirmation delay (s; - never)",
                            "false confirmed tracks", "identity switches"], runs), ""]
    paths = [directory / "evaluation.md", directory / "evaluation.json"]
    paths[0].write_text("\n".join(text))
    paths[1].write_text(json.dumps(_plain(body), indent=2, sort_keys=True) + "\n")
    return paths


def _num(value, digits: int = 1) -> str:
    if value is None:
        return "-"
    value = float(value)
    return f"{value:.{digits}f}" if math.isfinite(value) else "-"


def _bar_plot(path, labels, rmse, bound, ylabel, title, log=False) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(max(5.0, 0.9 * len(labels) + 2), 4.0))
    x = np.arange(len(labels))
    ax.bar(x - 0.2, [np.nan if v is None else v for v in rmse], 0.4, label="Monte Carlo RMSE")
    ax.bar(x + 0.2, bound, 0.4, label="sqrt tr CRLB")
    ax.set_xticks(x, labels, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel(ylabel)
    if log:
        ax.set_yscale("log")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _line_plot(path, x, series: dict, xlabel, ylabel, title, log=False) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.0))
    for label, values in series.items():
        values = np.array([np.nan if v is None else v for v in values], dtype=float)
        ax.plot(x, np.where(np.isfinite(values), values, np.nan), label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if log:
        ax.set_yscale("log")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _heat_map(path, curve: dict, title) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    grid = np.array(curve["grid"], dtype=float)
    image = ax.imshow(grid, origin="lower", extent=curve["extent_km"], vmin=0.9, vmax=1.1, cmap="coolwarm")
    stations = np.array(curve["stations_km"])
    ax.plot(stations[:, 0], stations[:, 1], "k^", label="sensors")
    ax.set_xlabel("east (km)")
    ax.set_ylabel("north (km)")
    ax.set_title(title, fontsize=9)
    fig.colorbar(image, ax=ax, label=curve["label"])
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- reproduce --------------------------------------------------------------------------------------------


def write_papers(results, directory: pathlib.Path, size: str, elapsed_s: float, scheduler=None) -> list[pathlib.Path]:
    """``papers.md`` (each table beside the paper's claim, the checks, the plots), ``papers.json`` and PNGs."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    text = ["# The five papers, reproduced", "",
            f"Written by `passive-locator reproduce{' --quick' if size == 'quick' else ''}` "
            f"({size} size, {elapsed_s:.0f} s{', on ' + str(scheduler) if scheduler else ', in one process'}). "
            "Scenarios: `core/simulation/scenarios.py` and `core/simulation/tracking.py` (the tests use the same); "
            "runs and checks: `core/simulation/papers.py`. A check marked *asserted* fails the command when it does "
            "not hold; *reported* rows record where a paper's claim does not hold here.", "",
            markdown_table(["paper", "title", "asserted checks", "result"],
                           [[r.paper, r.title, sum(c.asserted for c in r.checks),
                             "pass" if r.passed else "**FAIL**"] for r in results]), ""]
    for r in results:
        text += [f"## Paper {r.paper}: {r.title}", "", f"**The paper's claim.** {r.paper_claim}", "",
                 "**Measured here.**", "", markdown_table(r.columns, r.rows), "", r.notes, "",
                 markdown_table(["claim", "measured", "holds", ""],
                                [[c.claim, c.measured, "yes" if c.holds else "**no**",
                                  "asserted" if c.asserted else "reported"] for c in r.checks]), ""]
        for name, curve in r.curves.items():
            path = directory / f"{name}.png"
            title = f"paper {r.paper}: {name.split('_', 1)[1]}"
            if "grid" in curve:
                _heat_map(path, curve, title)
            elif "bars" in curve:
                _bar_plot(path, curve["bars"], curve["rmse_m"], curve["bound_m"], curve["ylabel"], title,
                          log=curve.get("log", False))
            else:
                _line_plot(path, curve["x"], curve["series"], curve["xlabel"], curve["ylabel"], title,
                           log=curve.get("log", False))
            paths.append(path)
            text += [f"![{title}]({path.name})", ""]
    md = directory / "papers.md"
    md.write_text("\n".join(text))
    js = directory / "papers.json"
    js.write_text(json.dumps(_plain([{"paper": r.paper, "title": r.title, "paper_claim": r.paper_claim,
                                      "columns": r.columns, "rows": r.rows, "notes": r.notes, "passed": r.passed,
                                      "checks": [vars(c) for c in r.checks]} for r in results]),
                             indent=2) + "\n")
    return [md, js, *paths]
