"""Coverage maps a planner can use elsewhere, each read back by a reader of its format: the PNG's axes and
legend (Pillow), the KMZ's KML against the KML 2.2 structure (lxml) and its overlay's placement, the GeoTIFF's
georeference and values (rasterio, tifffile)."""

from __future__ import annotations

import io
import math
import pathlib
import zipfile

import numpy as np
import pytest
from lxml import etree
from PIL import Image

from service.renderings import maps
from service import schemas
from service.routes.coverage import KMZ, PNG, TIFF
from service.planning import grid_of_request
from tests.service.test_crlb_grid import _grid_across, geodetic_request, local_request

KML_SCHEMA = etree.XMLSchema(etree.parse(str(pathlib.Path(__file__).parent / "data" / "kml-2.2-subset.xsd")))
KML = {"k": maps.KML_NAMESPACE}
ACROSS = _grid_across(-17.0, 179.9, [(-16.8, 179.2), (-17.6, -179.4), (-16.2, -179.7)], 30_000.0, 5_000.0)
POLE = _grid_across(89.97, 0.0, [(89.8, 0.0), (89.8, 120.0), (89.8, -120.0)], 20_000.0, 10_000.0)
SCENES = {"mid-latitude": geodetic_request(), "antimeridian": ACROSS, "pole": POLE}


def _post(client, body: dict, accept: str) -> bytes:
    response = client.post("/v1/crlb/grid", json=body, headers={"Accept": accept})
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == accept
    return response.content


def _cells(client, body: dict) -> list[dict]:
    """Points inside each observable cell, with its CEP50 (from the GeoJSON, the scene's own numbers): near
    each corner, 0.45 of a step from the centre both ways, so that a map misplaced by a twentieth of a cell
    puts some of them in a neighbour."""
    geo = client.post("/v1/crlb/grid", json=body).json()
    problem, grid = grid_of_request(schemas.CrlbGridRequest.model_validate(body))
    corners = 0.45 * grid.step_m * np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=float)
    lat, lon, _ = problem.frame.to_geodetic(grid.cells_enu_m[:, None, :] + corners)
    out = []
    cells = (f["properties"] for f in geo["features"] if f["properties"]["kind"] == "cell")
    for properties, lats, lons in zip(cells, np.degrees(lat).tolist(), np.degrees(lon).tolist()):
        if not properties["unobservable"]:
            out += [{"cep50_m": properties["cep50_m"], "lat": y, "lon": x} for y, x in zip(lats, lons)]
    return out


def _scale(client, body: dict) -> maps.ColourScale:
    problem, grid = grid_of_request(schemas.CrlbGridRequest.model_validate(body))
    from core.coverage import coverage_map

    return maps.ColourScale.of(coverage_map(problem, grid.cells_enu_m))


