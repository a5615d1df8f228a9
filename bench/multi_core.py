"""Bench row 11: unlabelled bearings of a large network associated in real time on one core.

20 ground emitters, 10 direction finders, each station scanning once a second and reporting every bearing it
measured (detection probability 0.9, 5 % false bearings; :func:`core.simulation.multi_emitter.scale_scene`),
fed scan by scan through :func:`core.tracking.association.apply_observations`. Measured: CPU seconds (this
process, one thread) per simulated second, over the whole run (the start of every track included) and over
its second half (steady state). Yardstick, same run: the labelled network session on the same scene's true
bearings (each labelled with its emitter, :func:`core.tracking.network.apply_reports` one scan at a time),
per bearing, the two run in turns scan by scan.
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np


def _cpu_per_scan(scans, apply, other_scans, other):
    """CPU seconds of ``apply(scan)`` over ``scans`` and of ``other(scan)`` over ``other_scans`` (as long), each
    scan's own, the two in turns scan by scan: both see the machine as it is at that moment (it is shared, and
    its speed moves within a run)."""
    out, other_out = [], []
    for scan, other_scan in zip(scans, other_scans, strict=True):
        t = time.process_time()
        apply(scan)
        out.append(time.process_time() - t)
        t = time.process_time()
        other(other_scan)
        other_out.append(time.process_time() - t)
    return np.array(out), np.array(other_out)


def multi_scale_row(duration_s: float = 120.0, seed: int = 0):
    """The row (module docstring)."""
    from dataclasses import replace

    from bench.rows import Row, committed, unavailable
    from core.simulation.multi_emitter import scale_scene, simulate_multi
    from core.tracking.association import (
        apply_observations,
        current_tracks,
        new_association_state,
    )
    from core.tracking.network import apply_reports, new_network_state

    number, what = 11, "20 emitters x 10 stations, unlabelled bearings, 1 scan/s each, one core"
    target = "<= 1 s CPU per simulated s; per bearing <= 2x labelled"
    if not committed("core/tracking/association.py"):
        return unavailable(number, what, target, "core/tracking/association.py has not landed in git yet")
    scene = scale_scene(20, 10, duration_s, seed)
    run = simulate_multi(scene, np.random.default_rng(seed))
    scans = [list(group) for _, group in itertools.groupby(run.observations, key=lambda o: (o.time_s, o.station_id))]
    warm = simulate_multi(scale_scene(3, 4, 5.0, seed + 1), np.random.default_rng(seed + 1))
    apply_observations(new_association_state(), warm.observations, scene.config)  # compile and warm

    state = new_association_state()

    def unlabelled(scan):
        nonlocal state
        state = apply_observations(state, scan, scene.config).state

    labelled_scans = [[replace(o.report, emitter_id=s) for o, s in zip(scan, sources) if s]
                      for scan, sources in zip(scans, _sources_by_scan(run, scans))]
    network_state = new_network_state(scene.config.network)

    def labelled(scan):
        nonlocal network_state
        if scan:
            network_state = apply_reports(network_state, scan, scene.config.network).state

    cpu, labelled_cpu = _cpu_per_scan(scans, unlabelled, labelled_scans, labelled)
    times = np.array([scan[0].time_s for scan in scans])
    half = times >= times[0] + duration_s / 2
    bearings = np.array([len(scan) for scan in scans])
    confirmed = sum(t.status == "confirmed" for t in current_tracks(state, times[-1], scene.config))
    true_bearings = np.array([len(scan) for scan in labelled_scans])
    per_second = cpu.sum() / duration_s
    steady = cpu[half].sum() / (duration_s / 2)
    per_bearing_us = cpu[half].sum() / bearings[half].sum() * 1e6
    labelled_us = labelled_cpu[half].sum() / true_bearings[half].sum() * 1e6
    ratio = per_bearing_us / labelled_us
    met = per_second <= 1.0 and ratio <= 2.0
    verdict = "met" if met else f"missed: {per_second:.3f} s/s, {ratio:.2f}x labelled"
    return Row(number, what, f"{per_second:.3f} s CPU per simulated s ({steady:.3f} steady; {per_bearing_us:,.0f} us "
               "per bearing)", f"labelled session on the true bearings: {labelled_us:,.0f} us per bearing",
               f"{ratio:.2f}x labelled per bearing", target, verdict,
               [(f"core.simulation.multi_emitter.scale_scene(20, 10, {duration_s:g} s, seed {seed}): "
                f"{int(bearings.sum()):,} bearings ({int(bearings.sum() - true_bearings.sum()):,} false) in "
                f"{len(scans):,} scans through apply_observations one scan at a time; process CPU time over the "
                f"whole run and over its second half (steady); {confirmed} confirmed tracks at the end. Yardstick: "
                "core.tracking.network.apply_reports on the same true bearings labelled with their emitter, one "
                "scan at a time, in turns with the unlabelled scans, second half.")])


def _sources_by_scan(run, scans):
    """Each scan's observations' emitters (``""``: false), in the scans' order."""
    sources = iter(run.sources)
    return [[next(sources) for _ in scan] for scan in scans]


