"""Snapshot bytes: every kind of value round-trips, versions 1 and 2 are still read, only data
loads."""

from __future__ import annotations

import io
import zlib
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

from app.workers import snapshots
from app.workers.device import DeviceSession
from app.workers.trackers import PF, SiteEngines
from tests.workers.office import T0, ble_scans, per_second

V1_BLOB = Path(__file__).parent / "data" / "snapshot_v1.npz"
"""Written by version 1's encoder (``np.savez_compressed`` of flat ``/``-joined keys)."""

V1_STATE: dict[str, Any] = {
    "processed_t": 1700000001000,
    "unflushed": True,
    "speed": 0.5,
    "buffer": "[]",
    "kinds": np.array(["ble", "imu"]),
    "tracker": {
        "kind": "pf",
        "state": {
            "rng": {
                "bit_generator": "PCG64",
                "state": np.array([12345678901234567890, 42], dtype=np.uint64),
            },
            "xy": np.arange(6, dtype=np.float32).reshape(3, 2),
            "weights": np.array([0.25, 0.75]),
            "floor": 1,
            "filters": {},
        },
    },
}
"""What the file holds."""


def _assert_same(got: Any, expected: Any) -> None:
    """Assert equal trees: the same keys, scalars of the same type, arrays bit for bit."""
    if isinstance(expected, dict):
        assert isinstance(got, dict) and list(got) == list(expected)
        for key in expected:
            _assert_same(got[key], expected[key])
    elif isinstance(expected, np.ndarray):
        assert isinstance(got, np.ndarray)
        assert got.dtype == expected.dtype and got.shape == expected.shape
        assert got.tobytes() == expected.tobytes()
    else:
        assert type(got) is type(expected)
        # NaN (an unknown heading, say) is stored as NaN
        assert got == expected or (got != got and expected != expected)


def _v1(state: dict[str, Any]) -> bytes:
    """Return ``state`` as version 1 wrote it (a second implementation of its format)."""
    flat: dict[str, np.ndarray] = {"__version__": np.asarray(1)}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            if not value:
                flat[prefix + "/{}"] = np.zeros(0)
            for key, item in value.items():
                walk(f"{prefix}/{key}" if prefix else key, item)
        else:
            flat[prefix] = np.asarray(value)

    walk("", state)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, allow_pickle=False, **flat)
    return buffer.getvalue()


def test_every_kind_of_value_round_trips() -> None:
    state = {
        "int": -(2**62),
        "big": 2**64 - 1,
        "float": 0.1,
        "nan": float("nan"),
        "bool": False,
        "text": "Lab ⟂ 2",
        # kept whole: numpy's fixed-width bytes would drop the trailing NUL
        "bytes": b"\x93\x00",
        "numpy_scalars": {"i": np.int32(7), "f": np.float32(0.5), "b": np.bool_(True)},
        "list": [1.5, 2.5],
        "empty": {},
        "arrays": {
            "f64": np.linspace(0, 1, 7),
            "f32_2d": np.arange(12, dtype=np.float32).reshape(3, 4),
            "big_endian": np.arange(3, dtype=">i4"),
            "u64": np.array([2**64 - 1, 0], dtype=np.uint64),
            "i8": np.array([-1, 1], dtype=np.int8),
            "bools": np.array([True, False]),
            "strings": np.array(["wifi", "ble"]),
            "none_of": np.zeros((0, 3)),
            "strided": np.arange(20.0).reshape(4, 5)[:, ::2],
        },
    }

    got = snapshots.decode(snapshots.encode(state))

    expected = dict(state)
    # 0-d values come back as Python scalars, sequences as arrays (as in version 1)
    expected["numpy_scalars"] = {"i": 7, "f": 0.5, "b": True}
    expected["list"] = np.array([1.5, 2.5])
    expected["arrays"] = {k: np.ascontiguousarray(v) for k, v in state["arrays"].items()}
    _assert_same(got, expected)
    assert all(a.flags.writeable for a in got["arrays"].values()), "filters update them in place"


