"""Tracks: devices upload dead-reckoned tracks; the server fits them to the floor plan."""

from __future__ import annotations

from typing import cast

from fastapi import APIRouter

from app.core.errors import Forbidden
from app.keys.deps import PrincipalDep
from app.state import SessionDep, StateDep
from app.tracks import service
from app.tracks.jobs import FIT_FIELDS
from app.tracks.schemas import FittedPoint, TrackAccepted, TrackCreate, TrackRead, TrackStatus

router = APIRouter(prefix="/v1/tracks", tags=["tracks"])


@router.post("", status_code=202, response_model=TrackAccepted)
async def create_track(
    principal: PrincipalDep, body: TrackCreate, db: SessionDep, state: StateDep
) -> TrackAccepted:
    """Queue a track for fitting; poll ``GET /v1/tracks/{track_id}`` for the result."""
    if not principal.can_report(body.site_id):
        raise Forbidden(f"this key may not upload tracks for site '{body.site_id}'")
    track, job = service.create_track(db=db, body=body)
    db.commit()
    state.track_fits.submit(track.id, job)
    return TrackAccepted(track_id=track.id)


@router.get("/{track_id}", response_model=TrackRead)
def get_track(principal: PrincipalDep, track_id: str, db: SessionDep) -> TrackRead:
    """Return a track's status and, when done, its fitted points."""
    track = service.get_track(db=db, track_id=track_id)
    if not (principal.can_read(track.site_id) or principal.can_report(track.site_id)):
        raise Forbidden(f"this key may not read site '{track.site_id}'")
    result = track.result or {}
    points = [FittedPoint(**p) for p in result.get("points", [])]
    known = {key: result[key] for key in FIT_FIELDS if key in result}
    return TrackRead(
        track_id=track.id,
        device_id=track.device_id,
        site_id=track.site_id,
        floor_id=track.floor_id,
        status=cast(TrackStatus, track.status),
        points=points,
        score=track.score,
        elapsed_ms=track.elapsed_ms,
        error=track.error,
        **known,
    )
