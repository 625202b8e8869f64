"""A simulated tag among eight UWB anchors / BLE locators, shared by the EKF and tracker tests."""

from __future__ import annotations

import numpy as np

from app.engine.plan import FloorPlan
from app.engine.samples import Batch, Ranges
from app.engine.site import Emitters, Floor, SiteModel

T0 = 1_700_000_000_000
"""Measurement time (ms) at which the simulations start."""

ANCHORS = np.array(
    [
        [-4.0, 3.0, 2.2],
        [0.0, 3.2, 2.4],
        [4.0, 3.0, 2.1],
        [4.2, 0.0, 2.5],
        [4.0, -3.0, 2.3],
        [0.0, -3.1, 2.2],
        [-4.0, -3.0, 2.4],
        [-4.1, 0.0, 2.0],
    ]
)
"""Eight anchors round an 8 m × 6 m room, 2.0–2.5 m high."""


def site_with(free: np.ndarray | None = None, anchors: np.ndarray = ANCHORS) -> SiteModel:
    """A 20 m × 16 m floor whose anchors are also its locators (A = -60 dBm, B = 8)."""
    free = np.ones((160, 200), bool) if free is None else free
    plan = FloorPlan.from_raster(origin=np.array([-10.0, -8.0]), cell=0.1, free=free)
    n = len(anchors)
    table = Emitters(
        ids=tuple(f"a{i}" for i in range(n)),
        floor=np.zeros(n, np.int32),
        xyz=anchors,
        A=np.full(n, -60.0),
        B=np.full(n, 8.0),
        sigma=np.full(n, 4.0),
    )
    return SiteModel("s", (Floor("F", 0, 4.0, plan),), anchors=table, locators=table)


def turning_walk(seed: int, seconds: float = 120.0, dt: float = 0.02, speed: float = 1.2):
    """A walk turning at a random constant rate (±0.4 rad/s) for 5 s at a time."""
    rng = np.random.default_rng(seed)
    n = int(seconds / dt)
    t = np.arange(n) * dt
    rate = np.repeat(rng.uniform(-0.4, 0.4, n // 250 + 1), 250)[:n]
    course = np.cumsum(rate) * dt
    v = speed + 0.1 * np.sin(0.3 * t)
    xy = np.column_stack([np.cumsum(v * np.cos(course)), np.cumsum(v * np.sin(course))]) * dt
    return (T0 + np.round(t * 1000)).astype(np.int64), xy, rate


def slice_batch(lo: int, hi: int, **parts) -> Batch:
    """Samples with lo <= t < hi of each part (Fixes, ImuSamples, Ranges, Sightings, ...)."""
    out = {}
    for name, arr in parts.items():
        sel = (arr.t >= lo) & (arr.t < hi)
        fields = {k: getattr(arr, k)[sel] for k in arr.__dataclass_fields__}
        out[name] = type(arr)(**fields)
    return Batch(**out)


def run(tracker, t_end: int, step: int = 1000, **parts):
    """Feed the parts to ``tracker`` in batches of ``step`` ms; return every estimate."""
    out = []
    start = min(int(p.t.min()) for p in parts.values())
    for lo in range(start, t_end + step, step):
        out += tracker.process(slice_batch(lo, lo + step, **parts))
    return out


def ranges_of(t: np.ndarray, xy: np.ndarray, bias: np.ndarray, rng, every: int = 5) -> Ranges:
    """Biased ranges with 5 cm noise from every anchor, at every ``every``-th point."""
    idx = np.arange(0, t.size, every)
    pos = np.column_stack([xy[idx], np.full(idx.size, 1.0)])
    d = (
        np.linalg.norm(pos[:, None] - ANCHORS[None], axis=-1)
        + bias
        + rng.normal(0, 0.05, (idx.size, 8))
    )
    return Ranges(
        t=np.repeat(t[idx], 8),
        anchor=np.tile(np.arange(8, dtype=np.int32), idx.size),
        range=d.ravel(),
        std=np.full(d.size, 0.1),
    )


def room_walk(seed: int, seconds: float = 60.0):
    """A tag circling inside the anchors' room at 0.5 m/s on a wobbling radius."""
    t = np.arange(0, seconds, 0.02)
    r = 2.0 + 0.8 * np.sin(0.23 * t + seed)
    a = 0.25 * t
    xy = np.column_stack([r * np.cos(a), 0.8 * r * np.sin(a)])
    return (T0 + np.round(t * 1000)).astype(np.int64), xy
