"""Floor selection: a forward filter over floors, and the patent's E_L ranking.

**The forward filter** (:class:`FloorFilter`, the engine's default) is a
hidden Markov model whose state is the floor. Per positioning window the
belief is carried by a sticky transition (a change of floor has probability
``switch_prob`` per window) and multiplied by how well the window's readings
fit each floor (:class:`FloorEvidence`); the floor is the belief's argmax.
A single contrary window cannot outweigh a belief built over many windows,
while a real change of floor, whose every scan favours the new floor, wins
within a few scans: the filter needs no separate hysteresis.

Two kinds of evidence, summed in the log domain (a log-linear pool):

- **the transmitter table** (always): the mean of the ``strongest_k``
  strongest readings of each floor's transmitters, divided by a temperature
  ``strength_temperature_db``. On ILC site1, a mall whose atria let about
  42% of readings come from other floors, the floor of the strongest
  readings is right in about 95% of windows, the patent's E_L below in 88%;
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

A barometer shapes the transition: air pressure falls about 0.12 hPa per
metre climbed, so a change of a storey shows within seconds of taking the
stairs or a lift, while radio needs a few scans. A height change of at least
``climb_min_m`` within ``climb_window_ms`` raises the probability of moving
to the floors in that direction to ``climb_switch_prob``; a flat barometer
lowers the probability of any change to ``flat_switch_prob``. Pressure is
compared only across that short window because weather drifts it by about
1 hPa in three hours.

**The patent's selection** (:class:`FloorSelector`, Eurasian patent 047000)
accumulates, per floor L over the last N seconds, the number n of readings
from transmitters on L, their summed RSSI and their summed A, and ranks the
floors with readings ("active floors") by

    E_L = -n² / Σ rssi_i - n / Σ A_i,

i.e. n / |mean RSSI| + 1 / |mean A|: more and stronger readings win.
Ranking alone flickers where the floors are coupled (atria, stairwells,
glass floors), so the first floor becomes *the* floor only after it has led
by a relative margin for several consecutive windows; a climb in the
challenger's direction switches at once, a flat barometer makes radio wait
``flat_dwell_windows`` instead.

Both selectors return the active floors (those heard within ``history_ms``)
with the chosen floor first; without any, no floor.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from app.engine.radiomap import RadioMap

NEVER = np.iinfo(np.int64).min // 2
"""Time (ms) standing for "never"; halved so that differences cannot overflow."""


@dataclass(frozen=True)
class FloorParams:
    """Constants of floor selection.

    Attributes
    ----------
    method : str
        ``"filter"``: the forward filter over floors; ``"patent"``: the
        patent's E_L ranking with hysteresis.
    history_ms : int
        N of the patent (its value is not given): readings of the last
        ``history_ms`` count. 10 s spans three to five WiFi scans of a phone.
        For the filter, a floor heard within it is active.
    window_ms : int
        Length of one positioning window (T_u), the unit of the dwell counts
        and of the transition probabilities.
    switch_margin : float
        Patent: a challenger must score at least (1 + margin) times the current floor.
    dwell_windows : int
        Patent: consecutive windows a challenger must lead before it becomes the floor.
    flat_dwell_windows : int
        Patent: the same when a barometer reports no climb.
    hpa_per_m : float
        Pressure drop (hPa) per metre of height near sea level: ρ g = 1.2 kg/m³ × 9.81 m/s².
    climb_min_m : float
        Height change (m) that counts as a change of floor: half a low storey.
    climb_window_ms : int
        Span (ms) over which pressure is compared: long enough for a flight of
        stairs or a lift ride, short against weather drift.
    switch_prob : float
        Filter: probability per window that the floor changes, without a
        barometer; shared evenly by the other floors. Its log, about -9 nats
        for five floors, is the evidence a new floor must gather: two or
        three scans of a real change, more than any single contrary scan.
    flat_switch_prob : float
        Filter: the same while a barometer shows no climb, and towards the
        floors against a climb it shows: people do not change floor without
        one, so radio alone needs more scans.
    climb_switch_prob : float
        Filter: probability per window of moving to a floor in the direction
        of a climb the barometer shows, shared by those floors; high, so the
        first scans of the new floor decide.
    strongest_k : int
        Filter: a floor's transmitter evidence is the mean of its k strongest
        readings in the window; one reading alone is often a multipath peak.
    strength_temperature_db : float
        Filter: τ of the softmax over floors of those means: floors whose
        strongest readings differ by τ dB differ by one nat of evidence.
        Larger than the spread of one reading (4–6 dB), since the readings
        of one scan are correlated and atria make other floors loud.
    missing_dbm : float
        Filter: a floor with fewer than k readings counts the missing ones at
        this level, below phones' sensitivity.
    map_weight : float
        Filter: weight of the radio maps' log-likelihood (a tempered
        likelihood): the readings of one window are correlated, and one
        window's map evidence is worth a few nats, not hundreds.
    map_sigma_db : float
        Filter: σ (dB) of a reading about a reference point's surveyed mean:
        the spread of readings at a point plus the point's own noise.
    map_outlier_nats : float
        Filter: a reading costs a point at most this much (before
        ``map_weight``): beyond σ √(2 × 4) ≈ 17 dB a reading is an outlier,
        not a measure of distance.
    unheard_dbm : float
        Filter: mean RSSI at a reference point of a transmitter its survey
        never heard there.
    map_readings : int
        Filter: at most this many readings of a window (the strongest) are
        scored against the maps, to bound the cost. Weak readings count: a
        transmitter a floor's survey never heard is evidence against that
        floor even when it is faint (on ILC site1's validation walks, with
        only the 20 strongest readings scored 2.3% of estimates fell on a
        wrong floor, with all of them 0.16%).
    map_block_m : float
        Filter: one reference point (the most surveyed) per block of this side
        (m) enters the floor likelihood; the maps are smooth over metres and
        the likelihood is averaged over the floor anyway. On ILC site1's
        validation walks 1, 2, 3 and 4 m blocks choose the same floors, 5 m
        start to miss; 4 m costs a sixteenth of scoring every point.
    """

    method: str = "filter"
    history_ms: int = 10_000
    window_ms: int = 1000
    switch_margin: float = 0.05
    dwell_windows: int = 3
    flat_dwell_windows: int = 10
    hpa_per_m: float = 0.118
    climb_min_m: float = 2.0
    climb_window_ms: int = 30_000
    switch_prob: float = 1e-3
    flat_switch_prob: float = 1e-4
    climb_switch_prob: float = 0.2
    strongest_k: int = 3
    strength_temperature_db: float = 4.0
    missing_dbm: float = -100.0
    map_weight: float = 0.05
    map_sigma_db: float = 6.0
    map_outlier_nats: float = 4.0
    unheard_dbm: float = -100.0
    map_readings: int = 100
    map_block_m: float = 4.0


def window_sums(
    floor: np.ndarray, rssi: np.ndarray, A: np.ndarray, n_floors: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return per-floor (count, Σ rssi, Σ A) of one window's readings.

    Parameters
    ----------
    floor : ndarray of int, shape (n,)
        Floor index of each reading's transmitter.
    rssi, A : ndarray, shape (n,)
        Reading (dBm) and its transmitter's A (dBm).
    """
    floor = np.asarray(floor, dtype=np.intp)
    count = np.bincount(floor, minlength=n_floors).astype(float)
    sum_rssi = np.bincount(floor, weights=rssi, minlength=n_floors)
    sum_a = np.bincount(floor, weights=A, minlength=n_floors)
    return count, sum_rssi, sum_a


