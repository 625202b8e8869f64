"""The bootstrap admin key: stored from the settings, or generated and shown once."""

from __future__ import annotations

import sys

from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.db import session_scope
from app.core.security import MAKE_KEY
from app.keys.service import create_key, ensure_key, has_admin, resolve_key


def bootstrap_admin(*, sessions: sessionmaker[Session], settings: Settings) -> str | None:
    """Make sure an admin key exists; return a generated key (to print once) or None.

    ``LOCUS_ADMIN_KEY`` is stored (hashed) if new; a revoked one stops the start
    (ValueError) rather than leaving a server nobody can administer. Without it, the
    first start generates a key; only its hash is kept, so it is shown this once.
    """
    with session_scope(sessions) as db:
        if settings.admin_key:
            if resolve_key(db=db, key=settings.admin_key) == "revoked":
                raise ValueError(
                    f"LOCUS_ADMIN_KEY names a revoked key; set a new one, made with {MAKE_KEY}"
                )
            ensure_key(db=db, key=settings.admin_key, role="admin", label="bootstrap")
            return None
        if has_admin(db=db):
            return None
        return create_key(db=db, role="admin", site_id=None, label="bootstrap")


def announce_admin_key(key: str) -> None:
    """Print a generated admin key once, where the operator will see it."""
    print(
        f"\nLocus generated the admin key (shown once, only its hash is stored):\n  {key}\n",
        file=sys.stderr,
        flush=True,
    )
