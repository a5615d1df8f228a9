"""CoT 2.0 and GeoJSON renderings of fixes and batches (service/renderings/points.py).

CoT events are validated against the CoT 2.0 event schema kept in tests/service/data; ce and le are checked
against the fix's own covariance turned into the ENU axes at the fix; GeoJSON is checked with the geojson
package and shapely, and the ellipse's vertices are mapped back into the fix's tangent plane to measure it.
"""

from __future__ import annotations

import math
import pathlib
from datetime import datetime, timedelta

import geojson
import numpy as np
import pytest
from lxml import etree
from shapely.geometry import LinearRing, shape

from core import geodesy
from core.error_summary import CHI2_2DOF_95
from service import schemas
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request
from tests.service.test_fixes_api import assert_problem

SCHEMA = etree.XMLSchema(etree.parse(str(pathlib.Path(__file__).parent / "data" / "cot-event-2.0.xsd")))


def cot_event(text: str) -> etree._Element:
    """Parse and validate one CoT event against the CoT 2.0 schema (raises with the schema's reason)."""
    event = etree.fromstring(text.encode())
    SCHEMA.assertValid(event)
    return event


def _time(value: str) -> datetime:
    return datetime.fromisoformat(value.replace("Z", "+00:00"))


def _fix(client, **extra) -> dict:
    response = client.post("/v1/fixes", json=bearing_request(STATIONS_300KM, TARGET, **extra))
    assert response.status_code == 200, response.text
    schemas.FixResponse.model_validate(response.json())
    return response.json()


def _covariance_at_fix(fix: dict) -> np.ndarray:
    lat, lon = math.radians(fix["position"]["lat_deg"]), math.radians(fix["position"]["lon_deg"])
    rotation = geodesy.ecef_to_enu_rotation(lat, lon)
    return rotation @ np.array(fix["covariance_ecef_m2"]) @ rotation.T


def test_schema_rejects_the_old_event():
    old = ('<event version="2.0" uid="passive-locator-fix" type="a-u-G" how="m-g">'
           '<point lat="35.0" lon="110.0" hae="0.0" ce="1.0" le="1.0"/></event>')
    with pytest.raises(etree.DocumentInvalid):
        cot_event(old)


def test_cot_is_valid_with_one_sigma_errors(client):
    fix = _fix(client, formats=["cot"])
    event = cot_event(fix["cot"])
    assert event.get("version") == "2.0" and event.get("type") == "a-u-G" and event.get("how") == "m-f"
    point = event.find("point")
    assert float(point.get("lat")) == pytest.approx(fix["position"]["lat_deg"], abs=1e-8)
    assert float(point.get("lon")) == pytest.approx(fix["position"]["lon_deg"], abs=1e-8)
    covariance = _covariance_at_fix(fix)
    horizontal = np.linalg.eigvalsh(covariance[:2, :2])
    assert float(point.get("ce")) == pytest.approx(math.sqrt(horizontal.sum() / 2), abs=0.006)
    assert float(point.get("le")) == pytest.approx(math.sqrt(covariance[2, 2]), abs=0.006)
    ellipse = event.find("detail/shape/ellipse")
    assert float(ellipse.get("major")) == pytest.approx(math.sqrt(CHI2_2DOF_95 * horizontal[1]), abs=0.006)
    assert float(ellipse.get("minor")) == pytest.approx(math.sqrt(CHI2_2DOF_95 * horizontal[0]), abs=0.006)
    assert event.find("detail/passive_locator").get("method") == "ml"
    start, stale = _time(event.get("start")), _time(event.get("stale"))
    assert stale - start == timedelta(seconds=300)
    assert abs((datetime.now(start.tzinfo) - start).total_seconds()) < 60


def test_ce_on_a_7_to_1_ellipse_is_the_rms_of_the_axis_sigmas():
    from service.renderings.points import one_sigma_errors

    ce, le = one_sigma_errors(np.diag([49.0, 1.0, 4.0]))  # sigmas 7 m and 1 m horizontally, 2 m up
    assert (ce, le) == (pytest.approx(5.0), pytest.approx(2.0))
    rotated = np.array([[25.0, 24.0, 0.0], [24.0, 25.0, 0.0], [0.0, 0.0, 4.0]])  # the same ellipse at 45 degrees
    assert one_sigma_errors(rotated) == (pytest.approx(5.0), pytest.approx(2.0))


