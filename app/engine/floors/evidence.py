"""How well one window's readings fit each floor: the forward filter's evidence.

Two kinds of evidence, summed in the log domain (a log-linear pool):

- **the transmitter table** (always): the mean of the ``strongest_k``
  strongest readings of each floor's transmitters, divided by a temperature
  ``strength_temperature_db``. In a mall whose atria let many readings
  come from other floors (ILC site1), the floor of the strongest readings
  is right more often than the patent's E_L;
- **radio maps** (when every floor has one): the likelihood of the window's
  strongest readings at each floor's reference points, a Gaussian on the
  difference from the surveyed mean (a transmitter the survey never heard at
  a point counts as ``unheard_dbm`` there, so a strong reading of a
  transmitter the floor never hears is evidence against the floor), each
  reading's term floored so one multipath outlier cannot veto a point, and
  averaged over the points. Only the readings heard enter: phones' scans
  are incomplete, so a mapped transmitter missing from a scan is weak
  evidence. The map knows what the table cannot, e.g. that in an atrium the
  floors above and below are heard loudest. The table's term still counts
  where the map is weak, e.g. in parts of a floor no survey walked.

The evidence is computed for a batch of devices at once, by the engine.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.engine.floors.params import FloorParams
from app.engine.radiomap import RadioMap

MAP_CHUNK_ELEMENTS = 1 << 20
"""Readings × reference points scored per numpy call: bounds the temporaries to a few MB."""


def rank_in_groups(group: np.ndarray, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the order sorting by group, then by decreasing value, and each sorted item's rank.

    Parameters
    ----------
    group : ndarray of int, shape (n,)
        Group of each item.
    value : ndarray, shape (n,)
        Value of each item.

    Returns
    -------
    order : ndarray of intp, shape (n,)
        Items by group, the largest value first within a group (ties by position).
    rank : ndarray of intp, shape (n,)
        Position of ``order[i]`` within its group (0 for the largest).
    """
    order = np.lexsort((-np.asarray(value), np.asarray(group)))
    g = np.asarray(group)[order]
    # rank = position - position of the group's first item
    rank = np.arange(g.size) - np.searchsorted(g, g, side="left")
    return order, rank


def strongest_means(
    device: np.ndarray,
    floor: np.ndarray,
    rssi: np.ndarray,
    n_devices: int,
    n_floors: int,
    k: int,
    missing_dbm: float,
) -> np.ndarray:
    """Return the mean of each device's k strongest readings per floor, shape (D, F), dBm.

    A floor with fewer than k readings counts the missing ones as ``missing_dbm``.

    Parameters
    ----------
    device, floor : ndarray of int, shape (n,)
        Device row and transmitter floor of each reading (one per transmitter).
    rssi : ndarray, shape (n,)
        Readings (dBm).
    """
    group = np.asarray(device, np.intp) * n_floors + np.asarray(floor, np.intp)
    order, rank = rank_in_groups(group, rssi)
    top = order[rank < k]
    size = n_devices * n_floors
    total = np.bincount(group[top], weights=np.asarray(rssi, float)[top], minlength=size)
    count = np.bincount(group[top], minlength=size)
    # s̄ = (Σ top-k + (k - n) s_miss) / k
    return ((total + (k - count) * missing_dbm) / k).reshape(n_devices, n_floors)


