"""Map-ready renderings of fixes and session states: Cursor-on-Target 2.0 events and GeoJSON.

Both are built from the fields of the response bodies (a fix's as
:func:`service.fixes.write.fix_bodies` writes them, from the solved batch's
numbers; a session's from :func:`service.sessions.observer.state_body`), so a rendering
says exactly what the JSON says. Errors are in the east/north/up axes at the rendered point itself
(a fix body's ``covariance_enu_m2`` already is; a session's ``covariance_enu``
is turned from the observer's axes to the emitter's):

- CoT ``ce`` is the one-sigma circular error ``sqrt((l1 + l2) / 2)`` of the
  horizontal covariance's eigenvalues ``l1, l2`` (the RMS of the two axes'
  sigmas, which is what the schema's "one sigma point" means for a circle),
  and ``le`` is the one-sigma vertical error ``sigma_up``.
- The GeoJSON ellipse is the 95 % horizontal ellipse of that covariance, its
  vertices placed in the point's tangent plane and converted to WGS84 exactly
  (:mod:`core.geodesy`), counter-clockwise (RFC 7946), and cut at the
  antimeridian into a MultiPolygon when it crosses it. An ellipse around a
  pole is not representable in longitude/latitude and is left out.
"""

from __future__ import annotations

import math
import uuid
from datetime import datetime, timedelta, timezone
from xml.sax.saxutils import quoteattr

import numpy as np

from core import geodesy
from core.error_summary import error_summary

#: Polygon vertices of an ellipse (the ring has one more: the first repeated).
ELLIPSE_VERTICES = 72
DEFAULT_TYPE = "a-u-G"
DEFAULT_STALE_S = 300.0
HOW_FIX = "m-f"
HOW_TRACK = "m-p"
UID_PREFIX = "passive-locator-"


class Renderings(tuple):
    """The formats a request asks for, with the options that shape them.

    A tuple of format names (``"geojson"``, ``"cot"``), so ``"cot" in it``
    works wherever a plain tuple of formats did; it also carries the request's
    ``observed_at`` (an aware datetime or None) and ``cot`` options
    (:class:`service.schemas.CotOptions` or None).
    """

    observed_at: datetime | None = None
    cot: object = None

    def __new__(cls, formats=(), observed_at: datetime | None = None, cot=None):
        self = super().__new__(cls, formats)
        self.observed_at, self.cot = observed_at, cot
        return self


def of_request(request) -> Renderings:
    """The renderings a :class:`service.schemas.FixRequest` asks for."""
    return Renderings(request.formats, request.observed_at, request.cot)


# -- shared geometry ----------------------------------------------------------------------------------------------

def one_sigma_errors(covariance_enu_m2) -> tuple[float, float]:
    """``(ce, le)``: one-sigma circular and vertical errors (m) of an ENU covariance at the point."""
    cov = np.asarray(covariance_enu_m2, dtype=float)
    horizontal = max(0.5 * (cov[0, 0] + cov[1, 1]), 0.0)
    return math.sqrt(horizontal), math.sqrt(max(cov[2, 2], 0.0))


def _ellipse_enu(covariance_enu_m2) -> tuple[np.ndarray, dict]:
    """Vertices ``(N, 3)`` of the 95 % ellipse in the point's tangent plane (CCW), and its axes."""
    summary = error_summary(covariance_enu_m2)
    a, b = float(summary.ellipse_semi_major_m[0]), float(summary.ellipse_semi_minor_m[0])
    theta = float(summary.ellipse_orientation_rad[0])
    major = np.array([math.sin(theta), math.cos(theta)])
    minor = np.array([-major[1], major[0]])  # the major axis turned 90 degrees counter-clockwise (east -> north)
    t = 2.0 * np.pi * np.arange(ELLIPSE_VERTICES) / ELLIPSE_VERTICES
    horizontal = a * np.cos(t)[:, None] * major + b * np.sin(t)[:, None] * minor
    vertices = np.concatenate([horizontal, np.zeros((ELLIPSE_VERTICES, 1))], axis=1)
    axes = {"semi_major_m": a, "semi_minor_m": b, "orientation_deg": math.degrees(theta), "probability": 0.95}
    return vertices, axes


