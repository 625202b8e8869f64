"""Extended Kalman filter of position fixes and gyro yaw rate (seed 001), and the trackers on it.

State ``x = [x, y, V, α]``: position (m), speed (m/s) and course α (rad,
counter-clockwise from +x). The report's process model (its eqs. 3–9)::

    x_k = x_{k−1} + V_{k−1} cos α_{k−1} T
    y_k = y_{k−1} + V_{k−1} sin α_{k−1} T
    V_k = V_{k−1} + ξ T
    α_k = α_{k−1} (1 − μ T) + α̇ T + ζ T

with the gyro's yaw rate α̇ added at extrapolation (eq. 7), the Jacobian of
eq. 9 and ``D_ξ = diag(σ_ξ², σ_ζ²)``. Observations are position fixes, ``H =
[[1, 0, 0, 0], [0, 1, 0, 0]]``; the covariance update is in Joseph form and
every fix passes a χ² innovation gate first.

The report writes the noise for one fixed period T (``G D_ξ Gᵀ = diag(0, 0,
σ_ξ² T², σ_ζ² T²)``). Measurements here arrive at irregular times, so the
noise is taken as continuous white noise of intensities σ_ξ², σ_ζ² (per
second), which gives ``diag(0, 0, σ_ξ² T, σ_ζ² T)``; the two coincide at
T = 1 s. A small position noise (not in the report) lets the track follow
sideways motion the course model cannot express. The report prints no
numbers for σ_ξ, σ_ζ, μ: the defaults below are physical scales of people
and trolleys, stated with each.

Tags without an IMU run the same filter with α̇ = 0 and a larger σ_ζ, so the
course comes from the motion alone. Until the fixes have moved
``init_distance_m`` the course is unknown and the filter holds only a
position (a random walk); speed and course are then set from that first
displacement.

:class:`PositionEkf` is that filter as a state machine; :class:`UwbTracker`
feeds it least-squares fixes of UWB ranges (with per-anchor bias
self-calibration, ``uwb_bias``) or given fixes; :class:`LocatorTracker`
feeds it windowed RSSI fixes of a tag heard by fixed locators.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.engine.lateration import LaterationParams, LaterationResult, Status, path_loss_B, solve
from app.engine.samples import Batch, Estimate
from app.engine.site import SiteModel
from app.engine.uwb_bias import BiasParams, accumulate, solve_biases

POSITION_H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
"""Observation matrix of a position fix (seed 001, eq. 12)."""

RADIUS_68 = float(np.sqrt(-2.0 * np.log(1.0 - 0.68)))
"""A circular 2-D Gaussian holds 68 % of its mass within this many σ (≈ 1.51)."""


@dataclass(frozen=True)
class EkfParams:
    """Noise, gating and start-up constants of the filter.

    Attributes
    ----------
    accel_noise : float
        σ_ξ: intensity of the speed's random walk ((m/s)/√s). People and
        trolleys change speed by a few tenths of a m/s within a second.
    turn_noise_gyro : float
        σ_ζ with a gyro (rad/√s): what the gyro's yaw rate misses (noise,
        bias drift, the device turning in the hand).
    turn_noise_motion : float
        σ_ζ without a gyro (rad/√s): the course must follow turns of about
        half a radian per second from the fixes alone.
    position_noise : float
        Intensity of a random walk on x and y (m/√s) for sideways motion.
    still_noise : float
        Intensity of the position random walk (m/√s) while the course is
        still unknown (tag not yet seen moving).
    mu : float
        μ of the report's first-order course model (1/s): the course relaxes
        to 0 with time constant 1/μ. The report simulates a course wandering
        around 0; a real course has no preferred value, hence 0.
    init_distance_m : float
        The fixes must move this far (m) before speed and course are set
        from the displacement: well beyond a fix's noise.
    init_speed_std : float
        σ of the speed (m/s) when it is first set, added to what the fixes'
        noise gives (the speed varied over the displacement).
    init_heading_std : float
        σ of the course (rad) when it is first set, added likewise.
    gate_probability : float
        A fix whose innovation lies beyond this quantile of χ²(2) is rejected.
    max_rejections : int
        After this many fixes in a row are rejected the filter restarts on
        the next fix (it has lost the tag, the fixes did not).
    max_gap_ms : int
        Without an accepted fix for this long the filter restarts.
    gyro_timeout_ms : int
        A yaw rate older than this is not used (the tag counts as without gyro).
    """

    accel_noise: float = 0.3
    turn_noise_gyro: float = 0.05
    turn_noise_motion: float = 0.5
    position_noise: float = 0.05
    still_noise: float = 0.3
    mu: float = 0.0
    init_distance_m: float = 0.5
    init_speed_std: float = 0.3
    init_heading_std: float = 0.5
    gate_probability: float = 0.999
    max_rejections: int = 20
    max_gap_ms: int = 5000
    gyro_timeout_ms: int = 1000

    @property
    def gate(self) -> float:
        """χ²(2) quantile of ``gate_probability``: −2 ln(1 − p)."""
        # χ²₂⁻¹(p) = −2 ln(1 − p)
        return float(-2.0 * np.log(1.0 - self.gate_probability))


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles (rad) into [−π, π)."""
    # ((a + π) mod 2π) − π
    return np.mod(np.asarray(a, dtype=float) + np.pi, 2.0 * np.pi) - np.pi


