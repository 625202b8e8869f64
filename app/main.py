"""The FastAPI application: routers, error handling, metrics, and the workers' lifecycle."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import Depends, FastAPI
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app import __version__
from app.analytics.router import router as analytics_router
from app.core.config import Settings, get_settings
from app.core.errors import install_error_handlers
from app.core.heap import settle_heap
from app.core.openapi import install_openapi
from app.core.query import reject_unknown_query
from app.devices.router import router as devices_router
from app.floors.router import router as floors_router
from app.ingest.direct import DirectIngest
from app.ingest.router import router as ingest_router
from app.keys.router import router as keys_router
from app.ops.router import router as ops_router
from app.outputs.router import router as outputs_router
from app.planning.router import router as planning_router
from app.positions.router import router as positions_router
from app.radiomaps.router import floor_router as guidance_router
from app.radiomaps.router import router as radiomaps_router
from app.sites.router import router as sites_router
from app.state import AppState
from app.surveys.router import router as surveys_router
from app.tracks.router import router as tracks_router

WEB_DIR = Path(__file__).parent / "web"


class RequestMetrics:
    """Count requests and time them by route template (plain ASGI: cheap on the hot path)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            state = getattr(scope["app"].state, "locus", None)
            if state is not None:
                path = getattr(scope.get("route"), "path", "unmatched")
                state.metrics.requests.labels(scope["method"], path, str(status)).inc()
                state.metrics.request_seconds.labels(path).observe(time.perf_counter() - started)


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app; the database schema must already be at head (``locus serve`` does it)."""
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state = await AppState.open(settings)
        app.state.locus = state
        settle_heap()
        try:
            yield
        finally:
            await state.close()

    # /docs and /redoc with their scripts served from a package, not a CDN: servers on a
    # site's network often have no internet. No validator badge either (it asks a website).
    app = FastAPIOffline(
        title="Locus",
        version=__version__,
        summary="Real-time indoor location engine for many tags.",
        lifespan=lifespan,
        dependencies=[Depends(reject_unknown_query)],
        swagger_ui_parameters={"validatorUrl": None},
        # off unless asked for: its check for a configured provider runs on every request
        # (bench/load.py measures the API's CPU at ingest saturation)
        telemetry={
            "tracing": settings.opentelemetry,
            "metrics": settings.opentelemetry,
            "logs": settings.opentelemetry,
        },
    )
    install_error_handlers(app)
    install_openapi(app)

    # the metrics wrap the direct ingest path too: a middleware added later runs outside
    app.add_middleware(DirectIngest, routes=ingest_router.routes)
    app.add_middleware(RequestMetrics)
    # ingest first: a request is matched against the routes in this order, and ingest
    # carries nearly all of them
    for router in (
        ingest_router,
        ops_router,
        keys_router,
        sites_router,
        floors_router,
        devices_router,
        positions_router,
        surveys_router,
        radiomaps_router,
        guidance_router,
        tracks_router,
        planning_router,
        outputs_router,
        analytics_router,
    ):
        app.include_router(router)
    if WEB_DIR.is_dir():
        app.mount("/", StaticFiles(directory=WEB_DIR, html=True), name="web")
    return app
