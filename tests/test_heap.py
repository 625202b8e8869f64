"""A started process's objects are kept out of the collector's full passes."""

from __future__ import annotations

import gc
import weakref

from app.core.heap import settle_heap


class _Node:
    """An object that can sit in a reference cycle."""

    def __init__(self) -> None:
        self.me: _Node | None = None


def test_objects_alive_at_start_are_frozen_and_later_ones_still_collected() -> None:
    gc.unfreeze()  # what other tests' apps froze: the count below is this test's own
    started = [_Node() for _ in range(1000)]
    try:
        settle_heap()
        assert gc.get_freeze_count() >= len(started)
        # a cycle made afterwards is garbage the collector still finds
        later = _Node()
        later.me = later
        alive = weakref.ref(later)
        del later
        gc.collect()
        assert alive() is None
    finally:
        gc.unfreeze()