def test_a_version_1_snapshot_is_still_read() -> None:
    blob = V1_BLOB.read_bytes()
    assert blob[:4] == b"PK\x03\x04"

    _assert_same(snapshots.decode(blob), V1_STATE)
    _assert_same(snapshots.decode(_v1(V1_STATE)), V1_STATE)


def test_a_particle_filter_device_stored_by_version_1_resumes_as_from_the_current_version(
    engines: SiteEngines,
) -> None:
    uploads = per_second(ble_scans(16))
    before = DeviceSession(device_id="phone", engines=engines, now=T0)
    for samples in uploads[:8]:
        before.add({"ble": samples}, now=T0)
        batch, _ = before.take(reorder_ms=2000, flush=False)
        if batch is not None and before.tracker is not None:
            before.tracker.process(batch)
    assert before.tracker is not None and before.tracker.kind == PF
    state = before.snapshot()
    before.close()

    resumed = []
    for blob in (_v1(state), snapshots.encode(state)):
        _assert_same(snapshots.decode(blob), snapshots.decode(_v1(state)))
        device = DeviceSession(device_id="phone", engines=engines, now=T0)
        device.restore(snapshots.decode(blob))
        estimates = []
        for samples in uploads[8:]:
            device.add({"ble": samples}, now=T0)
            batch, _ = device.take(reorder_ms=2000, flush=False)
            if batch is not None and device.tracker is not None:
                estimates += device.tracker.process(batch)
        device.close()
        resumed.append([(e.t, e.x, e.y, e.floor) for e in estimates])
    assert resumed[0] and resumed[0] == resumed[1]


def test_a_current_snapshot_is_smaller_than_version_1(engines: SiteEngines) -> None:
    device = DeviceSession(device_id="phone", engines=engines, now=T0)
    for samples in per_second(ble_scans(8)):
        device.add({"ble": samples}, now=T0)
        batch, _ = device.take(reorder_ms=2000, flush=False)
        if batch is not None and device.tracker is not None:
            device.tracker.process(batch)
    state = device.snapshot()
    device.close()
    assert len(snapshots.encode(state)) < len(_v1(state))


@pytest.mark.parametrize(
    "state",
    [{"x": None}, {"x": [{"a": 1}]}, {"x": np.array([object()])}, {"x": {1: 2.0}}],
    ids=["none", "dicts in a list", "object array", "integer key"],
)
def test_only_numeric_and_string_data_is_stored(state: dict[str, Any]) -> None:
    with pytest.raises(TypeError):
        snapshots.encode(state)


def _v2(payload: object) -> bytes:
    return bytes([2]) + zlib.compress(msgspec.msgpack.encode(payload))


def test_loading_refuses_what_is_not_snapshot_data() -> None:
    dtype = b"|O"
    head = bytes([len(dtype), 1]) + dtype + (1).to_bytes(8, "little")
    object_array = msgspec.msgpack.Ext(1, head + bytes(8))
    with pytest.raises(ValueError, match="object"):
        snapshots.decode(_v2({"x": object_array}))
    with pytest.raises(ValueError, match="extension"):
        snapshots.decode(_v2({"x": msgspec.msgpack.Ext(2, b"")}))
    with pytest.raises(ValueError, match="version 4"):
        snapshots.decode(bytes([4]) + zlib.compress(b"\x80"))


def test_a_version_2_snapshot_zlib_compressed_is_still_read() -> None:
    state = {"t": 5, "xy": np.arange(6, dtype=np.float32).reshape(3, 2), "inner": {"w": 0.5}}
    blob = bytes([2]) + zlib.compress(msgspec.msgpack.encode(snapshots._data(state)))
    _assert_same(snapshots.decode(blob), state)
    # what is written now is version 3
    assert snapshots.encode(state)[0] == 3
