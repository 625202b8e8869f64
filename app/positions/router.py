"""Positions: latest, history, and the live WebSocket stream."""

from __future__ import annotations

import asyncio
from typing import Annotated

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect

from app.core.errors import Forbidden, NotFound
from app.keys.deps import PrincipalDep, websocket_principal
from app.positions import service
from app.positions.models import PositionRecord
from app.positions.schemas import Position, PositionPage
from app.state import SessionDep, app_state

router = APIRouter(prefix="/v1", tags=["positions"])


def _message(row: PositionRecord) -> Position:
    return Position(
        device_id=row.device_id,
        site_id=row.site_id,
        floor_id=row.floor_id,
        t=row.t,
        x=row.x,
        y=row.y,
        z=row.z,
        heading=row.heading,
        accuracy=row.accuracy,
        speed=row.speed,
        method=row.method,
        computed_at=row.computed_at,
        smoothed=row.smoothed,
    )


@router.get("/devices/{device_id}/position", response_model=Position)
def latest_position(principal: PrincipalDep, device_id: str, db: SessionDep) -> Position:
    """Return the device's latest position."""
    row = service.latest(db=db, device_id=device_id)
    if row is None or not principal.can_read(row.site_id):
        if row is not None:
            raise Forbidden(f"this key may not read site '{row.site_id}'")
        raise NotFound(f"no position for device '{device_id}'")
    return _message(row)


@router.get("/devices/{device_id}/positions", response_model=PositionPage)
def position_history(
    principal: PrincipalDep,
    device_id: str,
    db: SessionDep,
    t_from: Annotated[int | None, Query(alias="from", ge=0, le=2**53)] = None,
    t_to: Annotated[int | None, Query(alias="to", ge=0, le=2**53)] = None,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
) -> PositionPage:
    """Return the device's positions in ``[from, to]``, ascending ``t``, a page at a time."""
    site_id = service.device_site(db=db, device_id=device_id)
    if site_id is not None and not principal.can_read(site_id):
        raise Forbidden(f"this key may not read site '{site_id}'")
    rows = service.history(db=db, device_id=device_id, t_from=t_from, t_to=t_to, limit=limit + 1)
    more = len(rows) > limit
    rows = rows[:limit]
    return PositionPage(
        items=[_message(r) for r in rows],
        limit=limit,
        next_from=rows[-1].t + 1 if more and rows else None,
    )


@router.websocket("/ws/positions")
async def position_stream(
    websocket: WebSocket,
    site_id: str | None = None,
    floor_id: str | None = None,
    device_id: str | None = None,
) -> None:
    """Stream position messages and zone events, filtered by site, floor and device."""
    principal = websocket_principal(websocket)
    if principal is None:
        await websocket.close(code=1008, reason="missing or unknown API key")
        return
    if principal.role == "viewer":
        site_id = site_id or principal.site_id
    if principal.role == "device" or (site_id is not None and not principal.can_read(site_id)):
        await websocket.close(code=1008, reason="this key may not read that site")
        return
    if principal.role != "admin" and site_id is None:
        await websocket.close(code=1008, reason="site_id is required")
        return
    runtime = app_state(websocket).runtime
    if runtime is None:
        await websocket.close(code=1011, reason="this node runs no filter workers")
        return
    await websocket.accept()
    sub = runtime.hub.subscribe(site_id=site_id, floor_id=floor_id, device_id=device_id)
    closed = asyncio.create_task(_wait_closed(websocket))
    try:
        while not closed.done():
            getter = asyncio.create_task(sub.queue.get())
            done, _ = await asyncio.wait({getter, closed}, return_when=asyncio.FIRST_COMPLETED)
            if getter not in done:
                getter.cancel()
                break
            await websocket.send_json(getter.result())
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        runtime.hub.unsubscribe(sub)
        closed.cancel()


async def _wait_closed(websocket: WebSocket) -> None:
    try:
        while True:
            await websocket.receive_text()
    except (WebSocketDisconnect, RuntimeError):
        return
