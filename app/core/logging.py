"""Logging set-up shared by the API and worker processes."""

from __future__ import annotations

import logging

QUIET = ("httpx", "httpcore", "alembic.runtime.plugins")
"""Loggers that say routine things at INFO: HTTP clients log every request (the demo's
devices post every second), Alembic each of its plugins at every start. Their warnings
still show."""

CONNECTION_LINES = frozenset(
    {'%s - "WebSocket %s" [accepted]', "connection open", "connection closed"}
)
"""What uvicorn logs, outside its access log, for every WebSocket: one line per dashboard
that connects, with the key from its URL."""


def configure_logging(level: str = "INFO") -> None:
    """Log to stderr with process names, so worker lines are told apart."""
    logging.basicConfig(
        level=level,
        format="%(asctime)s %(levelname)s %(processName)s %(name)s: %(message)s",
    )
    for name in QUIET:
        logging.getLogger(name).setLevel(logging.WARNING)


def _not_a_connection(record: logging.LogRecord) -> bool:
    return record.levelno > logging.INFO or record.msg not in CONNECTION_LINES


def quiet_connections() -> None:
    """Leave WebSocket connections out of the log, as the access log leaves out requests."""
    logging.getLogger("uvicorn.error").addFilter(_not_a_connection)
