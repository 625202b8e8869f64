"""Reader for the UWB trolley recording: three tags' ranges and motion-capture truth.

Jiang et al., LIAS-CUHKSZ "Efficient Pose Estimation via UWB measurements"
(MIT licence). A trolley carrying three UWB tags moves among 8 anchors;
``UWB_dynamic_exp_fast.csv`` has a wall time and 24 ranges per row (a0-t0,
a0-t1, a0-t2, a1-t0, …, a7-t2, m), about 100 Hz;
``motion_capture_dynamic_exp_fast.csv`` the trolley centroid (m) and attitude
quaternion, about 120 Hz. Anchor coordinates and the tags' lever arms are
tables of the folder's SOURCE_README.md, transcribed below.

Attitude. The README orders the quaternion w, x, y, z. Read that way the
body frame has its z axis pointing down (R₂₂ ≈ −1 throughout) and its x axis
along the direction of travel; tag positions built from it with the lever
arms lie farther off the UWB fixes of every tag than with the body frame
turned 180° about x (``BODY_FLIP``: z up, y to the left of travel): the
lever-arm table is written in that z-up frame.
:func:`check_attitude` measures the agreement of the body x axis with the
velocity so that a recording read with the wrong order is caught.

Time. Both files carry wall times (local time of the recording; converted
here as if UTC, only differences matter). ``uwb_eval`` searches the clock
offset on its calibration part: raw fixes agree with the truth best at 0 ms
(10 ms steps; ``locus eval uwb`` prints it), so the two clocks are one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.datasets import data_dir
from app.engine.plan import FloorPlan
from app.engine.samples import Ranges
from app.engine.site import Emitters, Floor, SiteModel

# SOURCE_README.md, "Coordinates of UWB anchors in the global reference frame" (m).
ANCHORS_XYZ = np.array(
    [
        [-3.4203, 3.0053, 1.0442],
        [0.0016, 3.0110, 1.0446],
        [3.6056, 2.9795, 1.0463],
        [3.6011, -0.0008, 1.0422],
        [3.5674, -3.0087, 1.0443],
        [-0.0072, -2.9652, 1.0444],
        [-3.4673, -2.9587, 1.0445],
        [-3.4858, -0.0098, 1.0457],
    ]
)
"""Anchor 0–7 positions x, y, z (m) in the motion-capture frame."""

# SOURCE_README.md, "Coordinates of UWB tags in the local reference frame" (m).
TAG_LEVER_ARMS = np.array(
    [
        [-0.0689, -0.1423, 0.0011],
        [-0.0750, 0.1402, 0.0016],
        [0.2034, 0.1451, -0.0008],
    ]
)
"""Tag 0–2 positions in the trolley's body frame (origin at the tracked centroid)."""

BODY_FLIP = np.diag([1.0, -1.0, -1.0])
"""Rotation of 180° about x from the lever-arm frame to the motion-capture body frame."""

N_ANCHORS = 8
N_TAGS = 3
RANGES_FILE = "UWB_dynamic_exp_fast.csv"
MOCAP_FILE = "motion_capture_dynamic_exp_fast.csv"


@dataclass(frozen=True)
class TrolleyRanges:
    """UWB rows: ``t`` (N,) int64 ms, ``ranges`` (N, anchors, tags) in m, NaN where missing."""

    t: np.ndarray
    ranges: np.ndarray

    def __len__(self) -> int:
        return int(self.t.size)


@dataclass(frozen=True)
class MotionCapture:
    """Motion-capture rows with distinct times: ``t`` (N,) int64 ms, ``centroid`` (N, 3) m,
    ``quaternion`` (N, 4) as in the file (w, x, y, z)."""

    t: np.ndarray
    centroid: np.ndarray
    quaternion: np.ndarray

    def __len__(self) -> int:
        return int(self.t.size)


@dataclass(frozen=True)
class AttitudeCheck:
    """Agreement of the body x axis with the direction of travel.

    ``offset_deg`` is the circular mean of (velocity heading − body-x heading)
    over moving samples; ``concentration`` its mean resultant length (1: the
    axis always points along the motion, 0: unrelated); ``up_z`` the median
    vertical component of the body z axis; ``moving`` the fraction of samples
    used.
    """

    offset_deg: float
    concentration: float
    up_z: float
    moving: float


def folder() -> Path:
    """Return the recording's folder."""
    return data_dir() / "uwb_trolley"


def parse_wall_times(stamps: list[str]) -> np.ndarray:
    """Convert ``YYYY-MM-DD H:MM:SS.fff`` stamps to int64 ms (as if UTC)."""
    out = np.empty(len(stamps), dtype=np.int64)
    for i, s in enumerate(stamps):
        day, clock = s.split(" ")
        h, m, sec = clock.split(":")
        whole, _, frac = sec.partition(".")
        base = np.datetime64(day, "ms").astype(np.int64)
        # t = day + ((h·60 + m)·60 + s)·1000 + ms
        out[i] = base + ((int(h) * 60 + int(m)) * 60 + int(whole)) * 1000 + int((frac + "000")[:3])
    return out


