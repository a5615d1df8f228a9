"""Coverage maps as GeoJSON and as a PNG heat map (the one place each is built: route and CLI alike).

Both take what :mod:`core.coverage` gives (the planning problem, its
:class:`~core.coverage.Grid` and the :class:`~core.coverage.Coverage` of its cells).

- GeoJSON (RFC 7946): one Polygon feature per cell, the square of side
  ``step_m`` around the cell centre in the common frame converted to WGS84
  corner by corner (null geometry in a flat local frame), then one Point per
  station. Longitudes are within [-180, 180]: a cell across the antimeridian
  is cut there into a MultiPolygon, and the cell around a pole, which no ring
  of longitudes and latitudes can draw, has a null geometry
  (:func:`service.renderings.polygon_geometries`, as for the fixes' ellipses).
- PNG: ``log10(CEP50)`` in the viridis colour map, small (good) bright, over
  at most :data:`DECADES` decades above the best cell (worse cells saturate),
  unobservable cells grey; the square grid keeps its aspect ratio in the
  requested picture (letterboxed), a colour bar on the right with its range
  in metres, stations as white rings with their ids. Drawn with Pillow, which
  sets the picture's size in pixels exactly. Measured side by side on a
  loaded two-core machine, 201 x 201 cells to 640 x 480: Pillow 132 ms, a
  matplotlib (Agg) imshow with a colour bar 477 ms; a process importing numpy
  and Pillow 0.6-1.5 s (numpy alone 1.0-1.5 s), numpy and matplotlib.pyplot
  5.2-8.7 s.
"""

from __future__ import annotations

import io

import numpy as np

from core.coverage import Coverage, Grid
from core.problem import Problem
from service.renderings import polygon_geometries

#: The PNG's colour scale spans at most this many decades of CEP50 above the best cell.
DECADES = 3.0
#: viridis at 0, 1/8, ..., 1 (matplotlib's table), interpolated linearly.
_VIRIDIS = np.array([[68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
                     [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]], dtype=float)
_UNOBSERVABLE = (128, 128, 128)
_BACKGROUND = (24, 24, 24)
_TEXT = (235, 235, 235)


def _float_or_none(values: np.ndarray) -> list:
    return [v if v == v else None for v in values.tolist()]


def coverage_geojson(problem: Problem, grid: Grid, coverage: Coverage) -> dict:
    """The coverage map as a GeoJSON FeatureCollection (the ``CrlbGridResponse`` schema).

    Parameters
    ----------
    problem : core.problem.Problem
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


def coverage_png(problem: Problem, grid: Grid, coverage: Coverage, width_px: int, height_px: int) -> bytes:
    """A PNG heat map of ``log10(CEP50)``, exactly ``width_px`` x ``height_px``, with the stations marked.

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
    bar_px = max(6, width_px // 24)
    label_px = 64 if width_px >= 320 else 0
    map_w = max(1, width_px - bar_px - label_px - 8)
    extent_e = grid.step_m * columns
    extent_n = grid.step_m * rows
    scale = min(map_w / extent_e, height_px / extent_n)  # pixels per metre, the same both ways
    plot_w, plot_h = max(1, int(round(extent_e * scale))), max(1, int(round(extent_n * scale)))
    left, top = (map_w - plot_w) // 2, (height_px - plot_h) // 2

    cep = coverage.cep50_m.reshape(rows, columns)
    log_cep = np.log10(np.where(coverage.observable.reshape(rows, columns), cep, np.nan))
    finite = np.isfinite(log_cep)
    best = float(np.min(log_cep[finite])) if np.any(finite) else 0.0
    worst = min(float(np.max(log_cep[finite])), best + DECADES) if np.any(finite) else 1.0
    span = max(worst - best, 1e-9)
    cell_rgb = np.where(finite[..., None], _colours(1.0 - (np.nan_to_num(log_cep, nan=best) - best) / span),
                        np.array(_UNOBSERVABLE, dtype=np.uint8))
    # pixel centres -> cell indices (image row 0 is the north edge)
    col_index = np.clip(((np.arange(plot_w) + 0.5) / plot_w * columns).astype(int), 0, columns - 1)
    row_index = np.clip(((plot_h - np.arange(plot_h) - 0.5) / plot_h * rows).astype(int), 0, rows - 1)
    picture = np.empty((height_px, width_px, 3), dtype=np.uint8)
    picture[:] = _BACKGROUND
    picture[top:top + plot_h, left:left + plot_w] = cell_rgb[row_index[:, None], col_index[None, :]]
    bar_left = map_w + 4
    ramp = _colours(np.linspace(1.0, 0.0, height_px))  # top: the best CEP (bright)
    picture[:, bar_left:bar_left + bar_px] = ramp[:, None, :]

    image = Image.fromarray(picture, "RGB")
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default()
    west = grid.east_m[0] - 0.5 * grid.step_m
    north_edge = grid.north_m[-1] + 0.5 * grid.step_m
    radius = max(2, min(width_px, height_px) // 80)
    for station_id, (e, n, _) in zip(problem.station_ids, problem.stations_enu_m.tolist()):
        x = left + (e - west) * scale
        y = top + (north_edge - n) * scale
        if -radius <= x <= map_w + radius and -radius <= y <= height_px + radius:
            draw.ellipse([x - radius, y - radius, x + radius, y + radius], outline=(255, 255, 255), width=2)
            if label_px:
                draw.text((x + radius + 2, y - radius - 2), station_id, fill=(255, 255, 255), font=font)
    if label_px and np.any(finite):
        text_left = bar_left + bar_px + 3
        draw.text((text_left, 2), _metres(10.0 ** best), fill=_TEXT, font=font)
        draw.text((text_left, height_px - 14), _metres(10.0 ** worst), fill=_TEXT, font=font)
        draw.text((text_left, height_px // 2 - 6), "CEP50", fill=_TEXT, font=font)
    out = io.BytesIO()
    image.save(out, format="PNG", optimize=False, compress_level=6)
    return out.getvalue()
