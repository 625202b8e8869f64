"""A short-lived cache of resolved API keys for the request path."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterable

from sqlalchemy.orm import Session, sessionmaker

from app.core.security import Principal, Refusal, hash_key
from app.keys.service import resolve_key


class KeyCache:
    """Key → principal, trusted for ``ttl_s`` seconds without the database.

    Unknown keys are remembered too (with why they fail), so repeated bad keys cost no
    queries. Only key hashes are held; past ``max_entries`` the cache starts afresh.
    Revoked keys are forgotten as soon as this node learns of the revocation.
    """

    def __init__(self, sessions: sessionmaker[Session], *, ttl_s: float, max_entries: int) -> None:
        self.sessions = sessions
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self._entries: dict[str, tuple[float, Principal | Refusal]] = {}
        self._lookups: dict[str, asyncio.Future[Principal | Refusal]] = {}

    def cached(self, key: str) -> Principal | Refusal | None:
        """Return the cached answer for the key without the database (None: not cached)."""
        hit = self._entries.get(hash_key(key))
        if hit is not None and time.monotonic() - hit[0] < self.ttl_s:
            return hit[1]
        return None

    def resolve(self, key: str) -> Principal | Refusal:
        """Look the key up in the database and remember the answer."""
        now = time.monotonic()
        with self.sessions() as db:
            answer = resolve_key(db=db, key=key)
        if len(self._entries) > self.max_entries:
            self._entries.clear()
        self._entries[hash_key(key)] = (now, answer)
        return answer

    async def lookup(self, key: str) -> Principal | Refusal:
        """Return the key's answer, from the cache or else from one database read in a thread,
        however many requests ask for the same key at once.

        A cached key expires for every request in flight at the same moment: a
        server that has fallen behind holds thousands of requests with the same
        key, and each sent its own read of the same row to the thread pool and
        the database.
        """
        answer = self.cached(key)
        if answer is not None:
            return answer
        digest = hash_key(key)
        pending = self._lookups.get(digest)
        if pending is None:
            pending = asyncio.ensure_future(asyncio.to_thread(self.resolve, key))
            self._lookups[digest] = pending
            pending.add_done_callback(lambda _: self._lookups.pop(digest, None))
        # one caller giving up (its client gone) does not cancel the others' lookup
        return await asyncio.shield(pending)

    def forget(self, hashes: Iterable[str]) -> None:
        """Drop the answers for these key hashes (the keys were revoked)."""
        for digest in hashes:
            self._entries.pop(digest, None)
