"""Request authentication: the caller's key resolved to a principal, and role checks."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from starlette.requests import HTTPConnection

from app.core.errors import ApiError, Forbidden
from app.core.security import Principal
from app.state import app_state

SEND_KEY = "send 'Authorization: Bearer <key>'"


def _unauthorized(message: str) -> ApiError:
    return ApiError(401, message, headers={"WWW-Authenticate": "Bearer"})


def presented_key(authorization: str | None, query_key: str | None = None) -> str:
    """Return the key from ``Authorization: Bearer`` or, for WebSockets, ``?key=``; raise a
    401 saying what is wrong: no key, another scheme, or a scheme without a key."""
    if authorization is None or not authorization.strip():
        if query_key:
            return query_key
        raise _unauthorized(f"missing API key: {SEND_KEY}")
    scheme, _, value = authorization.strip().partition(" ")
    if not value.strip():
        if scheme.lower() == "bearer":
            raise _unauthorized(f"the Authorization header has no key after 'Bearer': {SEND_KEY}")
        raise _unauthorized(f"the Authorization header names no scheme: {SEND_KEY}")
    if scheme.lower() != "bearer":
        raise _unauthorized(
            f"the Authorization header uses the '{scheme[:20]}' scheme, not Bearer: {SEND_KEY}"
        )
    return value.strip()


async def resolve(connection: HTTPConnection, key: str) -> Principal:
    """Return the key's principal (cached, else from the database off the loop), or 401."""
    answer = await app_state(connection).keys.lookup(key)
    if isinstance(answer, Principal):
        return answer
    raise _unauthorized("this API key was revoked" if answer == "revoked" else "unknown API key")


async def authenticate(request: Request) -> Principal:
    """Resolve the caller's key or answer 401 (async: no thread hop on the ingest path)."""
    return await resolve(request, presented_key(request.headers.get("authorization")))


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


async def websocket_principal(connection: HTTPConnection) -> Principal:
    """Resolve a WebSocket's key from the header or ``?key=``; ApiError(401) saying why not."""
    key = presented_key(connection.headers.get("authorization"), connection.query_params.get("key"))
    return await resolve(connection, key)
