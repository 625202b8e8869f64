"""Floor selection: the patent's E_L ranking with hysteresis, the forward filter over floors."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.floors.evidence import (
    FloorEvidence,
    map_log_likelihood,
    strongest_means,
    thin_points,
)
from app.engine.floors.forward import FloorFilter, forward_steps, transition_matrix
from app.engine.floors.params import FloorParams
from app.engine.floors.patent import (
    PatentFloorSelector,
    choose_floor,
    floor_scores,
    rank_floors,
    window_sums,
)
from app.engine.floors.pressure import pressure_climb
from app.engine.floors.window import NEVER, FloorWindow
from app.engine.radiomap import RadioMap
from app.workers.snapshots import decode, encode

PARAMS = FloorParams()


def test_scores_match_hand_computed_formula() -> None:
    floor = np.array([0, 0, 1, 2, 2, 2])
    rssi = np.array([-60.0, -70.0, -50.0, -90.0, -90.0, -90.0])
    a = np.array([-40.0, -45.0, -40.0, -45.0, -45.0, -45.0])
    count, s_rssi, s_a = window_sums(floor, rssi, a, 4)
    scores = floor_scores(count, s_rssi, s_a)
    # E_0 = -2²/(-130) - 2/(-85); E_1 = -1/(-50) - 1/(-40); E_2 = -3²/(-270) - 3/(-135)
    expected = [4 / 130 + 2 / 85, 1 / 50 + 1 / 40, 9 / 270 + 3 / 135]
    assert scores[:3] == pytest.approx(expected, rel=1e-12)
    assert np.isnan(scores[3])
    # three weak readings (E_2 = 0.0556) outrank two stronger ones (E_0 = 0.0543)
    assert rank_floors(scores).tolist() == [2, 0, 1]


def test_ranking_breaks_ties_by_floor_index_and_skips_inactive() -> None:
    scores = np.array([np.nan, 0.05, 0.07, 0.05])
    assert rank_floors(scores).tolist() == [2, 1, 3]
    assert rank_floors(np.full(3, np.nan)).size == 0


def _window(strong: int, weak: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Four readings of the strong floor at -60 dBm and two of the weak one at -80 dBm."""
    floor = np.array([strong] * 4 + [weak] * 2)
    rssi = np.array([-60.0] * 4 + [-80.0] * 2)
    return floor, rssi, np.full(6, -45.0)


def _reference_switch(leader: list[int], dwell: int, params: FloorParams) -> list[int]:
    """Second implementation: recompute E_L over the sliding history, apply dwell by hand."""
    current, run, out = -1, 0, []
    history: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    span = params.history_ms // params.window_ms
    for k, lead in enumerate(leader):
        history.append(_window(lead, 1 - lead))
        recent = history[max(0, k + 1 - span) :]
        floor = np.concatenate([h[0] for h in recent])
        rssi = np.concatenate([h[1] for h in recent])
        e = {}
        for f in (0, 1):
            on = floor == f
            n = on.sum()
            e[f] = n * n / -rssi[on].sum() + n / (45.0 * n)
        best = max(e, key=lambda f: (e[f], -f))
        if current < 0:
            current = best
        elif best != current and e[best] >= (1 + params.switch_margin) * e[current]:
            run += 1
            if run >= dwell:
                current, run = best, 0
        else:
            run = 0
        out.append(current)
    return out


def test_switch_waits_for_the_dwell_and_matches_a_second_implementation() -> None:
    leader = [0] * 12 + [1] * 15
    selector = PatentFloorSelector(np.array([0, 1]), PARAMS)
    chosen = []
    for k, lead in enumerate(leader):
        floor, rssi, a = _window(lead, 1 - lead)
        chosen.append(int(selector.update(FloorWindow(1000 * k, floor, rssi, a))[0]))
    assert chosen == _reference_switch(leader, PARAMS.dwell_windows, PARAMS)
    first = chosen.index(1)
    assert first > 12 + PARAMS.dwell_windows - 1
    assert set(chosen[first:]) == {1}


