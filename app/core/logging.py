"""Logging set-up shared by the API and worker processes."""

from __future__ import annotations

import logging

QUIET = ("httpx", "httpcore", "alembic.runtime.plugins")
"""Loggers that say routine things at INFO: HTTP clients log every request (the demo's
devices post every second), Alembic each of its plugins at every start. Their warnings
still show."""


def configure_logging(level: str = "INFO") -> None:
    """Log to stderr with process names, so worker lines are told apart."""
    logging.basicConfig(
        level=level,
        format="%(asctime)s %(levelname)s %(processName)s %(name)s: %(message)s",
    )
    for name in QUIET:
        logging.getLogger(name).setLevel(logging.WARNING)
