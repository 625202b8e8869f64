"""Device snapshots as bytes: a versioned npz of flat arrays, never pickle.

Stored state is data only: loading a snapshot cannot run code, whoever wrote
the database or Redis entry.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np

FORMAT_VERSION = 1
_SEP = "/"


def _flatten(prefix: str, value: Any, out: dict[str, np.ndarray]) -> None:
    if isinstance(value, dict):
        if not value:
            out[prefix + _SEP + "{}"] = np.zeros(0)
        for key, item in value.items():
            if _SEP in key:
                raise ValueError(f"snapshot key {key!r} contains {_SEP!r}")
            _flatten(f"{prefix}{_SEP}{key}" if prefix else key, item, out)
    else:
        array = np.asarray(value)
        if array.dtype == object:
            raise TypeError(f"snapshot value at {prefix!r} is not numeric or string data")
        out[prefix] = array


def encode(state: dict[str, Any]) -> bytes:
    """Serialise nested dicts of scalars, strings and ndarrays."""
    flat: dict[str, np.ndarray] = {"__version__": np.asarray(FORMAT_VERSION)}
    _flatten("", state, flat)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, allow_pickle=False, **flat)
    return buffer.getvalue()


def decode(blob: bytes) -> dict[str, Any]:
    """Inverse of :func:`encode`; 0-d arrays come back as Python scalars."""
    with np.load(io.BytesIO(blob), allow_pickle=False) as data:
        if int(data["__version__"]) != FORMAT_VERSION:
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
