"""The interface a worker's shard uses on every device's filter, whatever its kind."""

from __future__ import annotations

from typing import Any, Protocol

from app.engine.samples import Batch, Estimate


class Tracker(Protocol):
    """A device's filter: fed time-ordered batches, emits estimates, snapshots its state.

    ``process`` receives samples strictly later than everything it has seen;
    ``snapshot`` returns plain numbers, strings and ndarrays only, so workers
    can store it without pickling code.
    """

    def process(self, batch: Batch) -> list[Estimate]:
        """Consume one time-ordered batch and return the estimates it produced."""
        ...

    def flush(self) -> list[Estimate]:
        """Return the estimates of what the filter still holds back (the device went quiet)."""
        ...

    def snapshot(self) -> dict[str, Any]:
        """Return the state needed to resume exactly where this filter stands."""
        ...

    def close(self) -> None:
        """Free what the filter holds outside itself; it is not used afterwards."""
        ...