def floor_scores(count: np.ndarray, sum_rssi: np.ndarray, sum_a: np.ndarray) -> np.ndarray:
    """Return E_L per floor; NaN for floors without readings (inactive).

    Parameters
    ----------
    count, sum_rssi, sum_a : ndarray, shape (F,)
        n, Σ rssi_i (dBm) and Σ A_i (dBm) per floor over the history.
    """
    active = count > 0
    e = np.full(count.shape, np.nan)
    # E_L = -n² / Σ rssi - n / Σ A
    np.subtract(
        np.divide(-(count * count), sum_rssi, where=active, out=np.zeros(count.shape)),
        np.divide(count, sum_a, where=active, out=np.zeros(count.shape)),
        where=active,
        out=e,
    )
    return e


def rank_floors(scores: np.ndarray) -> np.ndarray:
    """Return the active floors (finite score) by decreasing score; ties by floor index."""
    active = np.flatnonzero(np.isfinite(scores))
    order = np.argsort(-scores[active], kind="stable")
    return active[order]


def pressure_climb(
    t: np.ndarray, hpa: np.ndarray, now: int, params: FloorParams
) -> tuple[bool, float]:
    """Return (barometer present, metres climbed) over the last ``climb_window_ms``.

    Parameters
    ----------
    t, hpa : ndarray, shape (k,)
        Times (ms, increasing) and mean pressure (hPa) of recent windows.
    now : int
        Current time (ms).
    """
    recent = t >= now - params.climb_window_ms
    if recent.sum() < 2:
        return bool(recent.any()), 0.0
    p = hpa[recent]
    # Δh = -(p_now - p_then) / (dp/dh)
    return True, float(-(p[-1] - p[0]) / params.hpa_per_m)


