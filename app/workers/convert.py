"""Turn validated JSON samples into the engine's arrays, mapping ids to table rows."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from app.engine.samples import Batch, Fixes, Pressure, Ranges, RssiReadings, Sightings
from app.ingest.arrays import imu_arrays, reading_age, wifi_times
from app.sites.assembly import LoadedSite
from app.sites.radio_ids import radio_id

_A = TypeVar("_A")


@dataclass
class Skipped:
    """Samples a batch left out: ``unknown_ids`` name nothing the site has, ``stale`` are WiFi
    readings last heard longer before their scan than the site's engines use."""

    unknown_ids: int = 0
    stale: int = 0


def to_batch(site: LoadedSite, samples: dict[str, list[dict[str, Any]]]) -> tuple[Batch, Skipped]:
    """Return the engine batch (sorted by t within each kind) and what it left out.

    Only the kinds present are converted: the others keep the batch's shared
    empty arrays (a phone's batch holds two or three kinds of the six).
    """
    skipped = Skipped()
    kinds: dict[str, Any] = {}
    if samples.get("wifi") or samples.get("ble"):
        kinds["rssi"] = _rssi(site, samples, skipped)
    if samples.get("sightings"):
        kinds["sightings"] = _sightings(site, samples["sightings"], skipped)
    if samples.get("imu"):
        kinds["imu"] = _sorted(imu_arrays(samples["imu"]))
    if samples.get("uwb"):
        kinds["ranges"] = _ranges(site, samples["uwb"], skipped)
    if samples.get("uwb_fix"):
        kinds["fixes"] = _fixes(site, samples["uwb_fix"], skipped)
    if samples.get("baro"):
        baro = samples["baro"]
        kinds["pressure"] = _sorted(Pressure(_times(baro), _floats(baro, "hpa")))
    return Batch(**kinds), skipped


def _rssi(
    site: LoadedSite, samples: dict[str, list[dict[str, Any]]], skipped: Skipped
) -> RssiReadings:
    """WiFi readings heard within the site's age limit, and BLE readings, of known ids."""
    max_age = site.tuning.wifi_max_age_ms
    wifi = samples.get("wifi", ())
    fresh = [s for s in wifi if reading_age(s) <= max_age]
    skipped.stale += len(wifi) - len(fresh)
    t_rssi: list[int] = []
    tx: list[int] = []
    rssi: list[float] = []
    index = site.transmitter_index
    for kind in ("wifi", "ble"):
        items = fresh if kind == "wifi" else samples.get(kind, ())
        times = wifi_times(items) if kind == "wifi" else [s["t"] for s in items]
        for s, t in zip(items, times, strict=True):
            row = index.get(radio_id(s["id"]))
            if row is None:
                skipped.unknown_ids += 1
                continue
            t_rssi.append(t)
            tx.append(row)
            rssi.append(s["rssi"])
    return _sorted(
        RssiReadings(np.array(t_rssi, np.int64), np.array(tx, np.int32), np.array(rssi, float))
    )


def _sightings(site: LoadedSite, items: list[dict[str, Any]], skipped: Skipped) -> Sightings:
    """Sightings by the site's locators."""
    index = site.locator_index
    known = _known(items, lambda s: s["locator_id"] in index, skipped)
    locator = np.array([index[s["locator_id"]] for s in known], np.int32)
    return _sorted(Sightings(_times(known), locator, _floats(known, "rssi")))


def _ranges(site: LoadedSite, items: list[dict[str, Any]], skipped: Skipped) -> Ranges:
    """Ranges to the site's anchors (NaN where a range carries no standard deviation)."""
    index = site.anchor_index
    known = _known(items, lambda s: s["anchor"] in index, skipped)
    anchor = np.array([index[s["anchor"]] for s in known], np.int32)
    std = np.array([s.get("std") or np.nan for s in known], float)
    return _sorted(Ranges(_times(known), anchor, _floats(known, "range"), std))


def _fixes(site: LoadedSite, items: list[dict[str, Any]], skipped: Skipped) -> Fixes:
    """Fixes on the site's floors, or on none named."""
    index = site.floor_index
    known = _known(items, lambda s: s.get("floor_id") is None or s["floor_id"] in index, skipped)
    xyz = np.array([[s["x"], s["y"], s.get("z", 0.0)] for s in known], float).reshape(-1, 3)
    floor = np.array([index.get(s.get("floor_id") or "", 0) for s in known], np.int32)
    std = np.array([s.get("std") or 1.0 for s in known], float)
    return _sorted(Fixes(_times(known), xyz, floor, std))


def _known(
    items: list[dict[str, Any]], names_known: Callable[[dict[str, Any]], bool], skipped: Skipped
) -> list[dict[str, Any]]:
    """Return the samples naming something the site has; count the others as unknown ids."""
    known = [s for s in items if names_known(s)]
    skipped.unknown_ids += len(items) - len(known)
    return known


def _times(items: list[dict[str, Any]]) -> np.ndarray:
    return np.array([s["t"] for s in items], np.int64)


def _floats(items: list[dict[str, Any]], key: str) -> np.ndarray:
    return np.array([s[key] for s in items], float)


def _sorted(arrays: _A) -> _A:
    t = arrays.t  # type: ignore[attr-defined]
    # most batches arrive in order, and most kinds empty: checking costs less than sorting
    if t.size < 2 or bool((t[1:] >= t[:-1]).all()):
        return arrays
    order = np.argsort(t, kind="stable")
    fields = {k: v[order] for k, v in vars(arrays).items()}
    return type(arrays)(**fields)