def _clip(ring: list, boundary: float, keep_below: bool) -> list:
    """Sutherland-Hodgman: the part of a closed convex ring on one side of ``lon = boundary`` (closed)."""
    inside = (lambda p: p[0] <= boundary) if keep_below else (lambda p: p[0] >= boundary)
    out = []
    for p, q in zip(ring[:-1], ring[1:]):
        if inside(p):
            out.append(p)
        if inside(p) != inside(q):
            s = (boundary - p[0]) / (q[0] - p[0])
            out.append([boundary, p[1] + s * (q[1] - p[1])])
    if out and out[0] != out[-1]:
        out.append(list(out[0]))
    return out


def polygon_geometries(lon_deg, lat_deg, centre_lon_deg) -> list[dict | None]:
    """GeoJSON (RFC 7946) geometries of convex rings given by their vertices in longitude and latitude.

    Each ring's longitudes are unwrapped around its centre's (so a ring near the antimeridian is one
    piece), then written within [-180, 180]: as a Polygon when it fits, else cut at the antimeridian
    into a MultiPolygon of its two sides. A ring around a pole (its unwrapped longitudes spanning 180
    degrees or more) has no such representation: its geometry is None.

    Parameters
    ----------
    lon_deg, lat_deg : ndarray, shape (N, K)
        The vertices of each ring, counter-clockwise, the first not repeated.
    centre_lon_deg : ndarray, shape (N,)
        A longitude inside each ring.

    Returns
    -------
    list of dict or None, length N
    """
    lon = np.asarray(lon_deg, dtype=float)
    lat = np.asarray(lat_deg, dtype=float)
    centre = np.asarray(centre_lon_deg, dtype=float).reshape(-1, 1)
    unwrapped = centre + (lon - centre + 180.0) % 360.0 - 180.0
    high, low = unwrapped.max(axis=1), unwrapped.min(axis=1)
    shift = np.where(low > 180.0, -360.0, np.where(high < -180.0, 360.0, 0.0))  # wholly across: move it back
    unwrapped += shift[:, None]
    high, low = high + shift, low + shift
    closed = np.stack([np.concatenate([unwrapped, unwrapped[:, :1]], axis=1),
                       np.concatenate([lat, lat[:, :1]], axis=1)], axis=-1)
    out: list[dict | None] = []
    for ring, top, bottom in zip(closed.tolist(), high.tolist(), low.tolist()):
        if top - bottom >= 180.0:
            out.append(None)
        elif top <= 180.0 and bottom >= -180.0:
            out.append({"type": "Polygon", "coordinates": [ring]})
        else:
            boundary = 180.0 if top > 180.0 else -180.0
            turn = -360.0 if boundary > 0 else 360.0
            near = _clip(ring, boundary, keep_below=boundary > 0)
            far = [[x + turn, y] for x, y in _clip(ring, boundary, keep_below=boundary < 0)]
            out.append({"type": "MultiPolygon", "coordinates": [[near], [far]]})
    return out


def _ellipse_geometry(position: dict, covariance_enu_m2) -> tuple[dict | None, dict]:
    """The 95 % ellipse as a GeoJSON Polygon (or MultiPolygon across the antimeridian), and its axes."""
    vertices, axes = _ellipse_enu(covariance_enu_m2)
    lat, lon, _ = geodesy.enu_to_geodetic(vertices, math.radians(position["lat_deg"]),
                                          math.radians(position["lon_deg"]), position["alt_m"])
    return polygon_geometries(np.degrees(lon)[None], np.degrees(lat)[None], [position["lon_deg"]])[0], axes


