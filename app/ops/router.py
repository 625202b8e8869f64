"""Operations: liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel
from sqlalchemy import text

from app import __version__
from app.core.errors import Unavailable
from app.state import StateDep

router = APIRouter(tags=["operations"])


class Health(BaseModel):
    """A health answer."""

    status: str
    database: bool | None = None
    workers: bool | None = None


class Alive(Health):
    """The liveness answer, with the installed package's version (pyproject.toml's)."""

    version: str = __version__


@router.get("/healthz", response_model=Alive)
def healthz() -> Alive:
    """Answer while the process serves requests (no key needed), with Locus's version."""
    return Alive(status="ok")


@router.get("/readyz", response_model=Health)
def readyz(state: StateDep) -> Health:
    """Answer 200 when the database answers and workers process this node's ingest, else 503
    with the reasons: a node without workers of its own or a broker to reach others (the
    embedded broker with ``--workers 0``) serves ingest it can never process."""
    try:
        with state.engine.connect() as conn:
            conn.execute(text("SELECT 1"))
        database = True
    except Exception:
        database = False
    reasons = [] if database else ["the database does not answer"]
    if state.runtime is None:
        workers = False
        reasons.append(
            "this node runs no filter workers and reaches none (embedded broker, --workers 0): "
            "it would accept ingest it cannot process"
        )
    else:
        workers = state.runtime.broker.healthy()
        if not workers:
            reasons.append("a shard has no live filter worker, or the broker does not answer")
    if reasons:
        raise Unavailable(
            "not ready",
            details=[{"database": database, "workers": workers, "reasons": reasons}],
        )
    return Health(status="ready", database=database, workers=workers)


@router.get("/metrics", response_class=Response)
def metrics(state: StateDep) -> Response:
    """Return Prometheus metrics of this API node and its workers."""
    return Response(generate_latest(state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