def test_the_png_has_km_axes_and_a_legend_in_metres(client):
    body = {**local_request(), "image": {"width_px": 640, "height_px": 480}}  # 21 x 21 cells of 1 km
    pixels = np.asarray(Image.open(io.BytesIO(_post(client, body, PNG))).convert("RGB")).astype(int)
    axes = np.all(pixels == maps._AXES, axis=-1)
    # The plot: 21 km square, letterboxed in the area left of the legend and between the margins.
    area_w, area_h = 640 - 46 - (640 // 24 + 78), 480 - 18 - 30
    side = round(21_000 * min(area_w / 21_000, area_h / 21_000))
    left, top = 46 + (area_w - side) // 2, 18 + (area_h - side) // 2
    assert axes[top - 1, left:left + side].mean() > 0.95 and axes[top + side, left:left + side].mean() > 0.95
    per_km = side / 21.0
    for km in (-10, -5, 0, 5, 10):  # east ticks every 5 km, below the plot
        x = round(left + (km + 10.5) * per_km)
        assert axes[top + side + 1:top + side + 4, x - 1:x + 2].any(), km
        y = round(top + (10.5 - km) * per_km)  # north ticks, left of the plot
        assert axes[y - 1:y + 2, left - 4:left - 1].any(), km
    # Tick labels: text pixels under the east axis and left of the north axis.
    text = np.all(pixels == (235, 235, 235), axis=-1) | (pixels.min(axis=-1) > 150) & ~axes
    assert text[top + side + 5:top + side + 16, left:left + side].sum() > 50
    assert text[top:top + side, :left - 5].sum() > 50
    # The legend: its colour at each labelled CEP50 is that value's colour in the map.
    scale = _scale(client, body)
    bar_left = 640 - (640 // 24 + 78) + 4
    for value in scale.ticks_m():
        y = round(top + (math.log10(value) - scale.best) / (scale.worst - scale.best) * (side - 1))
        assert np.abs(pixels[y, bar_left + 3] - scale.rgb(np.array(value))).max() <= 2, value
        assert axes[y, bar_left + 640 // 24:bar_left + 640 // 24 + 4].any(), value
    # A cell's colour in the map is its CEP50's colour: the cell north 5 km, east 0.
    cell = next(c for c in client.post("/v1/crlb/grid", json=body).json()["features"]
                if c["properties"].get("east_m") == 0.0 and c["properties"].get("north_m") == 5000.0)
    x, y = round(left + 10.5 * per_km), round(top + 5.5 * per_km)
    assert np.abs(pixels[y, x] - scale.rgb(np.array(cell["properties"]["cep50_m"]))).max() <= 2


@pytest.mark.parametrize("scene", SCENES)
def test_the_kmz_is_a_kml_ground_overlay_placed_on_the_cells(client, scene):
    body = SCENES[scene]
    archive = zipfile.ZipFile(io.BytesIO(_post(client, body, KMZ)))
    assert archive.namelist()[0] == "doc.kml" and {"coverage.png", "legend.png"} <= set(archive.namelist())
    # A fixed entry time, not the clock's: the same map is the same bytes whenever it is made.
    assert {entry.date_time for entry in archive.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    document = etree.fromstring(archive.read("doc.kml"))
    KML_SCHEMA.assertValid(document)
    box = {name: float(document.find(f"k:Document/k:GroundOverlay/k:LatLonBox/k:{name}", KML).text)
           for name in ("north", "south", "east", "west")}
    href = document.find("k:Document/k:GroundOverlay/k:Icon/k:href", KML).text
    overlay = np.asarray(Image.open(io.BytesIO(archive.read(href))).convert("RGBA")).astype(int)
    height, width = overlay.shape[:2]
    assert box["north"] > box["south"]
    east = box["east"] + (360.0 if box["east"] <= box["west"] else 0.0)  # across the antimeridian: east < west
    scale = _scale(client, body)
    checked = 0
    for cell in _cells(client, body):
        lon = cell["lon"] + (360.0 if cell["lon"] < box["west"] else 0.0)
        j = (lon - box["west"]) / (east - box["west"]) * width
        i = (box["north"] - cell["lat"]) / (box["north"] - box["south"]) * height
        j, i = int(j), int(i)
        if not (0 <= i < height and 0 <= j < width):
            continue
        assert overlay[i, j, 3] == 200, (cell, i, j)
        assert np.abs(overlay[i, j, :3] - scale.rgb(np.array(cell["cep50_m"]))).max() <= 2, cell
        checked += 1
    assert checked >= 0.9 * len(_cells(client, body))
    assert overlay[..., 3].min() == 0 or scene == "pole"  # transparent outside the grid
    names = [p.text for p in document.findall("k:Document/k:Folder/k:Placemark/k:name", KML)]
    assert names == [s["id"] for s in body["stations"]]
    assert Image.open(io.BytesIO(archive.read("legend.png"))).size == (maps._LEGEND_W, maps._LEGEND_H)


@pytest.mark.parametrize("scene", SCENES)
def test_the_geotiff_is_cep50_in_wgs84_read_back_by_gdal(client, scene, tmp_path):
    rasterio = pytest.importorskip("rasterio")
    tifffile = pytest.importorskip("tifffile")
    body = SCENES[scene]
    path = tmp_path / "coverage.tif"
    path.write_bytes(_post(client, body, TIFF))
    with tifffile.TiffFile(path) as tif:
        keys = tif.geotiff_metadata
        assert int(keys["GeographicTypeGeoKey"]) == 4326 and int(keys["GTRasterTypeGeoKey"]) == 1
    with rasterio.open(path) as raster:
        assert raster.crs.to_epsg() == 4326 and raster.count == 1 and raster.dtypes == ("float32",)
        assert math.isnan(raster.nodata)
        values = raster.read(1)
        assert max(raster.width, raster.height) == max(body.get("image", {}).get("width_px", 640),
                                                         body.get("image", {}).get("height_px", 480))
        checked = 0
        for cell in _cells(client, body):
            lon = cell["lon"] + (360.0 if cell["lon"] < raster.bounds.left else 0.0)
            i, j = raster.index(lon, cell["lat"])
            if 0 <= i < raster.height and 0 <= j < raster.width:
                assert values[i, j] == pytest.approx(cell["cep50_m"], rel=1e-6), cell
                checked += 1
        assert checked >= 0.9 * len(_cells(client, body))
        assert np.isnan(values).any() or scene == "pole"  # outside the grid


def test_a_flat_frame_has_no_georeferenced_map(client):
    for accept in (KMZ, TIFF):
        response = client.post("/v1/crlb/grid", json=local_request(), headers={"Accept": accept})
        assert response.status_code == 406 and response.json()["code"] == "not_acceptable", response.text
    response = client.post("/v1/crlb/grid/map", params={"format": "kmz"}, json=local_request())
    assert response.status_code == 422 and response.json()["errors"][0]["loc"] == ["format"]
    assert client.post("/v1/crlb/grid/map", json=local_request()).status_code == 200  # a PNG needs no place


def test_an_accept_the_map_cannot_meet_is_406(client):
    response = client.post("/v1/crlb/grid", json=local_request(),
                           headers={"Accept": "application/vnd.google-earth.kml+xml"})
    assert response.status_code == 406 and response.headers["content-type"].startswith("application/problem+json")


@pytest.mark.parametrize("format, accept, name", [("png", PNG, "coverage.png"), ("kmz", KMZ, "coverage.kmz"),
                                                  ("tiff", TIFF, "coverage.tif")])
def test_the_download_is_the_same_file(client, format, accept, name):
    body = geodetic_request()
    response = client.post("/v1/crlb/grid/map", params={"format": format}, json=body)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/octet-stream"
    assert response.headers["content-disposition"] == f'attachment; filename="{name}"'
    assert response.content == _post(client, body, accept)
