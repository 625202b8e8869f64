"""Surveys: upload recordings with surveyed waypoints, list them."""

from __future__ import annotations

from fastapi import APIRouter, Request
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from app.core.errors import Invalid, TooLarge, validation_failed
from app.core.openapi import json_body
from app.core.sample_policy import report, validate_screened
from app.core.schemas import LimitQuery, OffsetQuery, Page
from app.ingest.schemas import SAMPLE_MODELS
from app.ingest.service import drop_stale_wifi
from app.keys.deps import AdminDep, SiteReaderDep
from app.sites.deps import SiteDep
from app.state import SessionDep, SettingsDep, app_state
from app.surveys import service
from app.surveys.schemas import SurveyCreate, SurveyRead

router = APIRouter(prefix="/v1/sites/{site_id}/surveys", tags=["surveys"])


@router.post(
    "",
    status_code=201,
    response_model=SurveyRead,
    openapi_extra=json_body(SurveyCreate),
)
async def create_survey(
    _: AdminDep, site: SiteDep, request: Request, db: SessionDep, settings: SettingsDep
) -> SurveyRead:
    """Store a survey recording (admin): waypoints plus the sample lists of ingest."""
    raw = await request.body()
    if len(raw) > settings.survey_max_bytes:
        raise TooLarge(f"survey larger than {settings.survey_max_bytes} bytes")
    try:
        body, drops = await run_in_threadpool(
            validate_screened,
            SurveyCreate,
            raw,
            SAMPLE_MODELS,
            max_offset_ms=round(settings.time_outlier_s * 1000),
            anchors=("waypoints",),
        )
    except ValidationError as exc:
        errors = exc.errors(include_url=False)
        raise validation_failed(errors, "survey failed validation") from exc
    if body.site_id is not None and body.site_id != site.id:
        raise Invalid(
            f"the survey names site '{body.site_id}' but is posted to site '{site.id}'",
            details=[{"loc": ["site_id"], "msg": "another site", "type": "site_mismatch"}],
        )
    wifi, stale = drop_stale_wifi(body.wifi, settings.wifi_max_age_ms, drops)
    body = body.model_copy(update={"wifi": wifi})
    drops += stale
    app_state(request).metrics.count_drops(drops)
    survey = await run_in_threadpool(service.create_survey, db=db, site_id=site.id, body=body)
    db.commit()
    stored = SurveyRead.model_validate(survey).model_dump()
    return SurveyRead.model_validate(stored | report(drops))


@router.get("", response_model=Page[SurveyRead])
def list_surveys(
    _: SiteReaderDep,
    site: SiteDep,
    db: SessionDep,
    limit: LimitQuery = 100,
    offset: OffsetQuery = 0,
) -> Page[SurveyRead]:
    """List the site's surveys."""
    rows, total = service.list_surveys(db=db, site_id=site.id, limit=limit, offset=offset)
    items = [SurveyRead.model_validate(r) for r in rows]
    return Page[SurveyRead](items=items, total=total, limit=limit, offset=offset)
