"""Scan grouping: readings sharing a time stay one scan; per-reading times are regrouped."""

from __future__ import annotations

import numpy as np

from app.engine.scans import ScanParams, group_scans, scan_ids

PARAMS = ScanParams()


def _scan(t_end: int, tx: list[int], spread_ms: int, rng: np.random.Generator) -> np.ndarray:
    """Return per-reading last-seen times of one scan spread over ``spread_ms`` before its end."""
    return t_end - np.sort(rng.integers(0, spread_ms, size=len(tx)))[::-1]


def test_readings_sharing_a_time_are_one_scan_whatever_their_number() -> None:
    t = np.array([5000] * 30 + [5700] * 20 + [9000] * 3)
    tx = np.concatenate([np.arange(30), np.arange(20), np.arange(3)])
    ids = scan_ids(t, tx, PARAMS)
    assert ids.tolist() == [0] * 30 + [1] * 20 + [2] * 3


def test_per_reading_times_spread_over_a_second_are_regrouped_into_their_scans() -> None:
    rng = np.random.default_rng(3)
    aps = list(range(25))
    truth, times, txs = [], [], []
    for k in range(10):
        # a scan every 2 s whose readings spread over 1.4 s, as site1's phones report them
        heard = sorted(rng.choice(aps, size=18, replace=False).tolist())
        times.append(_scan(10_000 + 2000 * k, heard, 1400, rng))
        txs.append(np.array(heard))
        truth += [k] * len(heard)
    ids = scan_ids(np.concatenate(times), np.concatenate(txs), PARAMS)
    assert ids.tolist() == truth


def test_an_access_point_heard_again_starts_the_next_scan_at_the_largest_gap() -> None:
    # two scans 500 ms apart (less than the silence that always ends a scan)
    t = np.array([1000, 1050, 1100, 1600, 1650, 1700])
    tx = np.array([1, 2, 3, 1, 2, 4])
    assert scan_ids(t, tx, PARAMS).tolist() == [0, 0, 0, 1, 1, 1]


def test_no_scan_spans_longer_than_the_limit() -> None:
    t = np.arange(0, 5000, 400)
    ids = scan_ids(t, np.arange(t.size), PARAMS)
    for g in np.unique(ids):
        span = t[ids == g]
        assert span.max() - span.min() <= PARAMS.max_span_ms


def test_grouping_a_stream_in_pieces_gives_the_scans_of_the_whole() -> None:
    rng = np.random.default_rng(8)
    t = np.sort(rng.integers(0, 20_000, size=300))
    tx = rng.integers(0, 40, size=300)
    whole = [g.tolist() for g in group_scans(t, tx, PARAMS)]
    # a live tracker regroups what remains after taking every scan but the last
    first = group_scans(t[:150], tx[:150], PARAMS)
    taken = [g.tolist() for g in first[:-1]]
    offset = sum(len(g) for g in taken)
    rest = [(g + offset).tolist() for g in group_scans(t[offset:], tx[offset:], PARAMS)]
    assert taken + rest == whole


def test_no_readings_no_scans() -> None:
    assert group_scans(np.zeros(0, np.int64), np.zeros(0, np.int64), PARAMS) == []
