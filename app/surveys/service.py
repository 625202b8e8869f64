"""Storing and reading survey recordings."""

from __future__ import annotations

import json
import zlib
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.surveys.models import Survey
from app.surveys.schemas import SurveyCreate


def create_survey(*, db: Session, site_id: str, body: SurveyCreate) -> Survey:
    """Store a recording, its samples as compressed JSON."""
    payload = body.model_dump(exclude={"device_id", "floor_id", "name"}, exclude_none=True)
    survey = Survey(
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


def list_surveys(*, db: Session, site_id: str, limit: int, offset: int) -> list[Survey]:
    """Return a page of the site's surveys, oldest first."""
    query = select(Survey).where(Survey.site_id == site_id).order_by(Survey.id)
    return list(db.scalars(query.limit(limit).offset(offset)))


def survey_samples(survey: Survey) -> dict[str, Any]:
    """Return a stored survey's waypoints and sample lists."""
    return json.loads(zlib.decompress(survey.body))
