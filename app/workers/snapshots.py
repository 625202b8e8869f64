"""Device snapshots as bytes: a version byte, then msgpack of nested dicts, scalars and raw
arrays, compressed.

Stored state is data only: loading a snapshot cannot run code, whoever wrote
the database or Redis entry. An array is its dtype, shape and raw bytes in a
msgpack extension; object dtypes are refused both ways, never pickled.

Versions 1 and 2 are still read, so devices stored before version 3 resume.
Version 2 exists because a worker snapshots every device each
``snapshot_every_ms`` and at eviction: version 1's npz (flat ``/``-joined
keys, each compressed on its own) cost several times more than version 2's
one fast zlib pass over msgpack, in more bytes. Version 3 compresses the same
msgpack with an LZ4 frame instead of zlib: several times faster both ways,
for slightly more bytes (``python -m bench.snapshots`` times them).
"""

from __future__ import annotations

import io
import struct
import zlib
from typing import Any

import lz4.frame
import msgspec
import numpy as np

FORMAT_VERSION = 3
_ZLIB_VERSION = 2
"""Version 2: the same msgpack, zlib-compressed."""
_ARRAY = 1
"""The msgpack extension code of an ndarray."""
_HEAD = struct.Struct("<BB")
"""An array's dtype length and number of dimensions, before its dtype, shape and bytes."""
_ZIP = b"PK\x03\x04"
"""How a version-1 snapshot (an npz, a zip file) begins."""
_SEP = "/"


_PLAIN = (str, bytes, int, float, bool)
"""Values msgpack takes as they are (bytes kept whole: numpy's fixed-width bytes would drop
trailing NULs)."""


def _data(value: Any) -> Any:
    """Return ``value`` as msgpack takes it: dicts kept, 0-d values as scalars, arrays raw."""
    if isinstance(value, dict):
        out = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise TypeError(f"snapshot key {key!r} is not a string")
            out[key] = _data(item)
        return out
    if isinstance(value, _PLAIN):
        return value
    array = np.asarray(value)
    if array.dtype.hasobject:
        raise TypeError("snapshot value is not numeric or string data")
    if array.ndim == 0:
        # as version 1 read them back: a Python scalar of the value's kind
        return array.item()
    dtype = array.dtype.str.encode()
    head = _HEAD.pack(len(dtype), array.ndim) + dtype + struct.pack(f"<{array.ndim}q", *array.shape)
    return msgspec.msgpack.Ext(_ARRAY, head + np.ascontiguousarray(array).tobytes())


def _array(code: int, data: memoryview) -> np.ndarray:
    """Return the (writable) array of an extension written by :func:`_data`."""
    if code != _ARRAY:
        raise ValueError(f"unknown snapshot extension {code}")
    n_dtype, ndim = _HEAD.unpack_from(data)
    at = _HEAD.size + n_dtype
    dtype = np.dtype(bytes(data[_HEAD.size : at]).decode())
    if dtype.hasobject:
        raise ValueError("snapshot array of object dtype")
    shape = struct.unpack_from(f"<{ndim}q", data, at)
    return np.frombuffer(data, dtype, offset=at + 8 * ndim).reshape(shape).copy()


_encoder = msgspec.msgpack.Encoder()
_decoder = msgspec.msgpack.Decoder(dict[str, Any], ext_hook=_array)


def encode(state: dict[str, Any]) -> bytes:
    """Serialise nested dicts (string keys) of scalars, strings and ndarrays."""
    return bytes([FORMAT_VERSION]) + lz4.frame.compress(_encoder.encode(_data(state)))


def decode(blob: bytes) -> dict[str, Any]:
    """Inverse of :func:`encode`, also of versions 1 and 2; 0-d values come back as Python
    scalars."""
    if blob[:4] == _ZIP:
        return _decode_v1(blob)
    if blob[:1] == bytes([FORMAT_VERSION]):
        return _decoder.decode(lz4.frame.decompress(memoryview(blob)[1:]))
    if blob[:1] == bytes([_ZLIB_VERSION]):
        return _decoder.decode(zlib.decompress(memoryview(blob)[1:]))
    raise ValueError(f"unsupported snapshot version {blob[0] if blob else None}")


def _decode_v1(blob: bytes) -> dict[str, Any]:
    """Return the state of a version-1 snapshot: flat ``/``-joined keys in an npz."""
    with np.load(io.BytesIO(blob), allow_pickle=False) as data:
        if int(data["__version__"]) != 1:
            raise ValueError(f"unsupported snapshot version {int(data['__version__'])}")
        state: dict[str, Any] = {}
        for key in data.files:
            if key == "__version__":
                continue
            parts = key.split(_SEP)
            node = state
            for part in parts[:-1]:
                node = node.setdefault(part, {})
            if parts[-1] == "{}":
                continue
            value = data[key]
            node[parts[-1]] = value.item() if value.ndim == 0 else value
    return state
