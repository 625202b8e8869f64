"""Request and response bodies of the keys API."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, ConfigDict, Field, model_validator

from app.core.security import Role


class KeyCreate(BaseModel):
    """A key to create: admin keys are global, device and viewer keys belong to a site."""

    model_config = ConfigDict(extra="forbid")

    role: Role
    site_id: str | None = Field(default=None, min_length=1, max_length=64)
    label: str | None = Field(default=None, max_length=200)

    @model_validator(mode="after")
    def _scoped(self) -> KeyCreate:
        if self.role != "admin" and self.site_id is None:
            raise ValueError("device and viewer keys need a site_id")
        return self


class KeyCreated(BaseModel):
    """The new key, returned exactly once."""

    key: str
    role: Role
    site_id: str | None
    label: str | None


class KeyRead(BaseModel):
    """The calling key's role and the site it is scoped to."""

    role: Role
    site_id: str | None


class KeyInfo(BaseModel):
    """A stored key as listed: never the key itself, which only its creator saw."""

    model_config = ConfigDict(from_attributes=True)

    id: int
    role: Role
    site_id: str | None
    label: str | None
    created_at: datetime
    revoked_at: datetime | None