def test_cot_ce_holds_the_one_sigma_share_not_ninety_percent(client):
    """The circle of radius ce holds about the 2-D one-sigma share (39 % for a circular error), not 90 %."""
    fix = _fix(client, formats=["cot"])
    rng = np.random.default_rng(3)
    covariance = _covariance_at_fix(fix)[:2, :2]
    ce = float(cot_event(fix["cot"]).find("point").get("ce"))
    samples = rng.multivariate_normal(np.zeros(2), covariance, size=20000)
    inside = np.mean(np.hypot(samples[:, 0], samples[:, 1]) <= ce)
    # For a circular Gaussian the 1-sigma CE circle holds 1 - exp(-1/2) = 39.3 %; elongation lowers it a little.
    assert 0.30 < inside < 0.42


def test_cot_uid_type_stale_and_observed_at_from_the_request(client):
    fix = _fix(client, formats=["cot"], observed_at="2026-03-04T05:06:07.25+02:00",
               cot={"uid": "emitter-17", "type": "a-h-G", "stale_s": 90})
    event = cot_event(fix["cot"])
    assert (event.get("uid"), event.get("type")) == ("emitter-17", "a-h-G")
    assert event.get("start") == event.get("time") == "2026-03-04T03:06:07.250Z"
    assert _time(event.get("stale")) - _time(event.get("start")) == timedelta(seconds=90)


def test_two_fixes_without_uid_get_different_uids(client):
    first, second = (cot_event(_fix(client, formats=["cot"])["cot"]).get("uid") for _ in range(2))
    assert first != second


@pytest.mark.parametrize("field, value", [("observed_at", "2026-03-04T05:06:07"), ("observed_at", "yesterday"),
                                          ("cot", {"type": "a u G"}), ("cot", {"uid": "has space"}),
                                          ("cot", {"stale_s": 0})])
def test_bad_rendering_options_are_422_with_their_path(client, field, value):
    body = bearing_request(STATIONS_300KM, TARGET, formats=["cot"], **{field: value})
    problem = assert_problem(client.post("/v1/fixes", json=body), 422)
    assert problem["errors"][0]["loc"][0] == field


@pytest.mark.parametrize("observed_at", ["9999-12-31T23:59:59Z", "9999-12-23T00:00:00.001Z",
                                         "0001-01-01T00:00:00+14:00", "0001-01-01T23:59:59Z"])
def test_an_observed_at_whose_stale_time_is_past_year_9999_or_before_year_1_is_a_422_not_a_500(client, observed_at):
    """A week of stale time after 9999-12-31 (or a +14:00 offset before 0001-01-01 UTC) is no datetime: the
    request is at fault, so every fix route answers 422, never 500."""
    body = bearing_request(STATIONS_300KM, TARGET, formats=["cot", "geojson"], observed_at=observed_at,
                           cot={"stale_s": 7 * 86400.0})
    problem = assert_problem(client.post("/v1/fixes", json=body), 422)
    assert problem["errors"][0]["loc"] == ["observed_at"]
    slot = client.post("/v1/fixes/batch", json={"problems": [body]}).json()["results"][0]
    assert not slot["ok"] and slot["error"]["status"] == 422


@pytest.mark.parametrize("observed_at", ["9999-12-22T23:59:59+00:00", "0001-01-02T00:00:00Z"])
def test_the_first_and_last_observed_at_render(client, observed_at):
    fix = _fix(client, formats=["cot", "geojson"], observed_at=observed_at, cot={"stale_s": 7 * 86400.0})
    event = cot_event(fix["cot"])
    assert _time(event.get("stale")) - _time(event.get("start")) == timedelta(days=7)


def _ring_enu(ring, fix) -> np.ndarray:
    p = fix["position"]
    lon, lat = np.radians(np.array(ring)[:, 0]), np.radians(np.array(ring)[:, 1])
    return geodesy.geodetic_to_enu(lat, lon, np.full(lat.shape, p["alt_m"]), math.radians(p["lat_deg"]),
                                   math.radians(p["lon_deg"]), p["alt_m"])


