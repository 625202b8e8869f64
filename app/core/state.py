"""Typed access to what the app holds for its lifetime (sessions, runtime, metrics)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.errors import ApiError
from app.core.metrics import Metrics
from app.sites.cache import SiteVersions
from app.workers.runtime import Runtime


@dataclass
class AppState:
    """The app's long-lived objects, built by the lifespan."""

    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    metrics: Metrics
    sites: SiteVersions
    runtime: Runtime | None


async def get_state(request: Request) -> AppState:
    """Return the app's state."""
    return request.app.state.locus


StateDep = Annotated[AppState, Depends(get_state)]


async def get_runtime(state: StateDep) -> Runtime:
    """Return the worker runtime, or 503 on a node that runs no workers."""
    if state.runtime is None:
        raise ApiError(503, "this node runs no filter workers")
    return state.runtime


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
