"""Radio maps: build them (with transmitter calibration) from the site's surveys, follow
asynchronous builds, read the latest build's summary."""

from __future__ import annotations

import asyncio
import logging
from typing import Annotated, Any

from fastapi import APIRouter, Query, Response
from starlette.concurrency import run_in_threadpool

from app.core.deps import AdminDep, SessionDep, SiteReaderDep
from app.core.errors import ApiError
from app.core.state import AppState, StateDep
from app.radiomaps import service
from app.radiomaps.schemas import BuildAccepted, BuildJobRead, BuildSummary
from app.sites.deps import SiteDep

log = logging.getLogger(__name__)

router = APIRouter(prefix="/v1/sites/{site_id}/radiomap", tags=["radiomaps"])
_running: set[asyncio.Task[None]] = set()
_locks: dict[str, asyncio.Lock] = {}
PROGRESS_STEP = 0.05
"""An asynchronous job's progress is written when it moved at least this much."""


def _lock(site_id: str) -> asyncio.Lock:
    # one build per site at a time in this process: two would replace each other's rows
    return _locks.setdefault(site_id, asyncio.Lock())


async def _build(
    state: AppState, site_id: str, progress: Any = None, job_id: str | None = None
) -> dict[str, Any]:
    async with _lock(site_id):
        if job_id is not None:
            # a job waiting for another build of the site stays queued until it gets the lock
            await run_in_threadpool(
                service.update_job, sessions=state.sessions, job_id=job_id, status="running"
            )
        summary = await run_in_threadpool(
            service.build_site,
            sessions=state.sessions,
            site_id=site_id,
            raster_cell=state.settings.raster_cell,
            progress=progress,
        )
    # this node's ingest sees the new map version at once (other nodes within the cache TTL)
    state.sites.invalidate(site_id)
    return summary


async def _run_job(state: AppState, site_id: str, job_id: str) -> None:
    last = [0.0]

    def progress(fraction: float) -> None:
        if fraction - last[0] >= PROGRESS_STEP or fraction >= 1.0:
            last[0] = fraction
            service.update_job(sessions=state.sessions, job_id=job_id, progress=fraction)

    try:
        summary = await _build(state, site_id, progress, job_id)
    except ApiError as exc:
        await run_in_threadpool(
            service.update_job,
            sessions=state.sessions,
            job_id=job_id,
            status="failed",
            error=exc.message,
        )
        return
    except Exception as exc:  # the job must end failed, whatever went wrong
        log.exception("radio map build %s of site %s failed", job_id, site_id)
        await run_in_threadpool(
            service.update_job,
            sessions=state.sessions,
            job_id=job_id,
            status="failed",
            error=f"{type(exc).__name__}: {exc}",
        )
        return
    await run_in_threadpool(
        service.update_job,
        sessions=state.sessions,
        job_id=job_id,
        status="done",
        progress=1.0,
        summary=summary,
    )


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
        return BuildSummary.model_validate(await _build(state, site_id))
    job = service.create_job(db=db, site_id=site_id)
    db.commit()
    task = asyncio.create_task(_run_job(state, site_id, job.id))
    _running.add(task)
    task.add_done_callback(_running.discard)
    response.status_code = 202
    return BuildAccepted(job_id=job.id)


@router.get("/build/{job_id}", response_model=BuildJobRead)
def get_build_job(_: AdminDep, site: SiteDep, job_id: str, db: SessionDep) -> BuildJobRead:
    """Return an asynchronous build's status, progress and (when done) summary."""
    job = service.get_job(db=db, site_id=site.id, job_id=job_id)
    if job is None:
        raise ApiError(404, f"build job '{job_id}' not found in site '{site.id}'")
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
    if build is None:
        raise ApiError(404, f"site '{site.id}' has no radio map yet: POST .../radiomap/build")
    return BuildSummary.model_validate(build.summary)
