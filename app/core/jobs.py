"""Background jobs held by a lease, so a job whose process is gone does not stay unfinished.

Radio-map builds and track fits run inside the API process that accepted them:
a restart or crash ends them, but their rows would stay ``queued`` or
``running`` for good. A starting process cannot simply fail every unfinished
job it finds, because several API processes may share one database
(``docker/compose.yaml`` runs two behind a proxy) and a neighbour may be
running it. So each process renews its own unfinished jobs every third of the
lease, and any process marks failed the jobs nobody renewed for a whole lease.
A restarted process fails its predecessor's jobs at start when they are older
than a lease, otherwise within one lease.
"""

from __future__ import annotations

from collections.abc import Collection
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import update
from sqlalchemy.orm import Session

UNFINISHED = ("queued", "running")


def abandoned_reason(now: datetime) -> str:
    """Return the error recorded on a job whose process is gone."""
    return (
        "interrupted by a server restart or crash (found abandoned at "
        f"{now:%Y-%m-%dT%H:%M:%SZ}); submit it again"
    )


def tend_jobs(
    db: Session, model: type[Any], *, alive: Collection[str], now: datetime, lease_s: float
) -> int:
    """Renew the jobs this process runs (``alive``), fail every other unfinished job of
    ``model`` unrenewed for ``lease_s``, and return how many failed.

    ``model`` is a job table with ``id``, ``status``, ``error`` and ``updated_at``; ``now``
    is an aware UTC time.
    """
    if alive:
        db.execute(
            update(model)
            .where(model.id.in_(alive), model.status.in_(UNFINISHED))
            .values(updated_at=now)
        )
    result = db.execute(
        update(model)
        .where(model.status.in_(UNFINISHED), model.updated_at < now - timedelta(seconds=lease_s))
        .values(status="failed", error=abandoned_reason(now), updated_at=now)
    )
    return int(result.rowcount)  # type: ignore[attr-defined]
