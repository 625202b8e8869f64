"""Fan-out of positions and zone events to WebSocket subscribers.

Each subscriber has its own bounded queue: a slow or dead dashboard loses its
oldest messages (counted), never slows the others or the ingest path.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Any

from app.core.metrics import Metrics


@dataclass(eq=False)
class Subscriber:
    """One WebSocket's filter and queue."""

    site_id: str | None
    floor_id: str | None
    device_id: str | None
    queue: asyncio.Queue[dict[str, Any]] = field(default_factory=asyncio.Queue)
    dropped: int = 0

    def wants(self, message: dict[str, Any]) -> bool:
        """Return whether the message passes this subscriber's filters."""
        if self.site_id is not None and message.get("site_id") != self.site_id:
            return False
        if self.device_id is not None and message.get("device_id") != self.device_id:
            return False
        if self.floor_id is not None and message.get("type") == "position":
            return message.get("floor_id") == self.floor_id
        return True


class PositionHub:
    """Subscribers of the event loop; ``publish`` must be called on that loop."""

    def __init__(self, metrics: Metrics, queue_size: int) -> None:
        self.metrics = metrics
        self.queue_size = queue_size
        self.subscribers: set[Subscriber] = set()

    def subscribe(
        self, *, site_id: str | None, floor_id: str | None, device_id: str | None
    ) -> Subscriber:
        """Register a subscriber with its filters."""
        sub = Subscriber(site_id, floor_id, device_id, asyncio.Queue(self.queue_size))
        self.subscribers.add(sub)
        self.metrics.ws_subscribers.set(len(self.subscribers))
        return sub

    def unsubscribe(self, sub: Subscriber) -> None:
        """Forget a subscriber."""
        self.subscribers.discard(sub)
        self.metrics.ws_subscribers.set(len(self.subscribers))

    def publish(self, messages: list[dict[str, Any]]) -> None:
        """Offer messages to every interested subscriber, dropping their oldest when full."""
        for sub in self.subscribers:
            for message in messages:
                if not sub.wants(message):
                    continue
                if sub.queue.full():
                    sub.queue.get_nowait()
                    sub.dropped += 1
                    self.metrics.ws_dropped.inc()
                sub.queue.put_nowait(message)
