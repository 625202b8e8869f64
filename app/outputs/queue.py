"""The outbox's delivering side: leases on outputs, the next batch, acknowledgement, failure.

Plain SQLAlchemy on one session each, so the same statements run on SQLite
and PostgreSQL. An output is delivered by the one API node holding its lease
(``claimed_by`` until ``claimed_until``): the conditional UPDATE that takes it
is atomic on both (PostgreSQL re-checks the condition on the row it waited
for), so with several nodes each output, and so each message, has one sender.
"""

from __future__ import annotations

from datetime import datetime, timedelta

from sqlalchemy import delete, func, or_, select, update
from sqlalchemy.orm import Session
from sqlalchemy.sql.elements import ColumnElement

from app.outputs.models import OutboxRow, Output

OutputKey = tuple[str, str]
"""(site id, output id)."""
UNCHANGED = {"updated_at": Output.updated_at}
"""Values that keep an output's ``updated_at`` through the delivery's bookkeeping: it says
when the configuration changed, and the dispatcher restarts an output's delivery when it
does (a lease renewal or an acknowledgement moving it would cut every send short)."""


def claim(db: Session, *, node: str, now: datetime, lease_s: float) -> list[Output]:
    """Take or renew the lease of every output free or held by ``node``; return those held."""
    db.execute(
        update(Output)
        .where(
            or_(
                Output.claimed_by == node,
                Output.claimed_by.is_(None),
                Output.claimed_until < now,
            )
        )
        .values(claimed_by=node, claimed_until=now + timedelta(seconds=lease_s), **UNCHANGED)
        .execution_options(synchronize_session=False)
    )
    return list(db.scalars(select(Output).where(Output.claimed_by == node)))


def release(db: Session, *, node: str) -> None:
    """Give up ``node``'s leases, so another node takes its outputs at once."""
    db.execute(
        update(Output)
        .where(Output.claimed_by == node)
        .values(claimed_by=None, claimed_until=None, **UNCHANGED)
        .execution_options(synchronize_session=False)
    )


def _own(key: OutputKey) -> tuple[ColumnElement[bool], ColumnElement[bool]]:
    return OutboxRow.site_id == key[0], OutboxRow.output_id == key[1]


def next_batch(db: Session, *, key: OutputKey, limit: int, keep: bool) -> list[OutboxRow]:
    """Return the oldest messages waiting for the output, up to ``limit``.

    With ``keep`` (webhooks) the batch is written down on its rows: a batch
    that failed is sent again as it was, whatever has arrived since, so that
    its ``webhook-id`` (the first row's) is the same on every retry.
    """
    head = db.scalar(select(OutboxRow).where(*_own(key)).order_by(OutboxRow.id).limit(1))
    if head is None:
        return []
    if head.batch is not None:
        query = select(OutboxRow).where(*_own(key), OutboxRow.batch == head.batch)
        return list(db.scalars(query.order_by(OutboxRow.id)))
    query = select(OutboxRow).where(*_own(key), OutboxRow.batch.is_(None))
    rows = list(db.scalars(query.order_by(OutboxRow.id).limit(limit)))
    if keep and rows:
        db.execute(
            update(OutboxRow)
            .where(OutboxRow.id.in_([r.id for r in rows]))
            .values(batch=rows[0].id)
            .execution_options(synchronize_session=False)
        )
        for row in rows:
            row.batch = rows[0].id
    return rows


def acknowledge(db: Session, *, key: OutputKey, ids: list[int], now: datetime) -> None:
    """Remove delivered messages and count them on the output."""
    db.execute(delete(OutboxRow).where(OutboxRow.id.in_(ids)))
    db.execute(
        update(Output)
        .where(Output.site_id == key[0], Output.id == key[1])
        .values(delivered=Output.delivered + len(ids), last_ok_at=now, last_error=None, **UNCHANGED)
        .execution_options(synchronize_session=False)
    )


def record_failure(db: Session, *, key: OutputKey, error: str, stored_before: int) -> int:
    """Note a failed attempt; give up the messages stored before ``stored_before`` (epoch
    ms), count them failed, and return how many."""
    expired = db.execute(
        delete(OutboxRow).where(*_own(key), OutboxRow.stored_at < stored_before)
    ).rowcount  # type: ignore[attr-defined]
    db.execute(
        update(Output)
        .where(Output.site_id == key[0], Output.id == key[1])
        .values(failed=Output.failed + int(expired), last_error=error[:500], **UNCHANGED)
        .execution_options(synchronize_session=False)
    )
    return int(expired)


def drop_orphans(db: Session, *, known: set[OutputKey]) -> int:
    """Delete rows written for outputs that no longer exist (a worker had not yet seen the
    removal); return how many."""
    found = db.execute(select(OutboxRow.site_id, OutboxRow.output_id).distinct()).all()
    gone = [(s, o) for s, o in found if (s, o) not in known]
    removed = 0
    for site_id, output_id in gone:
        # an output created since ``known`` was read keeps its rows
        if db.get(Output, (site_id, output_id)) is None:
            removed += int(
                db.execute(delete(OutboxRow).where(*_own((site_id, output_id)))).rowcount  # type: ignore[attr-defined,unused-ignore]
            )
    return removed


def pending(db: Session) -> dict[OutputKey, int]:
    """Return the number of messages waiting for each output that has any."""
    rows = db.execute(
        select(OutboxRow.site_id, OutboxRow.output_id, func.count()).group_by(
            OutboxRow.site_id, OutboxRow.output_id
        )
    )
    return {(s, o): int(n) for s, o, n in rows}
