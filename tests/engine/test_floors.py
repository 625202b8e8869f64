"""Floor selection: the patent's E_L ranking, hysteresis against flicker, barometer evidence."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.floors import (
    FloorParams,
    FloorSelector,
    choose_floor,
    floor_scores,
    pressure_climb,
    rank_floors,
    window_sums,
)

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
    selector = FloorSelector(np.array([0, 1]), PARAMS)
    chosen = []
    for k, lead in enumerate(leader):
        floor, rssi, a = _window(lead, 1 - lead)
        chosen.append(int(selector.update(1000 * k, floor, rssi, a)[0]))
    assert chosen == _reference_switch(leader, PARAMS.dwell_windows, PARAMS)
    first = chosen.index(1)
    assert first > 12 + PARAMS.dwell_windows - 1
    assert set(chosen[first:]) == {1}


def test_alternating_leader_does_not_flicker() -> None:
    selector = FloorSelector(np.array([0, 1]), PARAMS)
    chosen = []
    for k in range(30):
        lead = k % 2
        floor, rssi, a = _window(lead, 1 - lead)
        chosen.append(int(selector.update(1000 * k, floor, rssi, a)[0]))
    assert set(chosen) == {0}


def test_climb_in_the_challengers_direction_switches_at_once() -> None:
    # floor 1 is one storey up; pressure falls 0.6 hPa (5 m) in the first window of the climb
    def run(hpa_step: float) -> int:
        selector = FloorSelector(np.array([0, 1]), PARAMS)
        hpa = 1000.0
        for k in range(40):
            lead = 0 if k < 12 else 1
            if k == 12:
                hpa += hpa_step
            floor, rssi, a = _window(lead, 1 - lead)
            if selector.update(1000 * k, floor, rssi, a, np.array([hpa]))[0] == 1:
                return k
        return -1

    flat = run(0.0)
    up = run(-0.6)
    down = run(+0.6)
    no_baro = FloorSelector(np.array([0, 1]), PARAMS)
    plain = -1
    for k in range(40):
        floor, rssi, a = _window(0 if k < 12 else 1, 1 if k < 12 else 0)
        if no_baro.update(1000 * k, floor, rssi, a)[0] == 1:
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
    selector = FloorSelector(np.array([0, 1]), PARAMS)
    out = selector.update(0, np.zeros(0, np.intp), np.zeros(0), np.zeros(0))
    assert out.size == 0 and selector.current == -1
    assert choose_floor(
        np.zeros(0, np.intp), np.full(2, np.nan), np.array([0, 1]), 1, -1, 0, False, 0.0, PARAMS
    ) == (-1, -1, 0)


def test_readings_of_transmitters_without_model_are_ignored_and_snapshot_resumes() -> None:
    selector = FloorSelector(np.array([0, 1]), PARAMS)
    floor, rssi, a = _window(0, 1)
    a = a.copy()
    a[:4] = np.nan
    assert selector.update(0, floor, rssi, a).tolist() == [1]
    twin = FloorSelector(np.array([0, 1]), PARAMS, selector.snapshot())
    for k in range(1, 8):
        f, r, aa = _window(0, 1)
        assert (
            selector.update(1000 * k, f, r, aa).tolist() == twin.update(1000 * k, f, r, aa).tolist()
        )
