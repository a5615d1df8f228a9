"""Coverage maps: the planning bound over a grid of target positions, as GeoJSON or a PNG heat map.

The grid is priced before anything is computed (``service.limits``: 422
``over_limit`` above ``max_grid_cost``); the cells are then computed in
chunks (:func:`service.translate.coverage_renderings`) on the app's CPU pool, or on the
Dask cluster of ``dask_scheduler``, and stop at the request deadline, on
disconnect and at shutdown like an evaluation (:func:`service.watch.watched`).
``Accept: image/png`` asks for the heat map (:func:`service.maps.coverage_png`),
anything else for the GeoJSON (:func:`service.maps.coverage_geojson`).
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from starlette.responses import Response

from service import schemas
from service.deps import OwnerDep
from service.responses import JsonResponse
from service.translate import coverage_renderings, grid_of_request
from service.watch import in_pool, watched

router = APIRouter(prefix="/v1", tags=["fixes"])

PNG = "image/png"
_JSON_TYPES = ("application/json", "application/geo+json")


def wants_png(accept: str | None) -> bool:
    """True when ``Accept`` prefers ``image/png`` to JSON (by q-value, then by order; ``*/*`` is JSON)."""
    if not accept:
        return False
    png_q = json_q = 0.0
    png_at = json_at = len(accept)
    for position, part in enumerate(accept.split(",")):
        media, *parameters = (p.strip() for p in part.split(";"))
        q = 1.0
        for parameter in parameters:
            name, _, value = parameter.partition("=")
            if name.strip().lower() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        media = media.lower()
        if media == PNG and q > png_q:
            png_q, png_at = q, position
        elif (media in _JSON_TYPES or media in ("*/*", "application/*")) and q > json_q:
            json_q, json_at = q, position
    return png_q > 0 and (png_q > json_q or (png_q == json_q and png_at < json_at))


@router.post("/crlb/grid", operation_id="fixes-crlb-grid",
             summary="Coverage map: the Cramer-Rao bound of a geometry over a grid of target positions",
             response_model=schemas.CrlbGridResponse,
             responses={200: {"description": "GeoJSON FeatureCollection of the cells and stations; with "
                                             "Accept: image/png, a heat map of log10(CEP50) of image.width_px x "
                                             "image.height_px with the stations marked",
                              "content": {PNG: {"schema": {"type": "string", "format": "binary"}}}},
                        422: {"model": schemas.Problem,
                              "description": "invalid geometry or grid, or over max_grid_cost (code over_limit)"},
                        503: {"model": schemas.Problem,
                              "description": "not finished within the request deadline (code deadline_exceeded)"}})
async def crlb_grid(request: schemas.CrlbGridRequest, owner: OwnerDep, http: Request) -> Response:
    settings = http.app.state.settings
    problem, grid = grid_of_request(request, settings.max_grid_cost)
    kind = "png" if wants_png(http.headers.get("accept")) else "geojson"

    def work(should_stop):
        return coverage_renderings(request, problem, grid, (kind,), scheduler=settings.dask_scheduler,
                                   should_stop=should_stop)[kind]

    body = await watched(http, in_pool(http.app.state.cpu_pool, work),
                         "ask for a coarser coverage map (a larger step_m or a smaller half_width_m)")
    if kind == "png":
        return Response(body, media_type=PNG)
    return JsonResponse(body)
