"""An ILC site's recordings as engine inputs: floors, transmitter table, surveys, batches.

Everything an evaluation of radio-map based positioning needs from the mall:
the floors in level order with their walkable rasters, a transmitter table
(WiFi BSSIDs heard on the training walks, as the service would know them
from surveys), located survey scans, and each walk replayed as the
one-second batches a phone would upload. Walks are read once per run and
kept in memory.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.datasets.ilc import Walk, fresh_wifi, imu_samples, read_floor, read_walk, site_walks
from app.engine.plan import FloorPlan
from app.engine.radiomap import Survey, locate_scans
from app.engine.samples import Batch, ImuSamples, RssiReadings
from app.geometry.floormap import parse_floor_map
from app.geometry.raster import floor_plan

PLAN_CELL_M = 0.5
"""Raster cell (m) of the walkable area: at 1 m the burnt shop outlines eat the
narrow corridors and many waypoints fall on blocked cells; at 0.5 m few do."""

MAX_WIFI_AGE_MS = 2000
"""WiFi readings older than this at their scan time are cached repeats and dropped."""


@dataclass(frozen=True)
class SiteRecordings:
    """A site's walks and floors, with WiFi readings mapped to transmitter indices.

    ``floors`` are floor names in level order (their position is the floor
    index); ``plans`` the walkable rasters in the same order; ``tx_ids`` the
    BSSIDs of the transmitter table.
    """

    floors: tuple[str, ...]
    plans: tuple[FloorPlan, ...]
    walks: tuple[Walk, ...]
    tx_ids: tuple[str, ...]

    def floor_index(self, walk: Walk) -> int:
        """Return the floor index of a walk."""
        return self.floors.index(walk.floor)

    def readings(self, walk: Walk) -> RssiReadings:
        """Return the walk's fresh WiFi readings of known transmitters, in time order."""
        scan = fresh_wifi(walk.wifi, MAX_WIFI_AGE_MS)
        lookup = {b: i for i, b in enumerate(self.tx_ids)}
        tx = np.array([lookup.get(b, -1) for b in scan.bssid.tolist()], dtype=np.int64)
        known = tx >= 0
        return RssiReadings(
            t=scan.t[known].astype(np.int64),
            tx=tx[known].astype(np.int32),
            rssi=scan.rssi[known].astype(float),
        )


def read_site_recordings(
    site_dir: Path, *, train_ids: Iterable[str] | None = None
) -> SiteRecordings:
    """Read every walk and floor of an ILC site.

    The transmitter table holds the BSSIDs heard (fresh) on the walks of
    ``train_ids`` (all walks when None), sorted.
    """
    site_dir = Path(site_dir)
    pairs = site_walks(site_dir)
    walks = tuple(read_walk(path, floor) for floor, path in pairs)
    names = sorted({floor for floor, _ in pairs}, key=lambda n: read_floor(site_dir / n).level)
    plans = tuple(
        floor_plan(parse_floor_map(read_floor(site_dir / name).geojson), cell=PLAN_CELL_M)
        for name in names
    )
    chosen = None if train_ids is None else set(train_ids)
    bssids: set[str] = set()
    for walk in walks:
        if chosen is None or walk.walk_id in chosen:
            bssids.update(fresh_wifi(walk.wifi, MAX_WIFI_AGE_MS).bssid.tolist())
    return SiteRecordings(
        floors=tuple(names), plans=plans, walks=walks, tx_ids=tuple(sorted(bssids))
    )


def survey_of(site: SiteRecordings, walk_ids: Iterable[str]) -> Survey:
    """Return the located scans of the chosen walks (walk numbers are positions in ``walks``)."""
    chosen = set(walk_ids)
    parts = [
        locate_scans(site.readings(w), w.waypoints, floor=site.floor_index(w), walk=i)
        for i, w in enumerate(site.walks)
        if w.walk_id in chosen and w.waypoints.shape[0] >= 2
    ]
    return Survey.concat(parts)


def walk_batches(site: SiteRecordings, walk: Walk, window_ms: int = 1000) -> Iterator[Batch]:
    """Replay a walk as the consecutive batches of ``window_ms`` a phone would upload."""
    readings = site.readings(walk)
    imu = imu_samples(walk)
    times = np.concatenate([readings.t, imu.t])
    if times.size == 0:
        return
    t0 = int(times.min())
    edges = np.arange(t0, int(times.max()) + window_ms + 1, window_ms)
    r_cut = np.searchsorted(readings.t, edges, side="left")
    i_cut = np.searchsorted(imu.t, edges, side="left")
    for k in range(edges.size - 1):
        r = slice(r_cut[k], r_cut[k + 1])
        i = slice(i_cut[k], i_cut[k + 1])
        yield Batch(
            rssi=RssiReadings(t=readings.t[r], tx=readings.tx[r], rssi=readings.rssi[r]),
            imu=ImuSamples(
                t=imu.t[i], acc=imu.acc[i], gyro=imu.gyro[i], mag=imu.mag[i], rot=imu.rot[i]
            ),
        )
