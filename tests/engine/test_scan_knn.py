"""Per-scan k-NN against survey scans, and the HMM emission and radius built on it.

A corridor 40 m long is surveyed every metre by a phone hearing path-loss
transmitters; the scan k-NN must find scans from a second walk where they
were made, compare scans only on what both heard, and travel with the radio
map through storage so the HMM can use it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.params import HmmParams
from app.engine.hmm.tracker import HmmTracker
from app.engine.plan import FloorPlan
from app.engine.radiomap import RadioMapParams, Survey, build_radio_map
from app.engine.samples import Batch, Estimate, RssiReadings
from app.engine.scan_knn import ReferenceScans, ScanKnnParams
from app.radiomaps.codec import decode_map, encode_map

TX_X = np.array([0.0, 10.0, 20.0, 30.0, 40.0])
"""Transmitters along the corridor, 2 m off its axis."""


def _heard(x: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Transmitters heard at ``x`` (within 25 m) and their RSSI, -40 - 25 log10(r) ± 2 dB."""
    r = np.hypot(TX_X - x, 2.0)
    on = r < 25.0
    rssi = -40.0 - 25.0 * np.log10(r[on]) + rng.normal(0.0, 2.0, int(on.sum()))
    return np.flatnonzero(on), rssi


def _walk(xs: np.ndarray, rng: np.random.Generator, walk: int) -> Survey:
    scan, tx, rssi = [], [], []
    for i, x in enumerate(xs):
        t, r = _heard(float(x), rng)
        scan += [i] * t.size
        tx += t.tolist()
        rssi += r.tolist()
    n = xs.size
    return Survey(
        scan_t=np.arange(n, dtype=np.int64) * 1000,
        scan_xy=np.stack([xs, np.full(n, 1.0)], axis=1),
        scan_floor=np.zeros(n, dtype=np.int32),
        scan_walk=np.full(n, walk, dtype=np.int32),
        reading_scan=np.array(scan, dtype=np.int32),
        reading_tx=np.array(tx, dtype=np.int32),
        reading_rssi=np.array(rssi, dtype=float),
    )


@pytest.fixture(scope="module")
def survey() -> Survey:
    rng = np.random.default_rng(3)
    xs = np.arange(0.0, 40.5, 1.0)
    return Survey.concat([_walk(xs, rng, 0), _walk(xs + 0.5, rng, 1)])


def test_a_scan_is_located_where_it_was_made(survey: Survey) -> None:
    refs = ReferenceScans(survey, n_tx=TX_X.size, params=ScanKnnParams(min_heard=1))
    rng = np.random.default_rng(11)
    errors = []
    for x in (3.3, 12.7, 25.2, 36.0):
        tx, rssi = _heard(x, rng)
        fix = refs.locate(tx, rssi, k=4)
        assert fix is not None and fix.floor == 0
        errors.append(abs(fix.xy[0] - x))
    assert max(errors) < 3.0


def test_what_only_one_scan_heard_is_a_penalty_and_unsurveyed_transmitters_say_nothing(
    survey: Survey,
) -> None:
    refs = ReferenceScans(survey, n_tx=TX_X.size + 1, params=ScanKnnParams(min_heard=1))
    rng = np.random.default_rng(2)
    tx, rssi = _heard(20.0, rng)
    full = refs.distances(tx, rssi)
    # dropping one transmitter every nearby survey scan heard makes them all match worse
    partial = refs.distances(tx[1:], rssi[1:])
    near = np.abs(refs.xy[:, 0] - 20.0) < 2.0
    assert np.all(partial[near] > full[near])
    # a transmitter no survey scan heard changes nothing
    extra = refs.distances(np.r_[tx, TX_X.size], np.r_[rssi, -70.0])
    assert extra == pytest.approx(full)
    # a query that shares nothing with the survey has no distance and no fix
    assert np.isinf(refs.distances(np.array([TX_X.size]), np.array([-50.0]))).all()
    assert refs.locate(np.array([TX_X.size]), np.array([-50.0])) is None


