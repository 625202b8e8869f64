"""Radio maps as bytes: an npz of flat numeric arrays, never pickle."""

from __future__ import annotations

import io

import numpy as np

from app.engine.radiomap import RadioMap


def encode_map(radio_map: RadioMap) -> bytes:
    """Serialise a radio map (its ``to_arrays()``) as compressed npz."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, allow_pickle=False, **radio_map.to_arrays())
    return buffer.getvalue()


def decode_map(blob: bytes) -> RadioMap:
    """Inverse of :func:`encode_map`; loading cannot run code."""
    with np.load(io.BytesIO(blob), allow_pickle=False) as data:
        return RadioMap.from_arrays({k: data[k] for k in data.files})
