"""Response bodies of the radio-map build API."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel

from app.engine.wifi_age import DEFAULT_MAX_AGE_MS


class FloorBuild(BaseModel):
    """One floor's radio map: reference points and how much of the walkable area they cover."""

    floor_id: str
    surveys: int
    scans: int
    reference_points: int
    walkable_cells: int
    coverage: float | None
    transmitters: int


class TransmitterCalibration(BaseModel):
    """One transmitter's fit and its quality figures."""

    id: str
    floor_id: str
    x: float | None
    y: float | None
    z: float | None
    A: float | None
    B: float | None
    sigma: float | None
    n_readings: int
    n_censored: int
    spread_m: float | None
    converged: bool
    plausible: bool
    position_known: bool


class CalibrationSummary(BaseModel):
    """Transmitters calibrated, how many fits are plausible, and each fit."""

    calibrated: int
    plausible: int
    positions_fitted: int
    median_A: float | None
    median_B: float | None
    median_sigma_db: float | None
    transmitters: list[TransmitterCalibration]


class TrackerAccuracy(BaseModel):
    """What the phone tracker (HMM) measured replaying survey walks on maps built without them."""

    method: Literal["hmm"]
    walks: int
    mean_walk_error_m: float | None


class HeldOutAccuracy(BaseModel):
    """Errors of scans located on maps built without their walk (walk-level k-fold)."""

    method: Literal["wknn"]
    k: int | None = None
    folds: int
    scans: int
    mean_error_m: float | None
    p50_error_m: float | None
    p90_error_m: float | None
    floor_error_rate: float | None
    tracker: TrackerAccuracy | None = None


class SiteTuningRead(BaseModel):
    """The building-dependent constants the build chose from the site's own surveys."""

    weinberg_k: float
    heading_offset_deg: float
    heading_std_deg: float
    wknn_k: int
    emission_weight: float
    floor_weight: float
    accuracy_floor_m: float
    pdr_walks: int
    radius_scale: float = 1.0
    fix_nats: float = 10.0
    lag_fix_scale: float = 1.0
    pass_fix_scale: float = 1.0
    wifi_max_age_ms: int = DEFAULT_MAX_AGE_MS
    """Oldest a WiFi reading's last-seen time may be before its scan's time for the engines
    to use it (ms)."""
    scan_knn_k: int = 10
    """Survey scans the per-scan k-NN averages."""
    scan_knn_power: float = 4.0
    """Exponent of the per-scan k-NN's neighbour weights (d / d_min)^-p."""
    scan_knn_level_power: int = 0
    """Exponent of a shared transmitter's mean level (+1 dB) in its weight in the scan
    distance."""
    scan_knn_floor_dbm: float = -100.0
    """Signal level (dBm) the scan distance counts as nothing."""
    scan_knn_unshared_penalty: float = 50.0
    """Scan distance (dB) of two scans that share nothing."""
    fix_sigma_m: float = 8.0
    """Spread (m) of each neighbour of the HMM's k-NN fix: the held-out k-NN errors' RMS."""
    walk_noise_m2_per_s: float = 0.05
    """The HMM's transition noise beyond the steps' own (m² per second)."""
    floor_classifier_weight: float = 0.0
    """Temper of the per-scan floor classifier in the HMM's floor evidence (0: off)."""


