"""BLE flat reader: parsing against the csv module, runs, readings, truth, the flat's plan."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from app.datasets import ble_flat

ROOT = ble_flat.root()

pytestmark = pytest.mark.skipif(not ROOT.is_dir(), reason="ble_flat recordings not present")


def test_track_matches_a_plain_csv_parse() -> None:
    anchors = ble_flat.read_anchors()
    track = ble_flat.test_robot()
    with open(ROOT / "tests" / "test_robot_df.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    rows.sort(key=lambda r: float(r["ts"]))
    assert len(track) == len(rows)
    assert track.t.tolist() == [round(float(r["ts"]) / 1e6) for r in rows]
    np.testing.assert_array_equal(track.xy, [[float(r["x"]), float(r["y"])] for r in rows])
    np.testing.assert_array_equal(track.heading, [float(r["heading"]) for r in rows])
    ref = [[float(r[f"rssi_{i}"]) if r[f"rssi_{i}"] else np.nan for i in anchors.ids] for r in rows]
    np.testing.assert_array_equal(track.rssi, ref)
    assert anchors.ids == (1, 2, 3, 4, 5, 6) and anchors.xyz.shape == (6, 3)


def test_runs_split_at_long_pauses_and_cover_the_recording() -> None:
    cal = ble_flat.calibration()
    runs = ble_flat.runs(cal)
    assert len(runs) > 1
    assert sum(len(r) for r in runs) == len(cal)
    assert all(np.diff(r.t).max() <= ble_flat.RUN_GAP_MS for r in runs)
    assert all(b.t[0] - a.t[-1] > ble_flat.RUN_GAP_MS for a, b in zip(runs, runs[1:], strict=False))
    np.testing.assert_array_equal(np.concatenate([r.t for r in runs]), cal.t)


def test_readings_hold_every_heard_value_once_in_time_order() -> None:
    track = ble_flat.calibration()
    r = ble_flat.readings(track)
    assert len(r) == int(np.isfinite(track.rssi).sum())
    assert np.all(np.diff(r.t) >= 0)
    row = np.searchsorted(track.t, r.t)
    np.testing.assert_array_equal(track.rssi[row, r.tx], r.rssi)


def test_truth_interpolates_between_rows() -> None:
    track = ble_flat.test_robot()
    mid = (track.t[:-1] + track.t[1:]) / 2.0
    got = ble_flat.truth_at(track, mid)
    np.testing.assert_allclose(got, (track.xy[:-1] + track.xy[1:]) / 2.0, atol=1e-9)
    np.testing.assert_array_equal(ble_flat.truth_at(track, track.t), track.xy)


def test_plan_keeps_walls_and_doors_and_the_truth_on_free_cells() -> None:
    layout = ble_flat.read_layout()
    walled = ble_flat.floor_plan(layout, 0.1, walls=True)
    open_plan = ble_flat.floor_plan(layout, 0.1, walls=False)
    # the left room's door to the hall spans x ∈ (0.73, 1.52) at y ≈ 2.1; left of it is wall
    door = walled.segment_free(np.array([[1.1, 2.6]]), np.array([[1.1, 1.5]]))
    wall = walled.segment_free(np.array([[0.4, 2.6]]), np.array([[0.4, 1.5]]))
    assert door.tolist() == [True] and wall.tolist() == [False]
    assert open_plan.segment_free(np.array([[0.4, 2.6]]), np.array([[0.4, 1.5]])).tolist() == [True]
    assert walled.is_free(ble_flat.test_robot().xy).all()
    assert walled.is_free(np.array([[9.5, 3.0], [4.5, 6.0]])).tolist() == [False, True]
