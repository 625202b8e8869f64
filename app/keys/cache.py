"""A short-lived cache of resolved API keys for the request path."""

from __future__ import annotations

import time

from sqlalchemy.orm import Session, sessionmaker

from app.core.security import Principal, hash_key
from app.keys.service import resolve_key


class KeyCache:
    """Key → principal, trusted for ``ttl_s`` seconds without the database.

    Unknown keys are remembered too (as None), so repeated bad keys cost no
    queries. Only key hashes are held; past ``max_entries`` the cache starts afresh.
    """

    def __init__(self, sessions: sessionmaker[Session], *, ttl_s: float, max_entries: int) -> None:
        self.sessions = sessions
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self._entries: dict[str, tuple[float, Principal | None]] = {}

    def cached(self, key: str) -> tuple[bool, Principal | None]:
        """Return (cached?, principal or None for a key known to be unknown) without the
        database."""
        hit = self._entries.get(hash_key(key))
        if hit is not None and time.monotonic() - hit[0] < self.ttl_s:
            return True, hit[1]
        return False, None

    def resolve(self, key: str) -> Principal | None:
        """Look the key up in the database (None if unknown) and remember the answer."""
        now = time.monotonic()
        with self.sessions() as db:
            principal = resolve_key(db=db, key=key)
        if len(self._entries) > self.max_entries:
            self._entries.clear()
        self._entries[hash_key(key)] = (now, principal)
        return principal
