"""The HTTP ingest routes' common request served without FastAPI's dependency solving."""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Any

from fastapi.routing import APIRoute
from starlette.requests import Request
from starlette.responses import Response

from app.keys.deps import authenticate

# the queries a device sends: none, or ``wait`` spelled as clients spell it
_PLAIN_WAIT = {
    b"": False,
    b"wait=false": False,
    b"wait=true": True,
    b"wait=0": False,
    b"wait=1": True,
}


class IngestRoute(APIRoute):
    """An ingest route, whose endpoint takes ``(principal, request, wait)``.

    A request whose query is empty or a plain ``wait`` is authenticated and handed to the
    endpoint directly: FastAPI's solving of the route's dependencies cost 15% of the API
    process's CPU at ingest saturation. Every other request goes FastAPI's way, which
    checks its query and answers its errors; the OpenAPI document is FastAPI's either way.
    """

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        general = super().get_route_handler()
        endpoint = self.endpoint

        async def handler(request: Request) -> Response:
            wait = _PLAIN_WAIT.get(request.scope["query_string"])
            if wait is None:
                return await general(request)
            principal = await authenticate(request)
            response: Response = await endpoint(principal=principal, request=request, wait=wait)
            return response

        return handler