def test_alternating_leader_does_not_flicker() -> None:
    selector = PatentFloorSelector(np.array([0, 1]), PARAMS)
    chosen = []
    for k in range(30):
        lead = k % 2
        floor, rssi, a = _window(lead, 1 - lead)
        chosen.append(int(selector.update(FloorWindow(1000 * k, floor, rssi, a))[0]))
    assert set(chosen) == {0}


def test_climb_in_the_challengers_direction_switches_at_once() -> None:
    # floor 1 is one storey up; pressure falls 0.6 hPa (5 m) in the first window of the climb
    def run(hpa_step: float) -> int:
        selector = PatentFloorSelector(np.array([0, 1]), PARAMS)
        hpa = 1000.0
        for k in range(40):
            lead = 0 if k < 12 else 1
            if k == 12:
                hpa += hpa_step
            floor, rssi, a = _window(lead, 1 - lead)
            window = FloorWindow(1000 * k, floor, rssi, a, pressure_hpa=np.array([hpa]))
            if selector.update(window)[0] == 1:
                return k
        return -1

    flat = run(0.0)
    up = run(-0.6)
    down = run(+0.6)
    no_baro = PatentFloorSelector(np.array([0, 1]), PARAMS)
    plain = -1
    for k in range(40):
        floor, rssi, a = _window(0 if k < 12 else 1, 1 if k < 12 else 0)
        if no_baro.update(FloorWindow(1000 * k, floor, rssi, a))[0] == 1:
            plain = k
            break
    # the climb lets the first leading window win; a flat barometer needs the longer dwell
    assert up < plain < flat
    assert flat - up == PARAMS.flat_dwell_windows - 1
    assert plain - up == PARAMS.dwell_windows - 1
    # a descent is evidence against going up: treated like a flat barometer, never faster
    assert down >= plain


def test_pressure_climb_converts_hpa_to_metres_over_the_window() -> None:
    t = np.array([0, 10_000, 20_000, 40_000])
    hpa = np.array([1000.0, 1000.1, 999.9, 999.5])
    present, climb = pressure_climb(t, hpa, 40_000, PARAMS)
    # only t ≥ 10 s counts: Δh = -(999.5 - 1000.1) / 0.118
    assert present
    assert climb == pytest.approx(0.6 / 0.118)
    assert pressure_climb(t[:1], hpa[:1], 40_000, PARAMS) == (False, 0.0)


def test_no_readings_means_no_floor_and_choose_floor_resets() -> None:
    selector = PatentFloorSelector(np.array([0, 1]), PARAMS)
    out = selector.update(FloorWindow(0, np.zeros(0, np.intp), np.zeros(0), np.zeros(0)))
    assert out.size == 0 and selector.current == -1
    assert choose_floor(
        np.zeros(0, np.intp), np.full(2, np.nan), np.array([0, 1]), 1, -1, 0, False, 0.0, PARAMS
    ) == (-1, -1, 0)


def test_readings_of_transmitters_without_model_are_ignored_and_snapshot_resumes() -> None:
    selector = PatentFloorSelector(np.array([0, 1]), PARAMS)
    floor, rssi, a = _window(0, 1)
    a = a.copy()
    a[:4] = np.nan
    assert selector.update(FloorWindow(0, floor, rssi, a)).tolist() == [1]
    twin = PatentFloorSelector(np.array([0, 1]), PARAMS, selector.snapshot())
    for k in range(1, 8):
        f, r, aa = _window(0, 1)
        assert (
            selector.update(FloorWindow(1000 * k, f, r, aa)).tolist()
            == twin.update(FloorWindow(1000 * k, f, r, aa)).tolist()
        )


# --- the forward filter over floors ---------------------------------------------------


def _tiny_map(floor: int, tx: list[int], mean: list[list[float]]) -> RadioMap:
    """A radio map with one reference point per row of ``mean`` (NaN: never heard there)."""
    m = np.array(mean, np.float32)
    n = m.shape[0]
    return RadioMap(
        floor=floor,
        cell=1.0,
        origin=np.zeros(2),
        shape=(1, n),
        ij=np.stack([np.zeros(n), np.arange(n)], axis=1).astype(np.int32),
        tx=np.array(tx, np.int32),
        mean=m,
        var=np.full(m.shape, 16.0, np.float32),
        detect=np.full(m.shape, 0.9, np.float32),
        weight=np.ones(n, np.float32),
    )


