"""UWB tracker: range epochs, bias self-calibration in the loop, snapshots, the plan constraint."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.plan import burn_segments
from app.engine.samples import Batch, Fixes, Ranges
from app.engine.uwb_tracker import UwbTracker, UwbTrackerParams, group_epochs
from app.workers.snapshots import decode, encode
from tests.engine.tag_sim import ANCHORS, T0, ranges_of, room_walk, run, site_with, slice_batch


def test_epochs_split_at_repeated_anchors_and_gaps() -> None:
    t = np.array([0, 0, 0, 10, 10, 50, 51, 52], dtype=np.int64)
    anchor = np.array([0, 1, 2, 0, 1, 2, 2, 3])
    epochs = group_epochs(t, anchor, np.arange(8.0), np.ones(8), epoch_ms=30)
    assert [e.anchors.tolist() for e in epochs] == [[0, 1, 2], [0, 1], [2], [2, 3]]
    assert [e.t for e in epochs] == [0, 10, 50, 52]


def test_self_calibration_recovers_range_biases_without_truth() -> None:
    """Biases U(0.1, 0.3) m on 8 anchors (two more anchors of the site never heard, ranges
    listed in reverse anchor order): learnt within 2 cm RMS, halving the position error."""
    rng = np.random.default_rng(42)
    bias = rng.uniform(0.1, 0.3, 8)
    t, xy = room_walk(0)
    ranges = ranges_of(t, xy, bias, rng)
    order = np.lexsort((-ranges.anchor, ranges.t))
    ranges = Ranges(*(getattr(ranges, k)[order] for k in ("t", "anchor", "range", "std")))
    site = site_with(anchors=np.vstack([ANCHORS, [[9.0, 7.0, 2.0], [-9.0, 7.0, 2.0]]]))
    errors = {}
    for learn in (False, True):
        tracker = UwbTracker(site, UwbTrackerParams(self_calibrate=learn, emit_every_ms=0))
        out = run(tracker, int(t[-1]), ranges=ranges)
        late = [e for e in out if e.t > T0 + 30_000]
        est = np.array([[e.x, e.y] for e in late])
        et = np.array([e.t for e in late])
        truth = np.column_stack([np.interp(et, t, xy[:, 0]), np.interp(et, t, xy[:, 1])])
        errors[learn] = np.sqrt(np.mean(np.sum((est - truth) ** 2, axis=1)))
        if learn:
            assert np.sqrt(np.mean((tracker.bias[:8] - bias) ** 2)) < 0.02
            assert (tracker.bias[8:] == 0).all() and sorted(tracker.bias_ids) == list(range(8))
            assert tracker.bias_S.shape == (8, 8)
    assert errors[True] < 0.5 * errors[False]


def test_snapshot_round_trip_continues_identically() -> None:
    rng = np.random.default_rng(3)
    t, xy = room_walk(1, seconds=20.0)
    ranges = ranges_of(t, xy, rng.uniform(0.1, 0.3, 8), rng)
    params = UwbTrackerParams(emit_every_ms=100)
    whole = UwbTracker(site_with(), params)
    first = run(whole, int(t[-1]), ranges=ranges)
    half = UwbTracker(site_with(), params)
    mid = T0 + 10_000
    out = run(half, mid - 1000, ranges=ranges)
    restored = UwbTracker.from_snapshot(site_with(), params, decode(encode(half.snapshot())))
    for lo in range(mid, int(t[-1]) + 1000, 1000):
        out += restored.process(slice_batch(lo, lo + 1000, ranges=ranges))
    assert [(e.t, e.x, e.y) for e in out] == [(e.t, e.x, e.y) for e in first]
    assert np.all(np.diff([e.t for e in first]) >= 100)


def test_given_fixes_are_projected_off_walls() -> None:
    free = np.ones((160, 200), bool)
    burn_segments(free, np.array([[0.0, -8.0, 0.0, 8.0]]), origin=np.array([-10.0, -8.0]), cell=0.1)
    site = site_with(free)
    tracker = UwbTracker(site, UwbTrackerParams(emit_every_ms=0))
    fix = Fixes(
        t=np.array([T0], np.int64),
        xyz=np.array([[0.02, 1.0, 1.2]]),
        floor=np.zeros(1, np.int32),
        std=np.array([0.2]),
    )
    (est,) = tracker.process(Batch(fixes=fix))
    plan = site.floors[0].plan
    assert not plan.is_free(np.array([0.02, 1.0]))
    assert plan.is_free(np.array([est.x, est.y]))
    assert np.hypot(est.x - 0.02, est.y - 1.0) < 0.15
    assert est.z == pytest.approx(1.2) and est.method == "ekf"
    assert est.accuracy == pytest.approx(np.sqrt(-2 * np.log(0.32)) * 0.2)
