"""Radio maps on hand-worked cases: scans located on the waypoints, per-point mean, variance
and detection rate, storage round trip, and WKNN cross-validation against scan-by-scan WKNN."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.crossval import cross_validate, wknn_scans
from app.engine.hmm.params import HmmParams
from app.engine.radiomap import (
    RadioMap,
    RadioMapParams,
    Survey,
    build_radio_map,
    interpolate_waypoints,
    locate_scans,
)
from app.engine.samples import RssiReadings
from app.engine.wknn import Fingerprints, WknnParams, wknn


def test_scans_are_located_by_straight_constant_speed_walking() -> None:
    waypoints = np.array([[0, 0.0, 0.0], [10_000, 10.0, 0.0], [15_000, 10.0, 5.0]])
    xy, inside = interpolate_waypoints(np.array([-1, 0, 5_000, 12_500, 15_001]), waypoints)
    assert inside.tolist() == [False, True, True, True, False]
    assert xy[1:4] == pytest.approx(np.array([[0.0, 0.0], [5.0, 0.0], [10.0, 2.5]]))
    # two scans; the second repeats transmitter 3 (mean kept); one reading after the walk
    readings = RssiReadings(
        t=np.array([2_000, 2_000, 7_500, 7_500, 7_500, 20_000], dtype=np.int64),
        tx=np.array([1, 3, 3, 3, 0, 1], dtype=np.int32),
        rssi=np.array([-50.0, -60.0, -70.0, -74.0, -80.0, -40.0]),
    )
    s = locate_scans(readings, waypoints, floor=2, walk=9)
    assert s.scan_t.tolist() == [2_000, 7_500]
    assert s.scan_xy == pytest.approx(np.array([[2.0, 0.0], [7.5, 0.0]]))
    assert s.scan_floor.tolist() == [2, 2] and s.scan_walk.tolist() == [9, 9]
    rows = zip(s.reading_scan.tolist(), s.reading_tx.tolist(), s.reading_rssi.tolist(), strict=True)
    got = sorted(rows)
    assert got == [(0, 1, -50.0), (0, 3, -60.0), (1, 0, -80.0), (1, 3, -72.0)]


def _survey(xy: list[tuple[float, float]], readings: list[dict[int, float]]) -> Survey:
    scan, tx, rssi = [], [], []
    for i, heard in enumerate(readings):
        for t, r in sorted(heard.items()):
            scan.append(i)
            tx.append(t)
            rssi.append(r)
    n = len(xy)
    return Survey(
        scan_t=np.arange(n, dtype=np.int64),
        scan_xy=np.array(xy, dtype=float),
        scan_floor=np.zeros(n, dtype=np.int32),
        scan_walk=np.arange(n, dtype=np.int32),
        reading_scan=np.array(scan, dtype=np.int32),
        reading_tx=np.array(tx, dtype=np.int32),
        reading_rssi=np.array(rssi, dtype=float),
    )


def test_point_statistics_match_the_hand_computation() -> None:
    params = RadioMapParams(cell_m=1.0, bandwidth_m=0.0, min_scans=1)
    # two scans in cell (row 0, col 0) hear tx 0 at -50 and -54; one in the next cell misses it
    survey = _survey(
        [(0.2, 0.5), (0.8, 0.5), (1.5, 0.5)], [{0: -50.0, 1: -70.0}, {0: -54.0}, {1: -66.0}]
    )
    m = build_radio_map(survey, 0, params)
    xy = m.xy
    p0 = int(np.flatnonzero(np.all(np.isclose(xy, [0.5, 0.5]), axis=1))[0])
    p1 = int(np.flatnonzero(np.all(np.isclose(xy, [1.5, 0.5]), axis=1))[0])
    assert m.n_points == 2 and m.tx.tolist() == [0, 1]
    assert m.mean[p0, 0] == pytest.approx(-52.0)
    # s² = 4 from n = 2 scans, shrunk to the prior 16 dB² with weight 2: (2·4 + 2·16) / 4
    assert m.var[p0, 0] == pytest.approx(10.0)
    # q = (heard + α) / (scans + α + β) = (2 + 0.1) / (2 + 1.1)
    assert m.detect[p0, 0] == pytest.approx(2.1 / 3.1)
    assert np.isnan(m.mean[p1, 0]) and m.detect[p1, 0] == pytest.approx(0.1 / 2.1)
    # one reading: variance is the prior's pull on s² = 0: (0 + 2·16) / 3, above the floor 4
    assert m.var[p1, 1] == pytest.approx(32.0 / 3.0)
    assert m.weight[[p0, p1]].tolist() == [2.0, 1.0]


def test_map_round_trips_through_arrays() -> None:
    survey = _survey([(0.2, 0.5), (3.5, 2.5)], [{0: -50.0, 2: -61.0}, {2: -70.0}])
    m = build_radio_map(survey, 0, RadioMapParams(min_scans=1))
    back = RadioMap.from_arrays(m.to_arrays())
    for key, value in m.to_arrays().items():
        np.testing.assert_array_equal(back.to_arrays()[key], value)


def _corridor(seed: int) -> Survey:
    """A 30 m corridor surveyed by 6 walks; 3 transmitters with a log-distance field."""
    rng = np.random.default_rng(seed)
    ap = np.array([[0.0, 1.0], [15.0, 1.0], [30.0, 1.0]])
    xy, readings = [], []
    for walk in range(6):
        for x in np.arange(0.5 + 0.3 * walk, 30.0, 1.5):
            p = np.array([x, 1.0 + 0.1 * walk])
            r = np.hypot(*(ap - p).T) + 1.0
            rssi = -40.0 - 15.0 * np.log(r) + rng.normal(0.0, 2.0, 3)
            xy.append(tuple(p))
            readings.append({t: float(v) for t, v in enumerate(rssi) if v > -95.0})
    s = _survey(xy, readings)
    walks = np.repeat(
        np.arange(6), [sum(1 for _ in np.arange(0.5 + 0.3 * w, 30.0, 1.5)) for w in range(6)]
    )
    return Survey(
        scan_t=s.scan_t,
        scan_xy=s.scan_xy,
        scan_floor=s.scan_floor,
        scan_walk=walks.astype(np.int32),
        reading_scan=s.reading_scan,
        reading_tx=s.reading_tx,
        reading_rssi=s.reading_rssi,
    )


def test_batched_wknn_equals_scan_by_scan_wknn() -> None:
    survey = _corridor(seed=2)
    # two "floors" mapped from different walks compete for the held-out walk's scans
    two = Survey(
        scan_t=survey.scan_t,
        scan_xy=survey.scan_xy,
        scan_floor=(survey.scan_walk >= 3).astype(np.int32),
        scan_walk=survey.scan_walk,
        reading_scan=survey.reading_scan,
        reading_tx=survey.reading_tx,
        reading_rssi=survey.reading_rssi,
    )
    params = WknnParams()
    train = two.select(two.scan_walk != 0)
    maps = [build_radio_map(train, f, RadioMapParams()) for f in (0, 1)]
    fp = Fingerprints(maps, params.missing_dbm)
    held = two.select(two.scan_walk == 0)
    xy, floor = wknn_scans(fp, held, params)
    floors = set()
    for i in range(held.n_scans):
        on = held.reading_scan == i
        ref = wknn(fp, held.reading_tx[on], held.reading_rssi[on], params)
        assert xy[i] == pytest.approx(ref.xy, abs=1e-9) and floor[i] == ref.floor
        floors.add(ref.floor)
    assert floors == {0, 1}


def test_cross_validation_holds_out_whole_walks_and_locates_the_corridor() -> None:
    survey = _corridor(seed=4)
    validation = cross_validate(survey, {}, RadioMapParams(), WknnParams(), folds=3)
    assert validation is not None
    held = validation.by_k[WknnParams().k]
    assert held.folds == 3
    assert sorted(held.scan.tolist()) == list(range(survey.n_scans))
    assert held.floor_ok.all()
    # a 1-D field with 3 transmitters at σ = 2 dB: most scans within a few metres
    assert float(np.median(held.error_m)) < 2.5
    one_walk = survey.select(survey.scan_walk == 0)
    assert cross_validate(one_walk, {}, RadioMapParams(), WknnParams()) is None


def test_cross_validation_scores_every_candidate_and_chooses_the_best() -> None:
    survey = _corridor(seed=4)
    validation = cross_validate(
        survey,
        {},
        RadioMapParams(),
        WknnParams(),
        folds=3,
        ks=(1, 2, 8),
        emission=HmmParams(),
        weights=(0.05, 0.3, 1.0),
    )
    assert validation is not None
    assert sorted(validation.by_k) == sorted({1, 2, 8, WknnParams().k})
    means = {k: float(np.mean(h.error_m)) for k, h in validation.by_k.items()}
    assert means[validation.best_k()] == min(means.values())
    assert set(validation.emission_score) == {0.05, 0.3, 1.0}
    assert validation.emission_scans > 0
    best = validation.best_emission_weight()
    assert validation.emission_score[best] == max(validation.emission_score.values())
    assert set(validation.floor_score) == {0.05, 0.3, 1.0}
    # one floor: its scans are on it whatever the weight
    assert all(v == pytest.approx(0.0) for v in validation.floor_score.values())
