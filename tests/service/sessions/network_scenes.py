"""core's network scenes (:mod:`core.simulation.network`) posted through the HTTP API as a client would."""

from __future__ import annotations

import math

import numpy as np

from core.measurements import AZIMUTH, ELEVATION, TOA
from core.problem import CommonFrame, GeodeticPoint
from core.simulation.network import NetworkScenario, epoch_times


def create_body(scene: NetworkScenario) -> dict:
    """A network session with the scene's stations, frame origin and tracker settings."""
    config = scene.config
    stations = [{"id": s.id, "position": {"lat_deg": s.lat_deg, "lon_deg": s.lon_deg, "alt_m": s.alt_m},
                 "moving": scene.platform is not None and i == 0} for i, s in enumerate(scene.stations)]
    noise = {"accel_sigma_mps2": config.accel_sigma_mps2}
    if config.vertical_accel_sigma_mps2 is not None:
        noise["vertical_accel_sigma_mps2"] = config.vertical_accel_sigma_mps2
    if config.imm_accel_sigmas_mps2:
        noise.update(imm_accel_sigmas_mps2=list(config.imm_accel_sigmas_mps2),
                     imm_mean_sojourn_s=config.imm_mean_sojourn_s)
    return {"frame": "wgs84",
            "origin": {"lat_deg": scene.origin_lat_deg, "lon_deg": scene.origin_lon_deg, "alt_m": scene.origin_alt_m},
            "stations": stations, "process_noise": noise,
            "start": {"velocity_sigma_mps": config.velocity_prior_sigma_mps, "range_min_m": config.range_min_m,
                      "range_max_m": config.range_max_m,
                      **({} if config.vertical_velocity_prior_sigma_mps is None else
                         {"vertical_velocity_sigma_mps": config.vertical_velocity_prior_sigma_mps})},
            "reorder_window_s": config.reorder_window_s, "coast_after_s": config.coast_after_s,
            "end_after_s": config.end_after_s, "ttl_s": 3600.0}


def api_report(posted) -> dict:
    """One :class:`core.simulation.network.PostedReport` as the API's report (degrees, the /v1/fixes objects)."""
    report = posted.report
    measurements = []
    kinds, values, sigmas, ids = report.kinds.tolist(), report.values.tolist(), report.sigmas.tolist(), \
        report.station_ids
    i = 0
    while i < len(kinds):
        if kinds[i] == AZIMUTH:
            bearing = {"type": "bearing", "station_id": ids[i], "azimuth_deg": math.degrees(values[i]),
                       "sigma_azimuth_deg": math.degrees(sigmas[i])}
            if i + 1 < len(kinds) and kinds[i + 1] == ELEVATION and ids[i + 1] == ids[i]:
                bearing.update(elevation_deg=math.degrees(values[i + 1]),
                               sigma_elevation_deg=math.degrees(sigmas[i + 1]))
                i += 1
            measurements.append(bearing)
        elif kinds[i] == TOA:
            measurements.append({"type": "toa", "station_id": ids[i], "toa_s": values[i], "sigma_s": sigmas[i]})
        else:
            measurements.append({"type": "range", "station_id": ids[i], "range_m": values[i], "sigma_m": sigmas[i]})
        i += 1
    body = {"seq": report.seq + 1, "time_s": report.time_s, "emitter_id": report.emitter_id,
            "measurements": measurements}
    if posted.moving_stations:
        body["stations"] = [{"id": sid, "position": {"lat_deg": lat, "lon_deg": lon, "alt_m": alt}}
                            for sid, lat, lon, alt in posted.moving_stations]
    return body


def in_common_frame(track: dict, frame: CommonFrame) -> tuple[np.ndarray, np.ndarray]:
    """A track body's state ``(6,)`` and covariance ``(6, 6)`` back in the session's common frame (the body gives
    velocity and covariance in the axes at the track)."""
    p = np.array([track["position_local"][k] for k in ("east_m", "north_m", "up_m")])
    axes = frame.local_axes(p)
    turn = np.zeros((6, 6))
    turn[:3, :3] = turn[3:, 3:] = axes
    state = np.concatenate([p, axes.T @ np.array(track["velocity_enu_mps"])])
    return state, turn.T @ np.array(track["covariance_enu"]) @ turn


def run_over_http(client, scene: NetworkScenario, run) -> dict:
    """Post one run's reports as they arrive (one post per epoch: those that arrived since the last), and read
    every track predicted to each epoch (``?at_time_s=``).

    Returns
    -------
    dict
        ``estimates`` ``(E, 6)`` and ``covariances`` ``(E, 6, 6)`` in the common frame (NaN without a track),
        ``statuses`` (E,), ``applied``, ``late``, ``duplicates`` totals, and the session ``id``.
    """
    created = client.post("/v1/sessions", json=create_body(scene))
    assert created.status_code == 201, created.text
    session = created.json()
    frame = CommonFrame(GeodeticPoint(*scene.origin_rad))
    epochs = epoch_times(scene)
    estimates = np.full((epochs.size, 6), np.nan)
    covariances = np.full((epochs.size, 6, 6), np.nan)
    statuses: list = [None] * epochs.size
    totals = {"applied": 0, "late": 0, "duplicates": 0}
    posted, next_report = run.posted, 0
    for j, t in enumerate(epochs.tolist()):
        batch = []
        while next_report < len(posted) and posted[next_report].arrival_s <= t:
            batch.append(api_report(posted[next_report]))
            next_report += 1
        if batch:
            response = client.post(f"/v1/sessions/{session['id']}/reports", json={"reports": batch})
            assert response.status_code == 200, response.text
            body = response.json()
            for key in totals:
                totals[key] += body[key]
        state = client.get(f"/v1/sessions/{session['id']}", params={"at_time_s": t})
        assert state.status_code == 200, state.text
        tracks = state.json()["tracks"]
        if tracks:
            estimates[j], covariances[j] = in_common_frame(tracks[0], frame)
            statuses[j] = tracks[0]["status"]
    return {"id": session["id"], "estimates": estimates, "covariances": covariances, "statuses": statuses, **totals}