class TuningScores(BaseModel):
    """The held-out figure of every candidate the build chose among."""

    hmm_walk_error_m_by_weight: dict[str, float | None] = {}
    hmm_walk_error_m_by_fix_weight: dict[str, float | None] = {}
    hmm_walk_error_m_by_walk_noise: dict[str, float | None] = {}
    wrong_floor_share_by_floor_weight: dict[str, float | None] = {}
    wrong_floor_share_by_floor_classifier_weight: dict[str, float | None] = {}
    floor_pairs: int = 0
    fixed_lag_walk_error_m_by_fix_scale: dict[str, float | None] = {}
    full_pass_walk_error_m_by_fix_scale: dict[str, float | None] = {}
    hmm_walks: int = 0
    wknn_mean_error_m_by_k: dict[str, float | None]
    emission_log_score_by_weight: dict[str, float | None]
    floor_log_score_by_weight: dict[str, float | None]
    emission_scans: int
    knn_walk_error_m_by_wifi_max_age_ms: dict[str, float | None] = {}
    knn_walk_error_m_by_weight_power: dict[str, float | None] = {}
    knn_walk_error_m_by_floor_dbm: dict[str, float | None] = {}
    knn_walk_error_m_by_unshared_penalty: dict[str, float | None] = {}
    knn_walk_error_m_by_level_power: dict[str, float | None] = {}
    knn_walk_error_m_by_k: dict[str, float | None] = {}


class GuidanceParamsRead(BaseModel):
    """The grid and smoothing of the survey guidance (``app.engine.survey_guidance``)."""

    cell_m: float
    """Grid cell side (m)."""
    bandwidth_m: float
    """Standard deviation of the Gaussian kernel weighing held-out scans (m)."""
    reach_m: float
    """Cells farther than this from every held-out scan are unsurveyed (m)."""
    wrong_floor_m: float
    """Error a scan located on a wrong floor counts as (m)."""
    high_error_m: float
    """Expected error above which a cell counts as needing more survey (m)."""


class FloorGuidance(BaseModel):
    """Where one floor's radio map is thin, in figures."""

    floor_id: str
    scans: int
    """Held-out scans of the floor the guidance was smoothed from."""
    walkable_cells: int
    mean_expected_error_m: float | None
    """Mean expected error over the walkable cells that were surveyed (m)."""
    unsurveyed_share: float | None
    """Share of the walkable cells farther than ``reach_m`` from every scan."""
    high_error_share: float | None
    """Share of the walkable cells whose expected error exceeds ``high_error_m``."""
    to_survey_share: float | None
    """Share unsurveyed or above ``high_error_m``: where to survey next."""


class GuidanceSummary(GuidanceParamsRead):
    """The survey guidance of a build: its parameters and each floor's figures."""

    floors: list[FloorGuidance]


class SurveyGuidance(BaseModel):
    """A floor's expected positioning error, from the latest build's held-out scans.

    Grids are (ny, nx) lists of rows, row 0 at ``origin[1]``; cell (r, c) spans
    x0 + c·cell to x0 + (c+1)·cell. ``expected_error_m`` is null outside the
    walkable area and where unsurveyed; ``distance_m`` (to the nearest held-out
    scan) is null outside the walkable area and on a floor with no held-out scan.
    """

    site_id: str
    floor_id: str
    built_at: datetime
    origin: list[float]
    cell: float
    shape: list[int]
    params: GuidanceParamsRead
    summary: FloorGuidance
    walkable: list[list[bool]]
    expected_error_m: list[list[float | None]]
    distance_m: list[list[float | None]]


class BuildSummary(BaseModel):
    """What a build produced; ``accuracy`` is null with fewer than two survey walks."""

    site_id: str
    surveys: int
    scans: int
    readings: int
    ble_windows: int = 0
    """BLE advertisements of the surveys grouped into windows (scans) to calibrate beacons."""
    ble_readings: int = 0
    transmitters_heard: int
    floors: list[FloorBuild]
    calibration: CalibrationSummary
    accuracy: HeldOutAccuracy | None
    tuning: SiteTuningRead | None = None
    tuning_scores: TuningScores | None = None
    guidance: GuidanceSummary | None = None
    """Where the radio map is thin, per floor; null with fewer than two survey walks."""
    map_version: int | None = None
    elapsed_ms: float | None = None


class BuildAccepted(BaseModel):
    """An asynchronous build was queued."""

    job_id: str


class BuildJobRead(BaseModel):
    """An asynchronous build's state; ``summary`` once done, ``error`` once failed."""

    job_id: str
    site_id: str
    status: Literal["queued", "running", "done", "failed"]
    progress: float
    summary: BuildSummary | None
    error: str | None