def test_strongest_means_average_each_devices_top_k_per_floor_padding_missing() -> None:
    device = np.array([0, 0, 0, 0, 1, 1])
    floor = np.array([0, 0, 0, 1, 1, 1])
    rssi = np.array([-50.0, -70.0, -60.0, -80.0, -65.0, -75.0])
    got = strongest_means(device, floor, rssi, 3, 2, 2, -100.0)
    # device 0: floor 0 keeps -50, -60; floor 1 has -80 and one missing
    # device 1: floor 0 has none; floor 1 keeps -65, -75; device 2 heard nothing
    expected = [[-55.0, -90.0], [-100.0, -70.0], [-100.0, -100.0]]
    assert got == pytest.approx(np.array(expected), abs=1e-12)


def test_map_log_likelihood_is_a_floored_gaussian_summed_per_device() -> None:
    rssi = np.array([-60.0, -70.0, -50.0])
    mean = np.array([[-62.0, -90.0], [-70.0, -70.0], [-56.0, -50.0]], np.float32)
    got = map_log_likelihood(rssi, mean.copy(), np.array([0, 2]), 4.0, 2.0)
    # ℓ = max(-(s - μ)² / 32, -2): device 0 = readings 0-1, device 1 = reading 2
    expected = [[-4 / 32 + 0.0, -2.0 + 0.0], [-36 / 32, 0.0]]
    assert got == pytest.approx(np.array(expected), abs=1e-6)


def test_thin_points_keep_the_most_surveyed_point_of_each_block() -> None:
    ij = np.array([[0, 0], [0, 1], [1, 1], [0, 2], [3, 3]])
    weight = np.array([1.0, 5.0, 2.0, 9.0, 1.0])
    # 2 × 2 blocks: {0, 1, 2} → 1 (weight 5), {3} → 3, {4} → 4
    assert thin_points(ij, weight, 1.0, 2.0).tolist() == [1, 3, 4]
    assert thin_points(ij, weight, 1.0, 1.0).tolist() == [0, 1, 2, 3, 4]


def _reference_evidence(
    tx: np.ndarray, rssi: np.ndarray, tx_floor: np.ndarray, maps: list[RadioMap], p: FloorParams
) -> np.ndarray:
    """Second implementation, one device, loops: s̄_f / τ + w ln mean_j Π_a L(s_a | j)."""
    out = []
    for f, m in enumerate(maps):
        on = np.sort(rssi[tx_floor[tx] == f])[::-1][: p.strongest_k]
        padded = list(on) + [p.missing_dbm] * (p.strongest_k - on.size)
        score = float(np.mean(padded)) / p.strength_temperature_db
        point_ll = []
        for j in range(m.n_points):
            total = 0.0
            for a, s in zip(tx, rssi, strict=True):
                col = np.flatnonzero(m.tx == a)
                mu = m.mean[j, col[0]] if col.size else np.nan
                mu = mu if np.isfinite(mu) else p.unheard_dbm
                total += max(-0.5 * ((s - mu) / p.map_sigma_db) ** 2, -p.map_outlier_nats)
            point_ll.append(total)
        score += p.map_weight * float(np.log(np.mean(np.exp(point_ll))))
        out.append(score)
    return np.array(out)


