"""Joined walks for the floor-change latency, and the latency of a track."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from app.datasets.ilc import BeaconScan, Walk, WifiScan
from app.engine.samples import Estimate
from app.evaluation.ilc.floor_change import floor_pairs, joined_walk, settle_latency


def _walk(walk_id: str, floor: str, t0: int) -> Walk:
    """A 10 s walk from ``t0``: IMU at 10 Hz, a scan and a beacon a second, waypoints at 0/10 s."""
    t_imu = t0 + np.arange(0, 10_000, 100)
    imu = np.column_stack([t_imu, np.ones((t_imu.size, 3))]).astype(float)
    t_scan = t0 + np.arange(500, 10_000, 1000)
    return Walk(
        walk_id=walk_id,
        floor=floor,
        path=Path(walk_id),
        acc=imu,
        gyro=imu.copy(),
        mag=imu.copy(),
        rot=imu.copy(),
        wifi=WifiScan(
            t=t_scan,
            bssid=np.array([f"{walk_id}-ap"] * t_scan.size),
            rssi=np.full(t_scan.size, -60.0),
            freq=np.full(t_scan.size, 2437.0),
            last_seen=t_scan - 200,
        ),
        beacons=BeaconScan(
            t=t_scan,
            id=np.array(["b"] * t_scan.size),
            rssi=np.full(t_scan.size, -70.0),
            tx_power=np.full(t_scan.size, -59.0),
            mac=np.array(["m"] * t_scan.size),
        ),
        waypoints=np.array([[t0, 1.0, 1.0], [t0 + 10_000, 11.0, 1.0]], dtype=float),
    )


def test_the_second_walk_starts_where_the_first_ends_on_its_own_floor() -> None:
    first, second = _walk("a", "F1", 1_000_000), _walk("b", "F2", 5_000_000)
    joined = joined_walk(first, second)
    assert joined.floor == "F2" and joined.walk_id == "a-b"
    end = 1_010_000
    # every sample of both, in time order, the second's shifted by end - its start
    assert joined.acc.shape[0] == first.acc.shape[0] + second.acc.shape[0] - 1
    assert np.all(np.diff(joined.acc[:, 0]) > 0)
    assert np.all(np.diff(joined.wifi.t) > 0) and np.all(np.diff(joined.beacons.t) > 0)
    np.testing.assert_array_equal(joined.wifi.t[10:], second.wifi.t + end - 5_000_000)
    np.testing.assert_array_equal(joined.wifi.last_seen - joined.wifi.t, -200)
    assert list(joined.wifi.bssid[9:11]) == ["a-ap", "b-ap"]
    # waypoints: the first's, then the second's after its start
    np.testing.assert_array_equal(joined.waypoints[:, 0], [1_000_000, end, end + 10_000])


def _track(times: list[int], floors: list[int]) -> list[Estimate]:
    return [
        Estimate(t, 0.0, 0.0, 0.0, f, np.nan, np.nan, np.nan, "hmm")
        for t, f in zip(times, floors, strict=True)
    ]


def test_latency_runs_until_the_last_position_off_the_new_floor() -> None:
    track = _track([900, 1500, 2500, 3500, 4500, 5500], [0, 0, 1, 0, 1, 1])
    # back on the old floor at 3.5 s: settled at 4.5 s, 3.5 s after the change at 1 s
    assert settle_latency(track, 1000, 1) == 3.5
    assert settle_latency(_track([900, 1500], [0, 1]), 1000, 1) == 0.5
    # still on the old floor at the end: never followed
    assert settle_latency(_track([1500, 2500], [1, 0]), 1000, 1) is None


def test_each_walk_is_paired_with_the_next_long_enough_on_another_floor() -> None:
    walks = [_walk(w, f, 0) for w, f in (("a", "F1"), ("b", "F1"), ("c", "F2"), ("d", "F2"))]
    # every walk lasts 10 s, too short to hear its floor, but d lasts 40 s
    walks[3] = replace(walks[3], waypoints=np.array([[0, 1.0, 1.0], [40_000, 11.0, 1.0]]))
    pairs = [(x.walk_id, y.walk_id) for x, y in floor_pairs(walks, limit=10)]
    assert pairs == [("a", "d"), ("b", "d")]
    walks[0] = replace(walks[0], waypoints=np.array([[0, 1.0, 1.0], [60_000, 11.0, 1.0]]))
    pairs = [(x.walk_id, y.walk_id) for x, y in floor_pairs(walks, limit=10)]
    assert pairs == [("a", "d"), ("b", "d"), ("c", "a"), ("d", "a")]
    assert len(floor_pairs(walks, limit=2)) == 2
