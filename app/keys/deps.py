"""Request authentication: the caller's key resolved to a principal, and role checks."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request, WebSocket
from starlette.concurrency import run_in_threadpool

from app.core.errors import ApiError, Forbidden
from app.core.security import Principal
from app.state import app_state


def bearer_key(authorization: str | None, query_key: str | None = None) -> str | None:
    """Return the key from ``Authorization: Bearer`` or, for WebSockets, ``?key=``."""
    if authorization:
        scheme, _, value = authorization.partition(" ")
        if scheme.lower() == "bearer" and value.strip():
            return value.strip()
    return query_key or None


async def authenticate(request: Request) -> Principal:
    """Resolve the caller's key or answer 401 (async: no thread hop on the ingest path)."""
    key = bearer_key(request.headers.get("authorization"))
    if key is None:
        raise ApiError(401, "missing API key", headers={"WWW-Authenticate": "Bearer"})
    keys = app_state(request).keys
    cached, principal = keys.cached(key)
    if not cached:
        principal = await run_in_threadpool(keys.resolve, key)
    if principal is None:
        raise ApiError(401, "unknown API key", headers={"WWW-Authenticate": "Bearer"})
    return principal


PrincipalDep = Annotated[Principal, Depends(authenticate)]


async def require_admin(principal: PrincipalDep) -> Principal:
    """Answer 403 unless the caller is an admin."""
    if principal.role != "admin":
        raise Forbidden("admin key required")
    return principal


AdminDep = Annotated[Principal, Depends(require_admin)]


async def site_reader(site_id: str, principal: PrincipalDep) -> Principal:
    """Answer 403 unless the caller may read ``site_id`` (admin, or its viewer)."""
    if not principal.can_read(site_id):
        raise Forbidden(f"this key may not read site '{site_id}'")
    return principal


SiteReaderDep = Annotated[Principal, Depends(site_reader)]


def websocket_principal(websocket: WebSocket) -> Principal | None:
    """Resolve a WebSocket's key from the header or ``?key=``; None if absent or unknown."""
    key = bearer_key(websocket.headers.get("authorization"), websocket.query_params.get("key"))
    if key is None:
        return None
    keys = app_state(websocket).keys
    cached, principal = keys.cached(key)
    return principal if cached else keys.resolve(key)
