"""Turn validated JSON samples into the engine's arrays, mapping ids to table rows."""

from __future__ import annotations

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
        kinds["pressure"] = _sorted(
            Pressure(
                np.array([s["t"] for s in baro], np.int64),
                np.array([s["hpa"] for s in baro], float),
            )
        )
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
    known = [s for s in items if s["locator_id"] in site.locator_index]
    skipped.unknown_ids += len(items) - len(known)
    return _sorted(
        Sightings(
            np.array([s["t"] for s in known], np.int64),
            np.array([site.locator_index[s["locator_id"]] for s in known], np.int32),
            np.array([s["rssi"] for s in known], float),
        )
    )


def _ranges(site: LoadedSite, items: list[dict[str, Any]], skipped: Skipped) -> Ranges:
    """Ranges to the site's anchors (NaN where a range carries no standard deviation)."""
    known = [s for s in items if s["anchor"] in site.anchor_index]
    skipped.unknown_ids += len(items) - len(known)
    return _sorted(
        Ranges(
            np.array([s["t"] for s in known], np.int64),
            np.array([site.anchor_index[s["anchor"]] for s in known], np.int32),
            np.array([s["range"] for s in known], float),
            np.array([s.get("std") or np.nan for s in known], float),
        )
    )


def _fixes(site: LoadedSite, items: list[dict[str, Any]], skipped: Skipped) -> Fixes:
    """Fixes on the site's floors, or on none named."""
    known = [s for s in items if s.get("floor_id") is None or s["floor_id"] in site.floor_index]
    skipped.unknown_ids += len(items) - len(known)
    return _sorted(
        Fixes(
            np.array([s["t"] for s in known], np.int64),
            np.array([[s["x"], s["y"], s.get("z", 0.0)] for s in known], float).reshape(-1, 3),
            np.array([site.floor_index.get(s.get("floor_id") or "", 0) for s in known], np.int32),
            np.array([s.get("std") or 1.0 for s in known], float),
        )
    )


def _sorted(arrays: _A) -> _A:
    t = arrays.t  # type: ignore[attr-defined]
    # most batches arrive in order, and most kinds empty: checking costs a third of sorting
    if t.size < 2 or bool((t[1:] >= t[:-1]).all()):
        return arrays
    order = np.argsort(t, kind="stable")
    fields = {k: v[order] for k, v in vars(arrays).items()}
    return type(arrays)(**fields)
