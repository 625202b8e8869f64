"""Radio maps: build them (with transmitter calibration) from the site's surveys, follow
asynchronous builds, read the latest build's summary and each floor's survey guidance."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request, Response
from starlette.concurrency import run_in_threadpool

from app.core.schemas import FloorIdPath
from app.floors.service import require_floor
from app.geometry.floormap import parse_floor_map
from app.keys.deps import AdminDep, SiteReaderDep
from app.radiomaps import guidance, service
from app.radiomaps.schemas import BuildAccepted, BuildJobRead, BuildSummary, SurveyGuidance
from app.sites.deps import SiteDep
from app.state import SessionDep, StateDep

router = APIRouter(prefix="/v1/sites/{site_id}/radiomap", tags=["radiomaps"])
floor_router = APIRouter(prefix="/v1/sites/{site_id}/floors/{floor_id}", tags=["radiomaps"])


@router.post(
    "/build",
    response_model=None,
    responses={200: {"model": BuildSummary}, 202: {"model": BuildAccepted}},
)
async def build_radiomap(
    _: AdminDep,
    site: SiteDep,
    db: SessionDep,
    state: StateDep,
    response: Response,
    run_async: Annotated[
        bool, Query(alias="async", description="Answer 202 with a job id at once.")
    ] = False,
) -> BuildSummary | BuildAccepted:
    """Build every floor's radio map and calibrate every heard transmitter (admin).

    Without ``async`` the request answers when the build is stored, with its
    summary; with ``async=true`` it answers 202 ``{"job_id"}`` and
    ``GET .../radiomap/build/{job_id}`` follows it. 409 when the site has no surveys.
    """
    service.check_buildable(db=db, site=site)
    site_id = site.id
    if not run_async:
        db.close()
        return BuildSummary.model_validate(await state.radiomap_builds.build(site_id))
    job = service.create_job(db=db, site_id=site_id)
    db.commit()
    state.radiomap_builds.start(site_id, job.id)
    response.status_code = 202
    return BuildAccepted(job_id=job.id)


@router.get("/build/{job_id}", response_model=BuildJobRead)
def get_build_job(_: AdminDep, site: SiteDep, job_id: str, db: SessionDep) -> BuildJobRead:
    """Return an asynchronous build's status, progress and (when done) summary."""
    job = service.get_job(db=db, site_id=site.id, job_id=job_id)
    return BuildJobRead(
        job_id=job.id,
        site_id=job.site_id,
        status=job.status,  # type: ignore[arg-type]
        progress=job.progress,
        summary=None if job.summary is None else BuildSummary.model_validate(job.summary),
        error=job.error,
    )


@router.get("", response_model=BuildSummary)
def get_radiomap(_: SiteReaderDep, site: SiteDep, db: SessionDep) -> BuildSummary:
    """Return the summary of the site's latest build (404 when never built)."""
    build = service.get_build(db=db, site_id=site.id)
    return BuildSummary.model_validate(build.summary)


@floor_router.get(
    "/survey-guidance",
    response_model=SurveyGuidance,
    responses={
        200: {"content": {"image/png": {}}, "description": "JSON grids, or a PNG over the plan"}
    },
)
async def survey_guidance(
    _: SiteReaderDep,
    site: SiteDep,
    floor_id: FloorIdPath,
    request: Request,
    db: SessionDep,
    format: Annotated[
        Literal["json", "png"] | None,
        Query(description="png draws it over the floor plan (as does Accept: image/png)."),
    ] = None,
) -> dict[str, Any] | Response:
    """Where the floor's radio map is thin: the positioning error to expect in each cell,
    from the latest build's held-out survey scans (404 before the first build)."""
    floor = require_floor(db=db, site_id=site.id, floor_id=floor_id)
    grid, built_at = guidance.get_guidance(db=db, site_id=site.id, floor_id=floor_id)
    if format == "png" or (format is None and "image/png" in request.headers.get("accept", "")):
        png = await run_in_threadpool(
            guidance.render_png,
            parse_floor_map(floor.geojson),
            grid,
            title=f"{site.id}/{floor_id}: expected error from held-out survey scans",
        )
        return Response(png, media_type="image/png")
    return guidance.to_json(site.id, floor_id, grid, built_at)
