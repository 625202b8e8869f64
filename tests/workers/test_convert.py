"""A batch's samples reach the engine sorted by time within each kind, fields kept together."""

from __future__ import annotations

import numpy as np

from app.engine.samples import RssiReadings
from app.workers.convert import _sorted


def _readings(t: list[int]) -> RssiReadings:
    return RssiReadings(
        np.array(t, np.int64), np.arange(len(t), dtype=np.int32), -50.0 - np.arange(len(t))
    )


def test_readings_out_of_order_are_sorted_with_their_fields_and_ties_kept_in_order() -> None:
    out = _sorted(_readings([30, 10, 20, 10]))
    assert out.t.tolist() == [10, 10, 20, 30]
    assert out.tx.tolist() == [1, 3, 2, 0]
    assert out.rssi.tolist() == [-51.0, -53.0, -52.0, -50.0]


def test_readings_in_order_and_empty_ones_are_passed_through() -> None:
    ordered = _readings([10, 10, 20])
    assert _sorted(ordered) is ordered
    empty = _readings([])
    assert _sorted(empty) is empty
