"""Zone occupancy in time buckets from visits (a device inside a zone from one time to
another): pure numpy, no database, so it is checked against hand-worked cases."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Visits:
    """Stays of devices inside one zone, clipped to the queried range.

    Attributes
    ----------
    device : ndarray of int, shape (n,)
        Index of the device of each stay.
    start, end : ndarray of int64, shape (n,)
        The stay's measurement times (ms), ``start <= end``.
    entered : ndarray of bool, shape (n,)
        Whether ``start`` is an entry inside the range (not a stay already under way
        at the range's start).
    """

    device: np.ndarray
    start: np.ndarray
    end: np.ndarray
    entered: np.ndarray


@dataclass(frozen=True)
class Occupancy:
    """Per bucket: distinct devices inside, entries, and summed dwell (ms); shape (m,)."""

    edges: np.ndarray
    devices: np.ndarray
    entries: np.ndarray
    dwell_ms: np.ndarray


def bucket_edges(t_from: int, t_to: int, bucket_ms: int) -> np.ndarray:
    """Return the m + 1 edges (ms) of buckets of ``bucket_ms`` from ``t_from``; the last
    bucket ends at ``t_to`` and may be shorter."""
    inner = np.arange(t_from, t_to, bucket_ms, dtype=np.int64)
    return np.append(inner, np.int64(t_to))


def _integral(times: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Return Σ max(0, e - tᵢ) over ``times`` at each edge e (ms), in O((n + m) log n)."""
    ordered = np.sort(times)
    before = np.searchsorted(ordered, edges, side="left")
    # prefix sums with a leading 0, so prefix[k] is the sum of the k smallest times
    prefix = np.concatenate(([0], np.cumsum(ordered, dtype=np.int64)))
    # Σ_{tᵢ < e} (e - tᵢ) = k e - Σ_{tᵢ < e} tᵢ
    return before * edges - prefix[before]


def bucket_occupancy(visits: Visits, edges: np.ndarray) -> Occupancy:
    """Count each bucket's devices, entries and dwell from ``visits``.

    A stay across an edge counts its device in both buckets and splits its dwell
    at the edge; buckets are half-open ``[edgeₖ, edgeₖ₊₁)``. A stay of no length
    counts its device in the bucket of its entry only.
    """
    m = edges.size - 1
    if visits.start.size == 0:
        zeros = np.zeros(m, dtype=np.int64)
        return Occupancy(edges, zeros, zeros.copy(), zeros.copy())
    # inside-time up to e: Σ clip(e - s, 0, end - s) = Σ max(0, e - s) - Σ max(0, e - end)
    inside = _integral(visits.start, edges) - _integral(visits.end, edges)
    dwell = np.diff(inside)
    first = np.searchsorted(edges, visits.start, side="right") - 1
    last = np.maximum(first, np.searchsorted(edges, visits.end, side="left") - 1)
    first, last = np.clip(first, 0, m - 1), np.clip(last, 0, m - 1)
    spans = last - first + 1
    offsets = np.arange(spans.sum()) - np.repeat(np.cumsum(spans) - spans, spans)
    buckets = np.repeat(first, spans) + offsets
    pairs = np.unique(np.repeat(visits.device.astype(np.int64), spans) * m + buckets)
    devices = np.bincount(pairs % m, minlength=m)
    entries = np.bincount(first[visits.entered], minlength=m)
    return Occupancy(edges, devices, entries, dwell)