def test_evidence_matches_a_second_implementation_for_each_device_of_a_batch() -> None:
    p = FloorParams(map_block_m=1.0)
    tx_floor = np.array([0, 0, 1, 1])
    maps = [
        _tiny_map(0, [0, 1, 2], [[-50, -70, -85], [-65, np.nan, -80]]),
        _tiny_map(1, [1, 2, 3], [[-80, -55, -60], [-90, -60, np.nan], [np.nan, -70, -50]]),
    ]
    evidence = FloorEvidence(tx_floor, 2, p, maps)
    assert evidence.uses_maps
    # device 0 near floor 0's first point, device 1 silent, device 2 on floor 1
    device = np.array([0, 0, 0, 2, 2, 2, 2])
    tx = np.array([0, 1, 2, 3, 2, 0, 2])
    rssi = np.array([-52.0, -72.0, -84.0, -52.0, -58.0, -88.0, -60.0])
    got = evidence.log_likelihood(device, tx, rssi, 3)
    assert got[0] == pytest.approx(_reference_evidence(tx[:3], rssi[:3], tx_floor, maps, p))
    assert got[1].tolist() == [0.0, 0.0]
    # device 2 heard transmitter 2 twice: it counts once, at the mean -59 dBm
    tx2, rssi2 = np.array([0, 2, 3]), np.array([-88.0, -59.0, -52.0])
    assert got[2] == pytest.approx(_reference_evidence(tx2, rssi2, tx_floor, maps, p))
    assert np.argmax(got[0]) == 0 and np.argmax(got[2]) == 1
    # a device's evidence does not depend on its batch mates
    alone = evidence.log_likelihood(np.zeros(4, np.intp), tx[3:], rssi[3:], 1)
    assert alone[0] == pytest.approx(got[2])


def test_evidence_uses_the_maps_only_when_every_floor_has_one() -> None:
    p = FloorParams()
    tx_floor = np.array([0, 1])
    maps = [_tiny_map(0, [0, 1], [[-50, -90]])]
    partial = FloorEvidence(tx_floor, 2, p, maps)
    table_only = FloorEvidence(tx_floor, 2, p)
    assert not partial.uses_maps
    args = (np.array([0, 0]), np.array([0, 1]), np.array([-60.0, -75.0]), 1)
    assert partial.log_likelihood(*args) == pytest.approx(table_only.log_likelihood(*args))
    # with the table alone: (s̄_0 - s̄_1) / τ = ((-60 - 200) - (-75 - 200)) / 3 / τ
    got = table_only.log_likelihood(*args)[0]
    assert got[0] - got[1] == pytest.approx(15.0 / 3.0 / p.strength_temperature_db)


def test_transition_rows_are_distributions_and_a_climb_favours_its_direction() -> None:
    levels = np.array([-1, 0, 1, 2])
    T = transition_matrix(levels, 0.003, 0.0, 0.2, 2.0)
    assert T.sum(axis=1) == pytest.approx(np.ones(4))
    assert T[1, 1] == pytest.approx(0.997) and T[1, 3] == pytest.approx(0.001)
    up = transition_matrix(levels, 0.003, 4.0, 0.2, 2.0)
    assert up.sum(axis=1) == pytest.approx(np.ones(4))
    # from level 0: levels 1 and 2 share the climb, level -1 (against it) gets ε
    assert up[1].tolist() == pytest.approx([0.003, 0.797, 0.1, 0.1])
    # from the top floor no floor lies upwards: the climb changes nothing
    assert up[3].tolist() == pytest.approx([0.001, 0.001, 0.001, 0.997])
    # a climb below climb_min_m is no climb
    assert transition_matrix(levels, 0.003, 1.5, 0.2, 2.0) == pytest.approx(T)


def test_forward_step_matches_hand_computed_posterior() -> None:
    T = transition_matrix(np.array([0, 1]), 0.1, 0.0, 0.0, 2.0)
    b = forward_steps(np.array([[0.8, 0.2]]), T[None], np.array([[0.0, np.log(3.0)]]))[0]
    # π = (0.8 · 0.9 + 0.2 · 0.1, 0.8 · 0.1 + 0.2 · 0.9) = (0.74, 0.26); b ∝ (0.74, 0.78)
    assert b == pytest.approx([0.74 / 1.52, 0.78 / 1.52])
    # two windows: π = b T²
    b2 = forward_steps(np.array([[1.0, 0.0]]), (T @ T)[None], np.zeros((1, 2)))[0]
    assert b2 == pytest.approx([0.82, 0.18])