class PressureHistory:
    """A device's mean barometer reading per window, kept for ``climb_window_ms``.

    Both floor selectors read the climb from it; its snapshot keys (``p_t``,
    ``p_hpa``) sit inside theirs.
    """

    def __init__(self, state: dict[str, Any] | None = None) -> None:
        state = state or {}
        self.t = np.asarray(state.get("p_t", np.zeros(0, np.int64)), dtype=np.int64).copy()
        self.hpa = np.asarray(state.get("p_hpa", np.zeros(0)), dtype=float).copy()

    def update(
        self, t: int, pressure_hpa: np.ndarray | None, params: FloorParams
    ) -> tuple[bool, float]:
        """Add a window's readings, forget the old ones; return ``pressure_climb``'s answer."""
        if pressure_hpa is not None and len(pressure_hpa):
            self.t = np.append(self.t, t)
            self.hpa = np.append(self.hpa, float(np.mean(pressure_hpa)))
        if self.t.size:
            recent = self.t >= t - params.climb_window_ms
            self.t, self.hpa = self.t[recent], self.hpa[recent]
        return pressure_climb(self.t, self.hpa, t, params)

    def snapshot(self) -> dict[str, Any]:
        """Return the kept times and pressures."""
        return {"p_t": self.t.copy(), "p_hpa": self.hpa.copy()}


def choose_floor(
    ranking: np.ndarray,
    scores: np.ndarray,
    levels: np.ndarray,
    current: int,
    candidate: int,
    lead: int,
    barometer: bool,
    climb_m: float,
    params: FloorParams,
) -> tuple[int, int, int]:
    """Apply hysteresis to the ranking.

    Parameters
    ----------
    ranking : ndarray of int
        Active floors by decreasing score (``rank_floors``).
    scores : ndarray, shape (F,)
        E_L per floor.
    levels : ndarray of int, shape (F,)
        Storey of each floor (0 ground, -1 first basement).
    current, candidate : int
        The floor now chosen and the challenger being timed (-1 for none).
    lead : int
        Consecutive windows the candidate has led so far.
    barometer : bool
        Whether pressure readings are present.
    climb_m : float
        Height change (m) over the climb window.

    Returns
    -------
    floor, candidate, lead
        The chosen floor (-1 when no floor is active) and the updated challenger state.
    """
    if ranking.size == 0:
        return -1, -1, 0
    best = int(ranking[0])
    if current < 0 or not np.isfinite(scores[current]):
        return best, -1, 0
    if best == current or scores[best] < (1.0 + params.switch_margin) * scores[current]:
        return current, -1, 0
    lead = lead + 1 if best == candidate else 1
    climbing = abs(climb_m) >= params.climb_min_m
    towards = np.sign(levels[best] - levels[current]) == np.sign(climb_m)
    if barometer and climbing and towards:
        return best, -1, 0
    need = params.flat_dwell_windows if barometer and not climbing else params.dwell_windows
    if lead >= need:
        return best, -1, 0
    return current, best, lead


