"""API keys: generation, hashing, and the principal a request acts as."""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass
from typing import Literal

Role = Literal["admin", "device", "viewer"]
ROLES: tuple[Role, ...] = ("admin", "device", "viewer")


@dataclass(frozen=True)
class Principal:
    """Who is calling: a role, and the site a non-admin key is scoped to."""

    role: Role
    site_id: str | None

    def can_read(self, site_id: str) -> bool:
        """Return whether this key may read the site's maps, positions and streams."""
        return self.role == "admin" or (self.role == "viewer" and self.site_id == site_id)

    def can_report(self, site_id: str) -> bool:
        """Return whether this key may ingest measurements and tracks for the site."""
        return self.role == "admin" or (self.role == "device" and self.site_id == site_id)


def new_key() -> str:
    """Return a fresh random key (256 bits) to show the caller once."""
    return "lk_" + secrets.token_urlsafe(32)


def hash_key(key: str) -> str:
    """Return the stored form of a key; keys are random, so a plain SHA-256 suffices."""
    return hashlib.sha256(key.encode()).hexdigest()
