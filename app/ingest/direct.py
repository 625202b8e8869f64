"""The ingest routes served ahead of the framework's routing, for the requests devices send.

A POST to an ingest route whose query is empty or a plain ``wait`` (nearly every request a
server carries) is authenticated and handed to the route's endpoint here, as plain ASGI:
no exception middleware, no route matching, no dependency solving, no exit stacks. Besides
the CPU, that is memory: a keep-alive connection keeps its last request's scope (under
1,000 devices the framework's path kept 3,000 exit stacks alive between requests), and a
request awaiting its positions keeps every frame it passed through, so the API holds less
memory under many devices and leaves less of the allocator's arenas behind after a stall
(``python -m bench.soak`` follows the API's memory).

Every other request (another query, which FastAPI checks, or any other route) goes the
framework's way; errors are rendered by the same function as its handlers'.
"""

from __future__ import annotations

from collections.abc import Sequence

from fastapi.routing import APIRoute
from starlette.requests import Request
from starlette.routing import BaseRoute
from starlette.types import ASGIApp, Receive, Scope, Send

from app.core.errors import error_response
from app.core.security import Principal
from app.keys.deps import authenticate

PLAIN_WAIT = {
    b"": False,
    b"wait=false": False,
    b"wait=true": True,
    b"wait=0": False,
    b"wait=1": True,
}
"""The queries a device sends: none, or ``wait`` spelled as clients spell it."""


class DirectIngest:
    """ASGI middleware serving the plain ingest requests itself (module docstring).

    ``routes`` are the ingest router's; its POST routes are served, each endpoint taking
    ``(principal, request, wait)``.
    """

    def __init__(self, app: ASGIApp, routes: Sequence[BaseRoute]) -> None:
        self.app = app
        self.routes = {
            route.path: route
            for route in routes
            if isinstance(route, APIRoute) and "POST" in (route.methods or ())
        }

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        route = self.routes.get(scope["path"]) if scope["type"] == "http" else None
        wait = PLAIN_WAIT.get(scope["query_string"]) if route is not None else None
        if route is None or wait is None or scope["method"] != "POST":
            await self.app(scope, receive, send)
            return
        # the request metrics label a request by its route's path template
        scope["route"] = route
        request = Request(scope, receive)
        try:
            principal: Principal = await authenticate(request)
            response = await route.endpoint(principal=principal, request=request, wait=wait)
        except Exception as exc:  # rendered as the framework's handlers render it
            response = await error_response(request, exc)
        await response(scope, receive, send)
