"""Which delivered batches a stored snapshot now holds, so that a broker may forget them.

A batch's positions are stored when it is processed, but its last samples
wait in the device's reorder window and its filter state lives in the
worker's memory until the device's next snapshot. A broker that forgot the
batch at once would lose those samples with a crashed worker: the next one
resumes the device from an older snapshot and never sees them. So a worker
acknowledges a batch only once a stored snapshot of its device holds it
(``DeviceSession.covered``); until then a crash re-delivers it, and the next
worker replays it on top of that snapshot (samples it already used count as
late or duplicate, positions it already stored are not emitted again).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from typing import Generic, TypeVar

from app.workers.device import DeviceSession
from app.workers.messages import Done, Ingest
from app.workers.shard import Shard

Token = TypeVar("Token")
"""What the broker acknowledges a batch by (a stream entry id, a batch id)."""


class CoverageLedger(Generic[Token]):
    """The processed batches each device's stored snapshot does not hold yet."""

    def __init__(self) -> None:
        self._held: dict[DeviceSession, deque[tuple[Token, int]]] = {}
        self._count = 0

    def __len__(self) -> int:
        """Return how many processed batches wait for a snapshot."""
        return self._count

    def hold(self, device: DeviceSession, token: Token) -> None:
        """Hold a batch the device has just consumed until a snapshot covers it."""
        self._held.setdefault(device, deque()).append((token, device.consumed))
        self._count += 1

    def hold_batches(
        self, shard: Shard, tokens: list[Token], messages: list[Ingest], results: list[Done]
    ) -> list[Token]:
        """Hold the batches the shard has just processed (one result each, in order);
        return those to acknowledge at once: no device took them, or they failed."""
        now: list[Token] = []
        for token, message, result in zip(tokens, messages, results, strict=True):
            device = shard.devices.get((message.site_id, message.device_id))
            if device is None or result.error is not None:
                now.append(token)
            else:
                self.hold(device, token)
        return now

    def release(self, devices: Iterable[DeviceSession]) -> list[Token]:
        """Return the held batches that the devices' newly stored snapshots cover."""
        released: list[Token] = []
        for device in devices:
            held = self._held.get(device)
            while held and held[0][1] <= device.covered:
                released.append(held.popleft()[0])
            if held is not None and not held:
                del self._held[device]
        self._count -= len(released)
        return released

    def release_all(self) -> list[Token]:
        """Return every held batch (the shard was drained: each device was snapshotted)."""
        released = [token for held in self._held.values() for token, _ in held]
        self._held.clear()
        self._count = 0
        return released