def multi_hour_row(duration_s: float = 3600.0, chunk_s: float = 60.0, seed: int = 0):
    """Row 12: an hour of the row 11 network's bearings replayed through one post per minute, in core.

    The scene of row 11 (:func:`core.simulation.multi_emitter.scale_scene`, 20 emitters x 10 stations, one
    scan a second each) over ``duration_s``, drawn a minute at a time (one generator: the same run as drawn
    whole) and applied as one :func:`core.tracking.association.apply_observations` call per minute, the state
    carried between calls as a session carries it (its ``to_dict``, then ``from_dict``: the JSON-able value
    a store holds). Measured: process CPU seconds per minute's call (max and mean), against the service's
    default ``request_deadline_s``; the state's round trip is timed apart.
    """
    from bench.rows import Row, committed, unavailable
    from core.simulation.multi_emitter import scale_scene, scan_times, simulate_multi
    from core.tracking.association import AssociationState, apply_observations, current_tracks, new_association_state
    from service.settings import Settings

    number, what = 12, "an hour of 20 emitters x 10 stations, one post of bearings per minute, in core"
    deadline_s = Settings.model_fields["request_deadline_s"].default
    target = f"each minute's post within the request deadline ({deadline_s:g} s)"
    if not committed("core/tracking/association.py"):
        return unavailable(number, what, target, "core/tracking/association.py has not landed in git yet")
    scene = scale_scene(20, 10, duration_s, seed)
    warm = simulate_multi(scale_scene(3, 4, 5.0, seed + 1), np.random.default_rng(seed + 1))
    apply_observations(new_association_state(), warm.observations, scene.config)  # compile and warm
    schedule = scan_times(scene)
    rng = np.random.default_rng(seed)
    state = new_association_state()
    apply_s, round_trip_s, bearings = [], [], []
    start = schedule[0][0]
    for k in range(math.ceil(duration_s / chunk_s)):
        scans = [(t, i) for t, i in schedule if start + k * chunk_s <= t < start + (k + 1) * chunk_s]
        if not scans:
            continue
        observations = simulate_multi(scene, rng, scans).observations
        t = time.process_time()
        state = apply_observations(state, observations, scene.config).state
        apply_s.append(time.process_time() - t)
        t = time.process_time()
        state = AssociationState.from_dict(state.to_dict())
        round_trip_s.append(time.process_time() - t)
        bearings.append(len(observations))
    apply_s, round_trip_s = np.array(apply_s), np.array(round_trip_s)
    end = schedule[-1][0]
    confirmed = sum(t.status == "confirmed" for t in current_tracks(state, end, scene.config))
    worst = float(np.max(apply_s + round_trip_s))
    verdict = "met" if worst <= deadline_s else f"missed: {worst:.1f} s for one minute"
    return Row(number, what, f"max {apply_s.max():.2f} s, mean {apply_s.mean():.2f} s CPU per minute's post",
               f"request_deadline_s {deadline_s:g} s", f"{worst / deadline_s:.3f} of the deadline (worst minute, "
               "state round trip included)", target, verdict,
               [f"core.simulation.multi_emitter.scale_scene(20, 10, {duration_s:g} s, seed {seed}) drawn a minute "
                f"at a time: {len(apply_s)} posts of {int(np.mean(bearings)):,} bearings on average "
                f"({int(np.max(bearings)):,} at most), each one apply_observations call; process CPU time per "
                f"call: max {apply_s.max():.2f} s, mean {apply_s.mean():.2f} s, first {apply_s[0]:.2f} s; the "
                f"state's to_dict + from_dict: max {round_trip_s.max():.3f} s, mean {round_trip_s.mean():.3f} s; "
                f"{confirmed} confirmed tracks at the end."])
