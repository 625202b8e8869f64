"""Replaying recorded batches through a positioning method, timing only the method's own CPU.

A walk goes through one filter batch by batch (``replay``), or many walks go
through one ``PositioningEngine`` as its devices, every device's i-th batch
in the engine's i-th call, as a server worker batches them
(``replay_devices``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Protocol

from app.engine.positioning import PositioningEngine, seed_from_id
from app.engine.samples import Batch, Estimate


class BatchPositioner(Protocol):
    """What a replay needs from a method: batches in, estimates out."""

    def process(self, batch: Batch) -> list[Estimate]:
        """Consume one batch; return the estimates it produced."""
        ...


@dataclass
class WalkReplay:
    """One method's estimates on one walk, the CPU time (s) its batches took and their count."""

    estimates: list[Estimate]
    cpu_s: float
    updates: int


def replay(
    positioner: BatchPositioner,
    batches: Iterable[Batch],
    *,
    transform: Callable[[Batch], Batch] | None = None,
    flush: Callable[[], list[Estimate]] | None = None,
) -> WalkReplay:
    """Feed a walk's batches to a positioner, timing only the positioner's own CPU."""
    out: list[Estimate] = []
    cpu = 0.0
    updates = 0
    for batch in batches:
        if transform is not None:
            batch = transform(batch)
        t0 = time.process_time()
        out.extend(positioner.process(batch))
        cpu += time.process_time() - t0
        updates += 1
    if flush is not None:
        t0 = time.process_time()
        out.extend(flush())
        cpu += time.process_time() - t0
    return WalkReplay(out, cpu, updates)


@dataclass
class DevicesReplay:
    """Each device's estimates, the engine's CPU time (s) and the number of device updates."""

    estimates: dict[str, list[Estimate]]
    cpu_s: float
    updates: int


def replay_devices(
    engine: PositioningEngine,
    streams: Mapping[str, Iterator[Batch]],
    *,
    transform: Callable[[Batch], Batch],
    progress: Callable[[int], None] = lambda _n: None,
) -> DevicesReplay:
    """Replay every stream as a device of ``engine``, seeded from its id, all in step.

    Device k's i-th batch goes in the engine's i-th call with every other
    device's i-th batch, so each call is one batched filter update per floor
    for all devices. A device's filter does not depend on its batch mates, so
    its estimates are those of replaying it alone; only the CPU per device
    update differs. A device is flushed and removed when its stream ends;
    ``progress`` gets the number of devices done so far.
    """
    pending = dict(streams)
    for device_id in pending:
        engine.add(device_id, seed_from_id(device_id))
    out: dict[str, list[Estimate]] = {device_id: [] for device_id in pending}
    cpu, updates = 0.0, 0
    while pending:
        due: dict[str, Batch] = {}
        for device_id, stream in list(pending.items()):
            batch = next(stream, None)
            if batch is None:
                del pending[device_id]
                t0 = time.process_time()
                out[device_id].extend(engine.flush([device_id])[device_id])
                cpu += time.process_time() - t0
                engine.remove(device_id)
                progress(len(out) - len(pending))
            else:
                due[device_id] = transform(batch)
        if due:
            t0 = time.process_time()
            for device_id, estimates in engine.process(due).items():
                out[device_id].extend(estimates)
            cpu += time.process_time() - t0
            updates += len(due)
    return DevicesReplay(out, cpu, updates)
