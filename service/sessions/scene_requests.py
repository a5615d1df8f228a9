"""core's network scenes (:mod:`core.simulation.network`) as the HTTP API's request bodies: the session a scene
describes and each of its reports as a client posts them (the bench's load and the tests' HTTP runs post these)."""

from __future__ import annotations

import math

from core.measurements import AZIMUTH, ELEVATION, TOA
from core.simulation.network import NetworkScenario


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


__all__ = ["api_report", "create_body"]