def _check_collection(collection: dict) -> tuple[dict, dict]:
    assert geojson.loads(geojson.dumps(collection)).is_valid
    point, ellipse = collection["features"]
    assert point["geometry"]["type"] == "Point" and point["properties"]["kind"] == "fix"
    assert ellipse["properties"]["kind"] == "error_ellipse"
    polygons = ([ellipse["geometry"]["coordinates"]] if ellipse["geometry"]["type"] == "Polygon"
                else ellipse["geometry"]["coordinates"])
    for rings in polygons:
        ring = rings[0]
        assert ring[0] == ring[-1]
        assert LinearRing(ring).is_ccw
        assert all(-180.0 <= x <= 180.0 for x, _ in ring)
        assert shape({"type": "Polygon", "coordinates": rings}).is_valid
    return point, ellipse


def test_geojson_point_and_95_ellipse(client):
    fix = _fix(client, formats=["geojson"], observed_at="2026-03-04T05:06:07Z")
    point, ellipse = _check_collection(fix["geojson"])
    assert point["geometry"]["coordinates"][:2] == pytest.approx([TARGET["lon_deg"], TARGET["lat_deg"]])
    assert point["properties"]["method"] == "ml" and point["properties"]["time"] == "2026-03-04T05:06:07.000Z"
    assert point["properties"]["ellipse95"] == fix["error"]["ellipse95"]
    ring = ellipse["geometry"]["coordinates"][0]
    assert len(ring) >= 65
    enu = _ring_enu(ring, fix)
    assert np.all(np.abs(enu[:, 2]) < 10.0)  # the tangent plane at the fix, 7 km out
    radii = np.hypot(enu[:, 0], enu[:, 1])
    e95 = fix["error"]["ellipse95"]
    assert radii.max() == pytest.approx(e95["semi_major_m"], rel=0.01)
    assert radii.min() == pytest.approx(e95["semi_minor_m"], rel=0.01)
    # Every vertex is on the 95 % ellipse of the covariance at the fix.
    inverse = np.linalg.inv(_covariance_at_fix(fix)[:2, :2])
    mahalanobis = np.einsum("ni,ij,nj->n", enu[:, :2], inverse, enu[:, :2])
    assert np.allclose(mahalanobis, CHI2_2DOF_95, rtol=1e-4)


ACROSS = {"rx-1": {"lat_deg": -16.8, "lon_deg": 179.2, "alt_m": 0.0},
          "rx-2": {"lat_deg": -17.6, "lon_deg": -179.4, "alt_m": 0.0},
          "rx-3": {"lat_deg": -16.2, "lon_deg": -179.7, "alt_m": 0.0}}
TARGET_ACROSS = {"lat_deg": -17.0, "lon_deg": 179.999, "alt_m": 0.0}


def test_geojson_ellipse_across_the_antimeridian(client):
    body = bearing_request(ACROSS, TARGET_ACROSS, sigma_deg=0.5, formats=["geojson", "cot"])
    response = client.post("/v1/fixes", json=body)
    assert response.status_code == 200, response.text
    fix = response.json()
    cot_event(fix["cot"])
    point, ellipse = _check_collection(fix["geojson"])
    assert ellipse["geometry"]["type"] == "MultiPolygon"
    west, east = (np.array(part[0]) for part in ellipse["geometry"]["coordinates"])
    assert west[:, 0].max() == pytest.approx(180.0) and east[:, 0].min() == pytest.approx(-180.0)
    # Both parts together are the ellipse: every vertex off the cut lies on it, in the fix's plane.
    inverse = np.linalg.inv(_covariance_at_fix(fix)[:2, :2])
    for part in (west, east):
        off_cut = part[np.abs(np.abs(part[:, 0]) - 180.0) > 1e-9]
        enu = _ring_enu(off_cut, fix)
        assert np.allclose(np.einsum("ni,ij,nj->n", enu[:, :2], inverse, enu[:, :2]), CHI2_2DOF_95, rtol=1e-4)
    assert len(west) + len(east) >= 64


