"""POST /v1/crlb/grid: coverage maps as GeoJSON and PNG, priced, and invalid grids refused with field paths."""

from __future__ import annotations

import struct
import zlib

import geojson
import numpy as np
import pytest

from service import schemas
from service.web.headers import parse_accept
from service.routes.coverage import negotiate as negotiate_ranges

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def local_request(step_m=1000.0, half_width_m=10_000.0, **grid) -> dict:
    """Two azimuth-only stations 10 km apart on the east axis, surface targets."""
    return {
        "frame": "local",
        "stations": [{"id": "a", "position": {"east_m": -5000.0, "north_m": 0.0}},
                     {"id": "b", "position": {"east_m": 5000.0, "north_m": 0.0}}],
        "sensors": [{"station_id": s, "elevation": False, "sigma_azimuth_deg": 1.0} for s in ("a", "b")],
        "constraints": {"altitude_m": 0.0},
        "grid": {"centre": {"east_m": 0.0, "north_m": 0.0}, "half_width_m": half_width_m, "step_m": step_m,
                 **grid},
    }


def geodetic_request() -> dict:
    return {
        "frame": "wgs84",
        "stations": [{"id": "rx-1", "position": {"lat_deg": 34.0, "lon_deg": 108.0, "alt_m": 100.0}},
                     {"id": "rx-2", "position": {"lat_deg": 34.0, "lon_deg": 108.6, "alt_m": 100.0}}],
        "sensors": [{"station_id": s, "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5}
                    for s in ("rx-1", "rx-2")],
        "grid": {"centre": {"lat_deg": 34.3, "lon_deg": 108.3}, "half_width_m": 30_000.0, "step_m": 10_000.0,
                 "altitude_m": 8000.0},
    }


def cells(body: dict) -> list[dict]:
    return [f["properties"] for f in body["features"] if f["properties"]["kind"] == "cell"]


def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == PNG_SIGNATURE
    length, kind = struct.unpack(">I4s", data[8:16])
    assert kind == b"IHDR" and length == 13
    assert zlib.crc32(data[12:29]) == struct.unpack(">I", data[29:33])[0]
    return struct.unpack(">II", data[16:24])


def test_local_map_cells_and_acceptance(client):
    response = client.post("/v1/crlb/grid", json=local_request())
    assert response.status_code == 200, response.text
    body = response.json()
    schemas.CrlbGridResponse.model_validate(body)
    assert body["grid"]["rows"] == body["grid"]["columns"] == 21
    grid = {(c["row"], c["column"]): c for c in cells(body)}
    assert len(grid) == 21 * 21
    # the cells at the stations: unobservable, their bound null
    for e in (-5000.0, 5000.0):
        at = next(c for c in grid.values() if c["east_m"] == e and c["north_m"] == 0.0)
        assert at["unobservable"] and at["cep50_m"] is None and at["gdop"] is None
    # broadside (east 0) is the best of its row, from half a baseline out
    for row in range(21):
        north = grid[(row, 0)]["north_m"]
        if abs(north) < 5000.0:
            continue
        centre = grid[(row, 10)]
        assert centre["east_m"] == 0.0
        others = [grid[(row, k)]["cep50_m"] for k in range(21) if k != 10]
        assert centre["cep50_m"] < min(others), north
    square = grid[(15, 10)]  # north 5 km: the lines of sight cross at 90 degrees
    assert square["gdop"] == pytest.approx(np.sqrt(2.0), rel=1e-9)
    assert square["sigma_ref_m"] == pytest.approx(np.radians(1.0) * np.hypot(5000.0, 5000.0), rel=1e-9)
    stations = [f for f in body["features"] if f["properties"]["kind"] == "station"]
    assert [f["properties"]["id"] for f in stations] == ["a", "b"]
    assert all(f["geometry"] is None for f in body["features"])  # a flat local frame has no place on earth


def test_geodetic_map_is_valid_geojson(client):
    response = client.post("/v1/crlb/grid", json=geodetic_request())
    assert response.status_code == 200, response.text
    body = response.json()
    schemas.CrlbGridResponse.model_validate(body)
    collection = geojson.loads(response.text)
    assert collection.is_valid, collection.errors()
    polygons = [f for f in body["features"] if f["geometry"]["type"] == "Polygon"]
    assert len(polygons) == 49
    ring = polygons[24]["geometry"]["coordinates"][0]
    assert ring[0] == ring[-1] and len(ring) == 5
    lon, lat = np.mean(np.array(ring[:4]), axis=0)
    # the corners lie in the frame's tangent plane 5 km from the centre: their mean is within metres of it
    assert (lon, lat) == pytest.approx((108.3, 34.3), abs=1e-4)  # 11 m
    # counter-clockwise (RFC 7946): positive shoelace area
    x, y = np.array(ring).T
    assert np.sum(x[:-1] * y[1:] - x[1:] * y[:-1]) > 0
    assert body["grid"]["altitude_m"] == pytest.approx(8000.0, abs=1e-3)
    assert all(not c["unobservable"] and c["gdop"] > 1.0 for c in cells(body))


@pytest.mark.parametrize("size", [(320, 200), (17, 16), (640, 480)])
def test_png_is_valid_and_of_the_requested_size(client, size):
    request = {**local_request(), "image": {"width_px": size[0], "height_px": size[1]}}
    response = client.post("/v1/crlb/grid", json=request, headers={"Accept": "image/png"})
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/png"
    assert png_size(response.content) == size
    from PIL import Image
    import io
    image = Image.open(io.BytesIO(response.content))
    image.load()
    assert image.size == size and image.mode == "RGB"
    assert len(set(map(tuple, np.asarray(image).reshape(-1, 3).tolist()))) > 8  # a heat map, not a blank


def test_png_marks_the_stations(client):
    request = {**local_request(step_m=500.0), "image": {"width_px": 400, "height_px": 400}}
    response = client.post("/v1/crlb/grid", json=request, headers={"Accept": "image/png"})
    from PIL import Image
    import io
    pixels = np.asarray(Image.open(io.BytesIO(response.content)))
    # the map is square: a 400-pixel-high plot of 21 cells (10.5 km each side); station a at east -5 km
    white = np.all(pixels > 250, axis=-1)
    assert white.sum() > 10
    ys, xs = np.nonzero(white[:, :300])
    assert abs(np.median(ys) - 200) < 20


def test_over_the_grid_cost_is_422_naming_the_limit(make_client):
    client = make_client(max_grid_cost=1000)
    response = client.post("/v1/crlb/grid", json=local_request(step_m=500.0))
    assert response.status_code == 422
    body = response.json()
    assert body["code"] == "over_limit" and "max_grid_cost" in body["detail"]
    assert body["errors"][0]["loc"] == ["grid", "step_m"]
    assert client.post("/v1/crlb/grid", json=local_request(step_m=5000.0)).status_code == 200


@pytest.mark.parametrize("grid, loc", [
    ({"step_m": 0.0}, ["grid", "step_m"]),
    ({"step_m": -10.0}, ["grid", "step_m"]),
    ({"half_width_m": 0.0}, ["grid", "half_width_m"]),
    ({"altitude_m": 100.0}, ["grid", "altitude_m"]),  # differs from constraints.altitude_m
])
def test_bad_grid_is_422_with_the_field_path(client, grid, loc):
    request = local_request()
    request["grid"].update(grid)
    response = client.post("/v1/crlb/grid", json=request)
    assert response.status_code == 422, response.text
    assert any(e["loc"][:len(loc)] == loc for e in response.json()["errors"]), response.json()


def test_geodetic_centre_needs_a_geodetic_frame(client):
    request = local_request()
    request["grid"]["centre"] = {"lat_deg": 34.0, "lon_deg": 108.0}
    response = client.post("/v1/crlb/grid", json=request)
    assert response.status_code == 422
    assert response.json()["errors"][0]["loc"] == ["grid", "centre"]


def negotiate(accept: str | None):
    """The negotiation of an ``Accept`` value as the middleware parses it (absent: None)."""
    return negotiate_ranges(parse_accept(accept.encode()) if accept is not None else ())


def test_accept_negotiation():
    json_, png, kmz, tiff = "application/json", "image/png", "application/vnd.google-earth.kmz", "image/tiff"
    assert negotiate(None) == negotiate("") == negotiate("*/*") == negotiate("application/json") == json_
    assert negotiate("application/geo+json") == json_
    assert negotiate("image/png") == negotiate("image/png, application/json") == png
    assert negotiate("application/json, image/png") == json_
    assert negotiate("application/json;q=0.5, image/png") == png and negotiate("image/png;q=0") is None
    assert negotiate("application/vnd.google-earth.kmz") == kmz and negotiate("image/tiff;q=0.9, */*;q=0.1") == tiff
    assert negotiate("image/*") == png and negotiate("image/*, image/png;q=0") == tiff
    assert negotiate("text/html, */*;q=0.8") == json_  # a browser
    assert negotiate("application/vnd.google-earth.kml+xml") is None and negotiate("text/html") is None


def test_openapi_declares_the_renderings(client):
    spec = client.get("/openapi.json").json()
    content = spec["paths"]["/v1/crlb/grid"]["post"]["responses"]["200"]["content"]
    for media_type in ("image/png", "application/vnd.google-earth.kmz", "image/tiff"):
        assert content[media_type]["schema"] == {"type": "string", "format": "binary"}
    assert next(iter(sorted(content))) == "application/json"  # what a generated client parses
    download = spec["paths"]["/v1/crlb/grid/map"]["post"]
    assert download["responses"]["200"]["content"] == {
        "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}
    assert download["parameters"][0]["schema"]["enum"] == ["png", "kmz", "tiff"]


def test_fix_and_crlb_gdop_is_dimensionless_and_sqrt_trace_keeps_the_metres(client):
    """Lines of sight crossing at 90 degrees, 7.07 km each, 1 degree: GDOP sqrt(2), sqrt(trace) 1.75 km."""
    scene = local_request()
    crlb = client.post("/v1/crlb", json={**{k: scene[k] for k in ("frame", "stations", "sensors", "constraints")},
                                         "target": {"east_m": 0.0, "north_m": 5000.0}})
    assert crlb.status_code == 200, crlb.text
    sigma_m = np.radians(1.0) * np.hypot(5000.0, 5000.0)
    fix = client.post("/v1/fixes", json={
        "frame": "local", "stations": scene["stations"], "constraints": {"altitude_m": 0.0}, "method": "ml",
        "measurements": [{"type": "bearing", "station_id": "a", "azimuth_deg": 45.0, "sigma_azimuth_deg": 1.0},
                         {"type": "bearing", "station_id": "b", "azimuth_deg": 315.0, "sigma_azimuth_deg": 1.0}]})
    assert fix.status_code == 200, fix.text
    for error in (crlb.json()["error"], fix.json()["error"]):
        assert error["gdop"] == pytest.approx(np.sqrt(2.0), rel=1e-6)
        assert error["sqrt_trace_m"] == pytest.approx(np.sqrt(2.0) * sigma_m, rel=1e-6)


def test_on_a_dask_scheduler_the_map_is_the_same_bytes(make_client):
    distributed = pytest.importorskip("distributed")
    request = local_request(step_m=500.0)  # 1,681 cells: two chunks
    here = make_client().post("/v1/crlb/grid", json=request)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        there = make_client(dask_scheduler=cluster.scheduler_address).post("/v1/crlb/grid", json=request)
    assert here.status_code == there.status_code == 200, there.text
    assert here.content == there.content


def test_past_the_deadline_is_503(make_client):
    client = make_client(request_deadline_s=1e-6)
    response = client.post("/v1/crlb/grid", json=local_request(step_m=100.0))  # 40,401 cells, 40 chunks
    assert response.status_code == 503, response.text
    assert response.json()["code"] == "deadline_exceeded" and "coverage map" in response.json()["detail"]


def _grid_across(centre_lat: float, centre_lon: float, stations: list[tuple[float, float]], half_width_m: float,
                 step_m: float) -> dict:
    ids = [f"rx-{k}" for k in range(len(stations))]
    return {
        "frame": "wgs84",
        "stations": [{"id": i, "position": {"lat_deg": lat, "lon_deg": lon, "alt_m": 0.0}}
                     for i, (lat, lon) in zip(ids, stations)],
        "sensors": [{"station_id": i, "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5} for i in ids],
        "grid": {"centre": {"lat_deg": centre_lat, "lon_deg": centre_lon}, "half_width_m": half_width_m,
                 "step_m": step_m, "altitude_m": 8000.0},
    }


def _rings(geometry: dict) -> list:
    parts = geometry["coordinates"] if geometry["type"] == "MultiPolygon" else [geometry["coordinates"]]
    return [ring for part in parts for ring in part]


@pytest.mark.parametrize("centre_lon", [179.9, -179.9, 180.0])
def test_a_map_across_the_antimeridian_is_cut_there(client, centre_lon):
    """RFC 7946 section 3.1.9: longitudes within [-180, 180], a geometry crossing the antimeridian cut in two."""
    from shapely.geometry import LinearRing, Polygon, shape

    request = _grid_across(-17.0, centre_lon, [(-16.8, 179.2), (-17.6, -179.4), (-16.2, -179.7)], 30_000.0, 5_000.0)
    response = client.post("/v1/crlb/grid", json=request)
    assert response.status_code == 200, response.text
    collection = geojson.loads(response.text)
    assert collection.is_valid, collection.errors()
    body = response.json()
    schemas.CrlbGridResponse.model_validate(body)
    cut = 0
    for feature in body["features"]:
        geometry = feature["geometry"]
        assert geometry is not None
        if geometry["type"] == "Point":
            assert -180.0 <= geometry["coordinates"][0] <= 180.0
            continue
        rings = _rings(geometry)
        for ring in rings:
            assert ring[0] == ring[-1] and LinearRing(ring).is_ccw
            assert all(-180.0 <= lon <= 180.0 for lon, _ in ring)
        assert shape(geometry).is_valid
        if geometry["type"] == "MultiPolygon":
            cut += 1
            west, east = sorted((np.array(ring) for ring in rings), key=lambda ring: -ring[:, 0].mean())
            assert west[:, 0].max() == pytest.approx(180.0) and east[:, 0].min() == pytest.approx(-180.0)
            # the two sides are the whole cell: together, their area is the area of the cell drawn in one piece
            whole = Polygon(np.vstack([west[:-1], east[:-1] + [360.0, 0.0]])).convex_hull
            assert Polygon(west).area + Polygon(east).area == pytest.approx(whole.area, rel=1e-9)
    assert cut == body["grid"]["rows"]  # one column of cells straddles the antimeridian


def test_a_map_around_a_pole_draws_every_cell_but_the_one_on_the_pole(client):
    from shapely.geometry import shape

    request = _grid_across(89.97, 0.0, [(89.8, 0.0), (89.8, 120.0), (89.8, -120.0)], 20_000.0, 10_000.0)
    response = client.post("/v1/crlb/grid", json=request)
    assert response.status_code == 200, response.text
    assert geojson.loads(response.text).is_valid
    body = response.json()
    cell_features = [f for f in body["features"] if f["properties"]["kind"] == "cell"]
    empty = [f["properties"] for f in cell_features if f["geometry"] is None]
    # the pole is 3.3 km north of the centre cell, inside it (cells are 10 km squares)
    assert [(c["row"], c["column"]) for c in empty] == [(2, 2)]
    for feature in cell_features:
        if feature["geometry"] is not None:
            assert shape(feature["geometry"]).is_valid
            assert all(-180.0 <= lon <= 180.0 and -90.0 <= lat <= 90.0
                       for ring in _rings(feature["geometry"]) for lon, lat in ring)
