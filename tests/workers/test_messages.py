"""The messages between API and workers survive each broker's carriage, and JSON of the
previous version is still read from a Redis stream or channel."""

from __future__ import annotations

import json
import uuid
from multiprocessing.reduction import ForkingPickler

import msgspec
import numpy as np
import pytest
import redis

from app.workers.messages import (
    STOP,
    Done,
    Emitted,
    Ingest,
    Ready,
    Result,
    Stats,
    decode_inbound,
    decode_ingest,
    decode_results,
    encode,
)

POSITION = {
    "type": "position",
    "device_id": "phone-1",
    "site_id": "hq",
    "floor_id": "F1",
    "t": 1_700_000_000_090,
    "x": 12.345,
    "y": 6.789,
    "z": 1.0,
    "heading": None,
    "accuracy": 1.234,
    "speed": 0.5,
    "method": "pf",
    "computed_at": 1_700_000_000_123,
    "smoothed": False,
}
EVENT = {
    "type": "zone",
    "event": "enter",
    "zone": "Lab",
    "device_id": "phone-1",
    "site_id": "hq",
    "floor_id": "F1",
    "t": 1_700_000_000_090,
}
INGEST = Ingest(
    "a1b2c3-7",
    "hq",
    "phone-1",
    3,
    {
        "ble": [{"t": 1_700_000_000_000, "id": "b1", "rssi": -71.5}],
        "imu": [{"t": 1_700_000_000_010, "acc": [0.1, 0.0, 9.8], "gyro": [0.0, 0.0, 0.01]}],
        "wifi": [{"t": 1_700_000_000_020, "id": "aa:bb:cc:dd:ee:ff", "rssi": -60, "freq": 2412}],
    },
    flush=True,
)
RESULTS: list[Result] = [
    Done(
        "a1b2c3-7",
        "hq",
        "phone-1",
        accepted=3,
        late=1,
        duplicate=2,
        positions=[POSITION],
        events=[EVENT],
        processed_t=1_700_000_000_020,
        processed_wifi_t=1_700_000_000_020,
    ),
    Done("a1b2c3-8", "nowhere", "phone-1"),
    Done("a1b2c3-9", "hq", "phone-2", error="boom"),
    Emitted("hq", "phone-1", [POSITION | {"smoothed": True}], []),
    Stats(0, 12, {"samples": 300, "late": 2}, 1.25),
    Ready(1),
]


def test_every_message_survives_the_memory_brokers_queues() -> None:
    # a multiprocessing queue pickles what it carries
    def carried(data: bytes) -> bytes:
        return ForkingPickler.loads(bytes(ForkingPickler.dumps(data)))

    assert decode_inbound(carried(encode(INGEST))) == INGEST
    assert decode_inbound(carried(encode(STOP))) == STOP
    assert decode_results(carried(encode(RESULTS))) == RESULTS


def test_the_type_field_names_each_message_as_before() -> None:
    wire = msgspec.msgpack.decode(encode(RESULTS))
    assert [m["type"] for m in wire] == ["done", "done", "done", "emitted", "stats", "ready"]
    assert json.loads(json.dumps(wire[0]))["positions"] == [POSITION]


def _legacy(message: Ingest | Result) -> dict[str, object]:
    """Return a message as the previous version wrote it: a dict, with its ``type``."""
    plain = msgspec.to_builtins(message)
    assert isinstance(plain, dict)
    return plain


def test_json_of_the_previous_version_is_still_read() -> None:
    ingest = json.dumps(_legacy(INGEST), separators=(",", ":")).encode()
    # an unknown site's acknowledgement had counts but no processed times; an error had neither
    results = [
        {"type": "done", "batch_id": "x-1", "site_id": "nowhere", "device_id": "d"}
        | {"accepted": 0, "late": 0, "duplicate": 0, "positions": [], "events": []},
        {"type": "done", "batch_id": "x-2", "site_id": "hq", "device_id": "d", "error": "boom"},
    ] + [_legacy(r) for r in RESULTS]

    assert decode_ingest(ingest) == INGEST
    assert decode_results(json.dumps(results).encode()) == [
        Done("x-1", "nowhere", "d"),
        Done("x-2", "hq", "d", error="boom"),
        *RESULTS,
    ]


def test_every_message_survives_a_redis_stream_and_channel(redis_client: redis.Redis) -> None:
    stream, channel = f"test:stream:{uuid.uuid4().hex}", f"test:results:{uuid.uuid4().hex}"
    pubsub = redis_client.pubsub(ignore_subscribe_messages=True)
    pubsub.subscribe(channel)
    try:
        redis_client.xadd(stream, {"m": encode(INGEST)})
        [(_, fields)] = redis_client.xrange(stream)
        assert decode_ingest(fields[b"m"]) == INGEST

        redis_client.publish(channel, encode(RESULTS))
        item = None
        for _ in range(50):
            item = pubsub.get_message(timeout=0.1)
            if item is not None:
                break
        assert item is not None
        assert decode_results(item["data"]) == RESULTS
    finally:
        pubsub.close()
        redis_client.delete(stream)


def test_numpy_scalars_in_a_position_are_carried_as_python_numbers() -> None:
    position = POSITION | {"x": np.float64(12.345), "floor": np.int64(2), "smoothed": np.bool_(1)}
    [done] = decode_results(encode([Done("b", "hq", "d", positions=[position])]))

    assert done.positions == [POSITION | {"x": 12.345, "floor": 2, "smoothed": True}]
    assert [type(done.positions[0][k]) for k in ("x", "floor", "smoothed")] == [float, int, bool]
    with pytest.raises(TypeError):
        encode([Done("b", "hq", "d", positions=[POSITION | {"x": object()}])])
