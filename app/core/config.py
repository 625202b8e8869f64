"""Service settings: one pydantic-settings object, read from flags and ``LOCUS_*`` env.

Every operational limit of a node lives here, with its range and what it is for.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError

from app.core.security import MAKE_KEY, MIN_ADMIN_KEY_CHARS, weak_key_reason

DATABASE_URL_FORMS = (
    "sqlite:///path/to/locus.db or postgresql+psycopg://user:password@host:5432/db "
    "(empty: an embedded SQLite file under home)"
)
DATABASE_DRIVERS = {"sqlite": ("", "pysqlite"), "postgresql": ("psycopg",)}
"""Database backends Locus runs on, with the drivers it ships ('' = the backend's default)."""
BROKER_FORMS = "'memory' (embedded) or a Redis URL such as redis://host:6379/0"
REDIS_SCHEMES = ("redis", "rediss", "unix")

MIB = 1 << 20
DAY_MS = 24 * 3600 * 1000


class Settings(BaseSettings):
    """Everything configurable about a Locus node, with documented defaults."""

    # URLs and keys carry passwords: errors name the setting, never echo its value
    model_config = SettingsConfigDict(
        env_prefix="LOCUS_", extra="ignore", hide_input_in_errors=True
    )

    home: Path = Field(
        default=Path("var"), description="Folder for the embedded database and other local state."
    )
    database_url: str = Field(
        default="", description=f"SQLAlchemy URL of the database: {DATABASE_URL_FORMS}."
    )
    admin_key: str | None = Field(
        default=None,
        description="Bootstrap admin key; generated and printed once when absent. A weak one "
        f"(under {MIN_ADMIN_KEY_CHARS} characters, a placeholder) is refused.",
    )
    host: str = Field(default="127.0.0.1", description="Address the API listens on.")
    port: int = Field(default=8000, ge=0, le=65535, description="Port the API listens on.")
    workers: int | None = Field(
        default=None, ge=0, le=1024, description="Filter worker processes; None = one per core."
    )
    broker: str = Field(
        default="memory", description=f"Where batches go to the workers: {BROKER_FORMS}."
    )
    shards: int = Field(
        default=16,
        ge=1,
        le=4096,
        description="Streams (shards) on the Redis broker; fixed per deployment.",
    )
    stream_maxlen: int = Field(
        default=200_000,
        ge=1,
        le=10**9,
        description="Approximate cap of each shard stream on Redis.",
    )
    lease_s: float = Field(
        default=3.0,
        gt=0,
        le=300,
        description="A worker that stops renewing loses its shards after this.",
    )
    access_log: bool = Field(default=False, description="Log every HTTP request.")
    keep_alive_s: int = Field(
        default=75,
        ge=1,
        le=3600,
        description="Seconds an idle HTTP connection stays open. Devices post every second "
        "to every minute; at uvicorn's 5 s a tag posting every 10 s opened a connection for "
        "each batch, and an API paused for 5 s closed every idle connection at once when it "
        "resumed, so that all its devices reconnected together. Longer than the 60 s idle "
        "timeout of common load balancers, which must not find a connection closed under them.",
    )
    opentelemetry: bool = Field(
        default=False,
        description="Trace and measure requests with FastAPI's OpenTelemetry instrumentation "
        "(for a deployment that configures an OpenTelemetry SDK); off, requests skip its "
        "per-request check for a configured provider.",
    )

    # Ingest limits (docs/api.md: 1 MiB body, 10,000 samples).
    max_body_bytes: int = Field(
        default=MIB, ge=1, le=1024 * MIB, description="Largest ingest body (bytes)."
    )
    max_samples: int = Field(
        default=10_000, ge=1, le=10_000_000, description="Most samples in one ingest batch."
    )
    bulk_max_body_bytes: int = Field(
        default=8 * MIB,
        ge=1,
        le=4096 * MIB,
        description="Largest bulk ingest body (bytes): eight single bodies; each of its batches "
        "is also held to max_body_bytes.",
    )
    bulk_max_batches: int = Field(
        default=1000, ge=1, le=1_000_000, description="Most batches in one bulk ingest body."
    )
    bulk_max_samples: int = Field(
        default=100_000,
        ge=1,
        le=100_000_000,
        description="Most samples in one bulk ingest body (ten single batches' worth); each "
        "batch is also held to max_samples.",
    )
    max_future_ms: int = Field(
        default=DAY_MS,
        ge=0,
        le=365 * DAY_MS,
        description="Reject samples this far ahead of the server clock.",
    )
    max_inflight_batches: int = Field(
        default=16,
        ge=1,
        le=1_000_000,
        description="Queued, unprocessed batches one device may have before 429.",
    )
    shard_backlog: int = Field(
        default=5000,
        ge=1,
        le=10_000_000,
        description="Queued batches per shard before ingest answers 429.",
    )
    overload_policy: Literal["reject", "latest"] = Field(
        default="reject",
        description="Over a shard's backlog: 'reject' answers 429; 'latest' accepts and keeps "
        "only each device's newest batch until the worker catches up (older ones counted dropped).",
    )
    ingest_wait_timeout_s: float = Field(
        default=60.0,
        gt=0,
        le=3600,
        description="How long ``?wait=true`` waits for a batch's processing before answering "
        "503 (the batch stays queued).",
    )
    floor_map_max_bytes: int = Field(
        default=32 * MIB, ge=1, le=1024 * MIB, description="Largest floor-map upload (bytes)."
    )
    floor_max_extent_m: float = Field(
        default=3000.0,
        gt=0,
        le=100_000,
        description="Widest floor map accepted (m, along x or y): a map drawn in another unit "
        "is refused naming its size instead of being rasterised.",
    )
    floor_max_raster_cells: int = Field(
        default=16_000_000,
        ge=1,
        le=1_000_000_000,
        description="Largest occupancy raster of one floor (cells of raster_cell; 16 million "
        "is 1 km × 1 km at 0.25 m), held by the API and every worker process.",
    )
    survey_max_bytes: int = Field(
        default=256 * MIB, ge=1, le=4096 * MIB, description="Largest survey upload (bytes)."
    )

    # Caches of the request path.
    site_cache_ttl_s: float = Field(
        default=2.0,
        ge=0,
        le=300,
        description="Ingest re-reads a site's map version at most this often: how long another "
        "node's map change may take to reach this node's batches.",
    )
    key_cache_ttl_s: float = Field(
        default=30.0,
        ge=0,
        le=3600,
        description="A resolved API key is trusted this long without the database (a revoked "
        "key is dropped from it within key_revocation_poll_s).",
    )
    key_revocation_poll_s: float = Field(
        default=0.5,
        gt=0,
        le=60,
        description="Each API node reads the keys revoked lately this often: a revoked key "
        "stops working on its open WebSockets (and in its key cache) within this.",
    )
    key_cache_size: int = Field(
        default=10_000,
        ge=1,
        le=10_000_000,
        description="Keys remembered at most; the cache starts afresh beyond this.",
    )

    # Workers.
    wifi_max_age_ms: int = Field(
        default=10_000,
        ge=0,
        le=600_000,
        description="A WiFi reading whose last_seen is older than this before its scan's t "
        "describes another place and is dropped at ingest. Below it, a site's radio-map build "
        "chooses how old a reading its engines use (the tuning's wifi_max_age_ms).",
    )
    time_outlier_s: float = Field(
        default=3600.0,
        gt=0,
        le=30 * 24 * 3600,
        description="A sample this far from the median time of its batch or survey comes from "
        "a clock that jumped: it is dropped (code time_outlier), and a survey waypoint that far "
        "refuses the survey. Times are compared within the body, never with the server's "
        "clock, so old recordings replay; a survey may span twice this.",
    )
    reorder_window_ms: int = Field(
        default=2000,
        ge=0,
        le=600_000,
        description="Samples are held this long (measurement time) to be ordered.",
    )
    flush_after_s: float = Field(
        default=2.5,
        ge=0,
        le=3600,
        description="Wall seconds of silence after which a device's buffer is flushed: longer "
        "than the usual 1 s upload period with its jitter, so a device that keeps uploading "
        "is never flushed between two batches.",
    )
    flush_after_periods: float = Field(
        default=2.5,
        ge=0,
        le=100,
        description="Nor is a device flushed within this many of its own upload periods (the "
        "smoothed gap between its batches' arrivals): a tag that uploads every 10 s, or a "
        "device whose answers come late under load, keeps uploading between its batches. "
        "0 flushes after flush_after_s whatever the device's period.",
    )
    idle_evict_s: float = Field(
        default=300.0,
        gt=0,
        le=7 * 24 * 3600,
        description="Wall seconds of silence after which a device is snapshotted and evicted.",
    )
    silence_scan_every_ms: int = Field(
        default=100,
        ge=1,
        le=60_000,
        description="Wall ms between a shard's scans for silent devices to flush or evict.",
    )
    worker_max_messages: int = Field(
        default=500,
        ge=1,
        le=100_000,
        description="At most this many queued messages a worker takes in one round.",
    )
    worker_linger_ms: float = Field(
        default=5.0,
        ge=0,
        le=1000,
        description="A worker of the embedded broker waits up to this long after a round's "
        "first message for more: a round costs about as much for one device as for a few "
        "(the filter's numpy calls, the database transaction), so lingering trades a few "
        "ms of latency for CPU per update.",
    )
    worker_stats_every_s: float = Field(
        default=1.0,
        gt=0,
        le=3600,
        description="Wall seconds between a worker's reports of its counters and queue depth.",
    )
    heap_trim_every_s: float = Field(
        default=5.0,
        ge=0,
        le=86400,
        description="Wall seconds between the API's and each worker's return of the C "
        "allocator's free pages to the system (glibc ``malloc_trim``); 0 never. Without it "
        "a process under steady load keeps growing by the freed pages it retains; trimmed, "
        "its resident memory stays flat (``python -m bench.soak`` follows it), and a trim is "
        "cheap.",
    )
    api_malloc_arenas: int = Field(
        default=2,
        ge=0,
        le=1024,
        description="The most C allocator arenas the API process keeps (glibc ``mallopt``, "
        "as ``MALLOC_ARENA_MAX``); 0 leaves glibc's eight a core. Each thread of the API's "
        "pool would otherwise hold an arena of its own whose freed pages no other reuses.",
    )
    worker_mmap_threshold_bytes: int = Field(
        default=128 * 1024,
        ge=0,
        le=32 * 1024 * 1024,
        description="A worker's C allocations of this many bytes or more get a mapping of "
        "their own, unmapped when freed (glibc ``mallopt``); 0 leaves glibc's threshold, "
        "which rises to the largest block freed so far and lets a worker's heap grow "
        "under steady load while the bytes it holds stay flat.",
    )
    snapshot_every_ms: int = Field(
        default=10_000,
        ge=0,
        le=DAY_MS,
        description="Measurement time between a device's periodic snapshots, each device at "
        "its own phase of the period so that devices started together do not store theirs "
        "in the same round.",
    )
    zone_dwell_s: float = Field(
        default=2.0,
        ge=0,
        le=3600,
        description="Measurement time a device must stay inside a zone before its enter event, "
        "and outside before its exit (each reported at the crossing's time), so a filter's "
        "jitter at a doorway does not flicker; 0 reports every crossing.",
    )
    zone_exit_tolerance: float = Field(
        default=1.0,
        ge=0,
        le=10,
        description="A position outside a zone the device is in, by less than this multiple "
        "of its accuracy radius, still counts as inside: the filter's error is not a step "
        "out (0: the zone's edge alone decides).",
    )
    output_refresh_s: float = Field(
        default=2.0,
        gt=0,
        le=300,
        description="Workers read a site's outputs again after this: a new output gets what "
        "is stored from at most this long after it was created.",
    )
    output_poll_s: float = Field(
        default=0.05,
        gt=0,
        le=60,
        description="How often an idle output's dispatcher looks for new messages.",
    )
    output_lease_s: float = Field(
        default=10.0,
        gt=0,
        le=600,
        description="An API node delivers an output under a lease it renews every third of "
        "this; another node takes the output over once the lease runs out.",
    )
    output_batch_max: int = Field(
        default=500,
        ge=1,
        le=10_000,
        description="Most messages an output's dispatcher reads and sends in one go.",
    )
    output_rate_limit: float = Field(
        default=5000,
        gt=0,
        le=100_000,
        description="Messages per second an output is sent at most, unless it sets its own.",
    )
    output_retry_base_s: float = Field(
        default=0.5,
        gt=0,
        le=60,
        description="First delay before a failed delivery is tried again; each further "
        "failure doubles it (with jitter) up to output_retry_max_s.",
    )
    output_retry_max_s: float = Field(
        default=30.0, gt=0, le=3600, description="Longest delay between delivery attempts."
    )
    output_retention_s: float = Field(
        default=86_400,
        gt=0,
        le=30 * 86_400,
        description="A message not delivered this long after it was stored is given up: "
        "counted failed in /metrics and on the output's status.",
    )
    output_timeout_s: float = Field(
        default=10.0,
        gt=0,
        le=300,
        description="Longest wait for a webhook's answer or a broker's acknowledgement.",
    )
    raster_cell: float = Field(default=0.25, gt=0, le=10, description="Floor raster cell (m).")
    warm_sites: bool = Field(
        default=True,
        description="Workers build every site's rasters and engines when they start and when "
        "the site changes, so a new device's first batch does not wait for them; off, a "
        "worker builds a site on its first batch there and holds only the sites it serves.",
    )
    site_poll_s: float = Field(
        default=1.0,
        gt=0,
        le=3600,
        description="Wall seconds between a worker's reads of the sites' map versions, to "
        "warm the sites that changed and forget deleted ones (with warm_sites).",
    )

    # Background jobs: radio-map builds and track fits.
    job_lease_s: float = Field(
        default=30.0,
        gt=0,
        le=3600,
        description="A process renews its unfinished radio-map builds and track fits every "
        "third of this; one that nobody renewed this long lost its process (a restart or "
        "crash) and is marked failed.",
    )

    # Radio-map builds.
    radiomap_folds: int = Field(
        default=5,
        ge=2,
        le=100,
        description="Folds of the held-out accuracy estimate of a build (whole walks held out).",
    )
    radiomap_tuning: bool = Field(
        default=True,
        description="A build chooses the site's constants (PDR, k-NN, emission and floor "
        "weights, heading noise) from its surveys; off, it keeps the engines' defaults and "
        "learns only the accuracy floor.",
    )
    radiomap_hmm_walks: int = Field(
        default=20,
        ge=0,
        le=1000,
        description="Held-out survey walks per fold a build replays through the HMM to choose "
        "its emission and k-NN fix weights and calibrate its radius (0: weights chosen on "
        "single scans instead). A few walks a fold leave the radius scale to the luck of the "
        "walks drawn (``LOCUS_RADIOMAP_HMM_WALKS=6 locus eval ilc`` prints the build's "
        "radius_scale at six).",
    )
    radiomap_progress_step: float = Field(
        default=0.05,
        gt=0,
        le=1,
        description="An asynchronous build's progress is written when it moved this much.",
    )

    # Planning.
    planning_max_cells: int = Field(
        default=400_000,
        ge=1,
        le=100_000_000,
        description="Largest accuracy-map grid computed for one request (cells).",
    )

    # Analytics.
    analytics_max_buckets: int = Field(
        default=10_080,
        ge=1,
        le=1_000_000,
        description="Most buckets one occupancy query answers (10,080: a week by the minute).",
    )
    analytics_max_range_days: float = Field(
        default=31.0,
        gt=0,
        le=3660,
        description="Longest time range (days of measurement time) of one occupancy or "
        "heatmap query.",
    )
    heatmap_gap_cap_s: float = Field(
        default=5.0,
        gt=0,
        le=3600,
        description="A position weighs the time until its device's next position, at most "
        "this long: a device sends at least once a second, so a longer gap is silence, and "
        "a device that went quiet does not paint its last cell for hours.",
    )
    heatmap_max_cells: int = Field(
        default=400_000,
        ge=1,
        le=100_000_000,
        description="Largest heatmap grid computed for one request (cells).",
    )
    export_page_rows: int = Field(
        default=5000,
        ge=1,
        le=1_000_000,
        description="Positions read per query while an export streams: bounds the memory an "
        "export of months holds at once.",
    )

    # Track fitting.
    trackfit_processes: int = Field(
        default=1, ge=1, le=256, description="Processes fitting tracks."
    )
    trackfit_time_limit_s: float = Field(
        default=30.0, gt=0, le=3600, description="Per-fit time limit."
    )

    # Positions fan-out.
    ws_queue_size: int = Field(
        default=1000, ge=1, le=1_000_000, description="Per-subscriber queue before drops."
    )

    @field_validator("admin_key")
    @classmethod
    def _check_admin_key(cls, value: str | None) -> str | None:
        if not value:
            return None
        reason = weak_key_reason(value)
        if reason is not None:
            raise ValueError(
                f"admin_key (LOCUS_ADMIN_KEY) is too weak: {reason}. Make a random one with "
                f"{MAKE_KEY}, or leave it unset and Locus generates one at the first start"
            )
        return value

    @field_validator("database_url")
    @classmethod
    def _check_database_url(cls, value: str) -> str:
        if not value:
            return value
        try:
            url = make_url(value)
        except ArgumentError:
            raise ValueError(
                f"database_url is not a database URL; use {DATABASE_URL_FORMS}"
            ) from None
        drivers = DATABASE_DRIVERS.get(url.get_backend_name())
        if drivers is None or (url.drivername.partition("+")[2] not in drivers):
            raise ValueError(
                f"database_url has the unsupported scheme {url.drivername!r}; "
                f"use {DATABASE_URL_FORMS}"
            )
        return value

    @field_validator("broker")
    @classmethod
    def _check_broker(cls, value: str) -> str:
        scheme, separator, _ = value.partition("://")
        if value != "memory" and not (separator and scheme in REDIS_SCHEMES):
            given = f"a {scheme!r} URL" if separator else "neither"
            raise ValueError(f"broker must be {BROKER_FORMS}; it is {given}")
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
