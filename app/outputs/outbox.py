"""The outbox's writing side: what a worker adds, in its own transaction, for each output.

A worker stores a round's positions in one transaction; the messages for the
site's outputs are inserted in that same transaction, so a position is stored
with its outbox rows or not at all, and a crash between the two cannot lose
one. Which outputs a site has is read from the database and kept for
``refresh_ms``: an output created or removed is seen by the workers within
that time.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

from sqlalchemy import Table, insert, select
from sqlalchemy.orm import Session
from sqlalchemy.sql.expression import Executable

from app.outputs.models import OutboxRow, Output

Message = dict[str, Any]
"""A position or zone event as the WebSocket streams it (``type``, ``site_id``, ...)."""


@dataclass(frozen=True)
class Target:
    """An output of a site and the kinds of message it takes."""

    output_id: str
    events: frozenset[str]


class Outbox:
    """Turns a round's messages into outbox rows for the outputs of their sites."""

    def __init__(self, *, refresh_ms: int, clock: Callable[[], int]) -> None:
        self.refresh_ms = refresh_ms
        self.clock = clock
        self._targets: dict[str, tuple[int, list[Target]]] = {}

    def targets(self, db: Session, site_ids: set[str]) -> dict[str, list[Target]]:
        """Return the outputs of each site, read again when older than ``refresh_ms``."""
        now = self.clock()
        stale = [s for s in site_ids if s not in self._targets or self._expired(s, now)]
        if stale:
            found: dict[str, list[Target]] = {s: [] for s in stale}
            rows = db.execute(
                select(Output.site_id, Output.id, Output.events).where(Output.site_id.in_(stale))
            )
            for site_id, output_id, events in rows:
                found[site_id].append(Target(output_id, frozenset(events.split(","))))
            for site_id, targets in found.items():
                self._targets[site_id] = (now, targets)
        return {s: self._targets[s][1] for s in site_ids}

    def _expired(self, site_id: str, now: int) -> bool:
        return now - self._targets[site_id][0] >= self.refresh_ms

    def add(self, db: Session, messages: Sequence[Message]) -> int:
        """Insert a row per message and output that takes it; return how many.

        Refined (smoothed) positions stay in the history: a receiver gets the
        live track, each position once, in time order per device.
        """
        wanted = [m for m in messages if not m.get("smoothed")]
        if not wanted:
            return 0
        targets = self.targets(db, {m["site_id"] for m in wanted})
        if not any(targets.values()):
            return 0
        stored_at = self.clock()
        rows = []
        for message in wanted:
            kind = message["type"]
            payload = None
            for target in targets[message["site_id"]]:
                if kind not in target.events:
                    continue
                payload = payload or json.dumps(_wire(message), separators=(",", ":"))
                rows.append(
                    {
                        "site_id": message["site_id"],
                        "output_id": target.output_id,
                        "device_id": message["device_id"],
                        "kind": kind,
                        "payload": payload,
                        "stored_at": stored_at,
                    }
                )
        if rows:
            db.execute(_insert(), rows)
        return len(rows)


def _wire(message: Message) -> Message:
    """Return the message as a receiver gets it: the WebSocket's, less internal fields."""
    return {k: v for k, v in message.items() if k not in ("odometry_x", "odometry_y")}


@cache
def _insert() -> Executable:
    table = OutboxRow.__table__
    assert isinstance(table, Table)
    return insert(table)
