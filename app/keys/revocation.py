"""Revoked keys reach every node quickly: open WebSockets close, cached answers are dropped.

Each API node polls the keys revoked lately (one indexed query per ``poll_s``), so a key
revoked on any node stops working on this node's open WebSockets and requests within a
poll. The window is generous to tolerate clocks of nodes that differ by seconds.
"""

from __future__ import annotations

import asyncio
import logging
from datetime import timedelta

from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from app.core.outages import is_outage
from app.core.security import Principal
from app.keys.cache import KeyCache
from app.keys.service import recently_revoked

log = logging.getLogger(__name__)

WINDOW = timedelta(minutes=2)


class Revocations:
    """The open WebSockets by key, each with an event set when its key is revoked."""

    def __init__(self, sessions: sessionmaker[Session], keys: KeyCache, poll_s: float) -> None:
        self.sessions = sessions
        self.keys = keys
        self.poll_s = poll_s
        self._open: dict[int, set[asyncio.Event]] = {}

    def watch(self, principal: Principal) -> asyncio.Event:
        """Return an event set when the principal's key is revoked (call ``unwatch`` after)."""
        event = asyncio.Event()
        if principal.key_id is not None:
            self._open.setdefault(principal.key_id, set()).add(event)
        return event

    def unwatch(self, principal: Principal, event: asyncio.Event) -> None:
        """Stop watching for a closed WebSocket."""
        events = self._open.get(principal.key_id or -1)
        if events is not None:
            events.discard(event)
            if not events:
                del self._open[principal.key_id or -1]

    def revoked(self, revoked: list[tuple[int, str]]) -> None:
        """Act on revoked keys ((id, hash)): forget their cached answers, close their sockets."""
        self.keys.forget(digest for _, digest in revoked)
        for key_id, _ in revoked:
            for event in self._open.get(key_id, ()):
                event.set()

    async def run(self) -> None:
        """Poll the revocations until cancelled."""
        while True:
            await asyncio.sleep(self.poll_s)
            try:
                found = await asyncio.to_thread(self._recent)
            except SQLAlchemyError as exc:  # the database may be away; the next poll retries
                if is_outage(exc):
                    log.warning("could not read revoked keys: %s", exc.__class__.__name__)
                else:
                    log.exception("could not read revoked keys")
                continue
            if found:
                self.revoked(found)

    def _recent(self) -> list[tuple[int, str]]:
        with self.sessions() as db:
            return recently_revoked(db=db, within=WINDOW)
