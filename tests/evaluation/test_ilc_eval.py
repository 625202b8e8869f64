"""The site1 evaluation's split, scoring and table statistics on hand-made cases."""

from __future__ import annotations

from dataclasses import astuple, dataclass
from pathlib import Path

import numpy as np
import pytest

from app.datasets.ilc import Walk, WifiScan
from app.engine.calibration import TransmitterFit
from app.engine.pdr import PdrParams
from app.engine.plan import FloorPlan
from app.engine.samples import Batch, Estimate, RssiReadings
from app.evaluation.ilc_eval import (
    Learned,
    WalkScore,
    format_cpu,
    make_runner,
    path_direction,
    pf_site_model,
    remap,
    replay_pf_batched,
    score_walk,
    summarise,
    table_cells,
)
from app.evaluation.site1 import SiteData, split_ids, walk_batches
from app.evaluation.split import walk_split


@dataclass(frozen=True)
class _Walk:
    walk_id: str


IDS = [f"5dd9{i:020x}" for i in range(600)]

# A walk east along y = 0 from x = 0 (t = 0) to x = 10 (t = 10 s), standing there
# until t = 20 s, then north to (10, 10) at t = 30 s.
WAYPOINTS = np.array(
    [[0, 0.0, 0.0], [10_000, 10.0, 0.0], [20_000, 10.0, 0.0], [30_000, 10.0, 10.0]]
)


def _est(t: int, x: float, y: float, floor: int = 0, heading: float = float("nan")) -> Estimate:
    return Estimate(t, x, y, 0.0, floor, heading, 1.0, 1.0, "test")


def test_split_puts_no_walk_on_two_sides_and_test_is_walk_splits() -> None:
    train, validation, test = split_ids([_Walk(i) for i in IDS], 0.2, 0.1)
    assert not set(train) & set(test)
    assert not set(train) & set(validation)
    assert not set(validation) & set(test)
    assert sorted(train + validation + test) == sorted(IDS)
    assert test == walk_split(IDS, 0.2)[1]
    # validation only takes walks out of training
    train0, _, test0 = split_ids([_Walk(i) for i in IDS], 0.2, 0.0)
    assert test0 == test and set(train0) == set(train) | set(validation)


def test_path_direction_is_clockwise_from_north_and_nan_when_standing() -> None:
    t = np.array([-1, 5_000, 15_000, 25_000, 30_001])
    d = path_direction(WAYPOINTS, t)
    assert np.isnan(d[0]) and np.isnan(d[-1])  # outside the span
    assert d[1] == pytest.approx(90.0)  # east
    assert np.isnan(d[2])  # standing: no direction
    assert d[3] == pytest.approx(0.0)  # north


def test_score_walk_interpolates_truth_and_splits_floor_from_distance() -> None:
    estimates = [
        _est(5_000, 5.0, 3.0, heading=100.0),  # truth (5, 0): 3 m, heading off by 10°
        _est(7_500, 7.5, -4.0, heading=80.0),  # truth (7.5, 0): 4 m, off by 10°
        _est(25_000, 10.0, 5.0, floor=2, heading=180.0),  # wrong floor, heading off 180°
        _est(40_000, 0.0, 0.0),  # after the last waypoint: not scored
        _est(15_000, 12.0, 0.0, heading=45.0),  # standing: error 2 m, no heading truth
    ]
    s = score_walk(WAYPOINTS, 0, estimates)
    assert s.floor_ok.tolist() == [True, True, False, True]
    np.testing.assert_allclose(s.error[[0, 1, 3]], [3.0, 4.0, 2.0])
    assert np.isnan(s.error[2])
    np.testing.assert_allclose(s.heading_error[:3], [10.0, 10.0, 180.0])
    assert np.isnan(s.heading_error[3])


def test_summary_statistics_on_a_hand_made_case() -> None:
    errors = np.array([1.0, 2.0, 3.0, 4.0, np.nan, 10.0, np.nan])
    ok = np.isfinite(errors)
    # reported radii: errors 1, 3 and 10 fall inside theirs, 2 and 4 outside
    a = WalkScore(
        ok[:4], errors[:4], np.array([10.0, np.nan, 30.0, 20.0]), np.array([1.0, 1.5, 5.0, 3.0])
    )
    b = WalkScore(
        ok[4:], errors[4:], np.array([np.nan, 350.0 - 340.0, 0.0]), np.array([9.0, 12.0, 1.0])
    )
    row = summarise("m", [a, b], cpu_s=0.5, updates=1000)
    assert row.n == 7 and row.walks == 2
    assert row.mean == pytest.approx(4.0)  # (1 + 2 + 3 + 4 + 10) / 5
    assert row.p50 == pytest.approx(3.0)
    assert row.p75 == pytest.approx(4.0)
    # numpy's linear rule: rank 0.95 × 4 = 3.8 → 4 + 0.8 × (10 - 4)
    assert row.p95 == pytest.approx(8.8)
    assert row.floor_error == pytest.approx(2 / 7)
    assert row.heading_error == pytest.approx(14.0) and row.n_heading == 5
    assert row.in_accuracy == pytest.approx(3 / 5)  # of the five on the right floor
    assert row.cpu_per_update_s == pytest.approx(5e-4)
    cells = table_cells(row)
    assert cells[3:8] == ["4.00", "3.00", "4.00", "8.80", "28.57%"]
    assert cells[-2] == "60%"
    assert cells[-1] == "500 µs"


