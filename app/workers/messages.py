"""The messages between the API and the workers, and their byte encoding.

The API publishes an :class:`Ingest` per device batch to the device's shard
(and :data:`STOP` to a worker process at shutdown); a worker answers with
:class:`Done` per batch, :class:`Emitted` for what silence flushed,
:class:`Acked` for batches a stored snapshot now holds, :class:`Stats` now
and then, and :class:`Ready` once it can take batches.
Each is a msgspec Struct tagged by its ``type`` field, and both brokers carry
the same msgpack bytes: the API process, where every batch and result passes,
encodes and decodes them faster than it pickled dicts (a multiprocessing queue
now pickles one bytes object), and far faster than it wrote and read JSON for
Redis.

Samples, positions and zone events stay the JSON objects clients send and
receive: a worker reads samples by key, and the API hands positions and events
to HTTP and WebSocket clients as they are.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import msgspec
import numpy as np

Sample = dict[str, Any]
"""One measurement as the ingest checked it (``t`` and its kind's fields)."""
Position = dict[str, Any]
"""A position as the API answers and streams it (``type`` "position")."""
ZoneEvent = dict[str, Any]
"""A zone entry or exit as the API streams it (``type`` "zone")."""


class Ingest(msgspec.Struct, tag="ingest", frozen=True):
    """A device's batch for its shard; ``flush`` releases its whole reorder buffer."""

    batch_id: str
    site_id: str
    device_id: str
    version: int
    samples: dict[str, list[Sample]]
    flush: bool = False


class Stop(msgspec.Struct, tag="stop", frozen=True):
    """Ask a worker process to snapshot its devices and exit."""


STOP = Stop()


class Done(msgspec.Struct, tag="done", frozen=True):
    """The acknowledgement of a batch: what was used, what it emitted, or why it failed.

    ``processed_t`` is None when no device took the batch (an unknown site, an
    error); ``error`` is set only when processing failed.
    """

    batch_id: str
    site_id: str
    device_id: str
    accepted: int = 0
    late: int = 0
    duplicate: int = 0
    positions: list[Position] = msgspec.field(default_factory=list)
    events: list[ZoneEvent] = msgspec.field(default_factory=list)
    processed_t: int | None = None
    processed_wifi_t: int | None = None
    error: str | None = None


class Emitted(msgspec.Struct, tag="emitted", frozen=True):
    """Positions and zone events a quiet device's flush produced, outside any batch."""

    site_id: str
    device_id: str
    positions: list[Position]
    events: list[ZoneEvent]


class Stats(msgspec.Struct, tag="stats", frozen=True):
    """A shard's running totals for the API's metrics."""

    shard: int
    devices: int
    counters: dict[str, int]
    update_seconds: float


class Acked(msgspec.Struct, tag="acked", frozen=True):
    """Processed batches that stored snapshots now hold: the broker may forget them."""

    batch_ids: list[str]


class Ready(msgspec.Struct, tag="ready", frozen=True):
    """A worker process has built its sites and takes batches."""

    shard: int


Inbound = Ingest | Stop
"""What a worker reads."""
Result = Done | Emitted | Stats | Ready | Acked
"""What a worker answers."""


def _plain(value: Any) -> Any:
    """Return a numpy scalar left in a message (a position's number, say) as Python's."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"a message cannot hold {type(value).__name__}")


# msgpack takes plain data only; the hook runs for nothing else, so costs nothing otherwise
_encoder = msgspec.msgpack.Encoder(enc_hook=_plain)
_inbound = msgspec.msgpack.Decoder(Inbound)
_ingest = msgspec.msgpack.Decoder(Ingest)
_results = msgspec.msgpack.Decoder(list[Result])
_json_ingest = msgspec.json.Decoder(Ingest)
_json_results = msgspec.json.Decoder(list[Result])


def encode(message: Inbound | Sequence[Result]) -> bytes:
    """Return a message, or a worker's results, as msgpack."""
    return _encoder.encode(message)


def decode_inbound(data: bytes) -> Inbound:
    """Return the message a worker process read from its queue."""
    return _inbound.decode(data)


def decode_ingest(data: bytes) -> Ingest:
    """Return the batch of a Redis stream entry.

    JSON is still read: a stream may hold entries an earlier version published,
    re-processed after an upgrade.
    """
    # a tagged struct is a msgpack map (first byte 0x80-0x8f, 0xde or 0xdf), never "{"
    return _json_ingest.decode(data) if data[:1] == b"{" else _ingest.decode(data)


def decode_results(data: bytes) -> list[Result]:
    """Return a worker's results (JSON from a worker of an earlier version)."""
    # a list is a msgpack array (first byte 0x90-0x9f, 0xdc or 0xdd), never "["
    return _json_results.decode(data) if data[:1] == b"[" else _results.decode(data)
