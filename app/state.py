"""The app's long-lived objects, built once by the lifespan, and the request dependencies
that hand them to routes."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy import Engine
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker
from starlette.requests import HTTPConnection

from app.core.config import Settings
from app.core.db import make_engine, make_sessionmaker
from app.core.errors import Unavailable
from app.core.heap import trim_allocator
from app.core.metrics import Metrics
from app.keys.cache import KeyCache
from app.keys.revocation import Revocations
from app.outputs.dispatcher import Dispatcher
from app.radiomaps.jobs import RadioMapBuilds
from app.sites.cache import SiteVersions
from app.tracks.jobs import TrackFitter
from app.workers.runtime import Runtime

log = logging.getLogger(__name__)


@dataclass
class AppState:
    """Everything one app holds for its lifetime; ``runtime`` is None on a node without workers."""

    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    metrics: Metrics
    sites: SiteVersions
    keys: KeyCache
    runtime: Runtime | None
    track_fits: TrackFitter
    radiomap_builds: RadioMapBuilds
    revocations: Revocations
    outputs: Dispatcher
    job_leases: asyncio.Task[None] | None = None
    revocation_poll: asyncio.Task[None] | None = None
    heap_trims: asyncio.Task[None] | None = None

    @classmethod
    async def open(cls, settings: Settings) -> AppState:
        """Connect the database, start the workers (when this node runs or reaches any) and
        the track-fit pool; fail the jobs a stopped process left, and keep this one's alive."""
        engine = make_engine(settings.resolved_database_url)
        sessions = make_sessionmaker(engine)
        metrics = Metrics()
        runtime = None
        if settings.worker_count > 0 or settings.broker != "memory":
            runtime = Runtime(settings, metrics)
            await runtime.start()
        track_fits = TrackFitter(
            settings, sessions, runtime.hub.publish if runtime is not None else None
        )
        track_fits.start()
        sites = SiteVersions(sessions, ttl_s=settings.site_cache_ttl_s)
        keys = KeyCache(
            sessions, ttl_s=settings.key_cache_ttl_s, max_entries=settings.key_cache_size
        )
        state = cls(
            settings=settings,
            engine=engine,
            sessions=sessions,
            metrics=metrics,
            sites=sites,
            keys=keys,
            runtime=runtime,
            track_fits=track_fits,
            radiomap_builds=RadioMapBuilds(settings, sessions, sites),
            revocations=Revocations(sessions, keys, settings.key_revocation_poll_s),
            outputs=Dispatcher(settings, sessions, metrics),
        )
        state.outputs.start()
        await state.tend_jobs()
        state.job_leases = asyncio.create_task(state._keep_jobs())
        state.revocation_poll = asyncio.create_task(state.revocations.run())
        if settings.heap_trim_every_s:
            state.heap_trims = asyncio.create_task(state._trim_heap())
        return state

    async def tend_jobs(self) -> None:
        """Renew this process's background jobs and fail those whose process is gone."""
        try:
            failed = await self.track_fits.tend() + await self.radiomap_builds.tend()
        except SQLAlchemyError:  # the database may be away for a while; the next round retries
            log.exception("could not renew the background jobs")
            return
        if failed:
            log.warning("marked %d background jobs of stopped processes failed", failed)

    async def _keep_jobs(self) -> None:
        while True:
            await asyncio.sleep(self.settings.job_lease_s / 3)
            await self.tend_jobs()

    async def _trim_heap(self) -> None:
        while True:
            await asyncio.sleep(self.settings.heap_trim_every_s)
            trim_allocator()

    async def close(self) -> None:
        """Stop the job leases, the revocation poll, the track fits and the workers (they
        snapshot their devices); close the database."""
        for task in (self.job_leases, self.revocation_poll, self.heap_trims):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        await self.outputs.stop()
        self.track_fits.stop()
        if self.runtime is not None:
            await self.runtime.stop()
        self.engine.dispose()


def app_state(connection: HTTPConnection) -> AppState:
    """Return the state of the app serving a request or WebSocket."""
    return connection.app.state.locus


async def get_state(request: Request) -> AppState:
    """Return the app's state (a dependency)."""
    return app_state(request)


StateDep = Annotated[AppState, Depends(get_state)]


async def _settings(state: StateDep) -> Settings:
    return state.settings


SettingsDep = Annotated[Settings, Depends(_settings)]


def get_db(request: Request) -> Iterator[Session]:
    """Yield a session from the app's factory; handlers commit what they change."""
    session = app_state(request).sessions()
    try:
        yield session
    finally:
        session.close()


SessionDep = Annotated[Session, Depends(get_db)]


def runtime_of(state: AppState) -> Runtime:
    """Return the worker runtime, or 503 on a node that runs no workers.

    A plain call, not a dependency: the ingest handlers are the hottest path, and
    FastAPI's solving of each dependency cost them more than this check.
    """
    if state.runtime is None:
        raise Unavailable("this node runs no filter workers")
    return state.runtime
