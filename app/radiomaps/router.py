"""Radio maps: build them (with transmitter calibration) from the site's surveys, follow
asynchronous builds, read the latest build's summary."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from app.keys.deps import AdminDep, SiteReaderDep
from app.radiomaps import service
from app.radiomaps.schemas import BuildAccepted, BuildJobRead, BuildSummary
from app.sites.deps import SiteDep
from app.state import SessionDep, StateDep

router = APIRouter(prefix="/v1/sites/{site_id}/radiomap", tags=["radiomaps"])


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
