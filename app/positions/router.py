"""Positions of a site's devices: latest, history, and the live WebSocket stream.

A device is (site, device id): the site-scoped paths are the API; the older
``/v1/devices/{device_id}/...`` paths remain where the site is unambiguous (a
key scoped to one site, ``?site_id=``, or an id that only one site has).
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import StreamingResponse
from sqlalchemy.orm import Session

from app.analytics import export
from app.core.errors import ApiError, Conflict, Forbidden, NotFound
from app.core.schemas import ID_PATTERN, DeviceIdPath
from app.core.security import Principal
from app.devices.service import get_device, sites_of
from app.keys.deps import PrincipalDep, SiteReaderDep, websocket_principal
from app.positions import service
from app.positions.schemas import Position, PositionPage
from app.sites.assembly import site_tuning
from app.sites.deps import SiteDep
from app.state import SessionDep, SettingsDep, app_state

router = APIRouter(prefix="/v1", tags=["positions"])

TimeQuery = Annotated[int | None, Query(ge=0, le=2**53)]


class HistoryQuery:
    """The history's window and page size: ``[from, to]`` ms, at most ``limit`` items; with
    ``smoothed``, the window's live track refined by a full backward pass."""

    def __init__(
        self,
        t_from: Annotated[TimeQuery, Query(alias="from")] = None,
        t_to: Annotated[TimeQuery, Query(alias="to")] = None,
        limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
        smoothed: Annotated[
            bool,
            Query(
                description="Refine the page's live positions by a full backward pass "
                "(every position weighed against those before and after it and the "
                "device's steps); each is marked smoothed"
            ),
        ] = False,
    ) -> None:
        self.t_from, self.t_to, self.limit, self.smoothed = t_from, t_to, limit, smoothed


HistoryDep = Annotated[HistoryQuery, Depends()]


def _require_device(db: Session, site_id: str, device_id: str) -> None:
    if get_device(db=db, site_id=site_id, device_id=device_id) is None:
        raise NotFound(f"device '{device_id}' not found in site '{site_id}'")


def _latest(db: Session, site_id: str, device_id: str) -> Position:
    _require_device(db, site_id, device_id)
    row = service.latest(db=db, site_id=site_id, device_id=device_id)
    if row is None:
        raise NotFound(f"no position yet for device '{device_id}' in site '{site_id}'")
    return Position.model_validate(row)


def _history(db: Session, site_id: str, device_id: str, query: HistoryQuery) -> PositionPage:
    _require_device(db, site_id, device_id)
    read = service.live_history if query.smoothed else service.history
    rows = read(
        db=db,
        site_id=site_id,
        device_id=device_id,
        t_from=query.t_from,
        t_to=query.t_to,
        limit=query.limit + 1,
    )
    more = len(rows) > query.limit
    rows = rows[: query.limit]
    items = [Position.model_validate(r) for r in rows]
    if query.smoothed:
        # weighed as the site's radio-map build found best on its held-out walks
        refined = service.full_pass(rows, site_tuning(db, site_id).full_pass())
        items = [
            p.model_copy(update={"x": round(x, 3), "y": round(y, 3), "smoothed": True})
            for p, (x, y) in zip(items, refined, strict=True)
        ]
    return PositionPage(
        items=items,
        limit=query.limit,
        next_from=rows[-1].t + 1 if more and rows else None,
    )


@router.get("/sites/{site_id}/devices/{device_id}/position", response_model=Position)
def latest_position(
    _: SiteReaderDep, site: SiteDep, device_id: DeviceIdPath, db: SessionDep
) -> Position:
    """Return the device's latest live position (admin, or the site's viewers)."""
    return _latest(db, site.id, device_id)


@router.get(
    "/sites/{site_id}/devices/{device_id}/positions",
    response_model=PositionPage,
    responses={200: {"content": {"text/csv": {}, "application/geo+json": {}}}},
)
def position_history(
    _: SiteReaderDep,
    site: SiteDep,
    device_id: DeviceIdPath,
    db: SessionDep,
    query: HistoryDep,
    request: Request,
    settings: SettingsDep,
    format: Annotated[
        Literal["json", "csv", "geojson"] | None,
        Query(description="Export the whole of [from, to] streamed (or Accept: text/csv)"),
    ] = None,
) -> Any:
    """Return the device's positions in ``[from, to]``, ascending ``t``, a page at a time;
    with ``format=csv|geojson`` (or ``Accept: text/csv``) the whole range, streamed."""
    if format is None and "text/csv" in request.headers.get("accept", ""):
        format = "csv"
    if format is None or format == "json":
        return _history(db, site.id, device_id, query)
    _require_device(db, site.id, device_id)
    rows = export.pages(
        app_state(request).sessions,
        export.device_rows(site.id, device_id),
        t_from=query.t_from,
        t_to=query.t_to,
        page_rows=settings.export_page_rows,
    )
    return StreamingResponse(export.WRITERS[format](rows), media_type=export.MEDIA_TYPES[format])


