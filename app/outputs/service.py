"""Storing and reading a site's outputs, with their delivery status."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from app.core.errors import NotFound
from app.outputs.models import OutboxRow, Output
from app.outputs.schemas import MqttOutput, OutputRead, OutputStatus, WebhookOutput

OPTION_FIELDS = ("topic_prefix", "username", "home_assistant", "batch_max", "rate_limit")
"""Fields of a body kept in the ``options`` column (the rest have columns of their own)."""


def upsert_output(
    *, db: Session, site_id: str, output_id: str, body: MqttOutput | WebhookOutput
) -> tuple[Output, bool]:
    """Create or replace the output; return it and whether it is new.

    Replacing keeps its delivery totals and its outbox: what was stored for it
    is still delivered, to the new address.
    """
    output = db.get(Output, (site_id, output_id))
    created = output is None
    if output is None:
        output = Output(site_id=site_id, id=output_id, delivered=0, failed=0)
        db.add(output)
    fields = body.model_dump()
    output.kind = body.kind
    output.url = body.url
    output.events = ",".join(body.events)
    output.options = json.dumps({k: fields[k] for k in OPTION_FIELDS if k in fields})
    output.secret = body.secret if isinstance(body, WebhookOutput) else body.password
    db.flush()
    return output, created


def get_output(*, db: Session, site_id: str, output_id: str) -> Output:
    """Return the output or raise 404."""
    output = db.get(Output, (site_id, output_id))
    if output is None:
        raise NotFound(f"output {output_id!r} not found in site {site_id!r}")
    return output


def list_outputs(*, db: Session, site_id: str) -> list[Output]:
    """Return the site's outputs by id."""
    return list(db.scalars(select(Output).where(Output.site_id == site_id).order_by(Output.id)))


def delete_output(*, db: Session, output: Output) -> None:
    """Delete the output and what still waits for it."""
    db.execute(
        delete(OutboxRow).where(
            OutboxRow.site_id == output.site_id, OutboxRow.output_id == output.id
        )
    )
    db.delete(output)
    db.flush()


def pending_counts(*, db: Session, site_id: str) -> dict[str, int]:
    """Return the number of messages waiting for each of the site's outputs."""
    rows = db.execute(
        select(OutboxRow.output_id, func.count())
        .where(OutboxRow.site_id == site_id)
        .group_by(OutboxRow.output_id)
    )
    return {output_id: int(n) for output_id, n in rows}


def options(output: Output) -> dict[str, Any]:
    """Return the kind's settings stored with the output."""
    return dict(json.loads(output.options or "{}"))


def to_read(output: Output, pending: int) -> OutputRead:
    """Return the output as the API shows it: no secret, with its status."""
    return OutputRead(
        id=output.id,
        site_id=output.site_id,
        kind=output.kind,  # type: ignore[arg-type]
        url=output.url,
        events=output.events.split(","),
        has_secret=bool(output.secret),
        status=OutputStatus(
            delivered=output.delivered,
            pending=pending,
            failed=output.failed,
            last_error=output.last_error,
            last_ok_at=output.last_ok_at,
        ),
        created_at=output.created_at,
        updated_at=output.updated_at,
        **options(output),
    )


def read_all(*, db: Session, outputs: Sequence[Output], site_id: str) -> list[OutputRead]:
    """Return the outputs as the API shows them, each with its pending count."""
    pending = pending_counts(db=db, site_id=site_id)
    return [to_read(o, pending.get(o.id, 0)) for o in outputs]
