"""API keys: generation, hashing, and the principal a request acts as."""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass
from typing import Literal

Role = Literal["admin", "device", "viewer"]
ROLES: tuple[Role, ...] = ("admin", "device", "viewer")
Refusal = Literal["unknown", "revoked"]
"""Why a presented key does not authenticate."""


@dataclass(frozen=True)
class Principal:
    """Who is calling: a role, the site a non-admin key is scoped to, and the key's id."""

    role: Role
    site_id: str | None
    key_id: int | None = None

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


MIN_ADMIN_KEY_CHARS = 24
PLACEHOLDERS = ("changeme", "replaceme", "placeholder", "yourkey", "secret", "password", "example")
MAKE_KEY = 'python -c "import secrets; print(secrets.token_urlsafe(32))"'


def weak_key_reason(key: str) -> str | None:
    """Return why ``key`` is too weak to be an admin key given by configuration, or None.

    Too short, a known placeholder (``change-me``, ``secret``…), or too few distinct
    characters (``aaaa…``, ``1234…``) to be random.
    """
    letters = "".join(c for c in key.lower() if c.isalnum())
    if len(key) < MIN_ADMIN_KEY_CHARS:
        return f"it has {len(key)} characters, fewer than {MIN_ADMIN_KEY_CHARS}"
    found = next((p for p in PLACEHOLDERS if p in letters), None)
    if found is not None:
        return f"it contains the placeholder '{found}'"
    if len(set(key)) < 10:
        return f"it uses only {len(set(key))} distinct characters"
    return None
