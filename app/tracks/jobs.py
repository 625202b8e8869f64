"""Track-fit jobs: queued tracks fitted in a process pool off the event loop, their results
stored and the device's fitted position published."""

from __future__ import annotations

import asyncio
import math
import multiprocessing as mp
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.db import session_scope
from app.core.jobs import tend_jobs
from app.core.time import now_ms, utcnow
from app.devices.service import touch_devices
from app.positions.service import store as store_positions
from app.tracks.fitting import fit_in_pool
from app.tracks.models import Track

FIT_FIELDS = (
    "rotation",
    "scale",
    "drift",
    "relaxed",
    "spread",
    "accuracy",
    "anchors",
    "ambiguous",
    "candidates",
    "fitted",
    "reason",
    "margin",
    "bias",
)
"""What a fit knows of itself, stored with its points and shown by ``GET /v1/tracks/{id}``."""

Publish = Callable[[list[dict[str, Any]]], None]
"""Hands position messages to the live subscribers."""


def _finite(value: Any) -> Any:
    """Return ``value`` with every non-finite float replaced by None.

    A fit that fails scores infinity, which JSON (and PostgreSQL's JSON type)
    cannot hold: it is stored and shown as null.
    """
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


class TrackFitter:
    """Runs fits in a process pool and records their outcome; lives as long as the app."""

    def __init__(
        self, settings: Settings, sessions: sessionmaker[Session], publish: Publish | None
    ) -> None:
        self.settings = settings
        self.sessions = sessions
        self.publish = publish
        self.pool: ProcessPoolExecutor | None = None
        self._running: dict[str, asyncio.Task[None]] = {}
        """The unfinished jobs of this process, by id."""

    def start(self) -> None:
        """Create the pool (processes start on first use)."""
        self.pool = ProcessPoolExecutor(
            max_workers=self.settings.trackfit_processes, mp_context=mp.get_context("spawn")
        )

    def stop(self) -> None:
        """Stop the pool."""
        if self.pool is not None:
            self.pool.shutdown(wait=False, cancel_futures=True)

    def submit(self, track_id: str, job: dict[str, Any]) -> None:
        """Fit a stored, queued track in the background."""
        task = asyncio.create_task(self.run(track_id, job))
        self._running[track_id] = task
        task.add_done_callback(lambda _: self._running.pop(track_id, None))

    async def tend(self) -> int:
        """Renew this process's unfinished fits and fail those no process renewed for a lease
        (see ``app.core.jobs``); return how many failed."""
        alive = tuple(self._running)
        return await asyncio.to_thread(self._tend, alive)

    def _tend(self, alive: tuple[str, ...]) -> int:
        with session_scope(self.sessions) as db:
            return tend_jobs(
                db, Track, alive=alive, now=utcnow(), lease_s=self.settings.job_lease_s
            )

    async def run(self, track_id: str, job: dict[str, Any]) -> None:
        """Fit one queued track, store the result and publish the device's new position."""
        assert self.pool is not None
        job = job | {
            "cell": self.settings.raster_cell,
            "time_limit_s": self.settings.trackfit_time_limit_s,
        }
        await asyncio.to_thread(self._set_status, track_id, "running")
        result = await asyncio.get_running_loop().run_in_executor(self.pool, fit_in_pool, job)
        position = await asyncio.to_thread(self._finish, track_id, result)
        if position is not None and self.publish is not None:
            self.publish([position])

    def _set_status(self, track_id: str, status: str) -> None:
        with session_scope(self.sessions) as db:
            track = db.get(Track, track_id)
            if track is not None:
                track.status = status

    def _finish(self, track_id: str, result: dict[str, Any]) -> dict[str, Any] | None:
        with session_scope(self.sessions) as db:
            track = db.get(Track, track_id)
            if track is None:
                return None
            track.status = result["status"]
            track.result = _finite(
                {"points": result.get("points", [])}
                | {key: result[key] for key in FIT_FIELDS if key in result}
            )
            track.score = _finite(result.get("score"))
            track.elapsed_ms = result.get("elapsed_ms")
            track.error = result.get("error")
            if result["status"] != "done" or not result.get("points"):
                return None
            last = result["points"][-1]
            position = {
                "type": "position",
                "device_id": track.device_id,
                "site_id": track.site_id,
                "floor_id": track.floor_id,
                "t": last["t"],
                "x": last["x"],
                "y": last["y"],
                "z": 0.0,
                "heading": None,
                "accuracy": result["accuracy"],
                "speed": None,
                "method": "trackfit",
                "computed_at": now_ms(),
                "smoothed": False,
            }
            store_positions(db, [{k: v for k, v in position.items() if k != "type"}])
            key = (track.site_id, track.device_id)
            touch_devices(db=db, heard=[(key, last["t"])], now=position["computed_at"])
            return position