def test_summary_of_no_estimates_is_nan_not_an_error() -> None:
    row = summarise("m", [], cpu_s=0.0, updates=0)
    assert row.n == 0 and np.isnan(row.mean) and np.isnan(row.floor_error)
    assert table_cells(row)[3] == "—" and table_cells(row)[-1] == "—"


def test_format_cpu_switches_to_milliseconds() -> None:
    assert format_cpu(87e-6) == "87 µs"
    assert format_cpu(3.5e-3) == "3.50 ms"


def test_remap_drops_transmitters_unknown_to_the_filter() -> None:
    batch = Batch(
        rssi=RssiReadings(
            t=np.array([1, 1, 2], np.int64),
            tx=np.array([0, 1, 2], np.int32),
            rssi=np.array([-50.0, -60.0, -70.0]),
        )
    )
    out = remap(batch, np.array([-1, 0, 5]))
    assert out.rssi.tx.tolist() == [0, 5]
    assert out.rssi.rssi.tolist() == [-60.0, -70.0]
    assert out.rssi.t.tolist() == [1, 2]


def _fit(tx: int, floor: int, plausible: bool) -> TransmitterFit:
    return TransmitterFit(
        tx, floor, 1.0 * tx, 2.0, 3.0, -40.0, 15.0, 5.0, 20, 3, 4.0, True, plausible, False
    )


def test_pf_site_keeps_plausible_fits_and_maps_the_site_indices_to_them() -> None:
    plan = FloorPlan.from_raster(origin=np.zeros(2), cell=1.0, free=np.ones((4, 4), bool))
    site = SiteData(floors=("B1", "F1"), plans=(plan, plan), walks=(), tx_ids=("a", "b", "c", "d"))
    model, lookup = pf_site_model(site, [_fit(0, 1, True), _fit(2, 0, False), _fit(3, 0, True)])
    assert lookup.tolist() == [0, -1, -1, 1]
    assert model.transmitters.ids == ("a", "d")
    assert model.transmitters.floor.tolist() == [1, 0]
    assert model.transmitters.xyz[1].tolist() == [3.0, 2.0, 3.0]
    assert [f.level for f in model.floors] == [-1, 0]


def _synthetic_walk(walk_id: str, heard: int, rng: np.random.Generator) -> Walk:
    """A 12 s walk east along y = 5 at 1 m/s, one scan a second of the first ``heard`` APs."""
    t_scan = np.arange(12) * 1000 + 500
    x = 2.0 + t_scan / 1000.0
    r = np.hypot(x[:, None] - AP_XY[None, :heard, 0], 5.0 - AP_XY[None, :heard, 1])
    rssi = -40.0 - 15.0 * np.log(np.hypot(r, 1.8)) + rng.normal(0, 3, r.shape)
    t = np.repeat(t_scan, heard)
    empty = np.zeros((0, 4))
    return Walk(
        walk_id=walk_id,
        floor="F1",
        path=Path(walk_id),
        acc=empty,
        gyro=empty,
        mag=empty,
        rot=empty,
        wifi=WifiScan(
            t=t,
            bssid=np.tile(np.array(AP_IDS[:heard]), t_scan.size),
            rssi=rssi.ravel(),
            freq=np.full(t.size, 2437.0),
            last_seen=t.copy(),
        ),
        beacons=None,  # type: ignore[arg-type]
        waypoints=np.array([[0, 1.5, 5.0], [13_000, 14.5, 5.0]]),
    )


AP_IDS = ("ap0", "ap1", "ap2", "ap3", "ap4")
AP_XY = np.array([[2.0, 2.0], [18.0, 2.0], [18.0, 8.0], [2.0, 8.0], [10.0, 5.0]])


def test_batched_particle_filter_replay_equals_walk_by_walk() -> None:
    # Walks hearing 3, 4 and 5 APs widen the batch's readings table differently:
    # each walk's estimates must be those of replaying it alone.
    rng = np.random.default_rng(8)
    plan = FloorPlan.from_raster(origin=np.zeros(2), cell=0.5, free=np.ones((20, 40), bool))
    walks = tuple(_synthetic_walk(f"w{k}", k, rng) for k in (3, 5, 4))
    site = SiteData(floors=("F1",), plans=(plan,), walks=walks, tx_ids=AP_IDS)
    fits = [
        TransmitterFit(i, 0, *AP_XY[i], 3.0, -40.0, 15.0, 4.0, 50, 0, 5.0, True, True, False)
        for i in range(len(AP_IDS))
    ]
    model, lookup = pf_site_model(site, fits)
    learned = Learned((), tuple(fits), PdrParams(), model, lookup, 0)
    batched, _, updates = replay_pf_batched(site, learned, walks)
    assert updates == sum(len(list(walk_batches(site, w))) for w in walks)
    alone = make_runner("pf", learned)
    for walk, got in zip(walks, batched, strict=True):
        expected = alone(site, walk).estimates
        assert len(got) == len(expected) > 5
        np.testing.assert_array_equal(
            np.array([astuple(e)[:8] for e in got], float),
            np.array([astuple(e)[:8] for e in expected], float),
        )
        # and the filter does track the walk
        assert score_walk(walk.waypoints, 0, got).error[-3:].max() < 4.0
