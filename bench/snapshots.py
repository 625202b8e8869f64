"""Snapshot encoding cost: encode and decode time and size of two real device snapshots.

- ``pf``: a phone on the demo office's particle filter (the filter the load
  benchmark runs), after ``--seconds`` of BLE scans from the map's path-loss
  model along a corridor, fed through a ``DeviceSession`` as a worker does;
- ``hmm``: a phone on the HMM of ILC site1 (radio maps from its training
  walks) with the service's fixed-lag smoother, after one held-out walk
  replayed in one-second batches, its filter's state under a device's keys.

Prints the median and p95 of encode and decode time (µs, over ``--repeats``)
and the size of each snapshot in the format of the ``app`` imported; run it
against another checkout's ``app`` to compare formats:

    python bench/snapshots.py
    PYTHONPATH=../other-checkout python bench/snapshots.py

Takes about a minute, most of it reading site1 and building its maps.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from app.core.db import make_engine, make_sessionmaker, session_scope, upgrade_database
from app.datasets import data_dir
from app.datasets.ilc import site_walks
from app.demo import SITE_ID, load_map
from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.params import HmmParams
from app.engine.hmm.tracker import HmmTracker
from app.engine.pdr import PdrParams
from app.engine.radiomap import RadioMapParams
from app.engine.smoothing import FixedLagSmoother, SmootherParams
from app.evaluation.ilc.learn import radio_maps
from app.evaluation.ilc.recordings import read_site_recordings, survey_of, walk_batches
from app.evaluation.split import split_ids
from app.floors.service import put_floor
from app.geometry.extent import ExtentLimits
from app.sites.assembly import assemble_site
from app.sites.schemas import SiteUpsert
from app.sites.service import upsert_site
from app.workers import snapshots
from app.workers.device import DeviceSession
from app.workers.trackers import HMM, FilterDevice, SiteEngines

T0 = 1_700_000_000_000


def pf_snapshot(seconds: int) -> dict[str, Any]:
    """Return the snapshot of a phone walking the demo office on its particle filter."""
    with tempfile.TemporaryDirectory() as home:
        url = f"sqlite:///{home}/locus.db"
        upgrade_database(url)
        engine = make_engine(url)
        with session_scope(make_sessionmaker(engine)) as db:
            site, _ = upsert_site(db=db, site_id=SITE_ID, body=SiteUpsert(name="Demo office"))
            limits = ExtentLimits(max_extent_m=3000, max_raster_cells=16_000_000, cell=0.25)
            put_floor(db=db, site=site, floor_id="F1", doc=load_map(), limits=limits)
            db.flush()
            loaded = assemble_site(db=db, site=site, raster_cell=0.25)
        engine.dispose()
    beacons = [
        (f["properties"], np.array(f["geometry"]["coordinates"][:2], float))
        for f in load_map()["features"]
        if f["properties"]["kind"] == "transmitter"
    ]
    device = DeviceSession(device_id="phone", engines=SiteEngines.for_site(loaded), now=T0)
    rng = np.random.default_rng(1)
    for k in range(seconds):
        xy = np.array([5.0 + min(k, 30), 10.0])
        scan = []
        for props, at in beacons:
            r = max(0.5, float(np.linalg.norm(xy - at)))
            # rssi = A - B ln r + noise
            rssi = props["A"] - props["B"] * np.log(r) + props["sigma"] * rng.standard_normal()
            scan.append({"t": T0 + 1000 * k, "id": props["id"], "rssi": round(float(rssi), 1)})
        device.add({"ble": scan}, now=T0 + 1000 * k)
        batch, _ = device.take(reorder_ms=2000, flush=False)
        if batch is not None and device.tracker is not None:
            device.tracker.process(batch)
    return device.snapshot()


def hmm_snapshot(site_dir: Path) -> dict[str, Any]:
    """Return the snapshot of a phone after one of site1's held-out walks on the HMM."""
    ids = [path.name.split(".")[0] for _, path in site_walks(site_dir)]
    train, _, test = split_ids(ids, 0.2, 0.0)
    site = read_site_recordings(site_dir, train_ids=train)
    maps = radio_maps(site, survey_of(site, set(train)), RadioMapParams())
    model = EmissionModel(maps, HmmParams())
    walk = min(
        (w for w in site.walks if w.walk_id in set(test) and w.waypoints.shape[0] >= 2),
        key=lambda w: w.walk_id,
    )
    tracker = FilterDevice(
        HMM,
        HmmTracker(model, HmmParams(), PdrParams()),
        FixedLagSmoother(SmootherParams()),
    )
    last = T0
    for batch in walk_batches(site, walk):
        tracker.process(batch)
        last = int(max(batch.rssi.t.max(initial=last), batch.imu.t.max(initial=last)))
    # the keys DeviceSession.snapshot adds around its filter's state
    return {
        "processed_t": last,
        "processed_wifi_t": last,
        "emitted_t": last,
        "smoothed_t": last,
        "unflushed": True,
        "zones": [],
        "zones_pending": {},
        "kinds": ["imu", "wifi"],
        "buffer": b"\x90",  # an empty msgpack list
        "tracker": {"kind": HMM, "state": tracker.snapshot()},
    }


def timed(fn: Callable[[], object], repeats: int) -> np.ndarray:
    """Return the wall time (µs) of each of ``repeats`` calls of ``fn`` after one warm-up."""
    fn()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return 1e6 * np.array(out)


def main() -> None:
    """Build both snapshots, then time their encoding and decoding."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=int, default=30, help="seconds the PF phone walks")
    parser.add_argument("--repeats", type=int, default=2000)
    parser.add_argument("--site", type=Path, default=None, help="default: <data>/ilc/site1")
    args = parser.parse_args()
    states = {
        "pf": pf_snapshot(args.seconds),
        "hmm": hmm_snapshot(args.site or data_dir() / "ilc" / "site1"),
    }
    print(f"snapshot format version {snapshots.FORMAT_VERSION} ({snapshots.__file__})")
    print(f"{'device':>6} {'bytes':>7} {'enc p50':>8} {'enc p95':>8} {'dec p50':>8} {'dec p95':>8}")
    for name, state in states.items():
        blob = snapshots.encode(state)
        enc = timed(partial(snapshots.encode, state), args.repeats)
        dec = timed(partial(snapshots.decode, blob), args.repeats)
        print(
            f"{name:>6} {len(blob):>7d} {np.median(enc):>8.1f} {np.percentile(enc, 95):>8.1f} "
            f"{np.median(dec):>8.1f} {np.percentile(dec, 95):>8.1f}"
        )


if __name__ == "__main__":
    main()
