"""Request and response bodies of the sites API."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class SiteConfig(BaseModel):
    """Per-site engine choices."""

    model_config = ConfigDict(extra="forbid")

    engine: Literal["pf", "hmm"] = "pf"


class SiteUpsert(BaseModel):
    """Create or rename a site."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=200)
    config: SiteConfig | None = None


class SiteRead(BaseModel):
    """A site as stored."""

    model_config = ConfigDict(from_attributes=True)

    id: str
    name: str
    config: SiteConfig
    map_version: int
    created_at: datetime
    updated_at: datetime