def _read_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Return (times ms, values) of a CSV starting with a wall-time column; skip header lines."""
    stamps: list[str] = []
    rows: list[list[float]] = []
    with path.open() as f:
        for line in f:
            parts = line.strip().split(",")
            if not parts[0][:1].isdigit():
                continue
            stamps.append(parts[0])
            rows.append([float(v) if v else np.nan for v in parts[1:]])
    return parse_wall_times(stamps), np.array(rows, dtype=float)


def read_ranges(path: Path | None = None) -> TrolleyRanges:
    """Read the ranges file into (rows, anchors, tags)."""
    t, values = _read_csv(path or folder() / RANGES_FILE)
    return TrolleyRanges(t=t, ranges=values.reshape(-1, N_ANCHORS, N_TAGS))


def read_motion_capture(path: Path | None = None) -> MotionCapture:
    """Read the motion-capture file, keeping the first row of each repeated time."""
    t, values = _read_csv(path or folder() / MOCAP_FILE)
    _, first = np.unique(t, return_index=True)
    return MotionCapture(t=t[first], centroid=values[first, :3], quaternion=values[first, 3:7])


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Return rotation matrices (N, 3, 3) of unit quaternions (N, 4) ordered w, x, y, z."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    # R(q) for the Hamilton convention, body → world
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def body_attitude(mc: MotionCapture) -> np.ndarray:
    """Return the rotation (N, 3, 3) from the lever-arm frame to the world frame."""
    # R = R(q) · R_x(π)
    return quaternion_matrix(mc.quaternion) @ BODY_FLIP


def check_attitude(
    mc: MotionCapture, min_speed: float = 0.2, window_ms: int = 250
) -> AttitudeCheck:
    """Compare the heading of the body x axis with the heading of the centroid's velocity.

    Velocity is the centroid's displacement over ``window_ms`` (centred);
    samples slower than ``min_speed`` (m/s) have no direction of travel.
    """
    R = body_attitude(mc)
    half = window_ms // 2
    lo = np.searchsorted(mc.t, mc.t - half)
    hi = np.clip(np.searchsorted(mc.t, mc.t + half, side="right") - 1, 0, len(mc) - 1)
    dt = (mc.t[hi] - mc.t[lo]) / 1000.0
    disp = mc.centroid[hi, :2] - mc.centroid[lo, :2]
    speed = np.linalg.norm(disp, axis=1) / np.where(dt > 0, dt, np.inf)
    moving = speed >= min_speed
    # heading difference: atan2 of the velocity minus atan2 of the body x axis
    diff = np.arctan2(disp[:, 1], disp[:, 0]) - np.arctan2(R[:, 1, 0], R[:, 0, 0])
    resultant = np.mean(np.exp(1j * diff[moving])) if moving.any() else 0j
    return AttitudeCheck(
        offset_deg=float(np.degrees(np.angle(resultant))),
        concentration=float(np.abs(resultant)),
        up_z=float(np.median(R[:, 2, 2])),
        moving=float(moving.mean()),
    )


def tag_positions(mc: MotionCapture, tag: int) -> np.ndarray:
    """Return the tag's world positions (N, 3) at the motion-capture times: c + R l."""
    # p = c + R · l
    return mc.centroid + body_attitude(mc) @ TAG_LEVER_ARMS[tag]


def tag_truth(mc: MotionCapture, tag: int, t: np.ndarray, offset_ms: float = 0.0) -> np.ndarray:
    """Return the tag's true positions (M, 3) at times ``t`` (ms) of the ranges' clock.

    ``offset_ms`` is added to ``t`` to reach the motion-capture clock; times
    outside the capture are NaN. Linear interpolation between captures
    (8 ms apart: well under a millimetre at the trolley's speed).
    """
    pos = tag_positions(mc, tag)
    tq = np.asarray(t, dtype=float) + offset_ms
    tm = mc.t.astype(float)
    out = np.column_stack([np.interp(tq, tm, pos[:, k]) for k in range(3)])
    out[(tq < tm[0]) | (tq > tm[-1])] = np.nan
    return out


def to_ranges(rec: TrolleyRanges, tag: int, std: float = np.nan) -> Ranges:
    """Return one tag's ranges as engine samples (anchor index = column), NaN ranges dropped."""
    r = rec.ranges[:, :, tag]
    row, anchor = np.nonzero(np.isfinite(r))
    return Ranges(
        t=rec.t[row].astype(np.int64),
        anchor=anchor.astype(np.int32),
        range=r[row, anchor],
        std=np.full(row.size, std),
    )


def trolley_site(cell: float = 0.1, margin: float = 1.0) -> SiteModel:
    """Return a one-floor site with the 8 anchors and an open floor around them (margin in m)."""
    lo = ANCHORS_XYZ[:, :2].min(axis=0) - margin
    hi = ANCHORS_XYZ[:, :2].max(axis=0) + margin
    shape = tuple(np.ceil((hi - lo) / cell).astype(int)[::-1])
    plan = FloorPlan.from_raster(origin=lo, cell=cell, free=np.ones(shape, dtype=bool))
    anchors = Emitters(
        ids=tuple(f"a{i}" for i in range(N_ANCHORS)),
        floor=np.zeros(N_ANCHORS, dtype=np.int32),
        xyz=ANCHORS_XYZ.copy(),
        A=np.full(N_ANCHORS, np.nan),
        B=np.full(N_ANCHORS, np.nan),
        sigma=np.full(N_ANCHORS, np.nan),
    )
    return SiteModel(site_id="uwb_trolley", floors=(Floor("F0", 0, 4.0, plan),), anchors=anchors)
