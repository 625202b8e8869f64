"""The HMM's emission (step 3 in ``app.engine.hmm``) and its k-NN start (step 1).

Per-floor log-likelihood tables of every reference point, prepared once per
site and shared by all devices.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from app.engine.hmm.params import HmmParams
from app.engine.radiomap import RadioMap
from app.engine.wknn import Fingerprints


class EmissionModel:
    """Per-floor log-likelihood tables of every reference point, prepared once per site.

    Arrays are stored transmitter-major (T, P) so a scan gathers contiguous rows.

    Parameters
    ----------
    maps : sequence of RadioMap
        One map per floor.
    params : HmmParams
        Unmapped-transmitter constants.
    """

    def __init__(self, maps: Sequence[RadioMap], params: HmmParams) -> None:
        self.maps = tuple(maps)
        self.floors = tuple(m.floor for m in self.maps)
        self.fingerprints = Fingerprints(self.maps, params.missing_dbm)
        self.grids = [m.index_grid() for m in self.maps]
        self.xy = [m.xy for m in self.maps]
        self.mean: list[np.ndarray] = []
        self.inv_var: list[np.ndarray] = []
        self.base: list[np.ndarray] = []
        self.log_miss: list[np.ndarray] = []
        self.absent: list[np.ndarray] = []
        for m in self.maps:
            heard = np.isfinite(m.mean)
            mean = np.where(heard, m.mean, params.unmapped_dbm)
            var = np.where(heard, m.var, params.unmapped_var_db2)
            q = np.clip(m.detect, 1e-6, 1.0 - 1e-6)
            self.mean.append(np.ascontiguousarray(mean.T, dtype=np.float32))
            self.inv_var.append(np.ascontiguousarray((1.0 / var).T, dtype=np.float32))
            # ln q + ln N normaliser: ln q - ½ ln(2π σ²)
            base = np.log(q) - 0.5 * np.log(2.0 * np.pi * var)
            self.base.append(np.ascontiguousarray(base.T, dtype=np.float32))
            log_miss = np.log1p(-q)
            self.log_miss.append(np.ascontiguousarray(log_miss.T, dtype=np.float32))
            # S₀_j = Σ_a ln(1 - q_ja): every mapped transmitter unheard
            self.absent.append(log_miss.sum(axis=1, dtype=np.float64))
        n_tx = max(int(m.tx.max(initial=-1)) for m in self.maps) + 1
        self.columns = self.fingerprints.columns
        self.n_tx = n_tx
        # transmitters some floor's map has: only they are evidence of a position
        self.mapped = np.zeros(n_tx, dtype=bool)
        for lookup in self.columns:
            self.mapped[: lookup.size] |= lookup >= 0
        # ln q₀ + ln N(s; s₀, v₀) pieces for transmitters absent from a floor's map
        self.unmapped = (
            np.log(params.unmapped_detect) - 0.5 * np.log(2.0 * np.pi * params.unmapped_var_db2),
            params.unmapped_dbm,
            1.0 / params.unmapped_var_db2,
        )
        self.params = params

    def is_mapped(self, tx: np.ndarray) -> np.ndarray:
        """Return which site transmitter indices some floor's map has, shape (n,)."""
        tx = np.asarray(tx, dtype=np.int64)
        inside = tx < self.n_tx
        out = np.zeros(tx.size, dtype=bool)
        out[inside] = self.mapped[tx[inside]]
        return out

    def n_points(self, f: int) -> int:
        """Return the number of reference points of map ``f`` (position in ``maps``)."""
        return self.maps[f].n_points

    def log_likelihood(self, f: int, tx: np.ndarray, rssi: np.ndarray) -> np.ndarray:
        """Return the tempered log-likelihood of one scan at every point of map ``f``, (P,).

        Parameters
        ----------
        f : int
            Position of the map in ``maps``.
        tx : ndarray of int, shape (n,)
            Unique site transmitter indices heard.
        rssi : ndarray, shape (n,)
            Their RSSI (dBm).
        """
        p = self.params
        tx = np.asarray(tx, dtype=np.int64)
        rssi = np.asarray(rssi, dtype=np.float32)
        lookup = self.columns[f]
        col = np.full(tx.size, -1, dtype=np.int64)
        known = tx < lookup.size
        col[known] = lookup[tx[known]]
        on = col >= 0
        c, s = col[on], rssi[on][:, None]
        # ln q + ln N(s; μ, σ²) = base - ½ (s - μ)² / σ², floored
        term = self.base[f][c] - 0.5 * (s - self.mean[f][c]) ** 2 * self.inv_var[f][c]
        term = np.maximum(term, np.float32(p.loglik_floor))
        # heard ones are not among the unheard: remove their ln(1 - q)
        ll = self.absent[f] + (term - self.log_miss[f][c]).sum(axis=0, dtype=np.float64)
        base0, mean0, inv0 = self.unmapped
        off = rssi[~on].astype(float)
        # transmitters the floor's map lacks: constant over the floor
        ll += np.maximum(base0 - 0.5 * (off - mean0) ** 2 * inv0, p.loglik_floor).sum()
        # tempered: w ln L
        return p.emission_weight * ll

    def knn(self, f: int, tx: np.ndarray, rssi: np.ndarray, k: int) -> np.ndarray:
        """Return the weighted mean position (m) of the k nearest fingerprints on map ``f``."""
        d2 = self.fingerprints.sq_distances(tx, rssi)
        start = sum(m.n_points for m in self.maps[:f])
        d = np.sqrt(d2[start : start + self.maps[f].n_points])
        k = min(k, d.size)
        near = np.argpartition(d, k - 1)[:k]
        # w = 1 / (d + ε)
        w = 1.0 / (d[near] + 1e-3)
        return w @ self.xy[f][near] / w.sum()
