"""The worker loop's inbox: messages arrive in lists, one per turn of the API's event loop,
and a round waits a moment for more."""

from __future__ import annotations

import multiprocessing as mp
import threading
import time
from typing import Any

from app.workers.process import _drain


def _later(inbox: Any, item: list[bytes], delay_s: float) -> threading.Timer:
    timer = threading.Timer(delay_s, inbox.put, args=(item,))
    timer.start()
    return timer


def test_a_round_takes_what_arrives_within_the_linger_and_no_more() -> None:
    inbox = mp.get_context("spawn").Queue()
    inbox.put([b"a", b"b"])
    soon = _later(inbox, [b"c"], 0.02)
    late = _later(inbox, [b"d"], 0.6)
    try:
        assert _drain(inbox, timeout=1.0, most=100, linger=0.3) == [b"a", b"b", b"c"]
        assert _drain(inbox, timeout=1.0, most=100, linger=0.0) == [b"d"]
    finally:
        soon.cancel()
        late.cancel()


def test_without_linger_a_round_takes_only_what_is_queued() -> None:
    inbox = mp.get_context("spawn").Queue()
    inbox.put([b"a"])
    time.sleep(0.05)  # the queue's feeder has written it
    later = _later(inbox, [b"b"], 0.1)
    try:
        assert _drain(inbox, timeout=1.0, most=100, linger=0.0) == [b"a"]
        assert _drain(inbox, timeout=1.0, most=100, linger=0.0) == [b"b"]
    finally:
        later.cancel()


def test_a_round_stops_taking_at_most_messages() -> None:
    inbox = mp.get_context("spawn").Queue()
    for item in ([b"a", b"b"], [b"c"], [b"d"]):
        inbox.put(item)
    time.sleep(0.05)
    assert _drain(inbox, timeout=1.0, most=3, linger=0.2) == [b"a", b"b", b"c"]
    assert _drain(inbox, timeout=1.0, most=3, linger=0.0) == [b"d"]


def test_an_empty_inbox_gives_an_empty_round_after_the_timeout() -> None:
    inbox = mp.get_context("spawn").Queue()
    started = time.monotonic()
    assert _drain(inbox, timeout=0.05, most=10, linger=0.2) == []
    assert time.monotonic() - started < 0.2
