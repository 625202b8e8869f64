"""Ingest: check a parsed batch against limits and the site, then hand it to the runtime."""

from __future__ import annotations

import asyncio
from typing import Any

from app.core.config import Settings
from app.core.errors import ApiError
from app.core.security import Principal
from app.core.time import now_ms
from app.ingest.schemas import SAMPLE_KINDS, IngestBatch, LocatorBatch
from app.sites.cache import SiteVersions
from app.workers.runtime import Outcome, Runtime

WAIT_TIMEOUT_S = 60.0


def check_site(*, principal: Principal, site_id: str, sites: SiteVersions) -> int:
    """Return the site's map version; 403 if the key may not report there, 404 if unknown."""
    if not principal.can_report(site_id):
        raise ApiError(403, f"this key may not report measurements for site '{site_id}'")
    version = sites.get(site_id)
    if version is None:
        raise ApiError(404, f"site '{site_id}' not found")
    return version


def check_times(*, latest_t: int, settings: Settings) -> None:
    """Reject samples from a device clock far in the future (422)."""
    if latest_t > now_ms() + settings.max_future_ms:
        raise ApiError(
            422,
            f"sample time {latest_t} is more than {settings.max_future_ms} ms in the future",
            details=[{"loc": ["t"], "msg": "timestamp in the future", "type": "future_time"}],
        )


async def ingest_batch(
    *,
    batch: IngestBatch,
    principal: Principal,
    settings: Settings,
    runtime: Runtime,
    sites: SiteVersions,
    wait: bool,
) -> dict[str, Any]:
    """Validate against limits and the site, submit, and (with ``wait``) await positions."""
    count = batch.sample_count
    if count > settings.max_samples:
        raise ApiError(413, f"{count} samples in one batch; the limit is {settings.max_samples}")
    version = check_site(principal=principal, site_id=batch.site_id, sites=sites)
    check_times(latest_t=batch.max_t(), settings=settings)
    samples = {
        kind: [s.model_dump(exclude_none=True) for s in getattr(batch, kind)]
        for kind in SAMPLE_KINDS
        if getattr(batch, kind)
    }
    processed = runtime.last_processed_t(batch.device_id)
    late = sum(1 for items in samples.values() for s in items if s["t"] <= processed)
    _, future = runtime.submit(
        site_id=batch.site_id,
        device_id=batch.device_id,
        version=version,
        samples=samples,
        wait=wait,
    )
    if future is None:
        return {"accepted": count - late, "late": late}
    outcome = await _await(future)
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
    if count > settings.max_samples:
        raise ApiError(413, f"{count} sightings in one batch; the limit is {settings.max_samples}")
    version = check_site(principal=principal, site_id=batch.site_id, sites=sites)
    check_times(latest_t=max(s.t for s in batch.sightings), settings=settings)
    by_tag: dict[str, list[dict[str, Any]]] = {}
    for s in batch.sightings:
        by_tag.setdefault(s.tag_id, []).append(
            {"t": s.t, "locator_id": batch.locator_id, "rssi": s.rssi}
        )
    futures = []
    late = 0
    for tag, sightings in by_tag.items():
        processed = runtime.last_processed_t(tag)
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
    outcomes = [await _await(f) for f in futures if f is not None]
    positions = sorted((p for o in outcomes for p in o.positions), key=lambda p: p["t"])
    return {
        "accepted": sum(o.accepted for o in outcomes),
        "late": sum(o.late for o in outcomes),
        "positions": positions,
    }


async def _await(future: asyncio.Future[Outcome]) -> Outcome:
    try:
        outcome = await asyncio.wait_for(asyncio.shield(future), WAIT_TIMEOUT_S)
    except TimeoutError as exc:
        raise ApiError(
            503,
            "the batch was queued but not processed in time; it is kept",
            headers={"Retry-After": "5"},
        ) from exc
    if outcome.error is not None:
        raise outcome.error
    return outcome
