"""Absolute evidence along a track: cost rasters of occasional WiFi scans over the floor.

A phone in energy-saving mode can afford a WiFi scan every 10–30 s. Each scan
is a fingerprint observation at one point of the track. Its likelihood over
the floor comes from the survey scans it resembles most (the per-scan k-NN of
``app.engine.scan_knn``): a mixture of Gaussians at their surveyed positions.
For the track point the scan was taken at the fitter adds

    c(x) = min(cap, w (ℓ_max - ℓ(x)))

with ℓ the mixture's log-density and w its weight. On site1's validation
walks this placed a scan's best cell far nearer the truth than the HMM's
per-point emission on the pooled radio map does: a pooled cell's Gaussian
RSSI model ranks far-away cells too close to the right one for a single scan.
The costs are kept as one raster per scan on the radio map's own grid (1 m),
so a candidate end costs one gather.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from app.engine.radiomap import RadioMap
from app.engine.scan_knn import ReferenceScans


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
    """Per-anchor log-likelihood deficits (nats) on one grid.

    Attributes
    ----------
    point : ndarray of int, shape (A,)
        Track point (0 … n) each anchor observes.
    origin : ndarray, shape (2,)
        x, y (m) of the lower-left corner of the grid.
    cell : float
        Grid cell side (m).
    deficit : ndarray of float32, shape (A, ny, nx)
        ℓ_max - ℓ(x) per anchor at each cell centre.
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


def mixture_deficit(
    x: np.ndarray, y: np.ndarray, centres: np.ndarray, weight: np.ndarray, sigma: float
) -> np.ndarray:
    """Return a Gaussian mixture's negative log-density over a grid, relative to its minimum.

    ``x`` (nx,) and ``y`` (ny,) are the cell centres, ``centres`` (k, 2) and ``weight`` (k,)
    the components; the result is (ny, nx). One component's grid is held at a time.
    """

    def q(k: int) -> np.ndarray:
        # q_k = |x - c_k|² / 2σ²
        dy2 = (y[:, None] - centres[k, 1]) ** 2
        return (dy2 + (x[None, :] - centres[k, 0]) ** 2) / (2 * sigma**2)

    low = q(0)
    for k in range(1, len(weight)):
        np.minimum(low, q(k), out=low)
    # -log Σ_k w_k exp(-q_k) = low - log Σ_k w_k exp(low - q_k)
    total = np.zeros_like(low)
    for k, w in enumerate(weight):
        total += w * np.exp(low - q(k))
    nll = low - np.log(total)
    return nll - nll.min()


def wifi_anchor_costs(
    radio_map: RadioMap, refs: ReferenceScans, scans: Sequence[WifiScan], sigma: float
) -> AnchorCosts:
    """Return the anchor costs of ``scans`` on one floor, from their nearest survey scans.

    Each scan's k nearest reference scans in signal space (the per-scan k-NN,
    ``ReferenceScans.neighbours``) become a Gaussian mixture over the floor:
    their surveyed positions, their k-NN weights, and a common component
    spread ``sigma`` (m). Where the neighbours disagree the mixture is broad
    or has several modes, so a vague scan constrains the track little. The
    deficit is the mixture's negative log-density above its best cell, on the
    radio map's grid.
    """
    ny, nx = radio_map.shape
    # cell centres: x by column, y by row
    x = radio_map.origin[0] + (np.arange(nx) + 0.5) * radio_map.cell
    y = radio_map.origin[1] + (np.arange(ny) + 0.5) * radio_map.cell
    deficit = np.empty((len(scans), ny, nx), dtype=np.float32)
    for a, scan in enumerate(scans):
        tx, first = np.unique(np.asarray(scan.tx, dtype=np.int64), return_index=True)
        d = refs.distances(tx, np.asarray(scan.rssi, dtype=float)[first])
        if not np.isfinite(d).any():
            deficit[a] = 0.0
            continue
        near, weight = refs.neighbours(d, slice(None))
        deficit[a] = mixture_deficit(x, y, near, weight, sigma)
    return AnchorCosts(
        point=np.array([s.point for s in scans], dtype=np.int64),
        origin=np.asarray(radio_map.origin, dtype=float),
        cell=float(radio_map.cell),
        deficit=deficit,
    )
