"""Ingest checks: a parsed batch against the limits, the caller's key and the site."""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError

from app.core.config import Settings
from app.core.errors import Forbidden, Invalid, NotFound, TooLarge, validation_failed
from app.core.sample_policy import body_indices, validate_screened
from app.core.security import Principal
from app.core.time import now_ms
from app.ingest.schemas import (
    SAMPLE_KINDS,
    SAMPLE_MODELS,
    IngestBatch,
    LocatorBatch,
    RadioSample,
)
from app.sites.cache import SiteVersions


def check_site(*, principal: Principal, site_id: str, sites: SiteVersions) -> int:
    """Return the site's map version; Forbidden if the key may not report there, NotFound if
    the site is unknown."""
    if not principal.can_report(site_id):
        raise Forbidden(f"this key may not report measurements for site '{site_id}'")
    version = sites.get(site_id)
    if version is None:
        raise NotFound(f"site '{site_id}' not found")
    return version


def screen_batch(raw: bytes | str, settings: Settings) -> tuple[IngestBatch, list[dict[str, Any]]]:
    """Return a device's batch validated under the per-sample policy, cached WiFi repeats left
    out, and what was dropped; the one conversion of an ingest body for every path.

    Raises Invalid when the body's structure is wrong or no sample is physically possible.
    A batch of cached WiFi repeats only is sound: it is left with no sample.
    """
    try:
        batch, drops = validate_screened(
            IngestBatch, raw, SAMPLE_MODELS, max_offset_ms=round(settings.time_outlier_s * 1000)
        )
    except ValidationError as exc:
        raise validation_failed(exc.errors(include_url=False)) from exc
    wifi, stale = drop_stale_wifi(batch.wifi, settings.wifi_max_age_ms, drops)
    if stale:
        batch = batch.model_copy(update={"wifi": wifi})
    return batch, drops + stale


def drop_stale_wifi(
    wifi: list[RadioSample], max_age_ms: int, earlier_drops: list[dict[str, Any]]
) -> tuple[list[RadioSample], list[dict[str, Any]]]:
    """Return the WiFi readings heard during their scan, and the cached repeats left out.

    A scan lists every access point the phone still remembers; those last heard more
    than ``max_age_ms`` before the scan completed were measured by an earlier scan.
    ``earlier_drops`` (the per-sample policy's) keep the reported indices those of the body.
    """
    kept: list[RadioSample] = []
    drops: list[dict[str, Any]] = []
    for index, s in zip(body_indices("wifi", len(wifi), earlier_drops), wifi, strict=True):
        if s.last_seen is not None and s.t - s.last_seen > max_age_ms:
            drops.append(
                {
                    "kind": "wifi",
                    "index": index,
                    "field": "last_seen",
                    "code": "stale",
                    "reason": f"last heard {s.t - s.last_seen} ms before its scan "
                    f"(at most {max_age_ms})",
                    "dropped": "sample",
                }
            )
        else:
            kept.append(s)
    return kept, drops


def check_times(*, latest_t: int, settings: Settings) -> None:
    """Reject samples from a device clock far in the future."""
    if latest_t > now_ms() + settings.max_future_ms:
        raise Invalid(
            f"sample time {latest_t} is more than {settings.max_future_ms} ms in the future",
            details=[{"loc": ["t"], "msg": "timestamp in the future", "type": "future_time"}],
        )


def check_batch(
    *,
    site_id: str,
    count: int,
    noun: str,
    latest_t: int,
    principal: Principal,
    settings: Settings,
    sites: SiteVersions,
) -> int:
    """Check a batch of ``count`` ``noun`` against the size limit, the key, the site and the
    clock, in that order; return the site's map version."""
    if count > settings.max_samples:
        raise TooLarge(f"{count} {noun} in one batch; the limit is {settings.max_samples}")
    version = check_site(principal=principal, site_id=site_id, sites=sites)
    check_times(latest_t=latest_t, settings=settings)
    return version


def batch_samples(batch: IngestBatch) -> dict[str, list[dict[str, Any]]]:
    """Return a device batch's samples as the workers take them, by kind (empty kinds left out).

    One ``model_dump`` of the batch, not one per sample: on a scan of a few readings the
    per-call overhead is most of the cost.
    """
    present = {kind for kind in SAMPLE_KINDS if getattr(batch, kind)}
    return batch.model_dump(include=present, exclude_none=True)


def sightings_by_tag(batch: LocatorBatch) -> dict[str, list[dict[str, Any]]]:
    """Return a locator's sightings as each tag's samples, in the order they were sent."""
    by_tag: dict[str, list[dict[str, Any]]] = {}
    for s in batch.sightings:
        by_tag.setdefault(s.tag_id, []).append(
            {"t": s.t, "locator_id": batch.locator_id, "rssi": s.rssi}
        )
    return by_tag
