"""Tracks: queue a fit in the process pool, store its result, publish the device's position."""

from __future__ import annotations

import asyncio
import json
import logging
import uuid
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import shapely
from sqlalchemy import insert
from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.db import session_scope
from app.core.errors import ApiError
from app.core.time import now_ms
from app.floors.service import get_floor
from app.geometry.floormap import parse_floor_map
from app.positions.models import Position
from app.sites.models import Site
from app.tracks.fitting import run_fit
from app.tracks.models import Track
from app.tracks.schemas import TrackCreate

log = logging.getLogger(__name__)


def create_track(*, db: Session, body: TrackCreate) -> tuple[Track, dict[str, Any]]:
    """Check the track against its floor and store it queued; return it and the pool job."""
    site = db.get(Site, body.site_id)
    if site is None:
        raise ApiError(404, f"site '{body.site_id}' not found")
    floor = get_floor(db=db, site_id=body.site_id, floor_id=body.floor_id)
    if floor is None:
        raise ApiError(404, f"floor '{body.floor_id}' not found in site '{body.site_id}'")
    walkable = parse_floor_map(floor.geojson).walkable
    if not shapely.intersects_xy(walkable, body.start.x, body.start.y):
        raise ApiError(
            422,
            "the start point is outside the walkable area of the floor",
            details=[{"loc": ["start"], "msg": "outside the walkable area", "type": "off_map"}],
        )
    request = body.model_dump()
    track = Track(
        id=uuid.uuid4().hex,
        site_id=body.site_id,
        floor_id=body.floor_id,
        device_id=body.device_id,
        status="queued",
        request=request,
    )
    db.add(track)
    db.flush()
    job = {
        "site_id": site.id,
        "floor_id": floor.floor_id,
        "version": site.map_version,
        "floor_doc": json.dumps(floor.geojson),
        "request": request,
    }
    return track, job


class TrackFitter:
    """Runs fits in a process pool off the event loop and records their outcome."""

    def __init__(self, settings: Settings, sessions: sessionmaker[Session]) -> None:
        self.settings = settings
        self.sessions = sessions
        self.pool: ProcessPoolExecutor | None = None

    def start(self) -> None:
        """Create the pool (processes start on first use)."""
        import multiprocessing as mp

        self.pool = ProcessPoolExecutor(
            max_workers=self.settings.trackfit_processes, mp_context=mp.get_context("spawn")
        )

    def stop(self) -> None:
        """Stop the pool."""
        if self.pool is not None:
            self.pool.shutdown(wait=False, cancel_futures=True)

    async def run(self, track_id: str, job: dict[str, Any], publish: Any) -> None:
        """Fit one queued track, store the result and publish the device's new position."""
        assert self.pool is not None
        job = job | {
            "cell": self.settings.raster_cell,
            "time_limit_s": self.settings.trackfit_time_limit_s,
        }
        await asyncio.to_thread(self._set_status, track_id, "running")
        result = await asyncio.get_running_loop().run_in_executor(self.pool, run_fit, job)
        position = await asyncio.to_thread(self._finish, track_id, result)
        if position is not None:
            publish([position])

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
            track.result = {"points": result.get("points", [])}
            track.score = result.get("score")
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
                "accuracy": round(result["grid"] / 2, 3),
                "speed": None,
                "method": "trackfit",
                "computed_at": now_ms(),
            }
            db.execute(insert(Position), [{k: v for k, v in position.items() if k != "type"}])
            return position
