"""Length-prefixed frames on the pipes between the API and a worker process.

Each frame is a 4-byte big-endian length and that many bytes. The API reads and
writes its ends on its event loop (no threads, no pickling); a worker reads its
inbox with a timeout and writes its results with blocking writes.
"""

from __future__ import annotations

import os
import select
import time
from collections import deque
from collections.abc import Iterable
from multiprocessing.connection import Connection

HEADER = 4
READ_SIZE = 1 << 20


def frame(payload: bytes) -> bytes:
    """Return the payload as one frame."""
    return len(payload).to_bytes(HEADER, "big") + payload


def frame_all(payloads: Iterable[bytes]) -> bytes:
    """Return the payloads as consecutive frames, for one write."""
    return b"".join(frame(p) for p in payloads)


class Frames:
    """Split a byte stream into frame payloads as its chunks arrive."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, chunk: bytes) -> list[bytes]:
        """Add a chunk; return the payloads of the frames it completed."""
        buffer = self._buffer
        buffer += chunk
        payloads = []
        at = 0
        while len(buffer) - at >= HEADER:
            size = int.from_bytes(buffer[at : at + HEADER], "big")
            end = at + HEADER + size
            if end > len(buffer):
                break
            payloads.append(bytes(buffer[at + HEADER : end]))
            at = end
        del buffer[:at]
        return payloads


class Inbox:
    """A worker's end of the pipe the API writes batches to."""

    def __init__(self, connection: Connection) -> None:
        self._connection = connection
        self._fd = connection.fileno()
        self._frames = Frames()
        self._ready: deque[bytes] = deque()
        self.closed = False

    def take(self, timeout: float, most: int) -> list[bytes]:
        """Return up to ``most`` payloads, waiting up to ``timeout`` s for the first;
        ``closed`` turns true once the API's end is closed and everything is read."""
        deadline = time.monotonic() + timeout
        while not self._ready and not self.closed:
            left = max(deadline - time.monotonic(), 0.0)
            if not select.select([self._fd], [], [], left)[0]:
                break
            chunk = os.read(self._fd, READ_SIZE)
            if chunk:
                self._ready.extend(self._frames.feed(chunk))
            else:
                self.closed = True
        count = min(most, len(self._ready))
        return [self._ready.popleft() for _ in range(count)]


def send(connection: Connection, payload: bytes) -> None:
    """Write one frame to the connection's pipe, blocking until all of it is written."""
    view = memoryview(frame(payload))
    fd = connection.fileno()
    while view:
        view = view[os.write(fd, view) :]
