"""Per-scan k-NN against every survey scan: the strongest plain fingerprint method.

The benchmark's best per-scan locator on smartphone mall data (see the
README's references) keeps every survey scan as a reference point, at the
position interpolated between its walk's waypoints, instead of pooling
scans into grid cells, and compares two scans only on what both heard:

- ``d = Σ_a w_a |s_a - r_a| / Σ_a w_a`` over the transmitters ``a`` both
  scans heard, with ``w_a = (1 / walks that heard a)^rarity_power · (1 +
  (s_a + r_a) / 2)^level_power`` (rare transmitters say more about where a
  scan is; with ``level_power`` above 0 strong ones weigh more than those
  heard near the noise floor, whose level varies most from scan to scan);
- plus ``penalty · (1 - shared)²``, ``shared`` being the share of the two
  scans' signal (dB above ``floor_dbm``) on common transmitters: what only
  one of them heard counts against the match without imputing a level;
- the ``k`` nearest weighted by ``(d / d_min)^-weight_power``, on the
  floor their weights favour.

Transmitters heard in fewer than ``min_heard`` survey scans are left out,
of the references and of the query alike: one the survey never heard (a
phone's hotspot, an access point installed since) says nothing about where
a scan is.

References are held sparse, by transmitter (each usable transmitter's
column lists the reference scans that heard it and at what level, dB above
``floor_dbm``), so a query visits only the (scan, transmitter) pairs both
heard: a mall's survey holds thousands of scans but each transmitter is
heard in few of them, so the sparse pairs are a small share of a dense
matrix. The visit is a compiled loop (numba, compiled once and cached on
disk), several times faster than numpy's gather-and-bincount or a dense
matrix (``python -m bench.hmm`` times the distances per scan).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from app.engine.radiomap import RadioMap, Survey


@dataclass(frozen=True)
class ScanKnnParams:
    """Constants of the per-scan k-NN.

    Attributes
    ----------
    k : int
        Nearest reference scans averaged.
    min_heard : int
        Transmitters heard in fewer survey scans than this are ignored.
    floor_dbm : float
        Signal level counted as nothing when weighing what two scans share.
    unshared_penalty : float
        Distance (dB) added when two scans share nothing, scaled by
        ``(1 - shared)²``.
    rarity_power : float
        Exponent of a transmitter's weight ``(1 / walks that heard it)^p``.
    weight_power : float
        Exponent of the neighbour weights ``(d / d_min)^-p``.
    no_common_db : float
        Mean absolute difference assumed when two scans share no transmitter.
    level_power : int
        Exponent (0, 1 or 2) of a shared transmitter's mean level (dB above
        ``floor_dbm``, plus 1) in its weight: 0 weighs every shared
        transmitter alike; a build chooses the site's
        (``app.engine.scan_knn_cv``).
    """

    k: int = 10
    min_heard: int = 5
    floor_dbm: float = -100.0
    unshared_penalty: float = 50.0
    rarity_power: float = 0.2
    weight_power: float = 4.0
    no_common_db: float = 40.0
    level_power: int = 0


LEVEL_POWERS = (0, 1, 2)
"""The level weights' exponents the compiled distance supports."""


@dataclass(frozen=True)
class ScanFix:
    """One scan located: position (m), floor index, and the best match's distance (dB)."""

    xy: np.ndarray
    floor: int
    distance: float


