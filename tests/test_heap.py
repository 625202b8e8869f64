"""A started process's objects are kept out of the collector's full passes."""

from __future__ import annotations

import gc

from app.core.heap import settle_heap


def test_objects_alive_at_start_are_frozen_and_later_ones_still_collected() -> None:
    started = [{"site": i} for i in range(1000)]
    try:
        settle_heap()
        assert gc.get_freeze_count() >= len(started)
        frozen = gc.get_freeze_count()
        # a cycle made afterwards is garbage the collector still finds
        later: list[object] = []
        later.append(later)
        del later
        assert gc.collect() >= 1
        assert gc.get_freeze_count() == frozen
    finally:
        gc.unfreeze()
