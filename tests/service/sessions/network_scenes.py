"""core's network scenes (:mod:`core.simulation.network`) posted through the HTTP API as a client would."""

from __future__ import annotations

import numpy as np

from core.problem.frame import CommonFrame, GeodeticPoint
from core.simulation.network import NetworkScenario, epoch_times
from service.sessions.scene_requests import api_report, create_body


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