def test_rarely_heard_transmitters_are_left_out(survey: Survey) -> None:
    refs = ReferenceScans(survey, n_tx=TX_X.size, params=ScanKnnParams(min_heard=10**6))
    assert not refs.usable.any()
    assert refs.locate(np.array([0]), np.array([-50.0])) is None


def test_maps_carry_their_survey_scans_through_storage(survey: Survey) -> None:
    m = build_radio_map(survey, 0, RadioMapParams(min_scans=1))
    assert m.references is not None and m.references.xy.shape == (survey.n_scans, 2)
    back = decode_map(encode_map(m))
    assert back.references is not None
    for key in ("xy", "walk", "scan", "col", "rssi"):
        assert np.array_equal(getattr(back.references, key), getattr(m.references, key))
    # the readings name map columns: the map's transmitters give them back
    assert np.array_equal(
        np.sort(back.tx[back.references.col]), np.sort(survey.reading_tx.astype(np.int32))
    )


def test_the_hmm_emission_peaks_where_the_scan_was_made(survey: Survey) -> None:
    m = build_radio_map(survey, 0, RadioMapParams(min_scans=1))
    model = EmissionModel([m], HmmParams())
    assert model.references is not None
    rng = np.random.default_rng(5)
    tx, rssi = _heard(17.0, rng)
    (ll,) = model.log_likelihoods(tx, rssi)
    assert ll.shape == (m.n_points,) and np.all(ll <= 0.0)
    assert abs(m.xy[int(np.argmax(ll)), 0] - 17.0) < 3.0
    # the restart's k-NN position uses the same survey scans
    assert abs(model.knn(0, tx, rssi, 4)[0] - 17.0) < 3.0
    # a scan sharing nothing with the survey is no evidence
    (flat,) = model.log_likelihoods(np.array([TX_X.size + 3]), np.array([-60.0]))
    assert np.all(flat == 0.0)


def test_the_pooled_emission_and_floor_marginals_follow_their_formulas(survey: Survey) -> None:
    # floor 1 is the same corridor heard 45 dB louder: every scan there is far in signal space
    loud = replace(
        survey,
        scan_floor=np.ones(survey.n_scans, dtype=np.int32),
        reading_rssi=survey.reading_rssi + 45.0,
    )
    maps = [build_radio_map(s, f, RadioMapParams(min_scans=1)) for f, s in ((0, survey), (1, loud))]
    params = HmmParams(emission_weight=0.1, floor_weight=0.2, knn_max_db=30.0)
    model = EmissionModel(maps, params)
    assert model.references is not None
    tx, rssi = _heard(12.0, np.random.default_rng(9))
    d = model.references.distances(tx, rssi)
    lls = model.log_likelihoods(tx, rssi)
    marginal = model.floor_log_marginals(tx, rssi)
    # e_s = exp(-(d_s - d_min) / τ)
    e = np.exp(-(d - d.min()) / params.knn_pool_db)
    capped = -params.emission_weight * params.knn_nats_per_db * params.knn_max_db
    for f, m in enumerate(maps):
        block = model.ref_blocks[f]
        scans = model.references.xy[block]
        # K_js ∝ exp(-|x_j - x_s|² / 2b²) over the scans within the radius
        r2 = np.sum((m.xy[:, None] - scans[None]) ** 2, axis=2)
        kernel = np.where(r2 <= params.knn_radius_m**2, np.exp(-0.5 * r2 / params.knn_pool_m**2), 0)
        kernel /= kernel.sum(axis=1, keepdims=True)
        excess = np.minimum(-params.knn_pool_db * np.log(kernel @ e[block]), params.knn_max_db)
        by_hand = -params.emission_weight * params.knn_nats_per_db * excess
        if f == 1:
            # every scan of the loud floor is past the cap: the whole floor is capped
            assert d[block].min() > d.min() + params.knn_max_db
            by_hand = np.full(m.n_points, capped)
        assert lls[f] == pytest.approx(by_hand, abs=1e-9)
        # ln mean_j L_j^(w_f / w)
        tempered = params.floor_weight / params.emission_weight * by_hand
        assert marginal[f] == pytest.approx(np.log(np.mean(np.exp(tempered))), abs=1e-9)
    assert marginal[0] > marginal[1]


