"""Reader for the BLE locator recordings (``ble_locator/``): one tag heard by 12 fixed receivers.

Daniş et al., Pervasive and Mobile Computing 81 (2022), CC0. ``cnf/tetam.dev``
lists the receivers ("Dongles": MAC → [[x, y, z] m, colour, alias]);
``trk/*_all_sensors.mbd`` are tracks, one sighting per line: ``timestamp_s,
receiver_mac, beacon_mac, rssi, x, y, z, 3×3 orientation`` with x, y, z the
camera-annotated truth (median precision about 4 cm). Lines are merged from
per-receiver logs and not always in time order: they are sorted here.

Occupancy (``occ/tetam_<cell>.occ``): a header ``[[xmin, ymin], [xmax,
ymax]]::cell`` then ``[x, y]::v`` per cell, (x, y) its lower-left corner.
The folder's README says 1 marks traversable cells, but the 1-cells are the
furniture blocks of the plan image and nearly all of the tracks' truth lies
on 0-cells (the rest on 1-cells at block edges; ``tests/datasets/test_ble_locator.py``
checks over 95 %): 0 is free.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.datasets import data_dir
from app.engine.plan import FloorPlan
from app.engine.site import Emitters, Floor, SiteModel


@dataclass(frozen=True)
class Locators:
    """The fixed receivers: MAC ids, positions (K, 3) m, aliases (``sensor10`` …)."""

    ids: tuple[str, ...]
    xyz: np.ndarray
    alias: tuple[str, ...]


@dataclass(frozen=True)
class Track:
    """One track's sightings in time order: ``t`` (N,) int64 ms, ``locator`` (N,) index
    into :class:`Locators`, ``rssi`` (N,) dBm, ``truth`` (N, 3) m."""

    name: str
    t: np.ndarray
    locator: np.ndarray
    rssi: np.ndarray
    truth: np.ndarray

    def __len__(self) -> int:
        return int(self.t.size)


def folder() -> Path:
    """Return the recordings' folder."""
    return data_dir() / "ble_locator"


def read_locators(path: Path | None = None) -> Locators:
    """Parse the ``Dongles:`` line of ``cnf/tetam.dev``."""
    text = (path or folder() / "cnf" / "tetam.dev").read_text()
    match = re.search(r"^Dongles:\s*(\{.*\})\s*$", text, flags=re.MULTILINE)
    if match is None:
        raise ValueError("no Dongles line in the devices file")
    table = json.loads(match.group(1))
    ids = tuple(table)
    return Locators(
        ids=ids,
        xyz=np.array([table[k][0] for k in ids], dtype=float),
        alias=tuple(str(table[k][2]) for k in ids),
    )


def track_names() -> list[str]:
    """Return the names of the tracks (file names without ``_all_sensors.mbd``), sorted."""
    return sorted(p.name.removesuffix("_all_sensors.mbd") for p in (folder() / "trk").glob("*.mbd"))


def read_track(name: str, locators: Locators | None = None) -> Track:
    """Read one track, sorted by time (stable), with receiver MACs mapped to locator indices."""
    locators = locators or read_locators()
    index = {mac: i for i, mac in enumerate(locators.ids)}
    rows = [
        line.split(",")
        for line in (folder() / "trk" / f"{name}_all_sensors.mbd").read_text().splitlines()
        if line.strip()
    ]
    t = np.array([float(r[0]) for r in rows])
    order = np.argsort(t, kind="stable")
    return Track(
        name=name,
        t=np.round(t[order] * 1000.0).astype(np.int64),
        locator=np.array([index[r[1]] for r in rows], dtype=np.int32)[order],
        rssi=np.array([float(r[3]) for r in rows])[order],
        truth=np.array([[float(v) for v in r[4:7]] for r in rows])[order],
    )


def read_occupancy(cell: float = 0.2) -> FloorPlan:
    """Return the occupancy grid of the given cell size (0.1, 0.2, 0.5 or 1.0 m) as a plan."""
    lines = (folder() / "occ" / f"tetam_{cell}.occ").read_text().splitlines()
    step = float(lines[0].split("::")[1])
    corners = []
    values = []
    for line in lines[1:]:
        if line.strip():
            xy, v = line.split("::")
            corners.append(json.loads(xy))
            values.append(int(v))
    ij = np.round(np.array(corners) / step).astype(int)
    free = np.zeros((ij[:, 1].max() + 1, ij[:, 0].max() + 1), dtype=bool)
    free[ij[:, 1], ij[:, 0]] = np.array(values) == 0
    return FloorPlan.from_raster(origin=np.zeros(2), cell=step, free=free)


def locator_site(
    locators: Locators,
    A: np.ndarray | None = None,
    B: np.ndarray | None = None,
    sigma: np.ndarray | None = None,
    plan: FloorPlan | None = None,
) -> SiteModel:
    """Return a one-floor site whose locators carry path loss A, B, sigma (NaN: defaults)."""
    k = len(locators.ids)
    nan = np.full(k, np.nan)
    plan = plan or FloorPlan.from_raster(origin=np.zeros(2), cell=0.5, free=np.ones((36, 42), bool))
    table = Emitters(
        ids=locators.ids,
        floor=np.zeros(k, dtype=np.int32),
        xyz=locators.xyz.copy(),
        A=nan.copy() if A is None else np.asarray(A, dtype=float),
        B=nan.copy() if B is None else np.asarray(B, dtype=float),
        sigma=nan.copy() if sigma is None else np.asarray(sigma, dtype=float),
    )
    return SiteModel(site_id="ble_locator", floors=(Floor("tetam", 0, 4.0, plan),), locators=table)
