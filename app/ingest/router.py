"""Ingest: devices POST (or stream over a WebSocket) batches of measurements; gateways POST
many devices' batches in one body.

Every way in goes through ``_ingest_one``: one batch validated and submitted, answered as
the single ingest answers it.
"""

from __future__ import annotations

import asyncio
from typing import Any

import msgspec
from fastapi import APIRouter, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import Response
from pydantic import ValidationError

from app.core.errors import (
    ApiError,
    DomainError,
    Forbidden,
    TooLarge,
    error_body,
    validation_failed,
)
from app.core.openapi import json_body
from app.core.sample_policy import report, validate_screened
from app.core.security import Principal
from app.ingest import flows, service
from app.ingest.bulk import bulk_items
from app.ingest.schemas import (
    BulkAnswer,
    BulkIngest,
    IngestAccepted,
    IngestBatch,
    IngestProcessed,
    LocatorBatch,
    Sighting,
)
from app.keys.deps import PrincipalDep, websocket_principal
from app.state import AppState, app_state, runtime_of
from app.workers.runtime import Runtime

router = APIRouter(prefix="/v1", tags=["ingest"])


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


def _parse_batch(raw: bytes | str, state: AppState) -> tuple[IngestBatch, dict[str, Any]]:
    """Validate a device's batch under the per-sample policy; count and report the drops."""
    batch, drops = service.screen_batch(raw, state.settings)
    state.metrics.count_drops(drops)
    return batch, report(drops)


def _parse_locator(raw: bytes | str, state: AppState) -> tuple[LocatorBatch, dict[str, Any]]:
    """Validate a locator's report under the per-sample policy: an impossible sighting
    goes alone, and is counted and reported."""
    try:
        batch, drops = validate_screened(
            LocatorBatch,
            raw,
            {"sightings": Sighting},
            max_offset_ms=round(state.settings.time_outlier_s * 1000),
        )
    except ValidationError as exc:
        raise validation_failed(exc.errors(include_url=False)) from exc
    state.metrics.count_drops(drops)
    return batch, report(drops)


def _may_ingest(principal: Principal) -> None:
    """Refuse a viewer key before its body is read: what it sends is never processed, so the
    body's faults are not its business."""
    if principal.role not in ("admin", "device"):
        raise Forbidden("only device and admin keys may ingest")


def _answer(result: dict[str, Any], wait: bool) -> Response:
    """Return an ingest's answer, encoded by msgspec: many times faster than the json module
    behind ``JSONResponse`` on a bulk answer's many positions (``bench/load.py`` measures
    ingest's cost end to end)."""
    return Response(
        msgspec.json.encode(result),
        status_code=200 if wait else 202,
        media_type="application/json",
    )


def _submit_one(
    raw: bytes | str, *, principal: Principal, state: AppState, runtime: Runtime, wait: bool
) -> tuple[flows.Submitted, dict[str, Any]]:
    """Validate one device's batch, check it against the key and the site, submit it; return
    the submission and the drops to report. The parsed batch dies with this call."""
    batch, dropped = _parse_batch(raw, state)
    submitted = flows.submit_batch(
        batch=batch,
        principal=principal,
        settings=state.settings,
        runtime=runtime,
        sites=state.sites,
        wait=wait,
    )
    state.metrics.ingest_samples.labels("device").inc(batch.sample_count)
    return submitted, dropped


async def _ingest_one(
    raw: bytes | str, *, principal: Principal, state: AppState, runtime: Runtime, wait: bool
) -> dict[str, Any]:
    """Submit one device's batch; return the single ingest's answer (with ``wait``, after
    its positions)."""
    submitted, dropped = _submit_one(
        raw, principal=principal, state=state, runtime=runtime, wait=wait
    )
    timeout_s = state.settings.ingest_wait_timeout_s
    return await flows.settle(submitted, wait=wait, timeout_s=timeout_s) | dropped


def _refusal(exc: ApiError | DomainError) -> dict[str, Any]:
    """Return a refused batch's result: its status and the contract's error object."""
    result = {"status": exc.status} | error_body(exc.code, exc.message, exc.details)
    retry = getattr(exc, "retry_after_s", None)
    return result if retry is None else result | {"retry_after_s": retry}


