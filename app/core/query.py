"""Unknown query parameters are refused (422), never silently ignored: a client that thinks
it filters (``?site=``, ``?device=``) learns that it did not."""

from __future__ import annotations

from fastapi.dependencies.models import Dependant
from fastapi.exceptions import WebSocketException
from starlette.requests import HTTPConnection

from app.core.errors import Invalid

WEBSOCKET_KEY = "key"
"""WebSockets may carry their key as ``?key=`` (browsers cannot set the header)."""

_DECLARED: dict[int, frozenset[str]] = {}


def declared_query(dependant: Dependant) -> frozenset[str]:
    """Return the names of every query parameter a route and its dependencies declare."""
    names: set[str] = set()
    stack = [dependant]
    while stack:
        current = stack.pop()
        names.update(field.alias for field in current.query_params)
        stack.extend(current.dependencies)
    return frozenset(names)


async def reject_unknown_query(connection: HTTPConnection) -> None:
    """Refuse a request or WebSocket whose query names parameters its route does not take."""
    route = connection.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if dependant is None:
        return
    allowed = _DECLARED.get(id(route))
    if allowed is None:
        allowed = _DECLARED[id(route)] = declared_query(dependant)
    websocket = connection.scope["type"] == "websocket"
    unknown = sorted(
        {name for name in connection.query_params if name not in allowed}
        - ({WEBSOCKET_KEY} if websocket else set())
    )
    if not unknown:
        return
    message = f"unknown query parameter(s): {', '.join(unknown)}"
    if allowed:
        message += f"; this endpoint takes {', '.join(sorted(allowed))}"
    if websocket:
        raise WebSocketException(code=1008, reason=message[:120])
    raise Invalid(
        message,
        code="unknown_query",
        details=[
            {"loc": ["query", name], "msg": "unknown query parameter", "type": "extra_forbidden"}
            for name in unknown
        ],
    )
