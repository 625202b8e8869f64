"""Ingest flows: a checked batch handed to the worker runtime, and (with ``wait``) the
positions its processing emitted."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import Any

from app.core.config import Settings
from app.core.errors import Unavailable
from app.core.security import Principal
from app.ingest import service
from app.ingest.schemas import IngestBatch, LocatorBatch
from app.sites.cache import SiteVersions
from app.workers.device import late_before
from app.workers.runtime import Outcome, Runtime


@dataclass(frozen=True)
class Submitted:
    """A device's batch once submitted: its counts and, with ``wait``, its outcome to come.

    Nothing of the parsed batch is kept: a request awaiting its positions holds only this.
    """

    accepted: int
    late: int
    future: asyncio.Future[Outcome] | None


def submit_batch(
    *,
    batch: IngestBatch,
    principal: Principal,
    settings: Settings,
    runtime: Runtime,
    sites: SiteVersions,
    wait: bool,
) -> Submitted:
    """Check a device's batch and submit it; with ``wait`` the result carries its future.

    Synchronous, so that the caller's parsed batch is freed before it awaits the positions:
    a thousand requests waiting each with their batch's small objects alive spread them
    over the allocator's arenas, and Python's allocator keeps an arena while any object
    in it lives, so a stall under many devices would leave arenas held long after it.
    """
    count = batch.sample_count
    version = service.check_batch(
        site_id=batch.site_id,
        count=count,
        noun="samples",
        latest_t=batch.max_t(),
        principal=principal,
        settings=settings,
        sites=sites,
    )
    if count == 0:
        # only cached WiFi repeats, each reported as dropped: nothing to position
        return Submitted(0, 0, None)
    samples = service.batch_samples(batch)
    key = (batch.site_id, batch.device_id)
    processed = runtime.last_processed_t(key)
    processed_wifi = runtime.last_processed_wifi_t(key)
    late = sum(
        1
        for kind, items in samples.items()
        for s in items
        if s["t"] <= late_before(kind, processed, processed_wifi)
    )
    _, future = runtime.submit(
        site_id=batch.site_id,
        device_id=batch.device_id,
        version=version,
        samples=samples,
        wait=wait,
    )
    return Submitted(count - late, late, future)


async def settle(submitted: Submitted, *, wait: bool, timeout_s: float) -> dict[str, Any]:
    """Return a submitted batch's answer: its counts, and with ``wait`` its positions once
    processed (a batch of cached repeats only has none to wait for)."""
    if submitted.future is None:
        answer = {"accepted": submitted.accepted, "late": submitted.late}
        return answer | ({"positions": []} if wait else {})
    outcome = await _outcome(submitted.future, timeout_s)
    return {"accepted": outcome.accepted, "late": outcome.late, "positions": outcome.positions}


async def ingest_locator(
    *,
    batch: LocatorBatch,
    principal: Principal,
    settings: Settings,
    runtime: Runtime,
    sites: SiteVersions,
    wait: bool,
) -> dict[str, Any]:
    """Route each sighting to its tag's filter; with ``wait`` collect the tags' positions."""
    count = len(batch.sightings)
    version = service.check_batch(
        site_id=batch.site_id,
        count=count,
        noun="sightings",
        latest_t=max(s.t for s in batch.sightings),
        principal=principal,
        settings=settings,
        sites=sites,
    )
    futures = []
    late = 0
    for tag, sightings in service.sightings_by_tag(batch).items():
        processed = runtime.last_processed_t((batch.site_id, tag))
        late += sum(1 for s in sightings if s["t"] <= processed)
        _, future = runtime.submit(
            site_id=batch.site_id,
            device_id=tag,
            version=version,
            samples={"sightings": sightings},
            wait=wait,
            # other locators' reports of the same moments are still on their way:
            # waiting must not cut the tag's reorder window short
            flush=False,
        )
        futures.append(future)
    if not wait:
        return {"accepted": count - late, "late": late}
    timeout_s = settings.ingest_wait_timeout_s
    outcomes = [await _outcome(f, timeout_s) for f in futures if f is not None]
    positions = sorted((p for o in outcomes for p in o.positions), key=lambda p: p["t"])
    return {
        "accepted": sum(o.accepted for o in outcomes),
        "late": sum(o.late for o in outcomes),
        "positions": positions,
    }


async def _outcome(future: asyncio.Future[Outcome], timeout_s: float) -> Outcome:
    """Await a submitted batch's outcome; the batch stays queued when the wait times out.

    ``asyncio.wait`` leaves the future alone on a timeout or a cancellation, as
    ``wait_for(shield(...))`` does, with fewer objects alive per waiting request than that
    keeps.
    """
    done, _ = await asyncio.wait((future,), timeout=timeout_s)
    if not done:
        raise Unavailable(
            "the batch was queued but not processed in time; it is kept", retry_after_s=5
        )
    outcome = future.result()
    if outcome.error is not None:
        raise outcome.error
    return outcome
