"""Service settings: one pydantic-settings object, read from flags and ``LOCUS_*`` env."""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Everything configurable about a Locus node, with documented defaults."""

    model_config = SettingsConfigDict(env_prefix="LOCUS_", extra="ignore")

    environment: Literal["development", "production", "test"] = "development"
    home: Path = Field(
        default=Path("var"), description="Folder for the embedded database and other local state."
    )
    database_url: str = Field(
        default="", description="SQLAlchemy URL; empty means an embedded SQLite file under home."
    )
    admin_key: str | None = Field(
        default=None, description="Bootstrap admin key; generated and printed once when absent."
    )
    host: str = "127.0.0.1"
    port: int = 8000
    workers: int | None = Field(
        default=None, ge=0, description="Filter worker processes; None = one per core."
    )
    broker: str = Field(default="memory", description="'memory' or a redis:// URL.")
    shards: int = Field(
        default=16, ge=1, description="Streams (shards) on the Redis broker; fixed per deployment."
    )
    stream_maxlen: int = Field(
        default=200_000, description="Approximate cap of each shard stream on Redis."
    )
    lease_s: float = Field(
        default=3.0, gt=0, description="A worker that stops renewing loses its shards after this."
    )
    access_log: bool = Field(default=False, description="Log every HTTP request.")

    # Ingest limits (API.md: 1 MiB body, 10,000 samples).
    max_body_bytes: int = 1 << 20
    max_samples: int = 10_000
    max_future_ms: int = Field(
        default=24 * 3600 * 1000, description="Reject samples this far ahead of the server clock."
    )
    max_inflight_batches: int = Field(
        default=16, description="Queued, unprocessed batches one device may have before 429."
    )
    shard_backlog: int = Field(
        default=5000, description="Queued batches per shard before ingest answers 429."
    )
    overload_policy: Literal["reject", "latest"] = Field(
        default="reject",
        description="Over a shard's backlog: 'reject' answers 429; 'latest' accepts and keeps "
        "only each device's newest batch until the worker catches up (older ones counted dropped).",
    )
    floor_map_max_bytes: int = 32 << 20
    survey_max_bytes: int = 256 << 20

    # Workers.
    reorder_window_ms: int = Field(
        default=2000, description="Samples are held this long (measurement time) to be ordered."
    )
    flush_after_s: float = Field(
        default=2.5,
        description="Wall seconds of silence after which a device's buffer is flushed: longer "
        "than the usual 1 s upload period with its jitter, so a device that keeps uploading "
        "is never flushed between two batches.",
    )
    idle_evict_s: float = Field(
        default=300.0,
        description="Wall seconds of silence after which a device is snapshotted and evicted.",
    )
    snapshot_every_ms: int = Field(
        default=10_000, description="Measurement time between periodic device snapshots."
    )
    raster_cell: float = Field(default=0.25, gt=0, description="Floor raster cell (m).")

    # Track fitting.
    trackfit_processes: int = Field(default=1, ge=1, description="Processes fitting tracks.")
    trackfit_time_limit_s: float = Field(default=30.0, gt=0, description="Per-fit time limit.")

    # Positions fan-out.
    ws_queue_size: int = Field(default=1000, description="Per-subscriber queue before drops.")

    @field_validator("database_url")
    @classmethod
    def _check_url(cls, value: str) -> str:
        if value and "://" not in value:
            raise ValueError("database_url must be a SQLAlchemy URL such as sqlite:///file.db")
        return value

    @property
    def resolved_database_url(self) -> str:
        """Return the database URL, defaulting to a SQLite file under ``home``."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.home / 'locus.db').resolve()}"

    @property
    def worker_count(self) -> int:
        """Return the number of filter worker processes to start."""
        if self.workers is not None:
            return self.workers
        return os.cpu_count() or 1


@lru_cache
def get_settings() -> Settings:
    """Return the process-wide settings (cached; tests override via dependency_overrides)."""
    return Settings()