def _evidence_for(floor: int, lead_db: float) -> tuple[np.ndarray, np.ndarray]:
    """Log-likelihood and heard counts of a window whose floor ``floor`` leads by ``lead_db``."""
    p = FloorParams()
    strong = np.array([-60.0] * 3)
    weak = strong - lead_db
    rssi = np.concatenate([strong, weak]) if floor == 0 else np.concatenate([weak, strong])
    tx = np.arange(6)
    evidence = FloorEvidence(np.repeat([0, 1], 3), 2, p)
    return evidence.log_likelihood(np.zeros(6, np.intp), tx, rssi, 1)[0], np.array([3, 3])


def _filter_window(
    t: int, loglik: np.ndarray, heard: np.ndarray, pressure: np.ndarray | None = None
) -> FloorWindow:
    """A window with the evidence ``loglik`` and ``heard[f]`` readings of floor f's transmitters."""
    floor = np.repeat(np.arange(len(heard)), np.asarray(heard, int))
    rssi, a = np.full(floor.size, -60.0), np.full(floor.size, -45.0)
    return FloorWindow(t, floor, rssi, a, loglik, pressure)


def _run_filter(
    leaders: list[int], lead_db: float, hpa: list[float] | None = None, params: FloorParams = PARAMS
) -> list[int]:
    """Chosen floor per window of a filter fed windows led by ``leaders`` (one storey apart)."""
    f = FloorFilter(np.array([0, 1]), params)
    chosen = []
    for k, lead in enumerate(leaders):
        ll, heard = _evidence_for(lead, lead_db)
        pressure = None if hpa is None else np.array([hpa[k]])
        chosen.append(int(f.update(_filter_window(1000 * k, ll, heard, pressure))[0]))
    return chosen


def test_filter_follows_a_real_change_within_a_few_windows_and_stays() -> None:
    # 10 dB ahead on every window: 2.5 nats each against ln((1 - ε) / ε) ≈ 6.9
    chosen = _run_filter([0] * 20 + [1] * 20, 10.0)
    assert chosen[:20] == [0] * 20
    switch = chosen.index(1)
    # needs ⌈6.9 / 2.5⌉ = 3 windows, no sooner: the first contrary ones are not trusted
    assert switch == 20 + 2
    assert chosen[switch:] == [1] * (40 - switch)


def test_filter_does_not_flicker_on_single_contrary_windows() -> None:
    # a loud contrary window (20 dB, 5 nats) every fourth window
    leaders = [1 if k % 4 == 3 else 0 for k in range(40)]
    assert set(_run_filter(leaders, 20.0)[1:]) == {0}
    # once a floor is established, alternating leaders carry no net evidence
    assert set(_run_filter([0] * 5 + [k % 2 for k in range(30)], 10.0)) == {0}


def test_climb_lets_the_first_scan_decide_and_a_flat_barometer_waits_longer() -> None:
    leaders = [0] * 20 + [1] * 20
    flat = [1000.0] * 40
    # pressure falls 0.6 hPa (5 m up) at the change, rises as much for a descent
    up = [1000.0] * 20 + [999.4] * 20
    down = [1000.0] * 20 + [1000.6] * 20
    at = {
        name: _run_filter(leaders, 10.0, hpa).index(1)
        for name, hpa in (("none", None), ("flat", flat), ("up", up), ("down", down))
    }
    assert at["up"] == 20
    assert at["none"] < at["flat"]
    # a descent is evidence against going up: never faster than a flat barometer
    assert at["down"] >= at["flat"]


def test_filter_without_readings_in_the_history_has_no_floor_but_keeps_its_belief() -> None:
    f = FloorFilter(np.array([0, 1]), PARAMS)
    for k in range(5):
        ll, heard = _evidence_for(1, 20.0)
        assert f.update(_filter_window(1000 * k, ll, heard)).tolist() == [1, 0]
    # 15 s later, a window without readings: nothing heard within 10 s
    assert f.update(_filter_window(20_000, np.zeros(2), np.zeros(2))).size == 0
    assert f.current == -1 and f.belief[1] > 0.9
    ll, heard = _evidence_for(1, 0.0)
    assert f.update(_filter_window(21_000, ll, heard))[0] == 1