SiteQuery = Annotated[
    str | None,
    Query(pattern=ID_PATTERN, description="The device's site; needed where the id is in several"),
]


def _unambiguous_site(
    principal: Principal, db: Session, device_id: str, site_id: str | None
) -> str:
    """Return the site meant by a path that names only the device, or refuse.

    ``?site_id=`` names it; else a site-scoped key's own site; else (an admin) the one
    site that has the id: 404 when none has, 409 when several have.
    """
    if site_id is None and principal.site_id is not None:
        site_id = principal.site_id
    if site_id is None:
        sites = sites_of(db=db, device_id=device_id)
        if not sites:
            raise NotFound(f"device '{device_id}' not found in any site")
        if len(sites) > 1:
            raise Conflict(
                f"device id '{device_id}' exists in several sites ({', '.join(sites[:10])}): "
                f"name one with ?site_id= or use /v1/sites/{{site_id}}/devices/{device_id}",
                details=[{"sites": sites}],
            )
        site_id = sites[0]
    if not principal.can_read(site_id):
        raise Forbidden(f"this key may not read site '{site_id}'")
    return site_id


@router.get("/devices/{device_id}/position", response_model=Position)
def latest_position_by_id(
    principal: PrincipalDep, device_id: DeviceIdPath, db: SessionDep, site_id: SiteQuery = None
) -> Position:
    """The older path of the latest position: the site from ``?site_id=``, the key's site,
    or the only site with this id (409 when several have it)."""
    return _latest(db, _unambiguous_site(principal, db, device_id, site_id), device_id)


@router.get("/devices/{device_id}/positions", response_model=PositionPage)
def position_history_by_id(
    principal: PrincipalDep,
    device_id: DeviceIdPath,
    db: SessionDep,
    query: HistoryDep,
    site_id: SiteQuery = None,
) -> PositionPage:
    """The older path of the history, resolving the site as the latest position's does."""
    return _history(db, _unambiguous_site(principal, db, device_id, site_id), device_id, query)


@router.websocket("/ws/positions")
async def position_stream(
    websocket: WebSocket,
    site_id: str | None = None,
    floor_id: str | None = None,
    device_id: str | None = None,
) -> None:
    """Stream position messages and zone events, filtered by site, floor and device.

    Floor and device ids are per site, so filtering by them needs the site. The stream
    closes (1008) within a second of its key being revoked.
    """
    try:
        principal = await websocket_principal(websocket)
    except ApiError as exc:
        await websocket.close(code=1008, reason=exc.message[:120])
        return
    if principal.role == "viewer":
        site_id = site_id or principal.site_id
    refusal = _stream_refusal(principal, site_id, floor_id, device_id)
    if refusal is not None:
        await websocket.close(code=1008, reason=refusal)
        return
    state = app_state(websocket)
    if state.runtime is None:
        await websocket.close(code=1011, reason="this node runs no filter workers")
        return
    hub = state.runtime.hub
    await websocket.accept()
    sub = hub.subscribe(site_id=site_id, floor_id=floor_id, device_id=device_id)
    revoked = state.revocations.watch(principal)
    closed = asyncio.create_task(_wait_closed(websocket))
    ended = asyncio.create_task(revoked.wait())
    try:
        while not closed.done():
            getter = asyncio.create_task(sub.queue.get())
            done, _ = await asyncio.wait(
                {getter, closed, ended}, return_when=asyncio.FIRST_COMPLETED
            )
            if getter not in done:
                getter.cancel()
                if ended in done:
                    await websocket.close(code=1008, reason="this API key was revoked")
                break
            # send every message queued by now: waiting for each one on its own takes
            # several turns of an event loop that is busy with ingest
            for message in _queued(sub.queue, getter.result()):
                await websocket.send_json(message)
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        hub.unsubscribe(sub)
        state.revocations.unwatch(principal, revoked)
        closed.cancel()
        ended.cancel()


def _stream_refusal(
    principal: Principal, site_id: str | None, floor_id: str | None, device_id: str | None
) -> str | None:
    """Return why the key may not open this stream, or None."""
    if principal.role == "device":
        return "device keys may not read positions"
    if site_id is None and principal.role != "admin":
        return "site_id is required"
    if site_id is not None and not principal.can_read(site_id):
        return f"this key may not read site '{site_id}'"
    if site_id is None and (floor_id is not None or device_id is not None):
        return "site_id is required with floor_id or device_id: those ids are per site"
    return None


def _queued(queue: asyncio.Queue[dict[str, Any]], first: dict[str, Any]) -> list[dict[str, Any]]:
    """Return ``first`` and every message waiting behind it, taking them off the queue."""
    messages = [first]
    while not queue.empty():
        messages.append(queue.get_nowait())
    return messages


async def _wait_closed(websocket: WebSocket) -> None:
    try:
        while True:
            await websocket.receive_text()
    except (WebSocketDisconnect, RuntimeError):
        return
