"""Radio-map builds as the app runs them: one build per site at a time, synchronous or as
a background job whose progress and outcome are recorded."""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from sqlalchemy.orm import Session, sessionmaker
from starlette.concurrency import run_in_threadpool

from app.core.config import Settings
from app.core.db import session_scope
from app.core.errors import DomainError
from app.core.jobs import tend_jobs
from app.core.time import utcnow
from app.radiomaps import service
from app.radiomaps.models import RadioMapJob
from app.sites.cache import SiteVersions

log = logging.getLogger(__name__)


class RadioMapBuilds:
    """Runs the builds of this process; lives as long as the app."""

    def __init__(
        self, settings: Settings, sessions: sessionmaker[Session], sites: SiteVersions
    ) -> None:
        self.settings = settings
        self.sessions = sessions
        self.sites = sites
        self._locks: dict[str, asyncio.Lock] = {}
        self._running: dict[str, asyncio.Task[None]] = {}
        """The unfinished jobs of this process, by id."""

    async def tend(self) -> int:
        """Renew this process's unfinished build jobs and fail those no process renewed for a
        lease (see ``app.core.jobs``); return how many failed."""
        alive = tuple(self._running)
        return await run_in_threadpool(self._tend, alive)

    def _tend(self, alive: tuple[str, ...]) -> int:
        with session_scope(self.sessions) as db:
            return tend_jobs(
                db, RadioMapJob, alive=alive, now=utcnow(), lease_s=self.settings.job_lease_s
            )

    def _lock(self, site_id: str) -> asyncio.Lock:
        # one build per site at a time in this process: two would replace each other's rows
        return self._locks.setdefault(site_id, asyncio.Lock())

    async def build(
        self,
        site_id: str,
        progress: service.Progress | None = None,
        job_id: str | None = None,
    ) -> dict[str, Any]:
        """Build the site's radio maps now; return the build's summary."""
        async with self._lock(site_id):
            if job_id is not None:
                # a job waiting for another build of the site stays queued until it gets the lock
                await run_in_threadpool(
                    service.update_job, sessions=self.sessions, job_id=job_id, status="running"
                )
            summary = await run_in_threadpool(
                service.build_site,
                sessions=self.sessions,
                site_id=site_id,
                raster_cell=self.settings.raster_cell,
                folds=self.settings.radiomap_folds,
                tune=self.settings.radiomap_tuning,
                hmm_walks=self.settings.radiomap_hmm_walks,
                progress=progress,
            )
        # this node's ingest sees the new map version at once (other nodes within the cache TTL)
        self.sites.invalidate(site_id)
        return summary

    def start(self, site_id: str, job_id: str) -> None:
        """Run a recorded, queued job in the background."""
        task = asyncio.create_task(self._run(site_id, job_id))
        self._running[job_id] = task
        task.add_done_callback(lambda _: self._running.pop(job_id, None))

    async def _run(self, site_id: str, job_id: str) -> None:
        last = [0.0]
        step = self.settings.radiomap_progress_step

        def progress(fraction: float) -> None:
            if fraction - last[0] >= step or fraction >= 1.0:
                last[0] = fraction
                service.update_job(sessions=self.sessions, job_id=job_id, progress=fraction)

        try:
            summary = await self.build(site_id, progress, job_id)
        except DomainError as exc:
            await self._record(job_id, status="failed", error=exc.message)
            return
        except Exception as exc:  # the job must end failed, whatever went wrong
            log.exception("radio map build %s of site %s failed", job_id, site_id)
            await self._record(job_id, status="failed", error=f"{type(exc).__name__}: {exc}")
            return
        await self._record(job_id, status="done", progress=1.0, summary=summary)

    async def _record(self, job_id: str, **outcome: Any) -> None:
        await run_in_threadpool(
            service.update_job, sessions=self.sessions, job_id=job_id, **outcome
        )