def log_mean_exp(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Return ln mean exp(x) along ``axis``, without overflow."""
    peak = np.max(x, axis=axis, keepdims=True)
    # ln mean eˣ = m + ln Σ e^(x - m) - ln n
    out = peak + np.log(np.sum(np.exp(x - peak), axis=axis, keepdims=True)) - np.log(x.shape[axis])
    return np.squeeze(out, axis=axis)


def map_log_likelihood(
    rssi: np.ndarray, mean: np.ndarray, starts: np.ndarray, sigma_db: float, outlier_nats: float
) -> np.ndarray:
    """Return each device's log-likelihood at each reference point: Σ over its readings.

    Parameters
    ----------
    rssi : ndarray, shape (n,)
        Readings (dBm), grouped by device.
    mean : ndarray of float32, shape (n, P)
        Each reading's transmitter's mean RSSI (dBm) at each point; overwritten.
    starts : ndarray of int, shape (D,)
        First reading of each device (increasing, the first 0).
    sigma_db, outlier_nats : float
        σ of a reading and the most one reading may cost a point.

    Returns
    -------
    ndarray, shape (D, P)
        Σ_a max(-½ ((s_a - μ_ja) / σ)², -c), nats (the Gaussian's constant left out).
    """
    r = mean
    # r = (μ - s)², in place: the (n, P) temporaries dominate the cost
    np.subtract(r, np.asarray(rssi, np.float32)[:, None], out=r)
    np.multiply(r, r, out=r)
    # min((μ - s)², 2 c σ²): one reading costs at most c
    np.minimum(r, np.float32(2.0 * outlier_nats * sigma_db * sigma_db), out=r)
    ends = np.r_[starts[1:], r.shape[0]]
    # ln L_j = -Σ_a min(·) / 2σ²; a sum per device (np.add.reduceat along rows is slower)
    total = np.stack([r[lo:hi].sum(axis=0) for lo, hi in zip(starts, ends, strict=True)])
    return total.astype(float) * (-0.5 / (sigma_db * sigma_db))


@dataclass(frozen=True, eq=False)
class MapTable:
    """One floor's radio map prepared for floor likelihoods.

    Attributes
    ----------
    row : ndarray of intp, shape (T_site,)
        Row of ``mean`` for each site transmitter; the last row (all
        ``unheard_dbm``) for transmitters the map lacks.
    mean : ndarray of float32, shape (T + 1, P)
        Mean RSSI (dBm) of each mapped transmitter at each kept reference
        point, ``unheard_dbm`` where never heard; transmitter-major so a
        window's readings gather contiguous rows.
    """

    row: np.ndarray
    mean: np.ndarray


def thin_points(ij: np.ndarray, weight: np.ndarray, cell: float, block_m: float) -> np.ndarray:
    """Return the indices of the most weighted reference point of each block, sorted.

    Parameters
    ----------
    ij : ndarray of int, shape (P, 2)
        Grid row and column of each point.
    weight : ndarray, shape (P,)
        Survey weight of each point.
    cell : float
        Grid cell side (m).
    block_m : float
        Block side (m); at most one cell keeps every point.
    """
    step = max(int(round(block_m / cell)), 1)
    block = np.asarray(ij, np.int64) // step
    key = block[:, 0] * (int(block[:, 1].max(initial=0)) + 1) + block[:, 1]
    order = np.lexsort((-np.asarray(weight), key))
    _, first = np.unique(key[order], return_index=True)
    return np.sort(order[first])


def map_table(radio_map: RadioMap, n_tx: int, params: FloorParams) -> MapTable:
    """Prepare a floor's radio map (site transmitter columns) for :class:`FloorEvidence`."""
    keep = thin_points(radio_map.ij, radio_map.weight, radio_map.cell, params.map_block_m)
    mean = np.where(np.isfinite(radio_map.mean[keep]), radio_map.mean[keep], params.unheard_dbm)
    table = np.full((radio_map.tx.size + 1, keep.size), params.unheard_dbm, np.float32)
    table[:-1] = mean.T
    row = np.full(max(n_tx, int(radio_map.tx.max(initial=-1)) + 1), radio_map.tx.size, np.intp)
    row[radio_map.tx] = np.arange(radio_map.tx.size)
    return MapTable(row=row, mean=np.ascontiguousarray(table))


class FloorEvidence:
    """Per-window log-likelihood of every floor for a batch of devices, prepared once per site.

    Parameters
    ----------
    tx_floor : ndarray of int, shape (T,)
        Floor index of each site transmitter.
    n_floors : int
        Number of floors.
    params : FloorParams
    radio_maps : sequence of RadioMap, optional
        Radio maps in site transmitter indices; used only when every floor has
        one (a floor without one could not be compared with the others).
    """

    def __init__(
        self,
        tx_floor: np.ndarray,
        n_floors: int,
        params: FloorParams,
        radio_maps: Sequence[RadioMap] = (),
    ) -> None:
        self.tx_floor = np.asarray(tx_floor, np.intp)
        self.n_floors = int(n_floors)
        self.params = params
        by_floor = {m.floor: m for m in radio_maps}
        self.tables: tuple[MapTable, ...] = ()
        if n_floors and all(f in by_floor for f in range(n_floors)):
            n_tx = self.tx_floor.size
            self.tables = tuple(map_table(by_floor[f], n_tx, params) for f in range(n_floors))

    @property
    def uses_maps(self) -> bool:
        """Whether the radio maps enter the evidence."""
        return bool(self.tables)

    def log_likelihood(
        self, device: np.ndarray, tx: np.ndarray, rssi: np.ndarray, n_devices: int
    ) -> np.ndarray:
        """Return the log-likelihood (nats, up to a constant per device) of each floor, (D, F).

        Parameters
        ----------
        device : ndarray of int, shape (n,)
            Device row of each reading.
        tx : ndarray of int, shape (n,)
            Site transmitter index of each reading.
        rssi : ndarray, shape (n,)
            Readings (dBm); a transmitter read more than once by a device counts
            once, with its mean.
        n_devices : int
            Rows of the result; devices without readings get zeros.
        """
        p = self.params
        out = np.zeros((n_devices, self.n_floors))
        if len(tx) == 0 or self.n_floors == 0:
            return out
        n_tx = max(self.tx_floor.size, 1)
        key, inverse = np.unique(
            np.asarray(device, np.int64) * n_tx + np.asarray(tx, np.int64), return_inverse=True
        )
        # s̄ = Σ s / n per (device, transmitter)
        mean = np.bincount(inverse, weights=rssi) / np.bincount(inverse)
        dev, tx_u = key // n_tx, key % n_tx
        strongest = strongest_means(
            dev, self.tx_floor[tx_u], mean, n_devices, self.n_floors, p.strongest_k, p.missing_dbm
        )
        # ln L_tx = s̄_f / τ
        out += strongest / p.strength_temperature_db
        if self.tables:
            out += p.map_weight * self._map_log_likelihood(dev, tx_u, mean, n_devices)
        heard = np.zeros(n_devices, bool)
        heard[dev] = True
        out[~heard] = 0.0
        return out

    def _map_log_likelihood(
        self, dev: np.ndarray, tx: np.ndarray, rssi: np.ndarray, n_devices: int
    ) -> np.ndarray:
        """Return ln mean_j Π_a L(s_a | j) per device and floor over the kept points, (D, F)."""
        p = self.params
        order, rank = rank_in_groups(dev, rssi)
        use = order[rank < p.map_readings]
        dev, tx, rssi = dev[use], tx[use], rssi[use]
        starts = np.flatnonzero(np.r_[True, dev[1:] != dev[:-1]])
        bounds = np.r_[starts, dev.size]
        out = np.zeros((n_devices, self.n_floors))
        for f, table in enumerate(self.tables):
            n_points = table.mean.shape[1]
            per_chunk = max(MAP_CHUNK_ELEMENTS // max(n_points * p.map_readings, 1), 1)
            for c in range(0, starts.size, per_chunk):
                lo, hi = bounds[c], bounds[min(c + per_chunk, starts.size)]
                mu = table.mean[table.row[tx[lo:hi]]]
                per_point = map_log_likelihood(
                    rssi[lo:hi],
                    mu,
                    starts[c : c + per_chunk] - lo,
                    p.map_sigma_db,
                    p.map_outlier_nats,
                )
                rows = dev[starts[c : c + per_chunk]]
                out[rows, f] = log_mean_exp(per_point, axis=1)
        return out