class ReferenceScans:
    """Survey scans kept as reference fingerprints, prepared for per-scan queries.

    Parameters
    ----------
    survey : Survey
        Located survey scans (positions from the waypoints).
    n_tx : int
        Number of site transmitter indices (queries may name any below it).
    params : ScanKnnParams
        Constants.
    """

    def __init__(self, survey: Survey, n_tx: int, params: ScanKnnParams | None = None) -> None:
        self.params = p = params or ScanKnnParams()
        if p.level_power not in LEVEL_POWERS:
            raise ValueError(f"level_power must be one of {LEVEL_POWERS}, not {p.level_power}")
        n_tx = max(n_tx, int(survey.reading_tx.max(initial=-1)) + 1)
        tx = survey.reading_tx.astype(np.int64)
        heard = np.bincount(tx, minlength=n_tx)
        walk = survey.scan_walk[survey.reading_scan].astype(np.int64)
        pairs = np.unique(np.stack([tx, walk]), axis=1)
        walks_heard = np.bincount(pairs[0], minlength=n_tx)
        self.usable = heard >= p.min_heard
        # w_a = (1 / walks that heard a)^p
        self.tx_weight = np.where(self.usable, np.maximum(walks_heard, 1.0) ** -p.rarity_power, 0.0)
        keep = self.usable[tx]
        self.n_usable = int(self.usable.sum())
        self.column = np.full(n_tx, -1, dtype=np.int64)
        self.column[self.usable] = np.arange(self.n_usable)
        # one entry per (scan, transmitter) heard, the strongest reading's level kept
        scan = survey.reading_scan[keep].astype(np.int64)
        col = self.column[tx[keep]]
        level = np.maximum(survey.reading_rssi[keep] - p.floor_dbm, 0.0).astype(np.float32)
        order = np.lexsort((-level, scan, col))
        col, scan, level = col[order], scan[order], level[order]
        first = np.ones(col.size, dtype=bool)
        first[1:] = (col[1:] != col[:-1]) | (scan[1:] != scan[:-1])
        strongest = first & (level > 0)
        col, scan, level = col[strongest], scan[strongest], level[strongest]
        self.col_start = np.searchsorted(col, np.arange(self.n_usable + 1))
        self.ref_scan = scan.astype(np.int32)
        self.ref_level = level
        # the same entries by scan, to compare a query with a few reference scans
        by_scan = np.argsort(scan, kind="stable")
        self.scan_start = np.searchsorted(scan[by_scan], np.arange(survey.n_scans + 1))
        self.scan_col = col[by_scan].astype(np.int32)
        self.scan_level = level[by_scan]
        self.total = np.bincount(scan, weights=level, minlength=survey.n_scans)
        self.xy = np.asarray(survey.scan_xy, dtype=float)
        self.floor = np.asarray(survey.scan_floor, dtype=np.int64)
        self.n_tx = n_tx

    @classmethod
    def from_maps(
        cls, maps: Sequence[RadioMap], n_tx: int, params: ScanKnnParams | None = None
    ) -> ReferenceScans:
        """Gather the reference scans every map carries (all must carry them)."""
        parts = []
        for m in maps:
            ref = m.references
            if ref is None:
                raise ValueError(f"the map of floor {m.floor} carries no reference scans")
            n = ref.xy.shape[0]
            parts.append(
                Survey(
                    scan_t=np.zeros(n, dtype=np.int64),
                    scan_xy=ref.xy.astype(float),
                    scan_floor=np.full(n, m.floor, dtype=np.int32),
                    scan_walk=ref.walk.astype(np.int32),
                    reading_scan=ref.scan.astype(np.int32),
                    reading_tx=np.asarray(m.tx, dtype=np.int32)[ref.col],
                    reading_rssi=ref.rssi.astype(float),
                )
            )
        return cls(Survey.concat(parts), n_tx, params)

    @property
    def n_scans(self) -> int:
        """Number of reference scans."""
        return int(self.xy.shape[0])

    def distances(self, tx: np.ndarray, rssi: np.ndarray) -> np.ndarray:
        """Return the distance (dB) of one scan to every reference scan, shape (n_scans,).

        Parameters
        ----------
        tx : ndarray of int, shape (n,)
            Unique site transmitter indices heard (any outside the site are ignored).
        rssi : ndarray, shape (n,)
            Their RSSI (dBm).
        """
        p = self.params
        tx, level = self._query(tx, rssi)
        query_total = float(level.sum())
        if tx.size == 0:
            return np.full(self.n_scans, np.inf)
        return _distances(
            self.col_start,
            self.ref_scan,
            self.ref_level,
            self.column[tx],
            level,
            self.tx_weight[tx],
            self.total,
            query_total,
            p.no_common_db,
            p.unshared_penalty,
            p.level_power,
        )

    def _query(self, tx: np.ndarray, rssi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return a query's usable transmitters and their levels (dB above ``floor_dbm``).

        Transmitters outside the site, or that the survey never heard (installed
        since, a phone's hotspot), say nothing and are dropped.
        """
        tx = np.asarray(tx, dtype=np.int64)
        rssi = np.asarray(rssi, dtype=float)
        inside = (tx >= 0) & (tx < self.n_tx)
        tx, rssi = tx[inside], rssi[inside]
        on = self.usable[tx]
        return tx[on], np.maximum(rssi[on] - self.params.floor_dbm, 0.0)

    def neighbours(
        self, d: np.ndarray, block: slice, k: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Return the positions (k, 2) and weights (k,) of the ``k`` nearest scans of ``block``.

        ``d`` are the block's distances (some finite); weights are
        ``(d / d_min)^-weight_power``, summing to 1.
        """
        k = min(k or self.params.k, d.size)
        near = np.argpartition(d, k - 1)[:k]
        near = near[np.isfinite(d[near])]
        best = max(float(d[near].min()), 1e-3)
        weight = (np.maximum(d[near], best) / best) ** -self.params.weight_power
        return self.xy[block][near], weight / weight.sum()

    def level_offset(self, tx: np.ndarray, rssi: np.ndarray, scans: np.ndarray) -> float | None:
        """Return the median of the query's level minus each reference scan's (dB).

        Over the usable transmitters the query and each of ``scans`` (reference
        scan indices) both heard, levels clipped at ``floor_dbm`` as the
        distance clips them: how much louder this phone hears the same access
        points than the survey did. None when they share none.
        """
        tx, level = self._query(tx, rssi)
        query = np.full(self.n_usable, np.nan)
        query[self.column[tx]] = level
        offset = _median_offset(
            query,
            self.scan_start,
            self.scan_col,
            self.scan_level,
            np.asarray(scans, dtype=np.int64),
        )
        return None if np.isnan(offset) else float(offset)

    def weighted_mean(self, d: np.ndarray, block: slice, k: int | None = None) -> np.ndarray:
        """Return the position (m) of the ``k`` nearest scans of ``block`` (``neighbours``)."""
        xy, weight = self.neighbours(d, block, k)
        return weight @ xy

    def locate(self, tx: np.ndarray, rssi: np.ndarray, k: int | None = None) -> ScanFix | None:
        """Locate one scan: the k nearest reference scans on their favoured floor.

        Returns None when the scan shares no usable transmitter with the survey.
        """
        return self.fix(self.distances(tx, rssi), k)

    def fix(
        self, d: np.ndarray, k: int | None = None, weight_power: float | None = None
    ) -> ScanFix | None:
        """Return the fix of a scan from its distances ``d`` to every reference scan.

        ``k`` and ``weight_power`` default to the constants'; None when no
        distance is finite (the scan shared no usable transmitter).
        """
        if not np.isfinite(d).any():
            return None
        k = min(k or self.params.k, d.size)
        power = self.params.weight_power if weight_power is None else weight_power
        near = np.argpartition(d, k - 1)[:k]
        dn = d[near]
        best = max(float(dn.min()), 1e-3)
        # w_i = (d_i / d_min)^-p
        weight = (np.maximum(dn, best) / best) ** -power
        floors = self.floor[near]
        floor = int(np.bincount(floors, weights=weight).argmax())
        on = floors == floor
        xy = weight[on] @ self.xy[near[on]] / weight[on].sum()
        return ScanFix(xy=xy, floor=floor, distance=float(dn.min()))


@njit(cache=True)
def _distances(
    col_start: np.ndarray,
    ref_scan: np.ndarray,
    ref_level: np.ndarray,
    cols: np.ndarray,
    level: np.ndarray,
    weight: np.ndarray,
    total: np.ndarray,
    query_total: float,
    no_common_db: float,
    penalty: float,
    level_power: int,
) -> np.ndarray:  # pragma: no cover - compiled
    """Return every reference scan's distance to a query, visiting only the pairs both heard.

    ``cols`` are the query's transmitters' columns, ``level`` and ``weight``
    their levels (dB above the floor) and rarity weights; ``total`` each
    reference scan's summed level. A pair's weight is the rarity weight times
    its mean level plus 1 to the ``level_power`` (0, 1 or 2: products, as a
    power per pair would cost more than the rest of the visit).
    """
    n = total.size
    common_weight = np.zeros(n)
    weighted_abs = np.zeros(n)
    common_level = np.zeros(n)
    for q in range(cols.size):
        s, w = level[q], weight[q]
        for e in range(col_start[cols[q]], col_start[cols[q] + 1]):
            j, r = ref_scan[e], ref_level[e]
            # w_a (1 + (s + r) / 2)^g
            pair = w
            if level_power > 0:
                mean = 1.0 + 0.5 * (s + r)
                pair = w * mean if level_power == 1 else w * mean * mean
            common_weight[j] += pair
            weighted_abs[j] += pair * abs(s - r)
            common_level[j] += r + s
    out = np.empty(n)
    for j in range(n):
        # d₁ = Σ w |s - r| / Σ w over common transmitters
        mean_abs = weighted_abs[j] / common_weight[j] if common_weight[j] > 0 else no_common_db
        # shared = (Σ_common r + Σ_common s) / (Σ r + Σ s)
        shared = common_level[j] / max(total[j] + query_total, 1e-12)
        out[j] = mean_abs + penalty * (1.0 - shared) ** 2
    return out


@njit(cache=True)
def _median_offset(
    query: np.ndarray,
    scan_start: np.ndarray,
    scan_col: np.ndarray,
    scan_level: np.ndarray,
    scans: np.ndarray,
) -> float:  # pragma: no cover - compiled
    """Return the median of ``query[col] - level`` over the entries of ``scans`` heard.

    ``query`` is NaN at the columns the query did not hear; NaN when it heard
    none of the scans' transmitters.
    """
    total = 0
    for s in scans:
        total += scan_start[s + 1] - scan_start[s]
    diff = np.empty(total)
    k = 0
    for s in scans:
        for e in range(scan_start[s], scan_start[s + 1]):
            value = query[scan_col[e]] - scan_level[e]
            if np.isfinite(value):
                diff[k] = value
                k += 1
    return np.median(diff[:k]) if k else np.nan