def utc_timestamp(moment: datetime) -> str:
    """An aware time as RFC 3339 / xs:dateTime in UTC to the millisecond, ``0001-01-02T00:00:00.000Z`` (four-digit
    years: ``strftime("%Y")`` writes year 1 as ``1``)."""
    return moment.astimezone(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _decimal(value: float, places: int) -> str:
    """Fixed-point text (xs:decimal has no exponent)."""
    return f"{value:.{places}f}"


# -- fixes --------------------------------------------------------------------------------------------------------

def _fix_errors(body: dict) -> np.ndarray:
    """The fix's covariance in the ENU axes at the fix (as the body gives it)."""
    return np.asarray(body["covariance_enu_m2"], dtype=float)


def fix_cot(body: dict, options=()) -> str | None:
    """A fix as a CoT 2.0 event; None without a geodetic position (a flat local frame).

    Parameters
    ----------
    body : dict
        A fix response body.
    options : Renderings or tuple
        ``observed_at`` sets ``time`` and ``start`` (else now); ``cot`` sets ``uid`` (else unique per
        call), ``type``, ``stale_s`` and ``callsign`` (else the uid).
    """
    if "position" not in body:
        return None
    cot = getattr(options, "cot", None)
    observed = getattr(options, "observed_at", None)
    start = observed or datetime.now(timezone.utc)
    uid = cot.uid if cot is not None and cot.uid else f"{UID_PREFIX}fix-{uuid.uuid4().hex}"
    kind = cot.type if cot is not None else DEFAULT_TYPE
    stale_s = cot.stale_s if cot is not None else DEFAULT_STALE_S
    covariance = _fix_errors(body)
    _, axes = _ellipse_enu(covariance)
    detail = (f'<passive_locator method={quoteattr(body["method"])} '
              f'covariance_source={quoteattr(body.get("covariance_source", ""))} '
              f'cep50_m="{_decimal(body["error"]["cep50_m"], 2)}" '
              f'sep50_m="{_decimal(body["error"]["sep50_m"], 2)}"/>')
    return _event(uid, kind, HOW_FIX, start, stale_s, body["position"], covariance, axes, detail,
                  getattr(cot, "callsign", None))


def _event(uid, kind, how, start, stale_s, position, covariance, axes, detail="", callsign=None) -> str:
    """The one CoT event writer: every event carries ``<contact callsign>`` (the uid unless one is given),
    the label TAK shows on its marker."""
    ce, le = one_sigma_errors(covariance)
    stamp = utc_timestamp(start)
    return (
        f'<event version="2.0" uid={quoteattr(uid)} type={quoteattr(kind)} how="{how}" time="{stamp}" '
        f'start="{stamp}" stale="{utc_timestamp(start + timedelta(seconds=stale_s))}">'
        f'<point lat="{_decimal(position["lat_deg"], 8)}" lon="{_decimal(_lon180(position["lon_deg"]), 8)}" '
        f'hae="{_decimal(position["alt_m"], 2)}" ce="{_decimal(ce, 2)}" le="{_decimal(le, 2)}"/>'
        f'<detail><contact callsign={quoteattr(callsign or uid)}/>{detail}'
        f'<shape><ellipse major="{_decimal(axes["semi_major_m"], 2)}" minor="{_decimal(axes["semi_minor_m"], 2)}" '
        f'angle="{_decimal(axes["orientation_deg"], 2)}"/></shape>'
        f'<remarks>95 % error ellipse: semi-axes (m), major axis clockwise from true north (deg); '
        f'ce, le: one-sigma errors (m)</remarks>'
        f'</detail></event>'
    )


def _lon180(lon_deg: float) -> float:
    return (lon_deg + 180.0) % 360.0 - 180.0 if not -180.0 <= lon_deg <= 180.0 else lon_deg


def _features(position: dict | None, covariance, properties: dict) -> list[dict]:
    if position is None:
        return [{"type": "Feature", "geometry": None, "properties": properties}]
    point = {"type": "Point", "coordinates": [_lon180(position["lon_deg"]), position["lat_deg"], position["alt_m"]]}
    features = [{"type": "Feature", "geometry": point, "properties": properties}]
    geometry, axes = _ellipse_geometry(position, covariance)
    if geometry is not None:
        features.append({"type": "Feature", "geometry": geometry,
                         "properties": {"kind": "error_ellipse", **axes}})
    return features


def fix_features(body: dict, options=()) -> list[dict]:
    """The Point and 95 % ellipse Features of one fix (a null-geometry Point in a flat local frame)."""
    observed = getattr(options, "observed_at", None)
    properties = {"kind": "fix", "method": body["method"], "covariance_source": body.get("covariance_source"),
                  "time": utc_timestamp(observed or datetime.now(timezone.utc)), **body["error"]}
    cot = getattr(options, "cot", None)
    if cot is not None and cot.uid:
        properties["uid"] = cot.uid
    position = body.get("position")
    return _features(position, _fix_errors(body) if position is not None else None, properties)


def fix_geojson(body: dict, options=()) -> dict:
    """A fix as a GeoJSON FeatureCollection (RFC 7946: longitude, latitude, altitude)."""
    return {"type": "FeatureCollection", "features": fix_features(body, options)}


def batch_geojson(results: list[dict], problems: list) -> dict:
    """One FeatureCollection of a batch's solved fixes; each Feature's properties carry its ``index``.

    ``problems`` are the request's problem dicts: a solved one has passed its schema, so its
    ``observed_at`` and ``cot`` are read as they were validated.
    """
    features = []
    for result in results:
        if result.get("ok"):
            for feature in fix_features(result["fix"], problem_renderings(problems[result["index"]])):
                feature["properties"] = {"index": result["index"], **feature["properties"]}
                features.append(feature)
    return {"type": "FeatureCollection", "features": features}


def problem_renderings(problem) -> Renderings:
    """The ``observed_at`` and ``cot`` options of a parsed or decoded problem (a decoded one has neither)."""
    if type(problem) is not dict or "observed_at" not in problem and "cot" not in problem:
        return Renderings()
    from service.schemas import FixRequest

    fields = FixRequest.model_fields
    observed, cot = problem.get("observed_at"), problem.get("cot")
    return Renderings((), None if observed is None else _validator(fields["observed_at"]).validate_python(observed),
                      None if cot is None else _validator(fields["cot"]).validate_python(cot))


def _validator(field):
    from pydantic import TypeAdapter

    return TypeAdapter(field.annotation)


# -- sessions -----------------------------------------------------------------------------------------------------

def _session_point(state: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """The emitter's position covariance and velocity in the ENU axes at the emitter, or None."""
    if not state["initialized"] or state["position"] is None:
        return None
    observer, emitter = state["observer"]["position"], state["position"]
    turn = geodesy.enu_to_enu_rotation(math.radians(observer["lat_deg"]), math.radians(observer["lon_deg"]),
                                       math.radians(emitter["lat_deg"]), math.radians(emitter["lon_deg"]))
    covariance = np.asarray(state["covariance_enu"], dtype=float)[:3, :3]
    return turn @ covariance @ turn.T, turn @ np.asarray(state["velocity_enu_mps"], dtype=float)


def session_uid(state: dict, cot=None) -> str:
    return cot.uid if cot is not None and cot.uid else f"{UID_PREFIX}session-{state['id']}"


def session_cot(state: dict, cot=None) -> str | None:
    """A session's current estimate as a CoT track event (one uid per session); None before it has one.

    ``time`` and ``start`` are the session's ``updated_at`` (when the estimate was made).
    """
    found = _session_point(state)
    if found is None:
        return None
    covariance, velocity = found
    start = datetime.fromisoformat(state["updated_at"].replace("Z", "+00:00"))
    course = math.degrees(math.atan2(velocity[0], velocity[1])) % 360.0
    speed = math.hypot(velocity[0], velocity[1])
    _, axes = _ellipse_enu(covariance)
    detail = (f'<track course="{_decimal(course, 2)}" speed="{_decimal(speed, 3)}"/>'
              f'<passive_locator model={quoteattr(state["model"])} version="{state["version"]}" '
              f'updates="{state["updates"]}"/>')
    return _event(session_uid(state, cot), cot.type if cot is not None else DEFAULT_TYPE, HOW_TRACK, start,
                  cot.stale_s if cot is not None else DEFAULT_STALE_S, state["position"], covariance, axes, detail,
                  getattr(cot, "callsign", None))


def session_geojson(state: dict, cot=None) -> dict:
    """A session's track point (with course and speed) and its 95 % ellipse as a FeatureCollection."""
    found = _session_point(state)
    properties = {"kind": "track", "id": state["id"], "uid": session_uid(state, cot), "model": state["model"],
                  "version": state["version"], "time": state["updated_at"]}
    if found is None:
        return {"type": "FeatureCollection", "features": []}
    covariance, velocity = found
    properties.update(course_deg=math.degrees(math.atan2(velocity[0], velocity[1])) % 360.0,
                      speed_mps=math.hypot(velocity[0], velocity[1]),
                      range_m=state["range_m"], range_sigma_m=state["range_sigma_m"])
    return {"type": "FeatureCollection", "features": _features(state["position"], covariance, properties)}
