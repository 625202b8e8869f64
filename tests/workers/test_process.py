"""The worker loop's inbox: framed messages on a pipe, written a turn of the API's event
loop at a time, and a round waits a moment for more."""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
import time
from collections.abc import Iterator
from multiprocessing.connection import Connection

import pytest

from app.workers.pipes import Frames, Inbox, frame_all, send
from app.workers.process import _drain


@pytest.fixture
def pipe() -> Iterator[tuple[Connection, Connection]]:
    reading, writing = mp.Pipe(duplex=False)
    yield reading, writing
    reading.close()
    if not writing.closed:
        writing.close()


def _write(writing: Connection, *payloads: bytes) -> None:
    os.write(writing.fileno(), frame_all(payloads))


def _later(writing: Connection, payloads: list[bytes], delay_s: float) -> threading.Timer:
    timer = threading.Timer(delay_s, _write, args=(writing, *payloads))
    timer.start()
    return timer


def test_frames_come_out_whole_however_the_stream_is_cut() -> None:
    stream = frame_all([b"first", b"", b"x" * 70_000, b"last"])
    for cut in (1, 3, 4, 5, 1000, len(stream)):
        frames = Frames()
        payloads = []
        for at in range(0, len(stream), cut):
            payloads += frames.feed(stream[at : at + cut])
        assert payloads == [b"first", b"", b"x" * 70_000, b"last"]


def test_a_round_takes_what_arrives_within_the_linger_and_no_more(pipe) -> None:
    reading, writing = pipe
    inbox = Inbox(reading)
    _write(writing, b"a", b"b")
    soon = _later(writing, [b"c"], 0.02)
    late = _later(writing, [b"d"], 0.6)
    try:
        assert _drain(inbox, timeout=1.0, most=100, linger=0.3) == [b"a", b"b", b"c"]
        assert _drain(inbox, timeout=1.0, most=100, linger=0.0) == [b"d"]
    finally:
        soon.cancel()
        late.cancel()


def test_without_linger_a_round_takes_only_what_is_written(pipe) -> None:
    reading, writing = pipe
    inbox = Inbox(reading)
    _write(writing, b"a")
    later = _later(writing, [b"b"], 0.1)
    try:
        assert _drain(inbox, timeout=1.0, most=100, linger=0.0) == [b"a"]
        assert _drain(inbox, timeout=1.0, most=100, linger=0.0) == [b"b"]
    finally:
        later.cancel()


def test_a_round_stops_taking_at_most_messages(pipe) -> None:
    reading, writing = pipe
    inbox = Inbox(reading)
    _write(writing, b"a", b"b")
    _write(writing, b"c")
    _write(writing, b"d")
    assert _drain(inbox, timeout=1.0, most=3, linger=0.2) == [b"a", b"b", b"c"]
    assert _drain(inbox, timeout=1.0, most=3, linger=0.0) == [b"d"]


def test_an_empty_inbox_gives_an_empty_round_after_the_timeout(pipe) -> None:
    reading, _ = pipe
    inbox = Inbox(reading)
    started = time.monotonic()
    assert _drain(inbox, timeout=0.05, most=10, linger=0.2) == []
    assert time.monotonic() - started < 0.2
    assert not inbox.closed


def test_the_inbox_closes_once_the_api_closes_its_end_and_all_is_read(pipe) -> None:
    reading, writing = pipe
    inbox = Inbox(reading)
    _write(writing, b"last")
    writing.close()
    assert _drain(inbox, timeout=1.0, most=10, linger=0.0) == [b"last"]
    started = time.monotonic()
    assert _drain(inbox, timeout=1.0, most=10, linger=0.0) == []
    assert inbox.closed
    assert time.monotonic() - started < 0.5


def test_a_worker_sends_frames_the_api_reads_whole(pipe) -> None:
    reading, writing = pipe
    big = bytes(range(256)) * 1000  # over a pipe's buffer: the write blocks until read
    sender = threading.Thread(target=lambda: [send(writing, p) for p in (b"ready", big)])
    sender.start()
    frames = Frames()
    payloads: list[bytes] = []
    while len(payloads) < 2:
        payloads += frames.feed(os.read(reading.fileno(), 4096))
    sender.join()
    assert payloads == [b"ready", big]