def propagate(x: np.ndarray, dt: float, yaw_rate: float, mu: float) -> np.ndarray:
    """Return the state extrapolated by ``dt`` seconds (seed 001, eqs. 3 and 7), shape (4,)."""
    px, py, v, a = x
    return np.array(
        [
            # x + V cos α T
            px + v * np.cos(a) * dt,
            # y + V sin α T
            py + v * np.sin(a) * dt,
            v,
            # α (1 − μT) + α̇ T
            a * (1.0 - mu * dt) + yaw_rate * dt,
        ]
    )


def process_jacobian(x: np.ndarray, dt: float, mu: float) -> np.ndarray:
    """Return ∂f/∂x at ``x`` (seed 001, eq. 9), shape (4, 4)."""
    _, _, v, a = x
    c, s = np.cos(a), np.sin(a)
    return np.array(
        [
            [1.0, 0.0, c * dt, -v * s * dt],
            [0.0, 1.0, s * dt, v * c * dt],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0 - mu * dt],
        ]
    )


def process_noise(
    dt: float, accel_noise: float, turn_noise: float, position_noise: float
) -> np.ndarray:
    """Return Q for a step of ``dt`` seconds from continuous noise intensities, shape (4, 4)."""
    # Q = diag(q_p T, q_p T, σ_ξ² T, σ_ζ² T)
    return np.diag([position_noise**2, position_noise**2, accel_noise**2, turn_noise**2]) * dt


def ekf_predict(
    x: np.ndarray, P: np.ndarray, dt: float, yaw_rate: float, Q: np.ndarray, mu: float
) -> tuple[np.ndarray, np.ndarray]:
    """Extrapolate state and covariance by ``dt`` seconds (seed 001, eqs. 7–8)."""
    F = process_jacobian(x, dt, mu)
    x_new = propagate(x, dt, yaw_rate, mu)
    x_new[3] = wrap_angle(x_new[3])
    # P̃ = F P Fᵀ + Q
    return x_new, F @ P @ F.T + Q


def ekf_update(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray, H: np.ndarray, gate: float
) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """Fold observation ``z`` with noise ``R`` into the state, unless the χ² gate rejects it.

    Returns
    -------
    x, P : ndarray
        Updated (or unchanged when rejected) state (4,) and covariance (4, 4).
    d2 : float
        Squared Mahalanobis distance of the innovation.
    accepted : bool
    """
    # ν = z − H x̃
    nu = z - H @ x
    # S = H P̃ Hᵀ + R
    S = H @ P @ H.T + R
    S_inv = np.linalg.inv(S)
    # d² = νᵀ S⁻¹ ν
    d2 = float(nu @ S_inv @ nu)
    if not np.isfinite(d2) or d2 > gate:
        return x, P, d2, False
    # K = P̃ Hᵀ S⁻¹
    K = P @ H.T @ S_inv
    # x̂ = x̃ + K ν
    x_new = x + K @ nu
    x_new[3] = wrap_angle(x_new[3])
    # Joseph form: P = (I − KH) P̃ (I − KH)ᵀ + K R Kᵀ
    IKH = np.eye(P.shape[0]) - K @ H
    return x_new, IKH @ P @ IKH.T + K @ R @ K.T, d2, True