class FloorSelector:
    """Stateful floor selection over a device's windows.

    The per-window sums live in a ring of ``history_ms / window_ms + 1``
    windows; entries older than the history are masked out by their time.

    Parameters
    ----------
    levels : ndarray of int, shape (F,)
        Storey of each floor of the site.
    params : FloorParams
    state : dict, optional
        A :meth:`snapshot` to resume from.
    """

    def __init__(
        self, levels: np.ndarray, params: FloorParams, state: dict[str, Any] | None = None
    ) -> None:
        self.levels = np.asarray(levels, dtype=np.int64)
        self.params = params
        size = params.history_ms // params.window_ms + 1
        n_floors = self.levels.size
        state = state or {}
        self.t = np.asarray(state.get("t", np.full(size, NEVER)), dtype=np.int64).copy()
        self.sums = np.asarray(state.get("sums", np.zeros((size, 3, n_floors))), float).copy()
        self.pos = int(state.get("pos", 0))
        self.pressure = PressureHistory(state)
        self.current = int(state.get("current", -1))
        self.candidate = int(state.get("candidate", -1))
        self.lead = int(state.get("lead", 0))

    def snapshot(self) -> dict[str, Any]:
        """Return the accumulators and hysteresis state."""
        return {
            "t": self.t.copy(),
            "sums": self.sums.copy(),
            "pos": self.pos,
            **self.pressure.snapshot(),
            "current": self.current,
            "candidate": self.candidate,
            "lead": self.lead,
        }

    def update(
        self,
        t: int,
        floor: np.ndarray,
        rssi: np.ndarray,
        A: np.ndarray,
        pressure_hpa: np.ndarray | None = None,
    ) -> np.ndarray:
        """Add one window's readings and return the active floors, the chosen floor first.

        Parameters
        ----------
        t : int
            Window time (ms), increasing from call to call.
        floor, rssi, A : ndarray, shape (n,)
            Floor of each reading's transmitter, the reading (dBm) and the
            transmitter's A (dBm); readings with NaN A are ignored.
        pressure_hpa : ndarray, optional
            Barometer readings (hPa) of the window.

        Returns
        -------
        ndarray of int
            Empty when no floor has readings in the history.
        """
        p = self.params
        known = np.isfinite(A) & np.isfinite(rssi)
        sums = window_sums(floor[known], rssi[known], A[known], self.levels.size)
        self.t[self.pos] = t
        self.sums[self.pos] = sums
        self.pos = (self.pos + 1) % self.t.size
        barometer, climb = self.pressure.update(t, pressure_hpa, p)
        count, sum_rssi, sum_a = self.sums[self.t > t - p.history_ms].sum(axis=0)
        scores = floor_scores(count, sum_rssi, sum_a)
        ranking = rank_floors(scores)
        self.current, self.candidate, self.lead = choose_floor(
            ranking,
            scores,
            self.levels,
            self.current,
            self.candidate,
            self.lead,
            barometer,
            climb,
            p,
        )
        if self.current < 0 or ranking[0] == self.current:
            return ranking
        return np.concatenate([[self.current], ranking[ranking != self.current]]).astype(np.intp)


# --- the forward filter over floors ---------------------------------------------------

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


def transition_matrix(
    levels: np.ndarray, switch_prob: float, climb_m: float, climb_prob: float, climb_min_m: float
) -> np.ndarray:
    """Return T (F, F) with T[g, f] = P(floor f | floor g one window earlier).

    Parameters
    ----------
    levels : ndarray of int, shape (F,)
        Storey of each floor.
    switch_prob : float
        Probability of a change, shared evenly by the other floors.
    climb_m : float
        Height change (m) the barometer shows (0 without one); at least
        ``climb_min_m`` up or down gives the floors in that direction
        ``climb_prob`` between them, and the others ``switch_prob`` between them.
    """
    levels = np.asarray(levels)
    n = levels.size
    if n == 1:
        return np.ones((1, 1))
    other = ~np.eye(n, dtype=bool)
    # T_gf = ε / (F - 1) for f ≠ g
    T = np.where(other, switch_prob / (n - 1), 0.0)
    if abs(climb_m) >= climb_min_m:
        towards = np.sign(levels[None, :] - levels[:, None]) == np.sign(climb_m)
        n_towards = towards.sum(axis=1, keepdims=True)
        n_rest = (other & ~towards).sum(axis=1, keepdims=True)
        # T_gf = ε_climb / |towards(g)| towards the climb, ε / |rest(g)| elsewhere
        T = np.where(towards, climb_prob / np.maximum(n_towards, 1), 0.0) + np.where(
            other & ~towards, switch_prob / np.maximum(n_rest, 1), 0.0
        )
    # T_gg = 1 - Σ_{f≠g} T_gf
    T[np.arange(n), np.arange(n)] = 1.0 - T.sum(axis=1)
    return T


