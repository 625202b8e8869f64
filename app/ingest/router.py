"""Ingest: devices POST (or stream over a WebSocket) batches of measurements."""

from __future__ import annotations

import json
from typing import Any, TypeVar

from fastapi import APIRouter, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ValidationError

from app.core.errors import ApiError, DomainError, Invalid, TooLarge, error_body, validation_details
from app.core.openapi import json_body
from app.core.sample_policy import report, validate_screened
from app.ingest import flows, service
from app.ingest.schemas import (
    SAMPLE_MODELS,
    IngestAccepted,
    IngestBatch,
    IngestProcessed,
    LocatorBatch,
)
from app.keys.deps import PrincipalDep, websocket_principal
from app.state import AppState, RuntimeDep, StateDep, app_state

router = APIRouter(prefix="/v1", tags=["ingest"])
M = TypeVar("M", bound=BaseModel)


async def _read_body(request: Request, limit: int) -> bytes:
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise TooLarge(f"body larger than {limit} bytes")
    body = bytearray()
    async for chunk in request.stream():
        body.extend(chunk)
        if len(body) > limit:
            raise TooLarge(f"body larger than {limit} bytes")
    return bytes(body)


def _parse(model: type[M], raw: bytes | str) -> M:
    try:
        return model.model_validate_json(raw)
    except ValidationError as exc:
        raise Invalid(
            "request failed validation", details=validation_details(exc.errors(include_url=False))
        ) from exc


def _parse_batch(raw: bytes | str, state: AppState) -> tuple[IngestBatch, dict[str, Any]]:
    """Validate a device's batch under the per-sample policy, leave out cached WiFi repeats;
    count and report the drops."""
    try:
        batch, drops = validate_screened(
            IngestBatch,
            raw,
            SAMPLE_MODELS,
            max_offset_ms=round(state.settings.time_outlier_s * 1000),
        )
    except ValidationError as exc:
        raise Invalid(
            "request failed validation", details=validation_details(exc.errors(include_url=False))
        ) from exc
    wifi, stale = service.drop_stale_wifi(batch.wifi, state.settings.wifi_max_age_ms, drops)
    if stale:
        if len(wifi) + batch.sample_count - len(batch.wifi) == 0:
            raise Invalid("every sample was dropped", details=drops + stale)
        batch = batch.model_copy(update={"wifi": wifi})
    state.metrics.count_drops(drops + stale)
    return batch, report(drops + stale)


def _answer(result: dict[str, Any], wait: bool) -> JSONResponse:
    return JSONResponse(result, status_code=200 if wait else 202)


@router.post(
    "/ingest",
    status_code=202,
    response_model=IngestAccepted | IngestProcessed,
    openapi_extra=json_body(IngestBatch),
)
async def ingest(
    principal: PrincipalDep,
    request: Request,
    state: StateDep,
    runtime: RuntimeDep,
    wait: bool = Query(False, description="Answer after processing, with the positions"),
) -> JSONResponse:
    """Accept a device's batch; 202 at once, or 200 with its positions with ``?wait=true``."""
    raw = await _read_body(request, state.settings.max_body_bytes)
    batch, dropped = _parse_batch(raw, state)
    result = await flows.ingest_batch(
        batch=batch,
        principal=principal,
        settings=state.settings,
        runtime=runtime,
        sites=state.sites,
        wait=wait,
    )
    state.metrics.ingest_samples.labels("device").inc(batch.sample_count)
    return _answer(result | dropped, wait)


@router.post("/ingest/locator", status_code=202, response_model=IngestAccepted | IngestProcessed)
async def ingest_locator(
    principal: PrincipalDep,
    request: Request,
    state: StateDep,
    runtime: RuntimeDep,
    wait: bool = Query(
        False,
        description="Answer after processing, with the positions the tags' filters emitted; "
        "sightings stay in the reorder window, as other locators report the same moments",
    ),
) -> JSONResponse:
    """Accept a locator's sightings of tags; each goes to its tag's filter."""
    raw = await _read_body(request, state.settings.max_body_bytes)
    batch = _parse(LocatorBatch, raw)
    result = await flows.ingest_locator(
        batch=batch,
        principal=principal,
        settings=state.settings,
        runtime=runtime,
        sites=state.sites,
        wait=wait,
    )
    state.metrics.ingest_samples.labels("locator").inc(len(batch.sightings))
    return _answer(result, wait)


@router.websocket("/ws/ingest")
async def ingest_socket(websocket: WebSocket, wait: bool = False) -> None:
    """Ingest over a socket: each text message is an ingest body, each answer its result."""
    principal = websocket_principal(websocket)
    if principal is None:
        await websocket.close(code=1008, reason="missing or unknown API key")
        return
    state = app_state(websocket)
    if state.runtime is None:
        await websocket.close(code=1011, reason="this node runs no filter workers")
        return
    await websocket.accept()
    try:
        while True:
            raw = await websocket.receive_text()
            if len(raw) > state.settings.max_body_bytes:
                await websocket.send_json(error_body("payload_too_large", "message too large"))
                continue
            try:
                batch, dropped = _parse_batch(raw, state)
                result = await flows.ingest_batch(
                    batch=batch,
                    principal=principal,
                    settings=state.settings,
                    runtime=state.runtime,
                    sites=state.sites,
                    wait=wait,
                )
                state.metrics.ingest_samples.labels("device").inc(batch.sample_count)
                await websocket.send_text(json.dumps(result | dropped))
            except (ApiError, DomainError) as exc:
                await websocket.send_json(
                    error_body(exc.code, exc.message, exc.details) | {"status": exc.status}
                )
    except WebSocketDisconnect:
        return
