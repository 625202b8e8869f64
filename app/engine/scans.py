"""WiFi readings grouped into scans, whatever times the client gave them.

A phone's WiFi scan lists every access point it heard. Clients send either
the scan's completion time as every reading's ``t`` (readings sharing a time
are one scan), or each reading's own last-seen time (Android's
``ScanResult.timestamp``), which spreads a scan's fresh readings over up to
a second and a half: on ILC site1's phones, scanning every 2 s, the gaps
inside a scan come close to the gaps between scans, so no fixed gap
separates them. Readings are therefore taken in time order and a scan is
cut where it must be, at its largest gap: when an access point is heard again
well after its reading in the open scan (a scan hears each once, though
phones list some twice a few milliseconds apart) or when the scan would span
more than ``max_span_ms``. A silence longer than ``gap_ms`` always ends a
scan. On walks sent with per-reading times this recovers most scans
exactly, where any fixed gap splits or merges many (``tests/engine/test_scans.py``
pins the regrouping of scans spread as site1's phones report them). Readings
sharing a time are never split, so a
client that sends the scan's time gets its scans back exactly. Cuts are
final once made: a live tracker that feeds readings in time order sees the
same scans as a build that groups a whole walk at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, types
from numba.typed import Dict


@dataclass(frozen=True)
class ScanParams:
    """Constants of scan grouping.

    Attributes
    ----------
    gap_ms : int
        A silence longer than this between consecutive readings ends a scan.
    max_span_ms : int
        No scan spans longer than this from its first reading to its last.
    repeat_ms : int
        An access point heard again more than this after its last reading
        in the open scan starts the next scan; closer repeats are one scan
        listing it twice (phones do, e.g. one radio under two network names).
    """

    gap_ms: int = 1000
    max_span_ms: int = 2000
    repeat_ms: int = 500


def scan_ids(t: np.ndarray, tx: np.ndarray, params: ScanParams) -> np.ndarray:
    """Return each reading's scan number (0, 1, ... in time order), shape (n,).

    Parameters
    ----------
    t : ndarray of int64, shape (n,)
        Reading times (ms), in any order.
    tx : ndarray of int, shape (n,)
        Transmitter of each reading.
    params : ScanParams
        Gap and span limits.
    """
    t = np.asarray(t, dtype=np.int64)
    out = np.zeros(t.size, dtype=np.int64)
    if t.size == 0:
        return out
    order = np.argsort(t, kind="stable")
    new = _scan_starts(
        t[order],
        np.asarray(tx, dtype=np.int64)[order],
        params.gap_ms,
        params.max_span_ms,
        params.repeat_ms,
    )
    out[order] = np.cumsum(new) - 1
    return out


@njit(cache=True)
def _scan_starts(
    ts: np.ndarray, txs: np.ndarray, gap_ms: int, max_span_ms: int, repeat_ms: int
) -> np.ndarray:  # pragma: no cover - compiled
    """Return whether each reading (sorted by time) starts a scan.

    A silence longer than ``gap_ms`` starts one; inside a run without one,
    readings sharing a time are one scan, and ``_cut_run`` cuts the rest.
    """
    n = ts.size
    new = np.zeros(n, dtype=np.bool_)
    new[0] = True
    lo = 0
    for hi in range(1, n + 1):
        if hi < n and ts[hi] - ts[hi - 1] <= gap_ms:
            continue
        if hi < n:
            new[hi] = True
        if ts[hi - 1] != ts[lo]:
            _cut_run(ts, txs, lo, hi, new, max_span_ms, repeat_ms)
        lo = hi
    return new


@njit(cache=True)
def _cut_run(
    ts: np.ndarray,
    txs: np.ndarray,
    lo: int,
    hi: int,
    new: np.ndarray,
    max_span_ms: int,
    repeat_ms: int,
) -> None:  # pragma: no cover - compiled
    """Mark scan starts inside one run of readings without a long silence (sorted by time).

    When reading ``i`` cannot join the open scan (its transmitter was heard
    in it more than ``repeat_ms`` before, or the scan would span too long), the open scan
    and ``i`` are cut at their largest gap (the first of equals); what follows
    the cut opens the next scan, read again from its first reading, so
    grouping what remains after any scan gives the same scans as grouping the whole.
    """
    start = lo
    heard = Dict.empty(key_type=types.int64, value_type=types.int64)
    i = lo
    while i < hi:
        ti, tx = ts[i], txs[i]
        if ti - ts[start] > max_span_ms or ti - heard.get(tx, ti) > repeat_ms:
            widest, at = -1, start
            for k in range(start, i):
                if ts[k + 1] - ts[k] > widest:
                    widest, at = ts[k + 1] - ts[k], k
            start = at + 1
            new[start] = True
            # the next scan is read again from its first reading, as if the stream began there
            heard = Dict.empty(key_type=types.int64, value_type=types.int64)
            i = start
            continue
        heard[tx] = ti
        i += 1


def group_scans(t: np.ndarray, tx: np.ndarray, params: ScanParams) -> list[np.ndarray]:
    """Return the reading indices of each scan (ascending), scans in time order."""
    t = np.asarray(t, dtype=np.int64)
    if t.size == 0:
        return []
    index, bounds = _groups(
        t, np.asarray(tx, dtype=np.int64), params.gap_ms, params.max_span_ms, params.repeat_ms
    )
    return [index[lo:hi] for lo, hi in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True)]


@njit(cache=True)
def _groups(
    t: np.ndarray, tx: np.ndarray, gap_ms: int, max_span_ms: int, repeat_ms: int
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Return the reading indices grouped by scan (ascending within each) and the bounds.

    Scan k is ``index[bounds[k]:bounds[k + 1]]``. One compiled pass, where
    numpy took ten calls on every tracker update.
    """
    order = np.argsort(t, kind="mergesort")
    new = _scan_starts(t[order], tx[order], gap_ms, max_span_ms, repeat_ms)
    scan = np.empty(t.size, dtype=np.int64)
    k = -1
    for i in range(t.size):
        if new[i]:
            k += 1
        scan[order[i]] = k
    bounds = np.zeros(k + 2, dtype=np.int64)
    for i in range(t.size):
        bounds[scan[i] + 1] += 1
    for j in range(k + 1):
        bounds[j + 1] += bounds[j]
    index = np.empty(t.size, dtype=np.int64)
    filled = bounds[:-1].copy()
    for i in range(t.size):
        index[filled[scan[i]]] = i
        filled[scan[i]] += 1
    return index, bounds


def load_grouping() -> None:
    """Group two readings, so the compiled loops are ready before a device needs them.

    The first call in a process compiles them, or reads them from numba's disk cache.
    """
    group_scans(np.array([0, 1], dtype=np.int64), np.array([0, 0], dtype=np.int64), ScanParams())
