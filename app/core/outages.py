"""Storage outages: the database or Redis away for a while, told apart from bugs and bad data.

A request that meets one answers 503 with ``Retry-After``: the client keeps
its data and sends it again. Work the service has already acknowledged is
never dropped for one: workers and publishers run it again with
``retry_through_outage`` until the store takes it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TypeVar

import redis
from sqlalchemy import exc as sa

log = logging.getLogger(__name__)

T = TypeVar("T")

RETRY_AFTER_S = 2
"""What a request refused for an outage tells its client to wait (s)."""

FIRST_WAIT_S = 0.1
LONGEST_WAIT_S = 2.0
"""Backoff between attempts at work held through an outage: doubling, capped, so the service
resumes within about two seconds of the store's return."""


def is_outage(error: BaseException) -> bool:
    """Return whether ``error`` says the database or Redis cannot be reached or is restarting.

    A lost or refused connection, a pool that cannot hand one out, a server
    shutting down or starting, a locked SQLite file: each passes. A
    constraint violation or a bad statement does not.
    """
    if isinstance(error, sa.OperationalError | sa.InterfaceError | sa.TimeoutError):
        return True
    if isinstance(error, sa.DBAPIError):
        return bool(error.connection_invalidated)
    return isinstance(error, redis.ConnectionError | redis.TimeoutError)


def retry_through_outage(
    work: Callable[[], T], *, what: str, on_wait: Callable[[], None] = lambda: None
) -> T:
    """Run ``work`` until it completes; while it fails for an outage, wait and run it again.

    ``work`` must be safe to repeat after a failure (a transaction rolled back,
    a write that replaces). ``on_wait`` runs before each wait: a worker keeps
    its leases alive there. Any other error is raised at once.
    """
    wait_s = FIRST_WAIT_S
    down_since: float | None = None
    while True:
        try:
            result = work()
        except Exception as error:
            if not is_outage(error):
                raise
            if down_since is None:
                down_since = time.monotonic()
                log.warning("%s: storage unavailable (%s); held until it returns", what, error)
            on_wait()
            time.sleep(wait_s)
            wait_s = min(LONGEST_WAIT_S, wait_s * 2)
            continue
        if down_since is not None:
            log.warning("%s: storage back after %.1f s", what, time.monotonic() - down_since)
        return result