def test_local_frame_has_no_place_on_earth(client):
    body = {"frame": "local",
            "stations": [{"id": "a", "position": {"east_m": 0.0, "north_m": 0.0}},
                         {"id": "b", "position": {"east_m": 10000.0, "north_m": 0.0}}],
            "measurements": [{"type": "bearing", "station_id": "a", "azimuth_deg": 45.0, "sigma_azimuth_deg": 1.0},
                             {"type": "bearing", "station_id": "b", "azimuth_deg": 315.0, "sigma_azimuth_deg": 1.0}],
            "constraints": {"altitude_m": 0.0}, "formats": ["geojson", "cot"]}
    response = client.post("/v1/fixes", json=body)
    assert response.status_code == 200, response.text
    fix = response.json()
    assert fix["cot"] is None
    assert fix["geojson"]["features"][0]["geometry"] is None
    assert geojson.loads(geojson.dumps(fix["geojson"])).is_valid


def test_batch_formats_give_one_feature_collection(client):
    problems = [bearing_request(STATIONS_300KM, TARGET), {"stations": []},
                bearing_request(STATIONS_300KM, TARGET, cot={"uid": "e-2"}, observed_at="2026-01-01T00:00:00Z")]
    response = client.post("/v1/fixes/batch", json={"problems": problems, "formats": ["geojson"]})
    assert response.status_code == 200, response.text
    body = response.json()
    schemas.BatchResponse.model_validate(body)
    collection = body["geojson"]
    assert geojson.loads(geojson.dumps(collection)).is_valid
    assert [f["properties"]["index"] for f in collection["features"]] == [0, 0, 2, 2]
    assert collection["features"][2]["properties"]["time"] == "2026-01-01T00:00:00.000Z"
    assert "geojson" not in client.post("/v1/fixes/batch", json={"problems": problems}).json()


def test_batch_slot_with_cot_options_renders_them(client):
    problems = [bearing_request(STATIONS_300KM, TARGET, formats=["cot"], cot={"uid": "e-9", "stale_s": 10})]
    result = client.post("/v1/fixes/batch", json={"problems": problems}).json()["results"][0]
    event = cot_event(result["fix"]["cot"])
    assert event.get("uid") == "e-9"
    assert _time(event.get("stale")) - _time(event.get("start")) == timedelta(seconds=10)


def _callsign(cot: str) -> str:
    contacts = cot_event(cot).findall("detail/contact")
    assert len(contacts) == 1
    return contacts[0].get("callsign")


@pytest.mark.parametrize("cot, expected", [({"uid": "emitter-17"}, "emitter-17"),
                                           ({"uid": "emitter-17", "callsign": "Radar 7 <Alpha & \"Bravo\">"},
                                            "Radar 7 <Alpha & \"Bravo\">"),
                                           ({"callsign": "Ωmega-1"}, "Ωmega-1")])
def test_cot_carries_a_contact_callsign_default_the_uid(client, cot, expected):
    fix = _fix(client, formats=["cot"], cot=cot)
    assert _callsign(fix["cot"]) == expected
    batch = client.post("/v1/fixes/batch", json={"problems": [bearing_request(STATIONS_300KM, TARGET, cot=cot,
                                                                                 formats=["cot"])]}).json()
    assert _callsign(batch["results"][0]["fix"]["cot"]) == expected


def test_a_fix_without_cot_options_is_labelled_with_its_generated_uid(client):
    event = cot_event(_fix(client, formats=["cot"])["cot"])
    assert event.find("detail/contact").get("callsign") == event.get("uid")


@pytest.mark.parametrize("callsign", ["", "tab\there", "x" * 65, "nul\u0000", "c1\u0085", "\uffff"])
def test_a_callsign_xml_cannot_carry_is_422_with_its_path(client, callsign):
    body = bearing_request(STATIONS_300KM, TARGET, formats=["cot"], cot={"callsign": callsign})
    problem = assert_problem(client.post("/v1/fixes", json=body), 422)
    assert problem["errors"][0]["loc"][:2] == ["cot", "callsign"]
