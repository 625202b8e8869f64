"""Reader for the BLE flat recordings (``ble_flat/``, Kolakowski 2021, CC BY 4.0).

Six BLE anchors in a furnished flat; a robot carries a tag on a pole 1.3 m
above the floor and LiDAR SLAM gives its position. Seen from the phone's
side, the tag is a receiver moving among six known transmitters.

Files: ``anchors.csv`` (id, x, y, z in m), ``layout.csv`` (the flat's walls
as one closed polyline, m), ``calibration/calibration_df.csv`` and
``tests/test_robot_df.csv`` (``ts`` in ns, ``x``, ``heading``, ``y``,
``rssi_1`` … ``rssi_6`` in dBm, empty when not heard). Both hold tag positions
in the anchors' frame. The ``calibration/calibX_df.csv`` files are the same
runs before that processing: LiDAR positions in the SLAM frame and the
anchors' original ids, so they are not read here.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely

from app.datasets import data_dir
from app.engine.plan import FloorPlan, burn_segments
from app.engine.samples import RssiReadings

TAG_HEIGHT_M = 1.3
"""Height of the tag above the floor (dataset description, section III)."""

RUN_GAP_MS = 60_000
"""A pause this long between rows starts a new run of the robot."""


def root() -> Path:
    """Return the dataset folder."""
    return data_dir() / "ble_flat"


@dataclass(frozen=True)
class Anchors:
    """The transmitters: ids as in the ``rssi_<id>`` columns and positions (m), aligned."""

    ids: tuple[int, ...]
    xyz: np.ndarray


@dataclass(frozen=True)
class Track:
    """One recording: per row the time, tag position and the RSSI of every anchor.

    ``t`` is int64 ms; ``xy`` (n, 2) m; ``heading`` the robot's (rad, as
    recorded: ground truth, which a phone would not have); ``rssi`` (n, 6)
    dBm in anchor order, NaN when not heard.
    """

    t: np.ndarray
    xy: np.ndarray
    heading: np.ndarray
    rssi: np.ndarray

    def __len__(self) -> int:
        return int(self.t.size)

    def slice(self, rows: slice | np.ndarray) -> Track:
        """Return the rows ``rows`` as a track."""
        return Track(self.t[rows], self.xy[rows], self.heading[rows], self.rssi[rows])


def read_anchors(folder: Path | None = None) -> Anchors:
    """Read ``anchors.csv``."""
    table = np.loadtxt((folder or root()) / "anchors.csv", delimiter=",", skiprows=1, ndmin=2)
    return Anchors(ids=tuple(int(i) for i in table[:, 0]), xyz=table[:, 1:4].astype(float))


def read_layout(folder: Path | None = None) -> np.ndarray:
    """Read ``layout.csv``: the wall polyline's vertices (k, 2), first equal to last."""
    return np.loadtxt((folder or root()) / "layout.csv", delimiter=",", skiprows=1, ndmin=2)


def read_track(path: Path, anchors: Anchors) -> Track:
    """Read a ``*_df.csv`` recording with ``rssi_<id>`` columns for every anchor, sorted by time."""
    with open(path, newline="") as fh:
        header = next(csv.reader(fh))
    col = {name: i for i, name in enumerate(header)}
    table = np.genfromtxt(path, delimiter=",", skip_header=1, ndmin=2)
    # ts is in ns, stored as float: round to ms
    t = np.rint(table[:, col["ts"]] / 1e6).astype(np.int64)
    order = np.argsort(t, kind="stable")
    rssi = np.column_stack([table[:, col[f"rssi_{i}"]] for i in anchors.ids])
    return Track(
        t=t[order],
        xy=table[order][:, [col["x"], col["y"]]],
        heading=table[order, col["heading"]],
        rssi=rssi[order],
    )


def calibration(folder: Path | None = None) -> Track:
    """Read the calibration recording (all runs)."""
    folder = folder or root()
    return read_track(folder / "calibration" / "calibration_df.csv", read_anchors(folder))


def test_robot(folder: Path | None = None) -> Track:
    """Read the robot test track."""
    folder = folder or root()
    return read_track(folder / "tests" / "test_robot_df.csv", read_anchors(folder))


def runs(track: Track, gap_ms: int = RUN_GAP_MS) -> list[Track]:
    """Split a recording where consecutive rows are more than ``gap_ms`` apart."""
    cuts = np.flatnonzero(np.diff(track.t) > gap_ms) + 1
    edges = np.concatenate([[0], cuts, [len(track)]])
    return [track.slice(slice(a, b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def readings(track: Track) -> RssiReadings:
    """Return the track's readings in time order; ``tx`` is the anchor's position in ``Anchors``."""
    row, tx = np.nonzero(np.isfinite(track.rssi))
    return RssiReadings(
        t=track.t[row].astype(np.int64), tx=tx.astype(np.int32), rssi=track.rssi[row, tx]
    )


def truth_at(track: Track, t: np.ndarray) -> np.ndarray:
    """Return the tag position (m) at times ``t`` (ms), linearly interpolated, shape (k, 2)."""
    t = np.asarray(t, dtype=float)
    return np.column_stack(
        [np.interp(t, track.t, track.xy[:, 0]), np.interp(t, track.t, track.xy[:, 1])]
    )


def floor_plan(layout: np.ndarray, cell: float, *, walls: bool = True) -> FloorPlan:
    """Rasterise the flat at ``cell`` metres.

    With ``walls`` the free area is the inside of the wall polyline with the
    polyline burnt in; without, it is the polyline's bounding box, so no
    wall constrains a move but positions stay within the flat's extent.
    """
    xmin, ymin = layout.min(axis=0)
    xmax, ymax = layout.max(axis=0)
    origin = np.array([np.floor(xmin / cell) * cell - cell, np.floor(ymin / cell) * cell - cell])
    nx = int(np.ceil((xmax - origin[0]) / cell)) + 1
    ny = int(np.ceil((ymax - origin[1]) / cell)) + 1
    xs = origin[0] + (np.arange(nx) + 0.5) * cell
    ys = origin[1] + (np.arange(ny) + 0.5) * cell
    gx, gy = np.meshgrid(xs, ys)
    if walls:
        free = shapely.contains_xy(shapely.Polygon(layout), gx, gy)
        segments = np.hstack([layout[:-1], layout[1:]])
        burn_segments(free, segments, origin=origin, cell=cell)
    else:
        free = (gx >= xmin) & (gx <= xmax) & (gy >= ymin) & (gy <= ymax)
    return FloorPlan.from_raster(origin=origin, cell=cell, free=free)
