"""Storing and reading survey recordings."""

from __future__ import annotations

import hashlib
import json
import zlib
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.floors.service import require_floor
from app.surveys.models import SurveyRecord
from app.surveys.schemas import SurveyCreate


def create_survey(*, db: Session, site_id: str, body: SurveyCreate) -> SurveyRecord:
    """Store a recording on one of the site's floors, its samples as compressed JSON."""
    require_floor(db=db, site_id=site_id, floor_id=body.floor_id)
    payload = body.model_dump(
        exclude={"device_id", "floor_id", "site_id", "name"}, exclude_none=True
    )
    survey = SurveyRecord(
        site_id=site_id,
        floor_id=body.floor_id,
        device_id=body.device_id,
        name=body.name,
        counts=body.counts(),
        body=zlib.compress(json.dumps(payload, separators=(",", ":")).encode(), 6),
    )
    db.add(survey)
    db.flush()
    return survey


def count_surveys(*, db: Session, site_id: str) -> int:
    """Return the number of surveys stored for the site."""
    return db.scalar(select(func.count()).where(SurveyRecord.site_id == site_id)) or 0


def list_surveys(
    *, db: Session, site_id: str, limit: int, offset: int
) -> tuple[list[SurveyRecord], int]:
    """Return a page of the site's surveys, oldest first, and their total."""
    query = select(SurveyRecord).where(SurveyRecord.site_id == site_id).order_by(SurveyRecord.id)
    rows = list(db.scalars(query.limit(limit).offset(offset)))
    return rows, count_surveys(db=db, site_id=site_id)


def survey_identity(survey: SurveyRecord) -> str:
    """Return the survey's floor and the SHA-256 of its samples: the same recording has
    the same identity whatever its upload order, device label or name."""
    digest = hashlib.sha256(zlib.decompress(survey.body)).hexdigest()
    return f"{survey.floor_id}/{digest}"


def survey_samples(survey: SurveyRecord) -> dict[str, Any]:
    """Return a stored survey's waypoints and sample lists."""
    return json.loads(zlib.decompress(survey.body))