def test_filter_ranks_the_chosen_floor_then_active_floors_by_belief() -> None:
    f = FloorFilter(np.array([0, 1, 2]), PARAMS)
    ll = np.array([0.0, 5.0, 2.0])
    # floor 2 not heard: only floors 0 and 1 are active
    assert f.update(_filter_window(0, ll, np.array([2, 1, 0]))).tolist() == [1, 0]
    assert f.update(_filter_window(1000, ll, np.array([2, 1, 1]))).tolist() == [1, 2, 0]


def test_filter_snapshot_round_trips_through_the_codec_and_resumes_exactly() -> None:
    f = FloorFilter(np.array([0, 1]), PARAMS)
    for k in range(12):
        ll, heard = _evidence_for(k // 6, 10.0)
        f.update(_filter_window(1000 * k, ll, heard, np.array([1000.0 - 0.01 * k])))
    twin = FloorFilter(np.array([0, 1]), PARAMS, decode(encode({"floors": f.snapshot()}))["floors"])
    for k in range(12, 30):
        ll, heard = _evidence_for(1 if k < 20 else 0, 10.0)
        pressure = np.array([1000.0 - 0.01 * k])
        assert f.update(_filter_window(1000 * k, ll, heard, pressure)).tolist() == (
            twin.update(_filter_window(1000 * k, ll, heard, pressure)).tolist()
        )
        assert f.belief.tolist() == twin.belief.tolist()


def test_a_snapshot_with_the_ring_of_heard_counts_resumes_with_each_floors_last_time() -> None:
    ring = {
        "belief": np.array([0.2, 0.8]),
        "last_t": 3000,
        "t": np.array([1000, 2000, 3000, NEVER]),
        "heard": np.array([[2.0, 0.0], [0.0, 1.0], [1.0, 0.0], [0.0, 0.0]]),
        "pos": 3,
        "current": 1,
    }
    f = FloorFilter(np.array([0, 1]), PARAMS, ring)
    assert f.heard_t.tolist() == [3000, 2000]
    # at 12 s floor 0 (heard at 3 s) is still active, floor 1 (2 s) is not but leads the belief
    assert f.update(_filter_window(12_000, np.zeros(2), np.zeros(2))).tolist() == [1, 0]
    assert f.update(_filter_window(13_000, np.zeros(2), np.zeros(2))).size == 0


def test_filters_updated_together_end_where_each_alone_would() -> None:
    levels = np.array([0, 1, 2])
    alone = [FloorFilter(levels, PARAMS) for _ in range(3)]
    together = [FloorFilter(levels, PARAMS) for _ in range(3)]
    rng = np.random.default_rng(3)
    for k in range(15):
        # device 1 skips windows (a gap), device 2 climbs a storey at 8 s
        windows = [
            _filter_window(1000 * k, rng.normal(0.0, 2.0, 3), rng.integers(0, 3, 3))
            for _ in range(3)
        ]
        hpa = np.array([1000.0 - (0.6 if k >= 8 else 0.0)])
        windows[2] = FloorWindow(**{**vars(windows[2]), "pressure_hpa": hpa})
        due = [0, 2] if k % 3 else [0, 1, 2]
        expected = [alone[i].update(windows[i]).tolist() for i in due]
        got = FloorFilter.update_many([together[i] for i in due], [windows[i] for i in due])
        assert [r.tolist() for r in got] == expected
        assert [together[i].belief.tolist() for i in due] == [alone[i].belief.tolist() for i in due]


def test_a_reading_of_a_transmitter_on_no_floor_makes_no_floor_heard() -> None:
    first, second = FloorFilter(np.array([0, 1]), PARAMS), FloorFilter(np.array([0, 1]), PARAMS)
    nothing = np.zeros(0)
    windows = [
        FloorWindow(0, nothing.astype(np.intp), nothing, nothing, np.zeros(2)),
        FloorWindow(0, np.array([-1]), np.array([-60.0]), np.array([-45.0]), np.zeros(2)),
    ]
    ranked = FloorFilter.update_many([first, second], windows)
    # the second device's unplaced reading counts on no floor, not on the first device's
    assert first.heard_t.tolist() == [NEVER, NEVER] and second.heard_t.tolist() == [NEVER, NEVER]
    assert ranked[0].size == 0 and ranked[1].size == 0
