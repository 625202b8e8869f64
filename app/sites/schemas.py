"""Request and response bodies of the sites API."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, computed_field, model_validator


class SiteConfig(BaseModel):
    """Per-site engine choices: the older spelling of a site's ``engine``."""

    model_config = ConfigDict(extra="forbid")

    engine: Literal["pf", "hmm"] = "hmm"


EngineName = Literal["pf", "hmm"]
"""How the site's RSSI devices are positioned: ``pf`` the particle filter on path-loss
models, ``hmm`` the fingerprint + inertial HMM on the built radio map."""


class SiteUpsert(BaseModel):
    """Create or rename a site, optionally choosing its engine.

    ``engine`` is the field to use; ``config.engine`` is the older spelling and
    is kept in step with it. Leaving both out keeps the stored choice.
    """

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=200)
    engine: EngineName | None = None
    config: SiteConfig | None = None

    @model_validator(mode="after")
    def _one_engine(self) -> SiteUpsert:
        if (
            self.engine is not None
            and self.config is not None
            and "engine" in self.config.model_fields_set
            and self.config.engine != self.engine
        ):
            raise ValueError("engine and config.engine disagree")
        return self

    def chosen_engine(self) -> str | None:
        """Return the engine the body asks for, or None when it does not say."""
        if self.engine is not None:
            return self.engine
        if self.config is not None:
            return self.config.engine
        return None


class SiteRead(BaseModel):
    """A site as stored."""

    model_config = ConfigDict(from_attributes=True)

    id: str
    name: str
    engine: EngineName
    map_version: int
    created_at: datetime
    updated_at: datetime

    @computed_field  # type: ignore[prop-decorator]
    @property
    def config(self) -> SiteConfig:
        """The engine in its older spelling, for clients that read ``config.engine``."""
        return SiteConfig(engine=self.engine)
