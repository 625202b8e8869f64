"""The dispatcher: in each API node, deliver the outbox of every output this node leases.

Runs as tasks on the API's event loop (embedded default included: no other
process); database work runs in threads. Per output, messages are sent
oldest first and the next batch waits for the current one's acknowledgement,
so a device's messages arrive in order; a failure is retried after an
exponential backoff with jitter (seeded by the output's id), and messages
older than the retention bound are given up, counted failed.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import random
import socket
import time
import uuid
from collections.abc import Callable
from typing import Protocol, TypeVar

from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.db import session_scope
from app.core.metrics import Metrics
from app.core.time import now_ms, utcnow
from app.outputs import queue
from app.outputs.models import OutboxRow, Output
from app.outputs.mqtt import DeliveryError, MqttSender
from app.outputs.service import options
from app.outputs.webhook import WebhookSender

log = logging.getLogger(__name__)
T = TypeVar("T")


class Sender(Protocol):
    """What delivers one output's rows."""

    async def send(self, rows: list[OutboxRow]) -> None:
        """Deliver the rows or raise DeliveryError."""

    async def close(self) -> None:
        """Release connections."""


class RateLimit:
    """A token bucket: at most ``rate`` messages per second, in bursts of one second's."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.tokens = rate
        self.at = time.monotonic()

    async def take(self, n: int) -> None:
        """Wait until ``n`` messages may go."""
        now = time.monotonic()
        self.tokens = min(self.rate, self.tokens + (now - self.at) * self.rate)
        self.at = now
        self.tokens -= n
        if self.tokens < 0:
            await asyncio.sleep(-self.tokens / self.rate)


class Dispatcher:
    """Leases outputs for this node and runs one delivery task per leased output."""

    def __init__(self, settings: Settings, sessions: sessionmaker[Session], metrics: Metrics):
        self.settings = settings
        self.sessions = sessions
        self.metrics = metrics
        self.node = f"{socket.gethostname()[:30]}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.tasks: dict[queue.OutputKey, tuple[object, asyncio.Task[None]]] = {}
        self.main: asyncio.Task[None] | None = None

    def start(self) -> None:
        """Start leasing and delivering."""
        self.main = asyncio.create_task(self._run())

    async def stop(self) -> None:
        """Stop every delivery task and give up this node's leases."""
        tasks = [t for _, t in self.tasks.values()] + ([self.main] if self.main else [])
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self.tasks.clear()
        with contextlib.suppress(SQLAlchemyError):
            await asyncio.to_thread(self._db, lambda db: queue.release(db, node=self.node))

    def _db(self, work: Callable[[Session], T]) -> T:
        with session_scope(self.sessions) as db:
            return work(db)

    async def _run(self) -> None:
        every = min(1.0, self.settings.output_lease_s / 3)
        rounds = 0
        while True:
            try:
                await self._tend(orphans=rounds % 60 == 0)
            except SQLAlchemyError:
                log.exception("could not lease the outputs; trying again")
            rounds += 1
            await asyncio.sleep(every)

    async def _tend(self, *, orphans: bool) -> None:
        """Renew the leases, start a task per newly held output (again when it changed),
        stop those no longer held, and set the pending gauges."""

        def work(db: Session) -> tuple[list[Output], dict[queue.OutputKey, int]]:
            held = queue.claim(
                db, node=self.node, now=utcnow(), lease_s=self.settings.output_lease_s
            )
            if orphans:
                known = {(o.site_id, o.id) for o in db.query(Output.site_id, Output.id)}
                queue.drop_orphans(db, known=known)
            return held, queue.pending(db)

        held, pending = await asyncio.to_thread(self._db, work)
        current = {(o.site_id, o.id): o for o in held}
        for key, (version, task) in list(self.tasks.items()):
            output = current.get(key)
            if output is None or output.updated_at != version or task.done():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
                del self.tasks[key]
        for key, output in current.items():
            if key not in self.tasks:
                task = asyncio.create_task(self._deliver(output))
                self.tasks[key] = (output.updated_at, task)
            self.metrics.output_pending.labels(*key).set(pending.get(key, 0))

    def _sender(self, output: Output, batch_max: int) -> Sender:
        opts = options(output)
        timeout = self.settings.output_timeout_s
        if output.kind == "mqtt":
            return MqttSender(
                url=output.url,
                topic_prefix=opts.get("topic_prefix") or "locus",
                username=opts.get("username"),
                password=output.secret,
                home_assistant=bool(opts.get("home_assistant")),
                client_id=f"locus-{output.site_id}-{output.id}"[:64],
                timeout_s=timeout,
                batch_max=batch_max,
            )
        return WebhookSender(url=output.url, secret=output.secret or "", timeout_s=timeout)

    async def _deliver(self, output: Output) -> None:
        """Send the output's outbox, oldest first, until cancelled."""
        key = (output.site_id, output.id)
        opts = options(output)
        rate = opts.get("rate_limit") or self.settings.output_rate_limit
        limit = max(
            1, min(self.settings.output_batch_max, opts.get("batch_max") or 10**9, int(rate))
        )
        keep = output.kind == "webhook"
        sender = self._sender(output, limit)
        bucket = RateLimit(rate)
        rng = random.Random(f"{output.site_id}/{output.id}")
        failures = 0
        delivered, retried, failed = (
            m.labels(*key)
            for m in (
                self.metrics.output_delivered,
                self.metrics.output_retried,
                self.metrics.output_failed,
            )
        )
        try:
            while True:
                try:
                    rows = await asyncio.to_thread(
                        self._db,
                        functools.partial(queue.next_batch, key=key, limit=limit, keep=keep),
                    )
                except SQLAlchemyError:
                    log.exception("output %s/%s: could not read the outbox", *key)
                    await asyncio.sleep(self.settings.output_retry_max_s)
                    continue
                if not rows:
                    await asyncio.sleep(self.settings.output_poll_s)
                    continue
                await bucket.take(len(rows))
                try:
                    await sender.send(rows)
                except DeliveryError as exc:
                    failures += 1
                    retried.inc(len(rows))
                    cutoff = now_ms() - round(self.settings.output_retention_s * 1000)
                    expired = await asyncio.to_thread(
                        self._db,
                        functools.partial(
                            queue.record_failure, key=key, error=str(exc), stored_before=cutoff
                        ),
                    )
                    failed.inc(expired)
                    # P(delay) uniform in [d/2, d], d = base 2^(n-1) capped
                    base = self.settings.output_retry_base_s * 2 ** min(failures - 1, 30)
                    delay = min(self.settings.output_retry_max_s, base) * (0.5 + 0.5 * rng.random())
                    await asyncio.sleep(delay)
                    continue
                failures = 0
                ids = [row.id for row in rows]
                await asyncio.to_thread(
                    self._db, functools.partial(queue.acknowledge, key=key, ids=ids, now=utcnow())
                )
                delivered.inc(len(rows))
        finally:
            await sender.close()
