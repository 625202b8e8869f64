"""Absolute evidence along a track: cost rasters of occasional WiFi scans over the floor.

A phone in energy-saving mode can afford a WiFi scan every 10–30 s. Each scan
is a fingerprint observation at one point of the track: against the floor's
radio map (seed 002's emission, ``EmissionModel``) it has a log-likelihood ℓ_j
at every reference point j. The fitter adds, for the track point the scan was
taken at, the cost

    c(x) = min(cap, w (ℓ_max - ℓ_j(x)))

where j(x) is the reference point nearest to x (its own cell's when it has
one) and w the tempering of one scan's correlated readings. A position
nobody surveyed says nothing about the scan, so it takes its nearest
surveyed neighbour's cost rather than a penalty: a penalty would pull every
track into the surveyed corridors whatever the scan heard. The costs are kept
as one raster per scan on the radio map's own grid (1 m), so a candidate end
costs one gather.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.params import HmmParams
from app.engine.radiomap import RadioMap


@dataclass(frozen=True)
class WifiScan:
    """One scan taken at track point ``point`` (0 is the start): transmitters and RSSI (dBm).

    ``tx`` are the site's transmitter indices, as the radio map's ``tx`` names them.
    """

    point: int
    tx: np.ndarray
    rssi: np.ndarray


@dataclass(frozen=True)
class AnchorCosts:
    """Per-anchor log-likelihood deficits (nats, untempered) on one grid.

    Attributes
    ----------
    point : ndarray of int, shape (A,)
        Track point (0 … n) each anchor observes.
    origin : ndarray, shape (2,)
        x, y (m) of the lower-left corner of the grid.
    cell : float
        Grid cell side (m).
    deficit : ndarray of float32, shape (A, ny, nx)
        ℓ_max - ℓ(x) per anchor, of the nearest reference point.
    """

    point: np.ndarray
    origin: np.ndarray
    cell: float
    deficit: np.ndarray

    def __len__(self) -> int:
        """Return the number of anchors."""
        return int(self.point.size)

    def cost(
        self, anchor: int | np.ndarray, xy: np.ndarray, weight: float, cap: float
    ) -> np.ndarray:
        """Return ``min(cap, weight · deficit)`` of anchors ``anchor`` at points ``xy`` (..., 2)."""
        _, ny, nx = self.deficit.shape
        ij = np.floor((np.asarray(xy, dtype=float) - self.origin) / self.cell).astype(np.int64)
        col = np.clip(ij[..., 0], 0, nx - 1)
        row = np.clip(ij[..., 1], 0, ny - 1)
        d = self.deficit[np.asarray(anchor, dtype=np.int64), row, col]
        # c = min(cap, w (ℓ_max - ℓ))
        return np.minimum(weight * d.astype(float), cap)

    def for_point(
        self, point: int, weight: float, cap: float
    ) -> Callable[[np.ndarray], np.ndarray] | None:
        """Return the summed cost function of the anchors observing ``point``, None for none."""
        mine = np.flatnonzero(self.point == point)
        if mine.size == 0:
            return None

        def cost(xy: np.ndarray) -> np.ndarray:
            out = np.zeros(len(xy))
            for a in mine:
                out += self.cost(int(a), xy, weight, cap)
            return out

        return cost

    def total(self, tracks: np.ndarray, weight: float, cap: float) -> np.ndarray:
        """Return the summed anchor cost of each track, ``tracks`` (H, n + 1, 2) → (H,)."""
        if not len(self):
            return np.zeros(tracks.shape[0])
        xy = tracks[:, self.point, :]
        return self.cost(np.arange(len(self))[None, :], xy, weight, cap).sum(axis=1)


def wifi_anchor_costs(radio_map: RadioMap, scans: Sequence[WifiScan]) -> AnchorCosts:
    """Return the anchor costs of ``scans`` against one floor's radio map.

    The likelihood is the HMM's per-point emission (detection rates, Gaussian
    RSSI, floored per transmitter), untempered: the fitter's ``anchor_weight``
    tempers it.
    """
    model = EmissionModel((radio_map,), replace(HmmParams(), emission_weight=1.0))
    index = radio_map.index_grid()
    # every cell's nearest reference point (itself when it is one)
    _, (row, col) = ndimage.distance_transform_edt(index < 0, return_indices=True)
    nearest = index[row, col]
    deficit = np.empty((len(scans), *radio_map.shape), dtype=np.float32)
    for a, scan in enumerate(scans):
        tx, first = np.unique(np.asarray(scan.tx, dtype=np.int64), return_index=True)
        ll = model.log_likelihood(0, tx, np.asarray(scan.rssi, dtype=float)[first])
        # ℓ_max - ℓ_j(x)
        deficit[a] = (ll.max() - ll)[nearest]
    return AnchorCosts(
        point=np.array([s.point for s in scans], dtype=np.int64),
        origin=np.asarray(radio_map.origin, dtype=float),
        cell=float(radio_map.cell),
        deficit=deficit,
    )
