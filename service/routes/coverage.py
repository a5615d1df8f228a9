"""Coverage maps: the planning bound over a grid of target positions, as GeoJSON, a PNG, a KMZ or a GeoTIFF.

The grid is priced before anything is computed (``service.limits``: 422
``over_limit`` above ``max_grid_cost``); the cells are then computed in
chunks (:func:`service.planning.coverage_renderings`) on the app's CPU pool, or on the
Dask cluster of ``dask_scheduler``, and stop at the request deadline, on
disconnect and at shutdown like an evaluation (:func:`service.web.watch.watched`).

``POST /v1/crlb/grid`` answers the rendering ``Accept`` prefers
(:func:`negotiate`): GeoJSON (:func:`service.renderings.maps.coverage_geojson`), the PNG
heat map with axes and legend (:func:`service.renderings.maps.coverage_png`), a KMZ
GroundOverlay for TAK and Google Earth (:func:`service.renderings.maps.coverage_kmz`) or
a GeoTIFF for a GIS (:func:`service.renderings.maps.coverage_geotiff`). ``POST
/v1/crlb/grid/map`` gives the same pictures as a download named by a
``format`` query parameter, ``application/octet-stream``: what a generated
client passes through as bytes (it parses one declared media type per
answer, and would parse a PNG as the GeoJSON).
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from pydantic import Field
from starlette.responses import Response

from service.web import headers
from service import schemas
from service.web.deps import OwnerDep
from service.web.headers import MediaRange
from service.web.problems import ApiError
from service.web.responses import JsonResponse
from service.planning import coverage_renderings, grid_of_request
from service.web.watch import in_pool, watched

router = APIRouter(prefix="/v1", tags=["fixes"])

JSON = "application/json"
PNG = "image/png"
KMZ = "application/vnd.google-earth.kmz"
TIFF = "image/tiff"
#: The renderings by media type, in the order a tie in Accept is settled (JSON first, the default).
MEDIA_TYPES = {JSON: "geojson", PNG: "png", KMZ: "kmz", TIFF: "tiff"}
#: Renderings placed by latitude and longitude: a flat local frame without an origin has none.
GEOREFERENCED = ("kmz", "tiff")
_SUFFIX = {"png": "png", "kmz": "kmz", "tiff": "tif"}

_BINARY = {"schema": {"type": "string", "format": "binary"}}
_GRID_REQUEST_LIMITS = {
    422: {"model": schemas.Problem,
          "description": "invalid geometry or grid, or over max_grid_cost (code over_limit)"},
    503: {"model": schemas.Problem,
          "description": "not finished within the request deadline (code deadline_exceeded)"}}


def negotiate(accept: tuple[MediaRange, ...]) -> str | None:
    """The media type of :data:`MEDIA_TYPES` that ``Accept`` prefers, or None when it accepts none of them.

    Parameters
    ----------
    accept : tuple of MediaRange
        The request's ``Accept`` as the middleware parsed it (:func:`service.web.headers.parse_accept`); empty
        when absent.

    Each offered type takes the q-value of the most specific range that names it (``type/subtype``, then
    ``type/*``, then ``*/*``); the highest q wins, then the range listed first, then :data:`MEDIA_TYPES`'
    order. No header, or ``*/*``, is JSON; ``application/geo+json`` is JSON.
    """
    if not accept:
        return JSON
    ranges = [("application/json" if r.media == "application/geo+json" else r.media, r.q, position)
              for position, r in enumerate(accept)]
    best, best_key = None, None
    for order, offered in enumerate(MEDIA_TYPES):
        kind = offered.split("/")[0]
        for wanted in (offered, f"{kind}/*", "*/*"):
            if offered != JSON and wanted == "*/*":
                continue  # a wildcard asks for the default rendering, not for any picture
            matches = [(q, position) for media, q, position in ranges if media == wanted]
            if matches:
                q, position = max(matches, key=lambda m: (m[0], -m[1]))
                key = (q, -position, -order)
                if q > 0 and (best_key is None or key > best_key):
                    best, best_key = offered, key
                break
    return best


