"""Constants of floor selection: which selector runs, and each selector's own."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FloorParams:
    """Constants of floor selection.

    Attributes
    ----------
    method : str
        The floor selector (``selection.SELECTORS``): ``"filter"``, the
        forward filter over floors; ``"patent"``, the patent's E_L ranking
        with hysteresis.
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
        floor even when it is faint: scoring only the strongest few puts
        many more estimates on a wrong floor.
    map_block_m : float
        Filter: one reference point (the most surveyed) per block of this side
        (m) enters the floor likelihood; the maps are smooth over metres and
        the likelihood is averaged over the floor anyway. Blocks up to this
        side choose the same floors as every point does, larger ones start
        to miss; 4 m costs a sixteenth of scoring every point.
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
