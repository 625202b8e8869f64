"""Positioning loop: floors, refinement, projection, snapshots, batching over devices."""

from __future__ import annotations

from dataclasses import astuple, replace

import numpy as np
import pytest

from app.engine.plan import FloorPlan, burn_segments
from app.engine.positioning import (
    HeardByFloor,
    ParticleTracker,
    PositioningEngine,
    PositioningParams,
    refine,
    rng_from_state,
    rng_state,
    seed_from_id,
)
from app.engine.samples import Batch, Estimate, Fixes, RssiReadings
from app.engine.site import Emitters, Floor, SiteModel
from app.workers.snapshots import decode, encode

PARAMS = PositioningParams()
TX_XYZ = np.array([[1.0, 1.0, 2.5], [9.0, 1.0, 2.5], [9.0, 9.0, 2.5], [1.0, 9.0, 2.5]])


def two_floors() -> SiteModel:
    """Two stacked 10 × 10 m rooms with a wall along x = 5 (y < 8), four transmitters each."""
    free = np.ones((100, 100), bool)
    walls = [[5, 0, 5, 8], [0, 0, 10, 0], [10, 0, 10, 10], [10, 10, 0, 10], [0, 10, 0, 0]]
    burn_segments(free, np.array(walls, float), origin=np.zeros(2), cell=0.1)
    plan = FloorPlan.from_raster(origin=np.zeros(2), cell=0.1, free=free)
    tx = Emitters(
        ids=tuple(f"{i}{f}" for f in (0, 1) for i in "abcd"),
        floor=np.repeat(np.array([0, 1], np.int32), 4),
        xyz=np.vstack([TX_XYZ, TX_XYZ]),
        A=np.full(8, -40.0),
        B=np.full(8, 20.0),
        sigma=np.full(8, 4.0),
    )
    return SiteModel("two", (Floor("f0", 0, 3.0, plan), Floor("f1", 1, 3.0, plan, z0=3.0)), tx)


def walk_batch(k: int, floor: int, noise: np.random.Generator) -> Batch:
    """Three scans of window k of a walk along y = 9 on ``floor``, at 0.5 m/s."""
    t = 1000 * k + np.array([100, 400, 700])
    x = 1.5 + 0.5 * (t / 1000.0)
    d = np.hypot(x[:, None] - TX_XYZ[None, :, 0], 9.0 - TX_XYZ[None, :, 1])
    rssi = -40.0 - 20.0 * np.log(np.hypot(d, 1.3)) + noise.normal(0, 4, d.shape)
    return Batch(
        rssi=RssiReadings(
            t=np.repeat(t, 4).astype(np.int64),
            tx=np.tile(np.arange(4) + 4 * floor, 3).astype(np.int32),
            rssi=rssi.ravel(),
        )
    )


def same(a: list[Estimate], b: list[Estimate]) -> bool:
    """Equality of estimate lists where NaN equals NaN (unknown headings)."""
    try:
        np.testing.assert_equal([astuple(e) for e in a], [astuple(e) for e in b])
    except AssertionError:
        return False
    return True


def run(tracker: ParticleTracker, ks: range, floor: int = 0, seed: int = 0) -> list[Estimate]:
    noise = np.random.default_rng(seed)
    out: list[Estimate] = []
    for k in ks:
        out += tracker.process(walk_batch(k, floor, noise))
    return out


def test_refine_is_an_alpha_beta_step_with_a_speed_limit() -> None:
    p = replace(PARAMS, position_gain=0.5, velocity_gain=0.2, max_speed_mps=10.0)
    pos, vel = refine(np.array([3.0, 0.0]), np.zeros(2), np.array([1.0, 0.0]), 1.0, p)
    # predicted (1, 0), residual (2, 0): x = 1 + 0.5·2, v = 1 + 0.2·2 / 1
    assert pos.tolist() == pytest.approx([2.0, 0.0])
    assert vel.tolist() == pytest.approx([1.4, 0.0])
    _, vel = refine(
        np.array([30.0, 40.0]), np.zeros(2), np.zeros(2), 0.1, replace(p, max_speed_mps=2.0)
    )
    assert float(np.hypot(*vel)) == pytest.approx(2.0)


