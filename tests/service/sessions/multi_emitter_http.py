"""core's multi-emitter scene (:mod:`core.simulation.multi_emitter`) posted through the HTTP API as a client would:
unlabelled bearings, each with its signal's frequency, to a session created with ``"association": "auto"``."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from core.simulation.multi_emitter import MultiEmitterScenario, baseline_estimates, truth_at
from core.tracking.association import apply_observations, current_tracks, new_association_state
from core.tracking.gospa import gospa


def create_body(scene: MultiEmitterScenario, **changes) -> dict:
    """An auto session with the scene's stations, frame origin, track filter and association settings."""
    config, network = scene.config, scene.config.network
    body = {"frame": "wgs84", "association": "auto",
            "origin": {"lat_deg": scene.origin_lat_deg, "lon_deg": scene.origin_lon_deg, "alt_m": scene.origin_alt_m},
            "stations": [{"id": s.id, "position": {"lat_deg": s.lat_deg, "lon_deg": s.lon_deg, "alt_m": s.alt_m}}
                         for s in scene.stations],
            "process_noise": {"accel_sigma_mps2": network.accel_sigma_mps2,
                              "vertical_accel_sigma_mps2": network.vertical_accel_sigma_mps2},
            "start": {"velocity_sigma_mps": network.velocity_prior_sigma_mps,
                      "vertical_velocity_sigma_mps": network.vertical_velocity_prior_sigma_mps,
                      "range_min_m": network.range_min_m, "range_max_m": network.range_max_m},
            "association_config": {"method": config.method, "detection_probability": config.detection_probability,
                                   "false_density_per_rad2": config.false_density_per_rad2,
                                   "gate_probability": config.gate_probability,
                                   "confirm_hits": config.confirm_hits, "confirm_window": config.confirm_window,
                                   "frequency_tolerance_hz": config.frequency_tolerance_hz,
                                   "range_min_m": config.range_min_m, "range_max_m": config.range_max_m},
            "coast_after_s": config.coast_after_s, "end_after_s": config.end_after_s, "reorder_window_s": 2.0,
            "ttl_s": 3600.0}
    body.update(changes)
    return body


def api_report(observation, seq: int) -> dict:
    """One :class:`core.tracking.association.Observation` (a station's azimuth and elevation) as the API's report:
    degrees, the /v1/fixes bearing object, its frequency, no emitter_id."""
    report = observation.report
    (station,) = set(report.station_ids)
    values, sigmas = report.values.tolist(), report.sigmas.tolist()
    return {"seq": seq, "time_s": report.time_s, "frequency_hz": observation.frequency_hz,
            "measurements": [{"type": "bearing", "station_id": station, "azimuth_deg": math.degrees(values[0]),
                              "elevation_deg": math.degrees(values[1]), "sigma_azimuth_deg": math.degrees(sigmas[0]),
                              "sigma_elevation_deg": math.degrees(sigmas[1])}]}


def short_scene(scene: MultiEmitterScenario, duration_s: float = 40.0, silent_after_s: float = 10.0,
                **changes) -> MultiEmitterScenario:
    """``scene`` cut to ``duration_s``, its e4 silent after ``silent_after_s`` (so that e4's track ends soon),
    coasting after 3 s and ending after 8 s without a bearing."""
    emitters = tuple(replace(e, off_s=silent_after_s) if e.id == "e4" else e for e in scene.emitters)
    config = replace(scene.config, coast_after_s=3.0, end_after_s=8.0)
    return replace(scene, duration_s=duration_s, emitters=emitters, config=config, **changes)


def epochs(scene: MultiEmitterScenario, step_s: float) -> list[float]:
    from core.simulation.network import START_TIME_S

    count = int(round(scene.duration_s / step_s))
    return [START_TIME_S + step_s * (k + 1) for k in range(count)]


def confirmed_positions(tracks: list[dict]) -> tuple[list[str], np.ndarray]:
    """Ids and horizontal positions ``(K, 2)`` (east, north in the common frame) of a state's confirmed tracks."""
    chosen = [t for t in tracks if t["status"] == "confirmed"]
    return ([t["id"] for t in chosen],
            np.array([[t["position_local"]["east_m"], t["position_local"]["north_m"]] for t in chosen]).reshape(-1, 2))


def run_over_http(client, scene: MultiEmitterScenario, observations, step_s: float = 5.0, body: dict | None = None
                  ) -> dict:
    """Post the bearings as they are measured, one post per ``step_s`` (those measured since the last), and read
    every track predicted to the post's epoch (``?at_time_s=``).

    Returns
    -------
    dict
        ``id`` (the session), ``epochs``, per epoch ``ids`` and ``positions`` of the confirmed tracks, the
        ``applied``, ``late`` and ``duplicates`` totals and the ``last`` state body.
    """
    created = client.post("/v1/sessions", json=body or create_body(scene))
    assert created.status_code == 201, created.text
    session_id = created.json()["id"]
    out = {"id": session_id, "epochs": epochs(scene, step_s), "ids": [], "positions": [], "applied": 0, "late": 0,
           "duplicates": 0}
    cursor = 0
    for t in out["epochs"]:
        batch = []
        while cursor < len(observations) and observations[cursor].time_s <= t:
            batch.append(api_report(observations[cursor], cursor + 1))
            cursor += 1
        if batch:
            response = client.post(f"/v1/sessions/{session_id}/reports", json={"reports": batch})
            assert response.status_code == 200, response.text
            for key in ("applied", "late", "duplicates"):
                out[key] += response.json()[key]
        state = client.get(f"/v1/sessions/{session_id}", params={"at_time_s": t})
        assert state.status_code == 200, state.text
        ids, positions = confirmed_positions(state.json()["tracks"])
        out["ids"].append(ids)
        out["positions"].append(positions)
    out["last"] = client.get(f"/v1/sessions/{session_id}").json()
    return out


def run_in_core(scene: MultiEmitterScenario, observations, times_s: list[float]) -> dict:
    """core's association on the same bearings, fed up to each epoch, its confirmed tracks predicted to it."""
    state, cursor = new_association_state(), 0
    out = {"ids": [], "positions": []}
    for t in times_s:
        start = cursor
        while cursor < len(observations) and observations[cursor].time_s <= t:
            cursor += 1
        if cursor > start:
            state = apply_observations(state, observations[start:cursor], scene.config).state
        tracks = [tr for tr in current_tracks(state, t, scene.config) if tr.status == "confirmed"]
        out["ids"].append([tr.id for tr in tracks])
        out["positions"].append(np.array([tr.mean_enu[:2] for tr in tracks]).reshape(-1, 2))
    return out


def gospa_per_epoch(scene: MultiEmitterScenario, times_s: list[float], positions: list[np.ndarray]) -> np.ndarray:
    """GOSPA (the scene's cutoff, horizontal) of each epoch's estimates against the emitters on the air."""
    return np.array([gospa(p, truth_at(scene, t)[1][:, :2], scene.gospa_cutoff_m).distance
                     for t, p in zip(times_s, positions)])


def baseline_gospa_per_epoch(scene: MultiEmitterScenario, observations, times_s: list[float]) -> np.ndarray:
    """The pairwise-intersection + DBSCAN baseline's GOSPA at each epoch, from the bearings measured up to it."""
    out = []
    for t in times_s:
        seen = [o for o in observations if o.time_s <= t]
        out.append(gospa(baseline_estimates(scene, seen, t), truth_at(scene, t)[1][:, :2],
                         scene.gospa_cutoff_m).distance)
    return np.array(out)