def test_the_distance_is_the_mean_difference_on_shared_transmitters_plus_the_unshared_penalty() -> (
    None
):
    # scan 0 hears tx 0 at -60 (and a weaker repeat at -90, ignored) and tx 1 at -70;
    # scan 1 hears tx 1 at -80 and tx 2 at -50; levels are dB above -100
    survey = Survey(
        scan_t=np.array([0, 1000], dtype=np.int64),
        scan_xy=np.array([[0.0, 0.0], [10.0, 0.0]]),
        scan_floor=np.zeros(2, dtype=np.int32),
        scan_walk=np.array([0, 1], dtype=np.int32),
        reading_scan=np.array([0, 0, 0, 1, 1], dtype=np.int32),
        reading_tx=np.array([0, 0, 1, 1, 2], dtype=np.int32),
        reading_rssi=np.array([-60.0, -90.0, -70.0, -80.0, -50.0]),
    )
    params = ScanKnnParams(min_heard=1, rarity_power=0.0, unshared_penalty=50.0)
    refs = ReferenceScans(survey, n_tx=3, params=params)
    d = refs.distances(np.array([0, 1]), np.array([-65.0, -70.0]))
    # scan 0 shares both: (|35 - 40| + |30 - 30|) / 2, and all the signal is shared
    # scan 1 shares tx 1: |30 - 20|, shared (20 + 30) / (70 + 65) of the signal
    assert d == pytest.approx([2.5, 10.0 + 50.0 * (1.0 - 50.0 / 135.0) ** 2])


def test_with_a_level_power_strong_shared_transmitters_weigh_more() -> None:
    # the query hears tx 0 strongly (-50) and tx 1 near the floor (-90); the survey scan
    # heard tx 0 at -60 and tx 1 at -70: levels 50 against 40, 10 against 30
    survey = Survey(
        scan_t=np.array([0], dtype=np.int64),
        scan_xy=np.array([[0.0, 0.0]]),
        scan_floor=np.zeros(1, dtype=np.int32),
        scan_walk=np.array([0], dtype=np.int32),
        reading_scan=np.array([0, 0], dtype=np.int32),
        reading_tx=np.array([0, 1], dtype=np.int32),
        reading_rssi=np.array([-60.0, -70.0]),
    )
    base = ScanKnnParams(min_heard=1, rarity_power=0.0, unshared_penalty=0.0)
    query = (np.array([0, 1]), np.array([-50.0, -90.0]))
    plain = ReferenceScans(survey, 2, base).distances(*query)
    # w = (1 + (s + r) / 2)^g: 46 for tx 0, 21 for tx 1
    by_level = ReferenceScans(survey, 2, replace(base, level_power=1)).distances(*query)
    squared = ReferenceScans(survey, 2, replace(base, level_power=2)).distances(*query)
    assert plain == pytest.approx([(10.0 + 20.0) / 2])
    assert by_level == pytest.approx([(46 * 10.0 + 21 * 20.0) / (46 + 21)])
    assert squared == pytest.approx([(46**2 * 10.0 + 21**2 * 20.0) / (46**2 + 21**2)])
    with pytest.raises(ValueError, match="level_power"):
        ReferenceScans(survey, 2, replace(base, level_power=3))


