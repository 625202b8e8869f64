"""Locator tracker: windowed RSSI means, and tracking a simulated tag against its raw fixes."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.lateration.solver import solve
from app.engine.locator_tracker import (
    LocatorTracker,
    LocatorTrackerParams,
    strongest_centroid,
    window_means,
)
from app.engine.samples import Sightings
from app.workers.snapshots import decode, encode
from tests.engine.tag_sim import room_walk, run, site_with


def test_window_means_agree_with_a_loop() -> None:
    rng = np.random.default_rng(9)
    t = np.sort(rng.integers(0, 10_000, 300))
    tx = rng.integers(0, 5, 300)
    rssi = rng.normal(-70, 5, 300)
    times = np.arange(500, 10_001, 500)
    mean, count = window_means(t, tx, rssi, 5, times, 2000)
    for i, tau in enumerate(times):
        for k in range(5):
            sel = (t > tau - 2000) & (t <= tau) & (tx == k)
            assert count[i, k] == sel.sum()
            if sel.any():
                assert mean[i, k] == pytest.approx(rssi[sel].mean())
            else:
                assert np.isnan(mean[i, k])


def test_locator_tracker_follows_a_simulated_tag() -> None:
    """Readings every 0.5 s per locator from rssi = A − B ln d + N(0, 4 dB): the tracker stays
    within 20 % of the RMS of its own unfiltered fixes (RSSI fixes from overlapping windows are
    correlated and heavy-tailed: the filter smooths little) and restores from a snapshot."""
    rng = np.random.default_rng(12)
    t, xy = room_walk(2, seconds=60.0)
    site = site_with()
    loc = site.locators
    idx = np.arange(0, t.size, 25)
    pos = np.column_stack([xy[idx], np.full(idx.size, 1.0)])
    d = np.linalg.norm(pos[:, None] - loc.xyz[None], axis=-1)
    rssi = loc.A - loc.B * np.log(d) + rng.normal(0, 4.0, d.shape)
    readings = Sightings(
        t=np.repeat(t[idx], 8) + np.tile(np.arange(8), idx.size),
        locator=np.tile(np.arange(8, dtype=np.int32), idx.size),
        rssi=rssi.ravel(),
    )
    params = LocatorTrackerParams(tag_height_m=1.0, fix_std_floor_m=0.3)
    tracker = LocatorTracker(site, params)
    out = run(tracker, int(t[-1]), sightings=readings)
    et = np.array([e.t for e in out])
    assert np.all(et % params.step_ms == 0) and et.size > 0.9 * 60_000 / params.step_ms

    def rms(times: np.ndarray, est: np.ndarray) -> float:
        truth = np.column_stack([np.interp(times, t, xy[:, 0]), np.interp(times, t, xy[:, 1])])
        return float(np.sqrt(np.mean(np.sum((est - truth) ** 2, axis=1))))

    mean, count = window_means(readings.t, readings.locator, readings.rssi, 8, et, params.window_ms)
    x0 = strongest_centroid(mean, loc.xyz)
    x0[:, 2] = 1.0
    raw = solve(
        "rssi",
        loc.xyz,
        mean,
        loc.sigma[None, :] / np.sqrt(np.clip(count, 1, params.max_samples)),
        A=loc.A,
        B=loc.B,
        height=1.0,
        dims=2,
        x0=x0,
    )
    raw_rms = rms(et[raw.ok], raw.position[raw.ok, :2])
    assert raw_rms < 1.5
    assert rms(et, np.array([[e.x, e.y] for e in out])) < 1.2 * raw_rms
    restored = LocatorTracker.from_snapshot(site, params, decode(encode(tracker.snapshot())))
    assert restored.next_fix == tracker.next_fix and restored.t.size == tracker.t.size
