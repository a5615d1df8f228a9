"""A network session's renderings: one CoT track event per track (and a delete event for an ended one), and
GeoJSON of every track, from the session's state body (:func:`service.sessions.network.state_body`), so a
rendering says exactly what the state says. Which tracks a map shows: :func:`service.sessions.association.on_map`.
"""

from __future__ import annotations

import math
import uuid
from datetime import datetime, timedelta, timezone

import numpy as np

from core import geodesy
from service.schemas import sessions as schemas
from service.sessions import association as association_sessions


def track_uid(session_id: str, track_id: str, cot=None) -> str:
    """A track's CoT uid: the session's ``cot.uid`` for its single emitter, ``uid-<track>`` otherwise."""
    from service.renderings.points import UID_PREFIX

    if cot is not None and cot.uid:
        return cot.uid if track_id == schemas.DEFAULT_EMITTER_ID else f"{cot.uid}-{track_id}"
    return f"{UID_PREFIX}session-{session_id}-{track_id}"


def _course(velocity_enu_mps) -> tuple[float, float]:
    v = velocity_enu_mps
    return math.degrees(math.atan2(v[0], v[1])) % 360.0, math.hypot(v[0], v[1])


def track_callsign(track_id: str, cot=None) -> str:
    """A track's CoT callsign: the session's ``cot.callsign`` for its single emitter, ``callsign-<track>`` for
    the others; without one, the track id (a label a map can show, unlike the uid)."""
    callsign = getattr(cot, "callsign", None)
    if callsign:
        return callsign if track_id == schemas.DEFAULT_EMITTER_ID else f"{callsign}-{track_id}"
    return track_id


def track_cot(body: dict, track: dict, cot=None) -> str | None:
    """One track as a CoT 2.0 track event (how m-p, course and speed, :func:`track_callsign`); None in a flat
    local frame. ``time`` and ``start`` are the session's ``updated_at``."""
    from xml.sax.saxutils import quoteattr

    from service.renderings import points as renderings

    if track["position"] is None:
        return None
    covariance = np.asarray(track["covariance_enu"], dtype=float)[:3, :3]
    course, speed = _course(track["velocity_enu_mps"])
    _, axes = renderings._ellipse_enu(covariance)
    start = datetime.fromisoformat(body["updated_at"].replace("Z", "+00:00"))
    detail = (f'<track course="{renderings._decimal(course, 2)}" speed="{renderings._decimal(speed, 3)}"/>'
              f'<passive_locator session={quoteattr(body["id"])} model={quoteattr(body["model"])} '
              f'status={quoteattr(track["status"])} version="{body["version"]}" updates="{track["updates"]}"/>')
    return renderings._event(track_uid(body["id"], track["id"], cot),
                             cot.type if cot is not None else renderings.DEFAULT_TYPE, renderings.HOW_TRACK, start,
                             cot.stale_s if cot is not None else renderings.DEFAULT_STALE_S, track["position"],
                             covariance, axes, detail, track_callsign(track["id"], cot))


def ended_cot(session_id: str, track_id: str, cot=None, now: datetime | None = None) -> str:
    """A CoT delete event (type ``t-x-d-d``, a link to the track's uid, ``__forcedelete``): the track ended."""
    from xml.sax.saxutils import quoteattr

    from service.renderings.points import DEFAULT_TYPE, utc_timestamp

    start = now or datetime.now(timezone.utc)
    stamp = utc_timestamp(start)
    return (f'<event version="2.0" uid="{uuid.uuid4()}" type="t-x-d-d" how="h-g-i-g-o" time="{stamp}" '
            f'start="{stamp}" stale="{utc_timestamp(start + timedelta(seconds=20))}">'
            '<point lat="0" lon="0" hae="0" ce="9999999" le="9999999"/>'
            f'<detail><link uid={quoteattr(track_uid(session_id, track_id, cot))} relation="none" '
            f'type={quoteattr(cot.type if cot is not None else DEFAULT_TYPE)}/><__forcedelete/></detail></event>')


#: A track's course line in GeoJSON: where it goes in this many seconds at its velocity.
COURSE_LINE_S = 60.0


def _course_line(position: dict, velocity_enu_mps) -> dict | None:
    """A LineString from a track's point along its horizontal velocity for :data:`COURSE_LINE_S` (the end placed
    in the point's tangent plane, converted exactly); None when it would cross the antimeridian."""
    from service.renderings.points import _lon180

    step = np.array([velocity_enu_mps[0], velocity_enu_mps[1], 0.0]) * COURSE_LINE_S
    lat, lon, _ = geodesy.enu_to_geodetic(step, math.radians(position["lat_deg"]),
                                            math.radians(position["lon_deg"]), position["alt_m"])
    start = [_lon180(position["lon_deg"]), position["lat_deg"]]
    end = [_lon180(math.degrees(float(lon))), math.degrees(float(lat))]
    if abs(end[0] - start[0]) > 180.0:
        return None
    return {"type": "LineString", "coordinates": [start, end]}


def geojson(body: dict, cot=None) -> dict:
    """Every track's point (id, status, course, speed, time), its 95 % ellipse and its course line (where it
    goes in :data:`COURSE_LINE_S` at its velocity), as one FeatureCollection."""
    from service.renderings import points as renderings

    features = []
    for track in body["tracks"]:
        if track["position"] is None or not association_sessions.on_map(body, track):
            continue
        covariance = np.asarray(track["covariance_enu"], dtype=float)[:3, :3]
        course, speed = _course(track["velocity_enu_mps"])
        properties = {"kind": "track", "id": track["id"], "session": body["id"],
                      "uid": track_uid(body["id"], track["id"], cot), "status": track["status"],
                      "time_s": track["time_s"], "time": body["updated_at"], "course_deg": course,
                      "speed_mps": speed, "version": body["version"]}
        features.extend(renderings._features(track["position"], covariance, properties))
        line = _course_line(track["position"], track["velocity_enu_mps"])
        if line is not None:
            features.append({"type": "Feature", "geometry": line,
                             "properties": {"kind": "course", "id": track["id"], "course_deg": course,
                                            "speed_mps": speed, "seconds": COURSE_LINE_S}})
    return {"type": "FeatureCollection", "features": features}