def flip_negative_speed(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map a state with V < 0 to its twin (−V, α + π), transforming P alike."""
    if x[2] >= 0.0:
        return x, P
    J = np.diag([1.0, 1.0, -1.0, 1.0])
    x_new = x.copy()
    x_new[2] = -x[2]
    x_new[3] = wrap_angle(x[3] + np.pi)
    # P' = J P Jᵀ
    return x_new, J @ P @ J.T


def accuracy_radius(P_xy: np.ndarray) -> float:
    """Return the radius (m) holding the position with 68 % probability (circular approximation)."""
    # r₆₈ = √(−2 ln 0.32) · √(tr P / 2)
    return RADIUS_68 * float(np.sqrt(max(np.trace(P_xy), 0.0) / 2.0))


def heading_deg(course: float) -> float:
    """Return the API heading (degrees clockwise from +y, [0, 360)) of a course α (rad)."""
    # ψ = 90° − α
    return float(np.mod(90.0 - np.degrees(course), 360.0))


def imu_yaw_rate(acc: np.ndarray, gyro: np.ndarray) -> np.ndarray:
    """Return the counter-clockwise rotation rate about the vertical (rad/s), shape (n,).

    The accelerometer gives the up direction in the device frame; where it is
    missing the device is taken as lying flat (gyro z).
    """
    norm = np.linalg.norm(acc, axis=1)
    up_ok = np.isfinite(norm) & (norm > 1.0)
    # ω_up = ω · a / |a|
    along_up = np.sum(gyro * np.where(up_ok[:, None], acc, 0.0), axis=1) / np.where(
        up_ok, norm, 1.0
    )
    return np.where(up_ok, along_up, gyro[:, 2])


class PositionEkf:
    """The seed-001 filter as a small state machine: start-up, gyro, prediction, gated updates.

    The course is unknown until the position has moved ``init_distance_m``
    (the state then holds only a position doing a random walk); a run of
    rejected fixes or a long silence restarts the filter on the next fix.
    """

    def __init__(self, params: EkfParams, state: dict[str, Any] | None = None):
        self.params = params
        state = state or {}
        self.x = np.asarray(state.get("x", np.zeros(4)), dtype=float).copy()
        self.P = np.asarray(state.get("P", np.zeros((4, 4))), dtype=float).copy()
        self.t = int(state.get("t", -1))
        self.started = bool(state.get("started", False))
        self.moving = bool(state.get("moving", False))
        self.ref_xy = np.asarray(state.get("ref_xy", np.zeros(2)), dtype=float).copy()
        self.ref_t = int(state.get("ref_t", -1))
        self.yaw_rate = float(state.get("yaw_rate", 0.0))
        self.gyro_t = int(state.get("gyro_t", -(2**62)))
        self.last_fix_t = int(state.get("last_fix_t", -1))
        self.rejections = int(state.get("rejections", 0))

    def snapshot(self) -> dict[str, Any]:
        """Return the filter state as plain numbers and small arrays."""
        return {
            "x": self.x.copy(),
            "P": self.P.copy(),
            "t": self.t,
            "started": self.started,
            "moving": self.moving,
            "ref_xy": self.ref_xy.copy(),
            "ref_t": self.ref_t,
            "yaw_rate": self.yaw_rate,
            "gyro_t": self.gyro_t,
            "last_fix_t": self.last_fix_t,
            "rejections": self.rejections,
        }

    def gyro(self, t: int, rate: float) -> None:
        """Extrapolate to ``t`` with the previous yaw rate, then hold ``rate`` (rad/s, CCW)."""
        self.predict_to(t)
        self.yaw_rate, self.gyro_t = rate, t

    def predict_to(self, t: int) -> None:
        """Extrapolate the state to measurement time ``t`` (ms)."""
        if not self.started or t <= self.t:
            return
        p = self.params
        dt = (t - self.t) / 1000.0
        if self.moving:
            has_gyro = t - self.gyro_t <= p.gyro_timeout_ms
            rate = self.yaw_rate if has_gyro else 0.0
            turn = p.turn_noise_gyro if has_gyro else p.turn_noise_motion
            Q = process_noise(dt, p.accel_noise, turn, p.position_noise)
            self.x, self.P = ekf_predict(self.x, self.P, dt, rate, Q, p.mu)
        else:
            # course unknown: position random walk only, P_xy += q T I
            self.P[:2, :2] += np.eye(2) * p.still_noise**2 * dt
        self.t = t

    def update(self, t: int, xy: np.ndarray, R: np.ndarray) -> bool:
        """Predict to ``t`` and fold in a position fix (m) with covariance R; return if used."""
        p = self.params
        xy = np.asarray(xy, dtype=float)
        if not self.started or t - self.last_fix_t > p.max_gap_ms:
            self._restart(t, xy, R)
            return True
        self.predict_to(t)
        x, P, _, accepted = ekf_update(self.x, self.P, xy, R, POSITION_H, p.gate)
        if not accepted:
            self.rejections += 1
            if self.rejections >= p.max_rejections:
                self._restart(t, xy, R)
                return True
            return False
        self.x, self.P = flip_negative_speed(x, P)
        self.rejections = 0
        self.last_fix_t = t
        if not self.moving:
            self._start_moving(t)
        return True

    def estimate(self, extra_var: float = 0.0) -> tuple[float, float, float, float, float]:
        """Return x, y (m), heading (API degrees, NaN before motion), accuracy (m), speed (m/s).

        ``extra_var`` (m²) is added to each coordinate's variance in the accuracy radius.
        """
        moving = self.moving
        return (
            float(self.x[0]),
            float(self.x[1]),
            heading_deg(self.x[3]) if moving else float("nan"),
            accuracy_radius(self.P[:2, :2] + np.eye(2) * extra_var),
            float(self.x[2]) if moving else 0.0,
        )

    def _restart(self, t: int, xy: np.ndarray, R: np.ndarray) -> None:
        """Start over at a fix: position known, speed and course unknown."""
        self.x = np.array([xy[0], xy[1], 0.0, 0.0])
        self.P = np.zeros((4, 4))
        self.P[:2, :2] = R
        self.t = t
        self.started = True
        self.moving = False
        self.ref_xy = xy.copy()
        self.ref_t = t
        self.rejections = 0
        self.last_fix_t = t

    def _start_moving(self, t: int) -> None:
        """Set speed and course once the position has moved clearly beyond its noise.

        The displacement Δ from the reference position must exceed both
        ``init_distance_m`` and three σ of its own noise (σ² ≈ 2 σ_p² per axis,
        σ_p² the position variance now and at the reference); the speed and
        course variances are that noise propagated through |Δ|/Δt and
        atan2(Δ), plus the configured floors.
        """
        p = self.params
        delta = self.x[:2] - self.ref_xy
        dist = float(np.hypot(*delta))
        # σ_Δ² = 2 σ_p², σ_p² = tr(P_xy) / 2
        var_delta = float(np.trace(self.P[:2, :2]))
        if dist < max(p.init_distance_m, 3.0 * np.sqrt(var_delta)):
            return
        dt = max((t - self.ref_t) / 1000.0, 1e-3)
        # V = |Δ| / Δt, α = atan2(Δy, Δx)
        self.x[2] = dist / dt
        self.x[3] = float(np.arctan2(delta[1], delta[0]))
        self.P[2:, :] = 0.0
        self.P[:, 2:] = 0.0
        # σ_V² = σ_Δ² / Δt² + floor², σ_α² = σ_Δ² / |Δ|² + floor²
        self.P[2, 2] = var_delta / dt**2 + p.init_speed_std**2
        self.P[3, 3] = var_delta / dist**2 + p.init_heading_std**2
        self.moving = True


def _gyro_events(batch: Batch) -> list[tuple[int, int, Any]]:
    """Return (t, 0, yaw rate) events of the batch's IMU samples that carry a gyro."""
    imu = batch.imu
    if not len(imu):
        return []
    rate = imu_yaw_rate(imu.acc, imu.gyro)
    return [(int(t), 0, float(w)) for t, w in zip(imu.t, rate, strict=True) if np.isfinite(w)]


def _project(site: SiteModel, floor: int, ekf: PositionEkf) -> None:
    """Move the filter's position off blocked cells of the floor plan."""
    if not site.floors:
        return
    plan = site.floors[min(max(floor, 0), len(site.floors) - 1)].plan
    ekf.x[:2] = plan.project(ekf.x[:2])


@dataclass(frozen=True)
class UwbTrackerParams:
    """Everything a UWB tag's tracker is tuned by.

    Attributes
    ----------
    ekf, lateration, bias
        Parameters of the filter, of the fixes and of bias self-calibration.
    self_calibrate : bool
        Learn per-anchor range biases from the fixes' residuals.
    range_std_m : float
        Standard deviation (m) of a range that arrives without one.
    tag_height_m : float
        Known height of the tag above its floor (m) for 2-D fixes.
    dims : {2, 3}
        Solve fixes in 2-D at ``tag_height_m`` or in 3-D (anchors at
        several heights); 3-D falls back to 2-D where unobservable.
    epoch_ms : int
        Ranges within this time of an epoch's first range, without a repeated
        anchor, form one fix.
    emit_every_ms : int
        At most one estimate per this much measurement time (0: every fix).
    project_to_plan : bool
        Move the estimate off walls and barriers after each update.
    """

    ekf: EkfParams = field(default_factory=EkfParams)
    lateration: LaterationParams = field(default_factory=LaterationParams)
    bias: BiasParams = field(default_factory=BiasParams)
    self_calibrate: bool = True
    range_std_m: float = 0.1
    tag_height_m: float = 1.0
    dims: int = 2
    epoch_ms: int = 30
    emit_every_ms: int = 200
    project_to_plan: bool = True


@dataclass
class _Epoch:
    """Ranges of one fix: time (ms), anchor indices, ranges and stds (m)."""

    t: int
    anchors: np.ndarray
    ranges: np.ndarray
    std: np.ndarray


def group_epochs(
    t: np.ndarray, anchors: np.ndarray, ranges: np.ndarray, std: np.ndarray, epoch_ms: int
) -> list[_Epoch]:
    """Split time-sorted ranges into fixes: a new one at a repeated anchor or after ``epoch_ms``."""
    out: list[_Epoch] = []
    start = 0
    seen: set[int] = set()
    for i in range(t.size + 1):
        if i < t.size and int(anchors[i]) not in seen and t[i] - t[start] <= epoch_ms:
            seen.add(int(anchors[i]))
            continue
        if i > start:
            sl = slice(start, i)
            out.append(_Epoch(int(t[i - 1]), anchors[sl], ranges[sl], std[sl]))
        start = i
        seen = {int(anchors[i])} if i < t.size else set()
    return out


class UwbTracker:
    """A UWB tag's filter: ranges (or given fixes) and gyro in, EKF positions out.

    Each epoch of ranges is corrected by the tag's per-anchor bias estimates,
    turned into a least-squares fix and folded into the EKF; the residuals of
    accepted fixes update the biases. Given fixes (``uwb_fix``) go straight
    to the EKF with their std. Gyro samples drive the course between fixes.
    """

    method = "ekf"

    def __init__(
        self,
        site: SiteModel,
        params: UwbTrackerParams = UwbTrackerParams(),
        state: dict[str, Any] | None = None,
        *,
        initial_biases: np.ndarray | None = None,
    ):
        self.site = site
        self.params = params
        n = len(site.anchors)
        state = state or {}
        self.ekf = PositionEkf(params.ekf, state.get("ekf"))
        self.floor = int(state.get("floor", 0))
        self.z = float(state.get("z", params.tag_height_m))
        self.next_emit = int(state.get("next_emit", -1))
        prior = np.zeros(n) if initial_biases is None else np.asarray(initial_biases, float)
        self.bias_prior = np.asarray(state.get("bias_prior", prior), dtype=float).copy()
        self.bias = np.asarray(state.get("bias", self.bias_prior), dtype=float).copy()
        # normal equations over the anchors this tag has heard (site indices in bias_ids)
        self.bias_ids = np.asarray(state.get("bias_ids", np.zeros(0)), dtype=np.int64).copy()
        m = self.bias_ids.size
        self.bias_S = np.asarray(state.get("bias_S", np.zeros((m, m))), dtype=float).reshape(m, m)
        self.bias_g = np.asarray(state.get("bias_g", np.zeros(m)), dtype=float).copy()
        self.bias_t = int(state.get("bias_t", -1))

    @classmethod
    def from_snapshot(
        cls, site: SiteModel, params: UwbTrackerParams, state: dict[str, Any]
    ) -> UwbTracker:
        """Restore a tracker from :meth:`snapshot`."""
        return cls(site, params, state)

    def snapshot(self) -> dict[str, Any]:
        """Return the tracker state as plain numbers and small arrays."""
        return {
            "ekf": self.ekf.snapshot(),
            "floor": self.floor,
            "z": self.z,
            "next_emit": self.next_emit,
            "bias": self.bias.copy(),
            "bias_prior": self.bias_prior.copy(),
            "bias_ids": self.bias_ids.copy(),
            "bias_S": self.bias_S.copy(),
            "bias_g": self.bias_g.copy(),
            "bias_t": self.bias_t,
        }

    def process(self, batch: Batch) -> list[Estimate]:
        """Consume one batch in time order and return the estimates it produced."""
        events = _gyro_events(batch)
        fixes = batch.fixes
        events += [(int(fixes.t[i]), 1, i) for i in range(len(fixes))]
        rng = batch.ranges
        if len(rng):
            order = np.argsort(rng.t, kind="stable")
            std = np.where(np.isfinite(rng.std) & (rng.std > 0), rng.std, self.params.range_std_m)
            epochs = group_epochs(
                rng.t[order], rng.anchor[order], rng.range[order], std[order], self.params.epoch_ms
            )
            events += [
                (e.t, 2, pair) for e, pair in zip(epochs, self._laterate(epochs), strict=True)
            ]
        events.sort(key=lambda e: (e[0], e[1]))
        out: list[Estimate] = []
        for t, kind, payload in events:
            if kind == 0:
                self.ekf.gyro(t, payload)
                continue
            if kind == 1:
                z = fixes.xyz[payload]
                s = fixes.std[payload]
                s = s if np.isfinite(s) and s > 0 else self.params.range_std_m
                self.floor = int(fixes.floor[payload])
                self.z = float(z[2])
                updated = self.ekf.update(t, z[:2], np.eye(2) * s * s)
            else:
                updated = self._range_fix(t, *payload)
            if updated:
                if self.params.project_to_plan:
                    _project(self.site, self.floor, self.ekf)
                estimate = self._emit(t)
                if estimate is not None:
                    out.append(estimate)
        return out

    def _laterate(self, epochs: list[_Epoch]) -> list[tuple[int, LaterationResult]]:
        """Solve every epoch's fix at once with the current biases; return (floor, fix) pairs."""
        anchors = self.site.anchors
        n = len(anchors)
        if not epochs:
            return []
        obs = np.full((len(epochs), n), np.nan)
        std = np.full((len(epochs), n), np.nan)
        for j, e in enumerate(epochs):
            # r̃ = r − b̂
            obs[j, e.anchors] = e.ranges - self.bias[e.anchors]
            std[j, e.anchors] = e.std
        floor_of = np.asarray(anchors.floor)
        floors = [int(np.bincount(floor_of[e.anchors]).argmax()) for e in epochs]
        obs[floor_of[None, :] != np.asarray(floors)[:, None]] = np.nan
        start = None
        if self.ekf.started:
            start = np.tile([self.ekf.x[0], self.ekf.x[1], self.z], (len(epochs), 1))
        solved = solve(
            "range",
            np.asarray(anchors.xyz, dtype=float),
            obs,
            std,
            height=self.params.tag_height_m,
            dims=self.params.dims,
            x0=start,
            params=self.params.lateration,
        )
        return [(floors[j], solved.item(j)) for j in range(len(epochs))]

    def _range_fix(self, t: int, floor: int, result: LaterationResult) -> bool:
        """Fold one epoch's least-squares fix into the filter and, if accepted, the biases."""
        if result.status != Status.OK:
            return False
        self.floor = floor
        self.z = float(result.position[2])
        accepted = self.ekf.update(t, result.position[:2], result.covariance[:2, :2])
        if accepted and self.params.self_calibrate:
            self._learn_biases(t, result)
        return accepted

    def _learn_biases(self, t: int, result: LaterationResult) -> None:
        """Fold an accepted fix's residuals into the bias equations and re-solve them."""
        bp = self.params.bias
        dt = 0.0 if self.bias_t < 0 else max(t - self.bias_t, 0) / 1000.0
        self.bias_t = t
        heard = np.flatnonzero(np.isfinite(result.residuals))
        new = np.setdiff1d(heard, self.bias_ids)
        if new.size:
            m = self.bias_ids.size
            self.bias_ids = np.concatenate([self.bias_ids, new])
            S = np.zeros((self.bias_ids.size, self.bias_ids.size))
            S[:m, :m] = self.bias_S
            self.bias_S = S
            self.bias_g = np.concatenate([self.bias_g, np.zeros(new.size)])
        ids = self.bias_ids
        order = np.argsort(ids)
        # position of each heard anchor in bias_ids
        local = order[np.searchsorted(ids, heard, sorter=order)]
        self.bias_S, self.bias_g = accumulate(
            self.bias_S,
            self.bias_g,
            self.bias[ids],
            local,
            np.asarray(self.site.anchors.xyz, dtype=float)[ids],
            result.position,
            result.residuals[heard],
            result.weights[heard],
            # forgetting factor e^(−Δt/τ)
            float(np.exp(-dt / bp.time_constant_s)),
            result.dims,
            bp,
        )
        self.bias[ids] = solve_biases(self.bias_S, self.bias_g, self.bias_prior[ids], bp)

    def _emit(self, t: int) -> Estimate | None:
        """Return the current estimate if one is due at ``t``."""
        if self.next_emit >= 0 and t < self.next_emit:
            return None
        self.next_emit = t + self.params.emit_every_ms
        x, y, heading, accuracy, speed = self.ekf.estimate()
        return Estimate(t, x, y, self.z, self.floor, heading, accuracy, speed, self.method)


@dataclass(frozen=True)
class LocatorTrackerParams:
    """Everything a tag heard by fixed locators is tracked by.

    Attributes
    ----------
    ekf, lateration
        Parameters of the filter and of the RSSI fixes.
    window_ms : int
        Readings of the last this long are averaged per locator for a fix.
    step_ms : int
        A fix every this much measurement time (on multiples of it).
    tag_height_m : float
        Known height of the tag (m) for 2-D fixes.
    default_A, default_B, default_sigma : float
        Path loss ``rssi = A − B ln r`` (dBm, dB per ln m, dB) of locators
        whose table has no fitted values: a typical BLE tag, free-space
        exponent, seed 003's 5 dB.
    max_samples : int
        Readings counted per locator and window at most: RSSI readings a few
        hundred milliseconds apart share their fading, so σ/√M with the full
        M would make fixes look far more precise than they are.
    fix_std_floor_m : float
        Added in quadrature to each coordinate of a fix's σ (m), R = D + s² I,
        and to the filter's σ in the reported accuracy: the path-loss model's
        error that depends on where the tag is (walls, furniture, the
        carrier's body) is not in D and averages out neither over a window
        nor in the filter. Calibrated on the BLE locator tracks (per-locator
        path loss, leave one track out): 1.1–1.4 m.
    project_to_plan : bool
        Move the estimate off blocked cells after each update.
    """

    ekf: EkfParams = field(default_factory=EkfParams)
    lateration: LaterationParams = field(default_factory=LaterationParams)
    window_ms: int = 2000
    step_ms: int = 500
    tag_height_m: float = 1.0
    default_A: float = -60.0
    default_B: float = path_loss_B(2.0)
    default_sigma: float = 5.0
    max_samples: int = 4
    fix_std_floor_m: float = 1.25
    project_to_plan: bool = True


def window_means(
    t: np.ndarray, tx: np.ndarray, rssi: np.ndarray, n_tx: int, times: np.ndarray, window_ms: int
) -> tuple[np.ndarray, np.ndarray]:
    """Return mean RSSI (F, K) and reading counts (F, K) over (τ − window, τ] at each time τ.

    ``t`` must be sorted; means are NaN where a transmitter was not heard.
    """
    onehot = np.zeros((t.size + 1, n_tx))
    counts = np.zeros((t.size + 1, n_tx))
    onehot[np.arange(1, t.size + 1), tx] = rssi
    counts[np.arange(1, t.size + 1), tx] = 1.0
    # prefix sums: C[i] = Σ_{j < i} readings
    C = np.cumsum(onehot, axis=0)
    N = np.cumsum(counts, axis=0)
    hi = np.searchsorted(t, times, side="right")
    lo = np.searchsorted(t, times - window_ms, side="right")
    n = N[hi] - N[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, (C[hi] - C[lo]) / n, np.nan)
    return mean, n


def strongest_centroid(mean: np.ndarray, xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """Return the centroid (F, 3) of the ``k`` strongest emitters of each row of ``mean`` (F, K)."""
    filled = np.where(np.isfinite(mean), mean, -np.inf)
    top = np.argsort(-filled, axis=1)[:, :k]
    heard = np.take_along_axis(np.isfinite(filled), top, axis=1)
    w = heard.astype(float)
    # c = Σ w_i e_i / Σ w_i over the k strongest heard
    return np.einsum("fk,fkd->fd", w, xyz[top]) / np.maximum(w.sum(axis=1), 1.0)[:, None]


class LocatorTracker:
    """A tag heard by fixed locators: windowed RSSI least squares, then the EKF on motion.

    ``batch.rssi.tx`` indexes ``site.locators``, whose ``A``, ``B``, ``sigma``
    describe the tag-to-locator path loss.
    """

    method = "ekf"

    def __init__(
        self,
        site: SiteModel,
        params: LocatorTrackerParams = LocatorTrackerParams(),
        state: dict[str, Any] | None = None,
    ):
        self.site = site
        self.params = params
        state = state or {}
        self.ekf = PositionEkf(params.ekf, state.get("ekf"))
        self.t = np.asarray(state.get("t", np.zeros(0, np.int64)), dtype=np.int64)
        self.tx = np.asarray(state.get("tx", np.zeros(0, np.int32)), dtype=np.int32)
        self.rssi = np.asarray(state.get("rssi", np.zeros(0)), dtype=float)
        self.next_fix = int(state.get("next_fix", -1))
        self.floor = int(state.get("floor", 0))
        loc = site.locators
        self.A = np.where(np.isfinite(loc.A), loc.A, params.default_A)
        self.B = np.where(np.isfinite(loc.B) & (loc.B > 0), loc.B, params.default_B)
        self.sigma = np.where(
            np.isfinite(loc.sigma) & (loc.sigma > 0), loc.sigma, params.default_sigma
        )

    @classmethod
    def from_snapshot(
        cls, site: SiteModel, params: LocatorTrackerParams, state: dict[str, Any]
    ) -> LocatorTracker:
        """Restore a tracker from :meth:`snapshot`."""
        return cls(site, params, state)

    def snapshot(self) -> dict[str, Any]:
        """Return the recent readings and the filter state."""
        return {
            "ekf": self.ekf.snapshot(),
            "t": self.t.copy(),
            "tx": self.tx.copy(),
            "rssi": self.rssi.copy(),
            "next_fix": self.next_fix,
            "floor": self.floor,
        }

    def process(self, batch: Batch) -> list[Estimate]:
        """Consume one batch of sightings (and gyro, if any) and return the estimates."""
        p = self.params
        r = batch.rssi
        if len(r):
            order = np.argsort(r.t, kind="stable")
            self.t = np.concatenate([self.t, r.t[order]])
            self.tx = np.concatenate([self.tx, r.tx[order]])
            self.rssi = np.concatenate([self.rssi, r.rssi[order]])
        events = _gyro_events(batch)
        if self.t.size:
            if self.next_fix < 0:
                # first fix on the grid of multiples of step_ms after the first reading
                self.next_fix = (int(self.t[0]) // p.step_ms + 1) * p.step_ms
            last = int(self.t[-1])
            times = np.arange(self.next_fix, last + 1, p.step_ms, dtype=np.int64)
            if times.size:
                self.next_fix = int(times[-1]) + p.step_ms
                for tau, result in zip(times, self._fixes(times), strict=True):
                    events.append((int(tau), 1, result))
            keep = self.t > last - p.window_ms
            self.t, self.tx, self.rssi = self.t[keep], self.tx[keep], self.rssi[keep]
        events.sort(key=lambda e: (e[0], e[1]))
        out: list[Estimate] = []
        for t, kind, payload in events:
            if kind == 0:
                self.ekf.gyro(t, payload)
                continue
            if payload.status != Status.OK:
                continue
            # R = D + s² I
            R = payload.covariance[:2, :2] + np.eye(2) * p.fix_std_floor_m**2
            if self.ekf.update(t, payload.position[:2], R):
                if p.project_to_plan:
                    _project(self.site, self.floor, self.ekf)
                # the location-bound model error does not average out: r₆₈ of P_xy + s² I
                x, y, heading, accuracy, speed = self.ekf.estimate(p.fix_std_floor_m**2)
                out.append(
                    Estimate(t, x, y, p.tag_height_m, self.floor, heading, accuracy, speed, "ekf")
                )
        return out

    def _fixes(self, times: np.ndarray) -> list[LaterationResult]:
        """Solve the RSSI fixes at ``times`` (ms) from the buffered readings."""
        p = self.params
        loc = self.site.locators
        xyz = np.asarray(loc.xyz, dtype=float)
        mean, count = window_means(self.t, self.tx, self.rssi, len(loc), times, p.window_ms)
        floors = np.asarray(loc.floor)
        heard_floor = [
            int(np.bincount(floors[np.isfinite(row)]).argmax()) if np.isfinite(row).any() else 0
            for row in mean
        ]
        if heard_floor:
            self.floor = heard_floor[-1]
        mean[floors[None, :] != np.asarray(heard_floor)[:, None]] = np.nan
        # σ_mean = σ / √min(M, M_max)
        std = self.sigma[None, :] / np.sqrt(np.clip(count, 1, p.max_samples))
        x0 = strongest_centroid(mean, xyz)
        if self.ekf.started:
            x0[:, :2] = self.ekf.x[:2]
        x0[:, 2] = p.tag_height_m
        solved = solve(
            "rssi",
            xyz,
            mean,
            std,
            A=self.A,
            B=self.B,
            height=p.tag_height_m,
            dims=2,
            x0=x0,
            params=p.lateration,
        )
        return [solved.item(j) for j in range(len(times))]
