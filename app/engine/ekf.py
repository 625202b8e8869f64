"""Extended Kalman filter of position fixes and gyro yaw rate (Brovko's UWB + inertial EKF report).

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

:class:`PositionEkf` is that filter as a state machine. :func:`gyro_events`
and :func:`project_onto_plan` are what every tracker on it needs from a batch
and from the floor plan; the trackers themselves are ``uwb_tracker`` (UWB
ranges or given fixes) and ``locator_tracker`` (RSSI heard by fixed locators).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from app.engine.gaussian import R68_SIGMAS_2D
from app.engine.samples import Batch
from app.engine.site import SiteModel

POSITION_H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
"""Observation matrix of a position fix (Brovko's EKF report, eq. 12)."""


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
    """Return the state extrapolated by ``dt`` seconds (Brovko, eqs. 3 and 7), shape (4,)."""
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
    """Return ∂f/∂x at ``x`` (Brovko's EKF report, eq. 9), shape (4, 4)."""
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
    """Extrapolate state and covariance by ``dt`` seconds (Brovko's EKF report, eqs. 7–8)."""
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
    return R68_SIGMAS_2D * float(np.sqrt(max(np.trace(P_xy), 0.0) / 2.0))


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


def gyro_events(batch: Batch) -> list[tuple[int, int, Any]]:
    """Return (t, 0, yaw rate) events of the batch's IMU samples that carry a gyro.

    Kind 0 sorts them before the trackers' fixes (kinds 1 and up) of the same time.
    """
    imu = batch.imu
    if not len(imu):
        return []
    rate = imu_yaw_rate(imu.acc, imu.gyro)
    return [(int(t), 0, float(w)) for t, w in zip(imu.t, rate, strict=True) if np.isfinite(w)]


def project_onto_plan(site: SiteModel, floor: int, ekf: PositionEkf) -> None:
    """Move the filter's position off blocked cells of the floor plan."""
    if not site.floors:
        return
    plan = site.floors[min(max(floor, 0), len(site.floors) - 1)].plan
    ekf.x[:2] = plan.project(ekf.x[:2])
