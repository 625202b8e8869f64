"""The contract's error object and the one place that renders it."""

from __future__ import annotations

import logging
from typing import Any

import redis
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy import exc as sa
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Route

from app.core.outages import RETRY_AFTER_S, is_outage

log = logging.getLogger(__name__)

_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    409: "conflict",
    413: "payload_too_large",
    415: "unsupported_media_type",
    422: "invalid",
    429: "too_many_requests",
    503: "unavailable",
}


class ApiError(Exception):
    """An error the client caused or must handle, rendered as the contract's error object."""

    def __init__(
        self,
        status: int,
        message: str,
        *,
        code: str | None = None,
        details: list[Any] | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code or _CODES.get(status, "error")
        self.message = message
        self.details = details or []
        self.headers = headers


class DomainError(Exception):
    """A failure named by the domain, not by HTTP; the handlers below map each kind to a status.

    Services and workers raise these; only ``install_error_handlers`` knows status codes.
    ``code`` names a more specific failure than the kind's own code (e.g. ``no_surveys``).
    """

    status = 500
    code = "error"

    def __init__(
        self,
        message: str,
        *,
        code: str | None = None,
        details: list[Any] | None = None,
        retry_after_s: float | None = None,
    ) -> None:
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code
        self.details = details or []
        self.retry_after_s = retry_after_s


class BadRequest(DomainError):
    """The request cannot be read at all (its body is not JSON)."""

    status, code = 400, "bad_request"


class NotFound(DomainError):
    """The named resource does not exist (or is not visible to the caller)."""

    status, code = 404, "not_found"


class Forbidden(DomainError):
    """The caller's key may not do this."""

    status, code = 403, "forbidden"


class Conflict(DomainError):
    """The request contradicts the current state."""

    status, code = 409, "conflict"


class TooLarge(DomainError):
    """The request exceeds a configured size limit."""

    status, code = 413, "payload_too_large"


class Invalid(DomainError):
    """The request is well-formed but its content is not acceptable."""

    status, code = 422, "invalid"


class Overloaded(DomainError):
    """The work cannot be taken now; the client should retry after ``retry_after_s``."""

    status, code = 429, "too_many_requests"


class Unavailable(DomainError):
    """A dependency (workers, database, broker) cannot serve the request now."""

    status, code = 503, "unavailable"


class ProcessingFailed(DomainError):
    """The workers failed while processing an accepted batch."""

    status, code = 500, "processing_failed"


def error_body(code: str, message: str, details: list[Any] | None = None) -> dict[str, Any]:
    """Return the JSON error object of docs/api.md."""
    return {"error": {"code": code, "message": message, "details": details or []}}


def validation_details(errors: list[Any]) -> list[dict[str, Any]]:
    """Reduce pydantic errors to JSON-safe ``{loc, msg, type}`` items."""
    return [
        {"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg")), "type": e.get("type")}
        for e in errors
    ]


def not_json(reason: str) -> BadRequest:
    """Return the 400 of a body that is not JSON, with the parser's reason."""
    return BadRequest(
        f"body is not valid JSON: {reason}",
        code="invalid_json",
        details=[{"loc": ["body"], "msg": reason, "type": "json_invalid"}],
    )


def validation_failed(errors: list[Any], message: str = "request failed validation") -> DomainError:
    """Return the error of a body that failed validation: 400 when it is not JSON at all
    (as most HTTP APIs answer), else 422 listing every fault."""
    for error in errors:
        if error.get("type") == "json_invalid":
            reason = str(error.get("msg", "")).removeprefix("Invalid JSON: ")
            if reason == "JSON decode error":
                # FastAPI's own parse: the reason in ctx, the character's offset last in loc
                ctx, loc = error.get("ctx") or {}, error.get("loc") or ("",)
                reason = f"{ctx.get('error', reason)} (character {loc[-1]})"
            return not_json(reason)
    details = validation_details(errors)
    if details:
        # the first fault in the message itself: a client logging only the message learns it
        first = details[0]
        where = ".".join(p for p in first["loc"] if p != "body")
        more = f" (and {len(details) - 1} more in details)" if len(details) > 1 else ""
        message = f"{message}: {where + ': ' if where else ''}{first['msg']}{more}"
    return Invalid(message, details=details)


def _other_methods(request: Request) -> list[str]:
    """Return the methods of the routes whose path matches the request's (none: no route).

    The dashboard is mounted at ``/`` and answers every path no route took, so a
    route asked with the wrong method would read as missing (404) rather than 405.
    """
    methods: set[str] = set()
    routes = list(request.app.routes)
    while routes:
        route = routes.pop()
        if isinstance(route, Route) and route.matches(request.scope)[0] is Match.PARTIAL:
            methods |= route.methods or set()
        # an included router keeps its routes, their paths prefixed, in its original router
        routes.extend(getattr(getattr(route, "original_router", None), "routes", ()))
    return sorted(methods)


_STORAGE_ERRORS = (sa.DBAPIError, sa.TimeoutError, redis.ConnectionError, redis.TimeoutError)
"""Errors of the database or Redis: a 503 when the store is out, else a 500."""


async def error_response(request: Request, exc: Exception) -> JSONResponse:
    """Return the contract's answer to any error a request raised.

    The exception handlers render by it, and so does the ingest's direct path
    (``app.ingest.direct``), which the framework's handlers do not see.
    """
    if isinstance(exc, ApiError):
        return JSONResponse(
            error_body(exc.code, exc.message, exc.details), exc.status, headers=exc.headers
        )
    if isinstance(exc, DomainError):
        headers = None
        if exc.retry_after_s is not None:
            headers = {"Retry-After": str(max(1, round(exc.retry_after_s)))}
        return JSONResponse(
            error_body(exc.code, exc.message, exc.details), exc.status, headers=headers
        )
    if isinstance(exc, RequestValidationError):
        error = validation_failed(list(exc.errors()))
        return JSONResponse(error_body(error.code, error.message, error.details), error.status)
    if isinstance(exc, _STORAGE_ERRORS) and is_outage(exc):
        log.warning("storage unavailable: %s %s: %s", request.method, request.url.path, exc)
        store = "Redis" if isinstance(exc, redis.RedisError) else "the database"
        return JSONResponse(
            error_body("unavailable", f"{store} is unavailable; retry later"),
            503,
            headers={"Retry-After": str(RETRY_AFTER_S)},
        )
    log.exception("unhandled error", exc_info=exc)
    return JSONResponse(error_body("internal", "internal server error"), 500)


def install_error_handlers(app: FastAPI) -> None:
    """Render every error, ours or the framework's, as the contract's error object."""
    for kind in (ApiError, DomainError, RequestValidationError, Exception, *_STORAGE_ERRORS):
        app.add_exception_handler(kind, error_response)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        allowed = _other_methods(request) if exc.status_code == 404 else []
        if allowed:
            return JSONResponse(
                error_body(
                    "method_not_allowed", f"{request.method} not allowed; use {', '.join(allowed)}"
                ),
                405,
                headers={"Allow": ", ".join(allowed)},
            )
        code = _CODES.get(exc.status_code, "error")
        return JSONResponse(
            error_body(code, str(exc.detail)),
            exc.status_code,
            headers=getattr(exc, "headers", None),
        )
