"""Tracks: check an uploaded track against its floor and store it queued for fitting."""

from __future__ import annotations

import json
import uuid
from dataclasses import asdict
from typing import Any

import shapely
from sqlalchemy.orm import Session

from app.core.errors import Invalid, NotFound
from app.floors.service import require_floor
from app.geometry.floormap import parse_floor_map
from app.radiomaps.models import RadioMapFloor
from app.sites.assembly import site_tuning
from app.sites.service import require_site
from app.tracks.models import Track
from app.tracks.schemas import TrackCreate


def create_track(*, db: Session, body: TrackCreate) -> tuple[Track, dict[str, Any]]:
    """Check the track against its floor and store it queued; return it and the pool job."""
    site = require_site(db=db, site_id=body.site_id)
    floor = require_floor(db=db, site_id=body.site_id, floor_id=body.floor_id)
    walkable = parse_floor_map(floor.geojson).walkable
    if not shapely.intersects_xy(walkable, body.start.x, body.start.y):
        raise Invalid(
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
        "radiomap": _radio_map(db=db, body=body),
    }
    return track, job


def _radio_map(*, db: Session, body: TrackCreate) -> dict[str, Any] | None:
    """Return the floor's stored radio map (npz bytes, column ids and the per-scan k-NN's
    constants the site's build chose) when the track has scans."""
    if not any(s.wifi for s in body.segments):
        return None
    row = db.get(RadioMapFloor, (body.site_id, body.floor_id))
    if row is None:
        return None
    knn = site_tuning(db, body.site_id).scan_knn()
    return {"data": row.data, "transmitters": list(row.transmitters), "knn": asdict(knn)}


def get_track(*, db: Session, track_id: str) -> Track:
    """Return the track or raise NotFound."""
    track = db.get(Track, track_id)
    if track is None:
        raise NotFound(f"track '{track_id}' not found")
    return track