def test_the_hmm_knn_fix_is_a_mixture_at_the_scans_neighbours_relative_to_its_peak(
    survey: Survey,
) -> None:
    m = build_radio_map(survey, 0, RadioMapParams(min_scans=1))
    params = HmmParams(fix_nats=10.0, fix_sigma_m=4.0, fix_max_nats=5.0)
    model = EmissionModel([m], params)
    tx, rssi = _heard(25.0, np.random.default_rng(8))
    near = model.scan_neighbours(0, tx, rssi)
    assert near is not None
    centres, weight = near
    fix = model.fix_log_density(0, tx, rssi)
    assert fix is not None and fix.shape == (m.n_points,)

    def density(x: np.ndarray) -> np.ndarray:
        d2 = np.sum((x[:, None] - centres[None]) ** 2, axis=2)
        return np.exp(-0.5 * d2 / 4.0**2) @ weight

    # w c ln(f(x) / max_i f(c_i)), floored c_max below the peak
    peak = density(centres).max()
    by_hand = np.maximum(np.log(density(m.xy) / peak), -5.0) * 0.2 * 10.0
    assert fix == pytest.approx(by_hand, abs=1e-9)
    # it peaks among the neighbours, near where the scan was made, and rules nothing out
    assert abs(m.xy[int(np.argmax(fix)), 0] - 25.0) < 3.0
    assert fix.min() == pytest.approx(-5.0 * 0.2 * 10.0)
    # on a subset of points it gives the same values
    some = np.array([0, 7, 30])
    assert model.fix_log_density(0, tx, rssi, some) == pytest.approx(fix[some])
    # switched off, or for a scan that shares nothing with the survey: none
    off = EmissionModel([m], HmmParams(fix_nats=0.0))
    assert off.fix_log_density(0, tx, rssi) is None
    assert model.fix_log_density(0, np.array([TX_X.size + 3]), np.array([-60.0])) is None


def test_the_hmm_radius_grows_with_the_scans_distance_to_the_nearest_survey_scan(
    survey: Survey,
) -> None:
    m = build_radio_map(survey, 0, RadioMapParams(min_scans=1))
    rng = np.random.default_rng(9)
    scans = [_heard(10.0 + 0.7 * k, rng) for k in range(6)]
    model = EmissionModel([m], HmmParams())
    assert model.references is not None
    tx, rssi = scans[-1]
    nearest = model.references.distances(tx, rssi).min()
    assert model.best_match(0, tx, rssi) == pytest.approx(nearest)

    def run(params: HmmParams) -> list[Estimate]:
        tracker = HmmTracker(EmissionModel([m], params), params)
        out = []
        for k, (tx, rssi) in enumerate(scans):
            t = np.full(tx.size, 1000 * k, dtype=np.int64)
            out += tracker.process(Batch(rssi=RssiReadings(t, tx.astype(np.int32), rssi)))
        return out

    typical = run(HmmParams(min_accuracy_m=0.01, radius_match_db=6.0, radius_match_min_db=0.1))
    half = run(HmmParams(min_accuracy_m=0.01, radius_match_db=3.0, radius_match_min_db=0.1))
    assert [(e.x, e.y) for e in half] == [(e.x, e.y) for e in typical]
    # the radius is the posterior's, times best match / typical match
    assert [e.accuracy for e in half] == pytest.approx([2.0 * e.accuracy for e in typical])
    # without survey scans the radius is the posterior's alone
    assert model.best_match(0, np.array([TX_X.size + 3]), np.array([-60.0])) is None


def test_the_level_offset_is_the_median_difference_on_shared_transmitters(survey: Survey) -> None:
    refs = ReferenceScans(survey, n_tx=TX_X.size, params=ScanKnnParams(min_heard=1))
    tx, rssi = _heard(12.0, np.random.default_rng(6))
    near = np.flatnonzero(np.abs(refs.xy[:, 0] - 12.0) < 1.0)
    base = refs.level_offset(tx, rssi, near)
    assert base is not None and abs(base) < 3.0
    # the same scan heard 7 dB louder differs from the same survey scans by 7 dB more
    louder = refs.level_offset(tx, rssi + 7.0, near)
    assert louder == pytest.approx(base + 7.0)
    # nothing shared: no offset
    assert refs.level_offset(np.array([TX_X.size + 1]), np.array([-50.0]), near) is None


