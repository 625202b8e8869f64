"""Weighted k-nearest-neighbour fingerprinting per WiFi scan, without tracking.

The peer method of the HMM (CN106028450 uses it for the initial position): the
scan's RSSI vector is compared with every reference point's mean vector by
Euclidean distance over the union of transmitters, a transmitter missing on
either side counting as ``missing_dbm``; the k nearest points, weighted by
1/distance, give the position, and their weighted vote the floor.

With values shifted by the missing level (``v = rssi - missing``, 0 when
missing) the squared distance is ``|m|² - 2 m·s + |s|²``: one matrix-vector
product per floor over the transmitters the scan heard, whatever the number
of transmitters in the maps.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.engine.radiomap import RadioMap
from app.engine.samples import Batch, Estimate
from app.engine.scans import ScanParams, group_scans


@dataclass(frozen=True)
class WknnParams:
    """Tunable constants of WKNN.

    Attributes
    ----------
    k : int
        Neighbours averaged (the patent's 3–5).
    missing_dbm : float
        RSSI assumed for a transmitter not heard (scan) or never heard at a
        point (map): below the phones' sensitivity floor of about -95 dBm.
    eps_db : float
        Added to distances before inverting them, so an exact match does not
        divide by zero.
    accuracy_floor_m : float
        Smallest accuracy radius reported (m): the grid cell and survey
        positions limit what the neighbours' spread can say.
    """

    k: int = 4
    missing_dbm: float = -100.0
    eps_db: float = 1e-3
    accuracy_floor_m: float = 2.0


@dataclass(frozen=True)
class WknnResult:
    """One scan's WKNN answer: position (m), floor index, the neighbours and their weights."""

    xy: np.ndarray
    floor: int
    neighbours: np.ndarray
    weights: np.ndarray
    spread: float


class Fingerprints:
    """Shifted mean fingerprints of every floor, prepared for distance queries.

    Parameters
    ----------
    maps : sequence of RadioMap
        One map per floor (any order; each carries its floor index).
    missing_dbm : float
        Value of a missing reading.
    """

    def __init__(self, maps: Sequence[RadioMap], missing_dbm: float) -> None:
        self.maps = tuple(maps)
        self.missing = float(missing_dbm)
        # v = max(mean - missing, 0), 0 where never heard; stored (T, P) so that the
        # transmitters of a scan are contiguous rows
        self.values = [
            np.ascontiguousarray(
                np.nan_to_num(np.maximum(m.mean - np.float32(self.missing), 0.0)).T
            )
            for m in self.maps
        ]
        # |v_j|² per point
        self.norms = [np.einsum("tp,tp->p", v, v, dtype=np.float64) for v in self.values]
        self.xy = np.vstack([m.xy for m in self.maps])
        self.floor = np.concatenate([np.full(m.n_points, m.floor, np.int32) for m in self.maps])
        n_tx = max(int(m.tx.max(initial=-1)) for m in self.maps) + 1
        self.columns = []
        for m in self.maps:
            lookup = np.full(n_tx, -1, dtype=np.int64)
            lookup[m.tx] = np.arange(m.tx.size)
            self.columns.append(lookup)

    def sq_distances(self, tx: np.ndarray, rssi: np.ndarray) -> np.ndarray:
        """Return squared RSSI distances (dB²) of one scan to every point, shape (P_total,).

        Parameters
        ----------
        tx : ndarray of int, shape (n,)
            Site transmitter indices heard (unique).
        rssi : ndarray, shape (n,)
            Their RSSI (dBm).
        """
        tx = np.asarray(tx, dtype=np.int64)
        # s = max(rssi - missing, 0)
        s = np.maximum(np.asarray(rssi, dtype=float) - self.missing, 0.0)
        s_norm = float(s @ s)
        out = []
        for lookup, values, norms in zip(self.columns, self.values, self.norms, strict=True):
            known = tx < lookup.size
            col = np.full(tx.size, -1, dtype=np.int64)
            col[known] = lookup[tx[known]]
            on = col >= 0
            # d² = |v|² - 2 v·s + |s|²
            dot = s[on] @ values[col[on]].astype(np.float64)
            out.append(np.maximum(norms - 2.0 * dot + s_norm, 0.0))
        return np.concatenate(out)


def wknn(
    fingerprints: Fingerprints, tx: np.ndarray, rssi: np.ndarray, params: WknnParams
) -> WknnResult:
    """Locate one scan: weighted mean of the k nearest fingerprints on their voted floor.

    Parameters
    ----------
    fingerprints : Fingerprints
        Prepared maps of all floors.
    tx : ndarray of int, shape (n,)
        Site transmitter indices heard (unique).
    rssi : ndarray, shape (n,)
        Their RSSI (dBm).
    params : WknnParams
        k, missing value, epsilon.
    """
    d = np.sqrt(fingerprints.sq_distances(tx, rssi))
    k = min(params.k, d.size)
    nearest = np.argpartition(d, k - 1)[:k]
    nearest = nearest[np.argsort(d[nearest], kind="stable")]
    # w_i = 1 / (d_i + ε)
    w = 1.0 / (d[nearest] + params.eps_db)
    floors = fingerprints.floor[nearest]
    votes = np.bincount(floors, weights=w)
    floor = int(np.argmax(votes))
    on = floors == floor
    w_on = w[on] / w[on].sum()
    # x = Σ w_i x_i / Σ w_i
    xy = w_on @ fingerprints.xy[nearest[on]]
    # spread = sqrt(Σ w_i |x_i - x|²)
    spread = float(np.sqrt(w_on @ np.sum((fingerprints.xy[nearest[on]] - xy) ** 2, axis=1)))
    return WknnResult(xy=xy, floor=floor, neighbours=nearest, weights=w, spread=spread)


def unique_readings(tx: np.ndarray, rssi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return sorted unique transmitters of a scan and the mean RSSI of each."""
    u, inverse = np.unique(np.asarray(tx, dtype=np.int64), return_inverse=True)
    # mean of repeated readings of one transmitter
    mean = np.bincount(inverse, np.asarray(rssi, dtype=float)) / np.bincount(inverse)
    return u, mean


class WknnTracker:
    """Per-scan WKNN as a device filter: one estimate per scan, no state between scans."""

    method = "wknn"

    def __init__(
        self, fingerprints: Fingerprints, params: WknnParams, scans: ScanParams | None = None
    ) -> None:
        self.fingerprints = fingerprints
        self.params = params
        self.scans = scans or ScanParams()

    def process(self, batch: Batch) -> list[Estimate]:
        """Return one estimate per scan of the batch, at the scan's last reading."""
        out = []
        r = batch.rssi
        for idx in group_scans(r.t, r.tx, self.scans):
            tx, rssi = unique_readings(r.tx[idx], r.rssi[idx])
            res = wknn(self.fingerprints, tx, rssi, self.params)
            out.append(
                Estimate(
                    t=int(r.t[idx].max()),
                    x=float(res.xy[0]),
                    y=float(res.xy[1]),
                    z=0.0,
                    floor=res.floor,
                    heading=float("nan"),
                    accuracy=max(res.spread, self.params.accuracy_floor_m),
                    speed=float("nan"),
                    method=self.method,
                )
            )
        return out

    def snapshot(self) -> dict[str, Any]:
        """Return the (empty) state: every scan is located on its own."""
        return {}