def _render(http: Request, request: schemas.CrlbGridRequest, kind: str, not_placed: ApiError):
    settings = http.app.state.settings
    problem, grid = grid_of_request(request, settings.max_grid_cost)
    if kind in GEOREFERENCED and not problem.frame.is_geodetic:
        raise not_placed

    def work(should_stop):
        return coverage_renderings(request, problem, grid, (kind,), scheduler=settings.dask_scheduler,
                                   should_stop=should_stop)[kind]

    return watched(http, in_pool(http.app.state.cpu_pool, work),
                   "ask for a coarser coverage map (a larger step_m or a smaller half_width_m)")


_NOT_PLACED = ("a KMZ or GeoTIFF map is placed by latitude and longitude: it needs frame wgs84 or an origin "
               "(GeoJSON and PNG need neither)")


@router.post("/crlb/grid", operation_id="fixes-crlb-grid",
             summary="Coverage map: the Cramer-Rao bound of a geometry over a grid of target positions",
             response_model=schemas.CrlbGridResponse,
             responses={200: {"description": (
                 "by Accept: GeoJSON FeatureCollection of the cells and stations (application/json, the default); "
                 "image/png: a heat map of log10(CEP50), image.width_px x image.height_px, with east and north "
                 "axes in km, a colour legend in metres and the stations; application/vnd.google-earth.kmz: the "
                 "map as a KML GroundOverlay (with its PNG, a legend and the stations) for TAK and Google Earth; "
                 "image/tiff: a GeoTIFF of CEP50 in metres (float32, NaN where unobservable) in WGS84 latitude "
                 "and longitude (EPSG:4326). The KMZ and GeoTIFF rasters are max(image.width_px, "
                 "image.height_px) pixels along their longer side"),
                 "content": {PNG: _BINARY, KMZ: _BINARY, TIFF: _BINARY}},
                 406: {"model": schemas.Problem, "description": (
                     "Accept names none of application/json, image/png, application/vnd.google-earth.kmz, "
                     "image/tiff; or a KMZ or GeoTIFF of a flat local frame without an origin (code "
                     "not_acceptable)")},
                 **_GRID_REQUEST_LIMITS})
async def crlb_grid(request: schemas.CrlbGridRequest, owner: OwnerDep, http: Request) -> Response:
    media_type = negotiate(headers.of(http).accept)
    if media_type is None:
        raise ApiError(406, "not_acceptable", f"Accept names none of the coverage map's renderings: "
                                              f"{', '.join(MEDIA_TYPES)}")
    kind = MEDIA_TYPES[media_type]
    body = await _render(http, request, kind, ApiError(406, "not_acceptable", _NOT_PLACED))
    return JsonResponse(body) if kind == "geojson" else Response(body, media_type=media_type)


MapFormat = Annotated[Literal["png", "kmz", "tiff"], Field(title="Format")]


@router.post("/crlb/grid/map", operation_id="fixes-crlb-grid-map",
             summary="Coverage map as a file: PNG, KMZ (TAK, Google Earth) or GeoTIFF (GIS)",
             response_class=Response,
             responses={200: {"description": (
                 "the rendering `format` names (as /v1/crlb/grid gives it for that Accept), as "
                 "application/octet-stream with Content-Disposition naming the file (coverage.png, "
                 "coverage.kmz, coverage.tif): a generated client returns the bytes"),
                 "content": {"application/octet-stream": _BINARY},
                 "headers": {"Content-Disposition": {"description": "attachment; filename=coverage.<png|kmz|tif>",
                                                     "schema": {"type": "string"}}}},
                 **_GRID_REQUEST_LIMITS})
async def crlb_grid_map(request: schemas.CrlbGridRequest, owner: OwnerDep, http: Request,
                        format: Annotated[MapFormat, Query(description=(
                            "png: the heat map with axes and legend; kmz: a KML GroundOverlay; tiff: a GeoTIFF "
                            "of CEP50 in metres (kmz and tiff need frame wgs84 or an origin)"))] = "png",
                        ) -> Response:
    not_placed = ApiError(422, "invalid_input", _NOT_PLACED, [{"loc": ["format"], "msg": _NOT_PLACED}])
    body = await _render(http, request, format, not_placed)
    return Response(body, media_type="application/octet-stream",
                    headers={"Content-Disposition": f'attachment; filename="coverage.{_SUFFIX[format]}"'})