def test_estimates_follow_the_walk_on_its_floor_and_lie_on_free_cells() -> None:
    site = two_floors()
    tracker = ParticleTracker(site, PARAMS, seed=3)
    out = run(tracker, range(10), floor=1)
    assert len(out) == 9  # the tenth window is still open
    assert {e.floor for e in out} == {1} and {e.method for e in out} == {"pf"}
    assert all(e.z == 3.0 for e in out)
    plan = site.floors[1].plan
    assert plan.is_free(np.array([[e.x, e.y] for e in out])).all()
    last = out[-1]
    truth_x = 1.5 + 0.5 * last.t / 1000.0
    assert abs(last.x - truth_x) < 1.5 and abs(last.y - 9.0) < 1.5
    assert [e.t for e in out] == [1000 * k + 700 for k in range(9)]
    assert len(tracker.flush()) == 1


def test_accuracy_floor_adds_in_quadrature_and_changes_nothing_else() -> None:
    site = two_floors()
    plain = run(ParticleTracker(site, PARAMS, seed=3), range(8))
    floored = run(ParticleTracker(site, replace(PARAMS, accuracy_floor_m=4.0), seed=3), range(8))
    assert len(plain) == len(floored) == 7
    for a, b in zip(plain, floored, strict=True):
        # same positions; accuracy = √(r_cloud² + floor²)
        assert (a.x, a.y, a.floor) == (b.x, b.y, b.floor)
        assert b.accuracy == pytest.approx(np.hypot(a.accuracy, 4.0))
        assert b.accuracy >= 4.0 > a.accuracy


def test_no_active_floor_resets_and_emits_nothing() -> None:
    tracker = ParticleTracker(two_floors(), PARAMS, seed=1)
    run(tracker, range(3))
    quiet = Batch(
        fixes=Fixes(
            t=np.array([30_500], np.int64),
            xyz=np.zeros((1, 3)),
            floor=np.zeros(1, np.int32),
            std=np.ones(1),
        )
    )
    # the open window is released; 27 s later the 10 s history is empty: no floor, no position
    assert [e.t for e in tracker.process(quiet)] == [2700]
    assert tracker.flush() == []
    assert tracker.engine.devices["device"].out_floor == -1


def test_same_seed_same_input_is_identical_and_snapshot_resumes_exactly() -> None:
    site = two_floors()
    a = ParticleTracker(site, PARAMS, seed=7)
    b = ParticleTracker(site, PARAMS, seed=7)
    assert same(run(a, range(5)), run(b, range(5)))
    blob = encode(a.snapshot())
    restored = ParticleTracker(site, PARAMS, decode(blob))
    assert same(run(a, range(5, 9), seed=1), run(restored, range(5, 9), seed=1))
    other = ParticleTracker(site, PARAMS, seed=8)
    assert not same(run(other, range(5)), run(ParticleTracker(site, PARAMS, seed=7), range(5)))


def test_a_device_does_not_depend_on_the_devices_batched_with_it() -> None:
    site = two_floors()
    alone = PositioningEngine(site, PARAMS)
    crowd = PositioningEngine(site, PARAMS, alone.models)
    alone.add("a")
    for d in ("a", "b", "c"):
        crowd.add(d)
    noise_a, noise_b = np.random.default_rng(0), np.random.default_rng(1)
    for k in range(6):
        batch = walk_batch(k, 0, noise_a)
        mate = walk_batch(k, 1 if k % 2 else 0, noise_b)
        got_alone = alone.process({"a": batch})["a"]
        got_crowd = crowd.process({"b": mate, "a": batch, "c": mate})["a"]
        assert same(got_alone, got_crowd)