@router.post(
    "/ingest",
    status_code=202,
    response_model=IngestAccepted | IngestProcessed,
    openapi_extra=json_body(IngestBatch),
)
async def ingest(
    principal: PrincipalDep,
    request: Request,
    wait: bool = Query(False, description="Answer after processing, with the positions"),
) -> Response:
    """Accept a device's batch; 202 at once, or 200 with its positions with ``?wait=true``."""
    _may_ingest(principal)
    state = app_state(request)
    runtime = runtime_of(state)
    raw = await _read_body(request, state.settings.max_body_bytes)
    result = await _ingest_one(raw, principal=principal, state=state, runtime=runtime, wait=wait)
    return _answer(result, wait)


@router.post(
    "/ingest/bulk",
    status_code=202,
    response_model=BulkAnswer,
    openapi_extra=json_body(BulkIngest),
)
async def ingest_bulk(
    principal: PrincipalDep,
    request: Request,
    wait: bool = Query(False, description="Answer after processing, with each batch's positions"),
) -> Response:
    """Accept many devices' batches (a gateway's); each is validated and processed on its own.

    The answer lists one result per batch, in order, as the single ingest would answer it:
    ``{"status": 202|200, "accepted", "late", "dropped", "dropped_total", "positions"?}``
    or ``{"status": 4xx, "error"}``. A batch for a site the key may not report to is refused
    alone (403). The body is refused whole only when its own structure is wrong or it is too
    large.
    """
    _may_ingest(principal)
    state = app_state(request)
    runtime = runtime_of(state)
    raw = await _read_body(request, state.settings.bulk_max_body_bytes)
    items = bulk_items(raw, state.settings)

    async def one(item: bytes | str) -> dict[str, Any]:
        try:
            if len(item) > state.settings.max_body_bytes:
                raise TooLarge(f"batch larger than {state.settings.max_body_bytes} bytes")
            result = await _ingest_one(
                item, principal=principal, state=state, runtime=runtime, wait=wait
            )
        except (ApiError, DomainError) as exc:
            return _refusal(exc)
        return {"status": 200 if wait else 202} | result

    # each batch is submitted before the first await, so in the order sent
    results = await asyncio.gather(*(one(item) for item in items))
    return _answer({"results": list(results)}, wait)


@router.post("/ingest/locator", status_code=202, response_model=IngestAccepted | IngestProcessed)
async def ingest_locator(
    principal: PrincipalDep,
    request: Request,
    wait: bool = Query(
        False,
        description="Answer after processing, with the positions the tags' filters emitted; "
        "sightings stay in the reorder window, as other locators report the same moments",
    ),
) -> Response:
    """Accept a locator's sightings of tags; each goes to its tag's filter."""
    _may_ingest(principal)
    state = app_state(request)
    runtime = runtime_of(state)
    raw = await _read_body(request, state.settings.max_body_bytes)
    batch, dropped = _parse_locator(raw, state)
    result = await flows.ingest_locator(
        batch=batch,
        principal=principal,
        settings=state.settings,
        runtime=runtime,
        sites=state.sites,
        wait=wait,
    )
    state.metrics.ingest_samples.labels("locator").inc(len(batch.sightings))
    return _answer(result | dropped, wait)


@router.websocket("/ws/ingest")
async def ingest_socket(websocket: WebSocket, wait: bool = False) -> None:
    """Ingest over a socket: each text message is an ingest body, each answer its result.

    The socket closes (1008) within a second of its key being revoked.
    """
    try:
        principal = await websocket_principal(websocket)
    except ApiError as exc:
        await websocket.close(code=1008, reason=exc.message[:120])
        return
    state = app_state(websocket)
    runtime = state.runtime
    if runtime is None:
        await websocket.close(code=1011, reason="this node runs no filter workers")
        return
    await websocket.accept()
    revoked = state.revocations.watch(principal)
    ended = asyncio.create_task(revoked.wait())
    try:
        while True:
            receiver = asyncio.create_task(websocket.receive_text())
            await asyncio.wait({receiver, ended}, return_when=asyncio.FIRST_COMPLETED)
            if not receiver.done():
                receiver.cancel()
                await websocket.close(code=1008, reason="this API key was revoked")
                return
            raw = receiver.result()
            if len(raw) > state.settings.max_body_bytes:
                await websocket.send_json(error_body("payload_too_large", "message too large"))
                continue
            try:
                result = await _ingest_one(
                    raw, principal=principal, state=state, runtime=runtime, wait=wait
                )
                await websocket.send_text(msgspec.json.encode(result).decode())
            except (ApiError, DomainError) as exc:
                await websocket.send_json(_refusal(exc))
    except WebSocketDisconnect:
        return
    finally:
        state.revocations.unwatch(principal, revoked)
        ended.cancel()
