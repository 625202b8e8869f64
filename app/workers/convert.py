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
    """Return the engine batch (sorted by t within each kind) and what it left out."""
    unknown = 0
    max_age = site.tuning.wifi_max_age_ms
    wifi = samples.get("wifi", ())
    fresh = [s for s in wifi if reading_age(s) <= max_age]
    t_rssi: list[int] = []
    tx: list[int] = []
    rssi: list[float] = []
    for kind in ("wifi", "ble"):
        items = fresh if kind == "wifi" else samples.get(kind, ())
        times = wifi_times(items) if kind == "wifi" else [s["t"] for s in items]
        for s, t in zip(items, times, strict=True):
            row = site.transmitter_index.get(radio_id(s["id"]))
            if row is None:
                unknown += 1
                continue
            t_rssi.append(t)
            tx.append(row)
            rssi.append(s["rssi"])
    t_seen: list[int] = []
    locator: list[int] = []
    seen_rssi: list[float] = []
    for s in samples.get("sightings", ()):
        row = site.locator_index.get(s["locator_id"])
        if row is None:
            unknown += 1
            continue
        t_seen.append(s["t"])
        locator.append(row)
        seen_rssi.append(s["rssi"])
    imu = samples.get("imu", ())
    ranges_t: list[int] = []
    anchor: list[int] = []
    dist: list[float] = []
    std: list[float] = []
    for s in samples.get("uwb", ()):
        row = site.anchor_index.get(s["anchor"])
        if row is None:
            unknown += 1
            continue
        ranges_t.append(s["t"])
        anchor.append(row)
        dist.append(s["range"])
        std.append(s.get("std") or np.nan)
    fixes = [
        s
        for s in samples.get("uwb_fix", ())
        if s.get("floor_id") is None or s["floor_id"] in site.floor_index
    ]
    unknown += len(samples.get("uwb_fix", ())) - len(fixes)
    baro = samples.get("baro", ())
    batch = Batch(
        rssi=_sorted(
            RssiReadings(np.array(t_rssi, np.int64), np.array(tx, np.int32), np.array(rssi, float))
        ),
        sightings=_sorted(
            Sightings(
                np.array(t_seen, np.int64),
                np.array(locator, np.int32),
                np.array(seen_rssi, float),
            )
        ),
        imu=_sorted(imu_arrays(imu)),
        ranges=_sorted(
            Ranges(
                np.array(ranges_t, np.int64),
                np.array(anchor, np.int32),
                np.array(dist, float),
                np.array(std, float),
            )
        ),
        fixes=_sorted(
            Fixes(
                np.array([s["t"] for s in fixes], np.int64),
                np.array([[s["x"], s["y"], s.get("z", 0.0)] for s in fixes], float).reshape(-1, 3),
                np.array(
                    [site.floor_index.get(s.get("floor_id") or "", 0) for s in fixes], np.int32
                ),
                np.array([s.get("std") or 1.0 for s in fixes], float),
            )
        ),
        pressure=_sorted(
            Pressure(
                np.array([s["t"] for s in baro], np.int64),
                np.array([s["hpa"] for s in baro], float),
            )
        ),
    )
    return batch, Skipped(unknown_ids=unknown, stale=len(wifi) - len(fresh))


def _sorted(arrays: _A) -> _A:
    t = arrays.t  # type: ignore[attr-defined]
    # most batches arrive in order, and most kinds empty: checking costs a third of sorting
    if t.size < 2 or bool((t[1:] >= t[:-1]).all()):
        return arrays
    order = np.argsort(t, kind="stable")
    fields = {k: v[order] for k, v in vars(arrays).items()}
    return type(arrays)(**fields)