def test_the_hmm_learns_a_phones_rssi_offset_and_a_survey_like_phone_keeps_none(
    survey: Survey,
) -> None:
    m = build_radio_map(survey, 0, RadioMapParams(min_scans=1))
    params = HmmParams()
    model = EmissionModel([m], params)

    def offset_after_walk(shift_db: float) -> float:
        tracker = HmmTracker(model, params)
        rng = np.random.default_rng(12)
        for k, x in enumerate(np.linspace(5.0, 35.0, 40)):
            tx, rssi = _heard(float(x), rng)
            t = np.full(tx.size, 1000 * k, dtype=np.int64)
            tracker.process(Batch(rssi=RssiReadings(t, tx.astype(np.int32), rssi + shift_db)))
        return tracker.rssi_offset

    # 40 scans against a prior worth 10: about four fifths of the true 8 dB
    assert 4.5 < offset_after_walk(8.0) < 8.5
    assert 4.5 < -offset_after_walk(-8.0) < 8.5
    assert abs(offset_after_walk(0.0)) < 1.5


def _open_floor() -> FloorPlan:
    """A hall 50 m by 14 m, free everywhere, around the surveyed corridor (y = 1)."""
    free = np.ones((28, 100), dtype=bool)
    return FloorPlan.from_raster(origin=np.array([-5.0, -4.0]), cell=0.5, free=free)


def test_points_reach_past_the_survey_scored_as_the_survey_nearest_them(survey: Survey) -> None:
    plan = _open_floor()
    m = build_radio_map(survey, 0, RadioMapParams(min_scans=1), walkable=plan)
    params = HmmParams(reach_m=8.0)
    model = EmissionModel([m], params, plans={0: plan})
    (wide,) = model.maps
    # the map's own points first and unchanged, then cells past its 3 m, up to 8 m
    assert model.surveyed_points == [m.n_points] and wide.n_points > m.n_points
    assert np.array_equal(wide.ij[: m.n_points], m.ij)
    added = wide.xy[m.n_points :]
    reach = np.min(np.hypot(*(added[:, None] - survey.scan_xy[None]).transpose(2, 0, 1)), axis=1)
    assert reach.min() > 2.5 and reach.max() <= 8.0
    # without a plan, or with no reach, the points are the map's
    assert EmissionModel([m], params).maps[0] is m
    assert EmissionModel([m], replace(params, reach_m=0.0), {0: plan}).maps[0] is m

    rng = np.random.default_rng(5)
    tx, rssi = _heard(17.0, rng)
    (ll,) = model.log_likelihoods(tx, rssi)
    (own,) = EmissionModel([m], params).log_likelihoods(tx, rssi)
    # the map's own points score as before; the best point is still where the scan was made
    assert ll[: m.n_points] == pytest.approx(own)
    assert abs(wide.xy[int(np.argmax(ll)), 0] - 17.0) < 3.0
    # points straight across the hall from x = 17 score as the survey scans near x = 17,
    # points across from the far end as those at the far end: the worse match
    across = [
        int(np.argmin(np.hypot(wide.xy[:, 0] - x, wide.xy[:, 1] - 8.0))) for x in (17.25, 39.75)
    ]
    assert all(i >= m.n_points for i in across)
    nearest = [int(np.argmin(np.hypot(*(m.xy - wide.xy[i]).T))) for i in across]
    assert ll[across] == pytest.approx(own[nearest], abs=1.5)
    assert ll[across[0]] > ll[across[1]]


def test_points_reaching_past_the_survey_do_not_weigh_the_floors(survey: Survey) -> None:
    plan = _open_floor()
    m = build_radio_map(survey, 0, RadioMapParams(min_scans=1), walkable=plan)
    other = build_radio_map(
        replace(survey, scan_floor=np.ones(survey.n_scans, np.int32)),
        1,
        RadioMapParams(min_scans=1),
    )
    params = HmmParams(reach_m=8.0)
    rng = np.random.default_rng(9)
    tx, rssi = _heard(20.0, rng)
    beliefs = []
    for plans in (None, {0: plan}):
        tracker = HmmTracker(EmissionModel([m, other], params, plans), params)
        for k in range(3):
            t = np.full(tx.size, 1000 * k, np.int64)
            tracker.process(Batch(rssi=RssiReadings(t=t, tx=tx, rssi=rssi)))
        beliefs.append(tracker.floor_logp)
    # floor 1 (no plan) is the same survey: the floors tie, however far floor 0's points reach
    assert beliefs[1] == pytest.approx(beliefs[0])
