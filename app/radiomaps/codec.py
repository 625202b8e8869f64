"""Radio maps and survey guidance as bytes: an npz of flat numeric arrays, never pickle."""

from __future__ import annotations

import io
from dataclasses import asdict, replace

import numpy as np

from app.engine.radiomap import RadioMap
from app.engine.survey_guidance import GuidanceGrid, GuidanceParams


def encode_arrays(arrays: dict[str, np.ndarray]) -> bytes:
    """Serialise named arrays as compressed npz."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, allow_pickle=False, **arrays)
    return buffer.getvalue()


def decode_arrays(blob: bytes) -> dict[str, np.ndarray]:
    """Inverse of :func:`encode_arrays`; loading cannot run code."""
    with np.load(io.BytesIO(blob), allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def encode_map(radio_map: RadioMap) -> bytes:
    """Serialise a radio map (its ``to_arrays()``) as compressed npz."""
    return encode_arrays(radio_map.to_arrays())


def decode_map(blob: bytes) -> RadioMap:
    """Inverse of :func:`encode_map`."""
    return RadioMap.from_arrays(decode_arrays(blob))


STORED_ERRORS = np.float16
"""Precision of the stored guidance grids: ±1 cm at 20 m, NaN and ∞ kept, 2 bytes a cell."""


def as_stored(grid: GuidanceGrid) -> GuidanceGrid:
    """Return the grid with its errors and distances rounded as storing them rounds them."""
    return replace(
        grid,
        error_m=grid.error_m.astype(STORED_ERRORS).astype(np.float64),
        distance_m=grid.distance_m.astype(STORED_ERRORS).astype(np.float64),
    )


def encode_guidance(grid: GuidanceGrid) -> bytes:
    """Serialise a floor's survey guidance: errors and distances as ``STORED_ERRORS``, its
    parameters as scalars beside them."""
    return encode_arrays(
        {
            "origin": grid.origin.astype(np.float64),
            "walkable": grid.walkable,
            "error_m": grid.error_m.astype(STORED_ERRORS),
            "distance_m": grid.distance_m.astype(STORED_ERRORS),
            "scans": np.array(grid.scans, dtype=np.int64),
        }
        | {k: np.array(v, dtype=np.float64) for k, v in asdict(grid.params).items()}
    )


def decode_guidance(blob: bytes) -> GuidanceGrid:
    """Inverse of :func:`encode_guidance` (errors and distances back as float64)."""
    a = decode_arrays(blob)
    params = GuidanceParams(**{k: float(a[k]) for k in GuidanceParams.__dataclass_fields__})
    return GuidanceGrid(
        origin=a["origin"],
        walkable=a["walkable"].astype(bool),
        error_m=a["error_m"].astype(np.float64),
        distance_m=a["distance_m"].astype(np.float64),
        scans=int(a["scans"]),
        params=params,
    )