def forward_step(belief: np.ndarray, T: np.ndarray, windows: int, loglik: np.ndarray) -> np.ndarray:
    """Return the belief after ``windows`` transitions and one window's evidence.

    Parameters
    ----------
    belief : ndarray, shape (F,)
        P(floor) after the previous window.
    T : ndarray, shape (F, F)
        One window's transition (``transition_matrix``).
    windows : int
        Windows elapsed since the previous one (≥ 1).
    loglik : ndarray, shape (F,)
        ln p(readings | floor), up to a constant.
    """
    # π = b Tⁿ
    prior = belief @ np.linalg.matrix_power(T, max(int(windows), 1))
    # b' ∝ π ⊙ exp(ln L - max ln L)
    post = prior * np.exp(loglik - np.max(loglik))
    total = post.sum()
    return post / total if total > 0 else np.full(belief.size, 1.0 / belief.size)


class FloorFilter:
    """Forward filter over one device's floor.

    Parameters
    ----------
    levels : ndarray of int, shape (F,)
        Storey of each floor of the site.
    params : FloorParams
    state : dict, optional
        A :meth:`snapshot` to resume from.
    """

    def __init__(
        self, levels: np.ndarray, params: FloorParams, state: dict[str, Any] | None = None
    ) -> None:
        self.levels = np.asarray(levels, dtype=np.int64)
        self.params = params
        n = self.levels.size
        size = params.history_ms // params.window_ms + 1
        state = state or {}
        self.belief = np.asarray(state.get("belief", np.full(n, 1.0 / max(n, 1))), float).copy()
        self.last_t = int(state.get("last_t", NEVER))
        self.t = np.asarray(state.get("t", np.full(size, NEVER)), dtype=np.int64).copy()
        self.heard = np.asarray(state.get("heard", np.zeros((size, n))), float).copy()
        self.pos = int(state.get("pos", 0))
        self.pressure = PressureHistory(state)
        self.current = int(state.get("current", -1))

    def snapshot(self) -> dict[str, Any]:
        """Return the belief, the recently heard floors and the pressure history."""
        return {
            "belief": self.belief.copy(),
            "last_t": self.last_t,
            "t": self.t.copy(),
            "heard": self.heard.copy(),
            "pos": self.pos,
            **self.pressure.snapshot(),
            "current": self.current,
        }

    def update(
        self,
        t: int,
        loglik: np.ndarray,
        heard: np.ndarray,
        pressure_hpa: np.ndarray | None = None,
    ) -> np.ndarray:
        """Add one window and return the active floors, the chosen floor first.

        Parameters
        ----------
        t : int
            Window time (ms), increasing from call to call.
        loglik : ndarray, shape (F,)
            The window's evidence (``FloorEvidence.log_likelihood``); zeros without readings.
        heard : ndarray, shape (F,)
            Readings of each floor's transmitters in the window.
        pressure_hpa : ndarray, optional
            Barometer readings (hPa) of the window.

        Returns
        -------
        ndarray of int
            The chosen floor, then the other active floors by decreasing
            belief; empty when no floor was heard within ``history_ms``.
        """
        p = self.params
        barometer, climb = self.pressure.update(t, pressure_hpa, p)
        # with a barometer, floors change only in the direction of a climb
        eps = p.flat_switch_prob if barometer else p.switch_prob
        T = transition_matrix(self.levels, eps, climb, p.climb_switch_prob, p.climb_min_m)
        # windows since the previous update: a gap lets the belief relax towards uniform
        windows = 1 if self.last_t == NEVER else max((t - self.last_t) // p.window_ms, 1)
        self.belief = forward_step(self.belief, T, windows, loglik)
        self.last_t = t
        self.t[self.pos] = t
        self.heard[self.pos] = heard
        self.pos = (self.pos + 1) % self.t.size
        active = np.flatnonzero(self.heard[self.t > t - p.history_ms].sum(axis=0) > 0)
        if active.size == 0:
            self.current = -1
            return active
        self.current = int(np.argmax(self.belief))
        rest = active[active != self.current]
        rest = rest[np.argsort(-self.belief[rest], kind="stable")]
        return np.concatenate([[self.current], rest]).astype(np.intp)
