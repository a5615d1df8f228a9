"""Coverage maps as GeoJSON, a PNG heat map, a KMZ and a GeoTIFF (the one place each is built: route and CLI).

All take what :mod:`core.coverage` gives (the planning problem, its
:class:`~core.coverage.Grid` and the :class:`~core.coverage.Coverage` of its cells).

- GeoJSON (RFC 7946): one Polygon feature per cell, the square of side
  ``step_m`` around the cell centre in the common frame converted to WGS84
  corner by corner (null geometry in a flat local frame), then one Point per
  station. Longitudes are within [-180, 180]: a cell across the antimeridian
  is cut there into a MultiPolygon, and the cell around a pole, which no ring
  of longitudes and latitudes can draw, has a null geometry
  (:func:`service.renderings.points.polygon_geometries`, as for the fixes' ellipses).
- PNG: ``log10(CEP50)`` in the viridis colour map, small (good) bright, over
  at most :data:`DECADES` decades above the best cell (worse cells saturate),
  unobservable cells grey (:class:`ColourScale`); the square grid keeps its
  aspect ratio in the requested picture (letterboxed), with east and north
  axes in kilometres of the common frame, a colour bar labelled in metres,
  and the stations as white rings with their ids.
- KMZ and GeoTIFF: the same cells resampled on a latitude/longitude box
  (:func:`lat_lon_raster`), so a TAK client, Google Earth or a GIS places
  them: a KML GroundOverlay of the colours (with the legend and stations), or
  a float32 band of CEP50 in metres with GeoTIFF keys for WGS84.

Everything is drawn and written with Pillow, a runtime dependency already
(matplotlib is not: it is the ``reports`` extra), which sets the picture's
size in pixels exactly and writes TIFF tags. Measured side by side on a
loaded two-core machine, 201 x 201 cells to 640 x 480: Pillow 132 ms, a
matplotlib (Agg) imshow with a colour bar 477 ms; a process importing numpy
and Pillow 0.6-1.5 s (numpy alone 1.0-1.5 s), numpy and matplotlib.pyplot
5.2-8.7 s.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from xml.sax.saxutils import escape

import numpy as np

from core.coverage import Coverage, Grid
from core.problem.frame import Problem
from service.renderings.points import polygon_geometries

#: The PNG's colour scale spans at most this many decades of CEP50 above the best cell.
DECADES = 3.0
#: viridis at 0, 1/8, ..., 1 (matplotlib's table), interpolated linearly.
_VIRIDIS = np.array([[68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
                     [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]], dtype=float)
_UNOBSERVABLE = (128, 128, 128)
_BACKGROUND = (24, 24, 24)
_TEXT = (235, 235, 235)
_AXES = (200, 200, 200)


def _float_or_none(values: np.ndarray) -> list:
    return [v if v == v else None for v in values.tolist()]


def coverage_geojson(problem: Problem, grid: Grid, coverage: Coverage) -> dict:
    """The coverage map as a GeoJSON FeatureCollection (the ``CrlbGridResponse`` schema).

    Parameters
    ----------
    problem : core.problem.frame.Problem
        The planning problem (its frame and stations).
    grid : core.coverage.Grid
    coverage : core.coverage.Coverage
        Of ``grid.cells_enu_m``, in order.

    Returns
    -------
    dict
    """
    cells = grid.cells_enu_m
    rows, columns = grid.shape
    index = np.arange(cells.shape[0])
    frame = problem.frame
    geometries: list = [None] * cells.shape[0]
    if frame.is_geodetic:
        half = 0.5 * grid.step_m
        square = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])
        lat, lon, _ = frame.to_geodetic(cells[:, None, :] + square)
        _, centre_lon, _ = frame.to_geodetic(cells)
        geometries = polygon_geometries(np.degrees(lon), np.degrees(lat), np.degrees(centre_lon))
    east, north, up = cells[:, 0].tolist(), cells[:, 1].tolist(), cells[:, 2].tolist()
    row_l, column_l = (index // columns).tolist(), (index % columns).tolist()
    cep, trace = _float_or_none(coverage.cep50_m), _float_or_none(coverage.sqrt_trace_crlb_m)
    gdop = _float_or_none(coverage.gdop)
    sigma_ref = _float_or_none(np.where(coverage.observable, coverage.reference_sigma_m, np.nan))
    unobservable = (~coverage.observable).tolist()
    features = [
        {"type": "Feature",
         "geometry": geometries[k],
         "properties": {"kind": "cell", "row": row_l[k], "column": column_l[k], "east_m": east[k],
                        "north_m": north[k], "up_m": up[k], "unobservable": unobservable[k], "cep50_m": cep[k],
                        "sqrt_trace_crlb_m": trace[k], "gdop": gdop[k], "sigma_ref_m": sigma_ref[k]}}
        for k in range(cells.shape[0])
    ]
    stations = problem.stations_enu_m
    points = None
    if frame.is_geodetic:
        s_lat, s_lon, s_alt = frame.to_geodetic(stations)
        points = np.stack([np.degrees(s_lon), np.degrees(s_lat), s_alt], axis=-1).tolist()
    for k, (station_id, (e, n, u)) in enumerate(zip(problem.station_ids, stations.tolist())):
        features.append({"type": "Feature",
                         "geometry": None if points is None else {"type": "Point", "coordinates": points[k]},
                         "properties": {"kind": "station", "id": station_id, "east_m": e, "north_m": n, "up_m": u}})
    altitude = float(cells[0, 2]) if not frame.is_geodetic else float(frame.to_geodetic(cells[:1])[2][0])
    return {"type": "FeatureCollection", "features": features,
            "grid": {"rows": rows, "columns": columns, "step_m": grid.step_m, "altitude_m": altitude,
                     "east_m": [float(grid.east_m[0]), float(grid.east_m[-1])],
                     "north_m": [float(grid.north_m[0]), float(grid.north_m[-1])]}}


def _colours(fraction: np.ndarray) -> np.ndarray:
    """viridis ``(..., 3)`` uint8 at ``fraction`` in [0, 1]."""
    x = np.clip(fraction, 0.0, 1.0) * (len(_VIRIDIS) - 1)
    low = np.minimum(np.floor(x).astype(int), len(_VIRIDIS) - 2)
    t = (x - low)[..., None]
    return np.rint(_VIRIDIS[low] * (1.0 - t) + _VIRIDIS[low + 1] * t).astype(np.uint8)


def _metres(value: float) -> str:
    return f"{value / 1000.0:.3g} km" if value >= 1000.0 else f"{value:.3g} m"


@dataclass(frozen=True)
class ColourScale:
    """The colours of a map: ``log10(CEP50 / m)`` from ``best`` (bright) to ``worst`` (dark; worse saturates).

    Attributes
    ----------
    best, worst : float
        ``log10`` of the best cell's CEP50 and of the scale's far end (at most :data:`DECADES` above).
    saturated : bool
        Some cell is worse than ``worst``.
    unobservable : bool
        Some cell is unobservable (grey).
    """

    best: float
    worst: float
    saturated: bool
    unobservable: bool

    @classmethod
    def of(cls, coverage: Coverage) -> "ColourScale":
        log_cep = np.log10(coverage.cep50_m[coverage.observable])
        if log_cep.size == 0:
            return cls(0.0, 1.0, False, True)
        best, highest = float(np.min(log_cep)), float(np.max(log_cep))
        worst = min(highest, best + DECADES)
        return cls(best, worst, highest > worst, bool(np.any(~coverage.observable)))

    def rgb(self, cep50_m: np.ndarray) -> np.ndarray:
        """``(..., 3)`` uint8 colours of CEP50 values (NaN: the unobservable grey)."""
        finite = np.isfinite(cep50_m) & (cep50_m > 0)
        log_cep = np.log10(np.where(finite, cep50_m, 1.0))
        fraction = 1.0 - (log_cep - self.best) / max(self.worst - self.best, 1e-9)
        return np.where(finite[..., None], _colours(fraction), np.array(_UNOBSERVABLE, dtype=np.uint8))

    def ticks_m(self) -> list[float]:
        """CEP50 values (m) to label on the colour bar: the decades within the scale, with 2 and 5 between them
        when it spans less than two decades; never fewer than its two ends."""
        span = self.worst - self.best
        steps = (1.0,) if span >= 2.0 else (1.0, 2.0, 5.0)
        values = [m * 10.0 ** k for k in range(math.floor(self.best), math.ceil(self.worst) + 1) for m in steps]
        inside = [v for v in values if self.best - 1e-9 <= math.log10(v) <= self.worst + 1e-9]
        return inside if len(inside) >= 2 else [10.0 ** self.best, 10.0 ** self.worst]


def _nice_step(span: float, count: int = 5) -> float:
    """A 1, 2 or 5 times a power of ten step giving about ``count`` ticks over ``span`` (> 0)."""
    raw = span / count
    power = 10.0 ** math.floor(math.log10(raw))
    return next(m * power for m in (1.0, 2.0, 5.0, 10.0) if m * power >= raw)


def _tick_text(value: float, step: float) -> str:
    places = max(0, -math.floor(math.log10(step) + 1e-9))
    text = f"{value:.{places}f}"
    return "0" if float(text) == 0.0 else text


def _draw_colour_bar(image, draw, font, scale: ColourScale, left: int, top: int, width: int, height: int,
                     labelled: bool) -> None:
    """The colour bar, best (bright) at the top, on ``image`` (a PIL RGB image; ``draw`` draws on it) at
    ``(left, top)``, with its ticks in metres and its title when ``labelled``."""
    from PIL import Image

    ramp = np.repeat(_colours(np.linspace(1.0, 0.0, height))[:, None, :], width, axis=1)
    image.paste(Image.fromarray(ramp, "RGB"), (left, top))
    if not labelled:
        return
    span = max(scale.worst - scale.best, 1e-9)
    lowest = top
    for value in scale.ticks_m():
        y = top + round((math.log10(value) - scale.best) / span * (height - 1))
        draw.line([(left + width, y), (left + width + 3, y)], fill=_AXES)
        draw.text((left + width + 5, y), _metres(value), fill=_TEXT, font=font, anchor="lm")
        lowest = max(lowest, y)
    if scale.saturated and top + height - 1 - lowest >= 12:  # worse cells take the bar's last colour
        draw.text((left + width + 5, top + height - 1), ">= " + _metres(10.0 ** scale.worst), fill=_TEXT,
                  font=font, anchor="lm")
    draw.text((left, top - 3), "CEP50", fill=_TEXT, font=font, anchor="ld")


def coverage_png(problem: Problem, grid: Grid, coverage: Coverage, width_px: int, height_px: int) -> bytes:
    """A PNG heat map of ``log10(CEP50)``, exactly ``width_px`` x ``height_px``, with axes, legend and stations.

    From 320 x 160 pixels on it has east and north axes in kilometres of the scene's common frame (the
    GeoJSON cells' ``east_m`` and ``north_m``), and a colour bar labelled in metres; smaller pictures are
    the map and the bar alone.

    Parameters
    ----------
    problem, grid, coverage
        As for :func:`coverage_geojson`.
    width_px, height_px : int
        At least 16 each.

    Returns
    -------
    bytes
        The PNG file.
    """
    from PIL import Image, ImageDraw, ImageFont

    rows, columns = grid.shape
    labelled = width_px >= 320 and height_px >= 160
    bar_px = max(6, width_px // 24)
    left_px, top_px, bottom_px = (46, 18, 30) if labelled else (0, 0, 0)
    right_px = bar_px + (78 if labelled else 4)
    area_w = max(1, width_px - left_px - right_px)
    area_h = max(1, height_px - top_px - bottom_px)
    extent_e = grid.step_m * columns
    extent_n = grid.step_m * rows
    scale = min(area_w / extent_e, area_h / extent_n)  # pixels per metre, the same both ways
    plot_w, plot_h = max(1, int(round(extent_e * scale))), max(1, int(round(extent_n * scale)))
    left, top = left_px + (area_w - plot_w) // 2, top_px + (area_h - plot_h) // 2

    colours = ColourScale.of(coverage)
    cep = np.where(coverage.observable, coverage.cep50_m, np.nan).reshape(rows, columns)
    cell_rgb = colours.rgb(cep)
    # pixel centres -> cell indices (image row 0 is the north edge)
    col_index = np.clip(((np.arange(plot_w) + 0.5) / plot_w * columns).astype(int), 0, columns - 1)
    row_index = np.clip(((plot_h - np.arange(plot_h) - 0.5) / plot_h * rows).astype(int), 0, rows - 1)
    picture = np.empty((height_px, width_px, 3), dtype=np.uint8)
    picture[:] = _BACKGROUND
    picture[top:top + plot_h, left:left + plot_w] = cell_rgb[row_index[:, None], col_index[None, :]]

    image = Image.fromarray(picture, "RGB")
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default()
    bar_left = width_px - right_px + 4
    bar_top, bar_h = (top, plot_h) if labelled else (0, height_px)
    _draw_colour_bar(image, draw, font, colours, bar_left, bar_top, bar_px, bar_h, labelled)
    west = grid.east_m[0] - 0.5 * grid.step_m
    south = grid.north_m[0] - 0.5 * grid.step_m
    north_edge = grid.north_m[-1] + 0.5 * grid.step_m
    if labelled:
        draw.rectangle([left - 1, top - 1, left + plot_w, top + plot_h], outline=_AXES)
        step_e = _nice_step(extent_e / 1000.0)
        for k in range(math.ceil(west / 1000.0 / step_e), math.floor((west + extent_e) / 1000.0 / step_e) + 1):
            x = left + (k * step_e * 1000.0 - west) * scale
            draw.line([(x, top + plot_h), (x, top + plot_h + 3)], fill=_AXES)
            draw.text((x, top + plot_h + 5), _tick_text(k * step_e, step_e), fill=_TEXT, font=font, anchor="mt")
        draw.text((left + plot_w, top + plot_h + 17), "east (km)", fill=_TEXT, font=font, anchor="rt")
        step_n = _nice_step(extent_n / 1000.0)
        for k in range(math.ceil(south / 1000.0 / step_n), math.floor((south + extent_n) / 1000.0 / step_n) + 1):
            y = top + (north_edge - k * step_n * 1000.0) * scale
            draw.line([(left - 4, y), (left - 1, y)], fill=_AXES)
            draw.text((left - 6, y), _tick_text(k * step_n, step_n), fill=_TEXT, font=font, anchor="rm")
        draw.text((left, top - 3), "north (km)", fill=_TEXT, font=font, anchor="ld")
    radius = max(2, min(width_px, height_px) // 80)
    for station_id, (e, n, _) in zip(problem.station_ids, problem.stations_enu_m.tolist()):
        x = left + (e - west) * scale
        y = top + (north_edge - n) * scale
        if left - radius <= x <= left + plot_w + radius and top - radius <= y <= top + plot_h + radius:
            draw.ellipse([x - radius, y - radius, x + radius, y + radius], outline=(255, 255, 255), width=2)
            if labelled:
                draw.text((x + radius + 2, y - radius - 2), station_id, fill=(255, 255, 255), font=font)
    return _png(image)


def _png(image) -> bytes:
    out = io.BytesIO()
    image.save(out, format="PNG", optimize=False, compress_level=6)
    return out.getvalue()


# -- georeferenced renderings -------------------------------------------------------------------------------------

class NotOnTheEarth(ValueError):
    """A flat local frame without an origin has no latitude or longitude to georeference a map by."""


@dataclass(frozen=True)
class LatLonRaster:
    """A coverage map resampled on a regular latitude/longitude grid (WGS84, EPSG:4326), north up.

    Pixel ``(i, j)`` covers longitudes ``west_deg + [j, j + 1] * lon_step_deg`` and latitudes
    ``north_deg - [i + 1, i] * lat_step_deg`` and takes the value of the cell its centre falls in.

    Attributes
    ----------
    west_deg, north_deg : float
        The raster's west and north edges; ``west_deg`` within [-180, 180), the east edge may pass 180
        (a map across the antimeridian).
    lon_step_deg, lat_step_deg : float
        Pixel size.
    cep50_m : ndarray, shape (H, W)
        NaN outside the grid and on unobservable cells.
    inside : ndarray of bool, shape (H, W)
        Pixels within the grid.
    """

    west_deg: float
    north_deg: float
    lon_step_deg: float
    lat_step_deg: float
    cep50_m: np.ndarray
    inside: np.ndarray

    @property
    def east_deg(self) -> float:
        return self.west_deg + self.cep50_m.shape[1] * self.lon_step_deg

    @property
    def south_deg(self) -> float:
        return self.north_deg - self.cep50_m.shape[0] * self.lat_step_deg


#: Points per grid edge when finding the map's latitude/longitude box.
_EDGE_POINTS = 65


def lat_lon_raster(problem: Problem, grid: Grid, coverage: Coverage, longer_side_px: int) -> LatLonRaster:
    """The map on the latitude/longitude box that holds the grid, ``longer_side_px`` pixels along its longer
    side on the ground (pixels about square on the ground; a map around a pole spans every longitude and is
    square in pixels).

    Each pixel centre is placed in the scene's frame at the grid's altitude and takes its cell's CEP50, so the
    raster is exact wherever the box is (across the antimeridian, around a pole). Raises
    :class:`NotOnTheEarth` in a flat local frame.
    """
    frame = problem.frame
    if not frame.is_geodetic:
        raise NotOnTheEarth("a georeferenced map needs a place on the earth: frame wgs84, or an origin")
    rows, columns = grid.shape
    half = 0.5 * grid.step_m
    west, east = grid.east_m[0] - half, grid.east_m[-1] + half
    south, north = grid.north_m[0] - half, grid.north_m[-1] + half
    altitude = float(frame.to_geodetic(grid.cells_enu_m[:1])[2][0])
    t = np.linspace(0.0, 1.0, _EDGE_POINTS)
    edge_e = np.concatenate([west + (east - west) * t, np.full_like(t, east), east - (east - west) * t,
                             np.full_like(t, west)])
    edge_n = np.concatenate([np.full_like(t, south), south + (north - south) * t, np.full_like(t, north),
                             north - (north - south) * t])
    lat, lon, _ = frame.to_geodetic(np.stack([edge_e, edge_n, np.zeros_like(edge_e)], axis=-1))
    lat_deg, lon_deg = np.degrees(lat), np.degrees(lon)
    _, centre_lon, _ = frame.to_geodetic(np.array([0.5 * (west + east), 0.5 * (south + north), 0.0]))
    centre_deg = float(np.degrees(centre_lon))
    pole = None
    for sign in (1.0, -1.0):
        e, n, u = frame.from_geodetic(sign * 0.5 * math.pi, 0.0, altitude)
        if west <= e <= east and south <= n <= north and u > -_NEAR_SIDE_M:
            pole = sign
    if pole is not None:  # every longitude, up to the pole
        box_w, box_e = -180.0, 180.0
        box_s, box_n = (float(lat_deg.min()), 90.0) if pole > 0 else (-90.0, float(lat_deg.max()))
        width = height = longer_side_px
    else:
        unwrapped = centre_deg + (lon_deg - centre_deg + 180.0) % 360.0 - 180.0
        box_w, box_e = float(unwrapped.min()), float(unwrapped.max())
        box_s, box_n = float(lat_deg.min()), float(lat_deg.max())
        ground = (box_e - box_w) * math.cos(math.radians(0.5 * (box_s + box_n))) / max(box_n - box_s, 1e-12)
        width = longer_side_px if ground >= 1.0 else max(1, round(longer_side_px * ground))
        height = longer_side_px if ground < 1.0 else max(1, round(longer_side_px / ground))
        shift = 360.0 * math.floor((box_w + 180.0) / 360.0)  # the west edge within [-180, 180)
        box_w, box_e = box_w - shift, box_e - shift
    lon_step, lat_step = (box_e - box_w) / width, (box_n - box_s) / height
    pixel_lon = np.radians(box_w + (np.arange(width) + 0.5) * lon_step)
    pixel_lat = np.radians(box_n - (np.arange(height) + 0.5) * lat_step)
    grid_lat, grid_lon = np.meshgrid(pixel_lat, pixel_lon, indexing="ij")
    enu = frame.from_geodetic(grid_lat, grid_lon, altitude)
    column = np.floor((enu[..., 0] - west) / grid.step_m).astype(np.int64)
    row = np.floor((enu[..., 1] - south) / grid.step_m).astype(np.int64)
    # the near side of the earth only: the far side's points project into the plane too
    inside = (column >= 0) & (column < columns) & (row >= 0) & (row < rows) & (enu[..., 2] > -_NEAR_SIDE_M)
    cep = np.where(coverage.observable, coverage.cep50_m, np.nan).reshape(rows, columns)
    values = np.where(inside, cep[np.clip(row, 0, rows - 1), np.clip(column, 0, columns - 1)], np.nan)
    return LatLonRaster(box_w, box_n, lon_step, lat_step, values, inside)


#: Below the tangent plane by more than the earth's radius: the far side of the earth.
_NEAR_SIDE_M = 6.3e6


def coverage_geotiff(problem: Problem, grid: Grid, coverage: Coverage, longer_side_px: int) -> bytes:
    """The map as a GeoTIFF for a GIS: one float32 band of CEP50 in metres on :func:`lat_lon_raster`
    (NaN, the GDAL_NODATA value, outside the grid and where unobservable), WGS84 geographic (EPSG:4326),
    pixel is area, georeferenced by a tie point at the north-west corner and the pixel scale."""
    from PIL import Image, TiffImagePlugin, TiffTags

    raster = lat_lon_raster(problem, grid, coverage, longer_side_px)
    tags = TiffImagePlugin.ImageFileDirectory_v2()
    for tag, value, kind in (
            (_MODEL_PIXEL_SCALE, (raster.lon_step_deg, raster.lat_step_deg, 0.0), TiffTags.DOUBLE),
            (_MODEL_TIEPOINT, (0.0, 0.0, 0.0, raster.west_deg, raster.north_deg, 0.0), TiffTags.DOUBLE),
            (_GEO_KEY_DIRECTORY, _GEO_KEYS_WGS84, TiffTags.SHORT),
            (_GDAL_NODATA, "nan", TiffTags.ASCII),
            (TiffImagePlugin.IMAGEDESCRIPTION, "CEP50 (m) of the Cramer-Rao bound; NaN: unobservable or outside "
                                               "the grid", TiffTags.ASCII)):
        tags[tag] = value
        tags.tagtype[tag] = kind
    out = io.BytesIO()
    Image.fromarray(raster.cep50_m.astype(np.float32), "F").save(out, format="TIFF", tiffinfo=tags,
                                                                  compression="tiff_adobe_deflate")
    return out.getvalue()


_MODEL_PIXEL_SCALE, _MODEL_TIEPOINT, _GEO_KEY_DIRECTORY, _GDAL_NODATA = 33550, 33922, 34735, 42113
#: GeoKey directory: version 1.1.0, 4 keys: model type geographic, raster pixel is area, WGS 84 (EPSG:4326),
#: angular unit degree.
_GEO_KEYS_WGS84 = (1, 1, 0, 4, 1024, 0, 1, 2, 1025, 0, 1, 1, 2048, 0, 1, 4326, 2054, 0, 1, 9102)

KML_NAMESPACE = "http://www.opengis.net/kml/2.2"
#: Modification time of every KMZ entry (the earliest a zip can say): a map's bytes do not depend on when it is made.
KMZ_ENTRY_TIME = (1980, 1, 1, 0, 0, 0)
#: Opacity of the overlay's cells (0-255): the base map shows through.
_OVERLAY_ALPHA = 200


def coverage_kmz(problem: Problem, grid: Grid, coverage: Coverage, longer_side_px: int) -> bytes:
    """The map as a KMZ for TAK clients and Google Earth: ``doc.kml`` (a KML 2.2 GroundOverlay on the
    :func:`lat_lon_raster` box, the colour legend as a ScreenOverlay, the stations as Placemarks), with the
    overlay ``coverage.png`` (transparent outside the grid) and ``legend.png`` beside it in the archive."""
    import zipfile

    from PIL import Image, ImageDraw, ImageFont

    raster = lat_lon_raster(problem, grid, coverage, longer_side_px)
    colours = ColourScale.of(coverage)
    rgba = np.zeros(raster.cep50_m.shape + (4,), dtype=np.uint8)
    rgba[..., :3] = colours.rgb(raster.cep50_m)
    rgba[..., 3] = np.where(raster.inside, _OVERLAY_ALPHA, 0)
    overlay = _png(Image.fromarray(rgba, "RGBA"))

    legend = Image.new("RGB", (_LEGEND_W, _LEGEND_H), _BACKGROUND)
    draw = ImageDraw.Draw(legend)
    font = ImageFont.load_default()
    _draw_colour_bar(legend, draw, font, colours, 8, 20, 14, _LEGEND_H - 48, True)
    if colours.unobservable:
        draw.rectangle([8, _LEGEND_H - 20, 22, _LEGEND_H - 8], fill=_UNOBSERVABLE)
        draw.text((27, _LEGEND_H - 14), "unobservable", fill=_TEXT, font=font, anchor="lm")

    box = {"north": raster.north_deg, "south": raster.south_deg, "east": _lon180(raster.east_deg),
           "west": _lon180(raster.west_deg)}
    if raster.east_deg - raster.west_deg >= 360.0 - 1e-9:
        box["west"], box["east"] = -180.0, 180.0
    lat, lon, alt = problem.frame.to_geodetic(problem.stations_enu_m)
    stations = "".join(
        f"<Placemark><name>{escape(station_id)}</name><Point><coordinates>{math.degrees(x):.8f},"
        f"{math.degrees(y):.8f},{h:.2f}</coordinates></Point></Placemark>"
        for station_id, y, x, h in zip(problem.station_ids, lat.tolist(), lon.tolist(), alt.tolist()))
    scale_text = (f"CEP50 of the Cramer-Rao bound from {_metres(10.0 ** colours.best)} (bright) to "
                  f"{_metres(10.0 ** colours.worst)} (dark){' and worse' if colours.saturated else ''}"
                  f"{'; grey: unobservable' if colours.unobservable else ''}; cells {_metres(grid.step_m)} apart")
    document = (
        f'<?xml version="1.0" encoding="UTF-8"?>\n<kml xmlns="{KML_NAMESPACE}"><Document>'
        f"<name>Coverage map</name><description>{escape(scale_text)}</description>"
        f"<GroundOverlay><name>CEP50</name><description>{escape(scale_text)}</description>"
        f"<Icon><href>coverage.png</href></Icon><altitudeMode>clampToGround</altitudeMode>"
        f"<LatLonBox><north>{box['north']:.9f}</north><south>{box['south']:.9f}</south>"
        f"<east>{box['east']:.9f}</east><west>{box['west']:.9f}</west></LatLonBox></GroundOverlay>"
        f"<ScreenOverlay><name>Legend</name><Icon><href>legend.png</href></Icon>"
        f'<overlayXY x="0" y="1" xunits="fraction" yunits="fraction"/>'
        f'<screenXY x="0.01" y="0.99" xunits="fraction" yunits="fraction"/>'
        f'<size x="0" y="0" xunits="pixels" yunits="pixels"/></ScreenOverlay>'
        f"<Folder><name>Stations</name>{stations}</Folder>"
        f"</Document></kml>\n")
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as archive:  # doc.kml first: the KML a reader opens
        for name, data, compression in (("doc.kml", document, zipfile.ZIP_DEFLATED),
                                        ("coverage.png", overlay, zipfile.ZIP_STORED),
                                        ("legend.png", _png(legend), zipfile.ZIP_STORED)):
            # A fixed entry time: the same map is the same bytes whenever it is made (an entry named by a
            # string alone would carry the clock's time, to two seconds).
            entry = zipfile.ZipInfo(name, date_time=KMZ_ENTRY_TIME)
            entry.compress_type = compression
            archive.writestr(entry, data)
    return out.getvalue()


_LEGEND_W, _LEGEND_H = 120, 260


def _lon180(lon_deg: float) -> float:
    """A longitude within [-180, 180] (KML's range)."""
    return lon_deg if -180.0 <= lon_deg <= 180.0 else (lon_deg + 180.0) % 360.0 - 180.0