def test_generator_state_round_trips_and_seeds_come_from_ids() -> None:
    rng = np.random.default_rng(12345)
    rng.random(3)
    twin = rng_from_state(rng_state(rng))
    assert np.array_equal(rng.random(5), twin.random(5))
    assert seed_from_id("tag-1") == seed_from_id("tag-1") != seed_from_id("tag-2")


def run_floors(tracker: ParticleTracker, floors: list[int], start: int = 0) -> list[Estimate]:
    """Windows ``start``, ``start + 1``, … of the walk, window k heard on ``floors[k - start]``."""
    noise = np.random.default_rng(start)
    out: list[Estimate] = []
    for k, floor in enumerate(floors, start):
        out += tracker.process(walk_batch(k, floor, noise))
    return out


def test_engine_follows_a_device_that_changes_floor_and_resumes_mid_change() -> None:
    site = two_floors()
    tracker = ParticleTracker(site, PARAMS, seed=5)
    before = run_floors(tracker, [0] * 12)
    assert {e.floor for e in before} == {0}
    # the change at window 12; snapshot after its first window, resume in a twin
    first = run_floors(tracker, [1], 12)
    twin = ParticleTracker(site, PARAMS, decode(encode(tracker.snapshot())))
    after = run_floors(tracker, [1] * 10, 13)
    assert same(after, run_floors(twin, [1] * 10, 13))
    floors = [e.floor for e in first + after]
    # estimates of window k come out with window k + 1; the new floor within three windows
    switch = floors.index(1)
    assert switch <= 3 and set(floors[switch:]) == {1}


def test_patent_floor_selection_stays_selectable_and_waits_for_its_dwell() -> None:
    patent = replace(PARAMS, floors=replace(PARAMS.floors, method="patent"))
    site = two_floors()
    tracker = ParticleTracker(site, patent, seed=5)
    floors = [e.floor for e in run_floors(tracker, [0] * 12 + [1] * 10)]
    filtered = [e.floor for e in run_floors(ParticleTracker(site, PARAMS), [0] * 12 + [1] * 10)]
    # estimate i is window i: E_L over 10 s of history needs floor 1 to outnumber floor 0
    # there, then the dwell; the filter follows within three windows
    assert floors.index(1) >= 12 + patent.floors.dwell_windows
    assert set(floors[floors.index(1) :]) == {1}
    assert filtered.index(1) <= 14 < floors.index(1)
    restored = ParticleTracker(site, patent, decode(encode(tracker.snapshot())))
    assert same(run_floors(tracker, [1] * 3, 22), run_floors(restored, [1] * 3, 22))
    with pytest.raises(ValueError, match="floor selection"):
        ParticleTracker(site, replace(PARAMS, floors=replace(PARAMS.floors, method="x")))


def test_readings_are_averaged_per_transmitter_and_grouped_by_device_and_floor() -> None:
    device = np.array([0, 0, 0, 1, 0, 0, 1])
    tx = np.array([1, 0, 3, 2, 1, 1, 4])
    # transmitter 4 has no floor
    tx_floor = np.array([0, 0, 1, 1, -1])[tx]
    rssi = np.array([-50.0, -60.0, -70.0, -80.0, -52.0, -54.0, -40.0])
    heard = HeardByFloor.of_readings(device, tx_floor, tx, rssi, 2, 2)
    tx0, mean0, count0 = heard.of(0, 0)
    assert tx0.tolist() == [0, 1] and mean0.tolist() == [-60.0, -52.0]
    assert count0.tolist() == [1.0, 3.0]
    assert [a.tolist() for a in heard.of(0, 1)] == [[3], [-70.0], [1.0]]
    # device 1's reading of transmitter 4 counts nowhere
    assert [a.tolist() for a in heard.of(1, 0)] == [[], [], []]
    assert [a.tolist() for a in heard.of(1, 1)] == [[2], [-80.0], [1.0]]
