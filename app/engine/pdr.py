"""Pedestrian dead reckoning: steps (time, length, heading) from a phone's IMU stream.

Step detection follows CN106028450 (seed 002): peaks of the low-passed
acceleration, keeping only the first peak within τ = 0.3 s. The magnitude of
the acceleration replaces the patent's z axis so that detection does not
depend on how the phone is held. Step length is Weinberg's
``K (a_max - a_min)^(1/4)``; heading is the azimuth of the phone's +y axis,
from the Android rotation vector when the device sends one, else from a
complementary filter of gyro yaw rate and tilt-compensated magnetometer.

Streams arrive in batches of about a second. Every stream is resampled onto
an absolute time grid (multiples of ``grid_ms``) and filtered with carried
state, so feeding a stream in any chunking emits the same steps as feeding it
at once; the state snapshots to a small dict of numbers and arrays.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import signal

from app.engine.samples import ImuSamples


@dataclass(frozen=True)
class PdrParams:
    """Tunable constants of step detection, step length and heading.

    Attributes
    ----------
    grid_ms : int
        Resampling period (ms); 50 Hz, the top of the 25–50 Hz the patent asks for.
    lowpass_hz : float
        Cut-off (Hz) of the Butterworth low-pass on |a|: at the top of walking
        cadence (1.5–2.5 steps/s), below the heel-strike ringing that splits a
        step in two. On the ILC site1 training walks 2.5 Hz gave a tighter
        spread of walked-distance ratios than 3 or 4 Hz.
    lowpass_order : int
        Order of that filter.
    min_step_interval_ms : int
        τ of the patent (0.3 s): of several peaks within τ only the first is a step.
    max_step_ms : int
        Longest step (ms): the window searched back for a_min and averaged for heading.
    peak_min : float
        A step's peak must exceed gravity by this much (m/s²).
    min_swing : float
        A step's a_max - a_min must reach this much (m/s²); rejects sway while standing.
    gravity : float
        Standard gravity (m/s²).
    weinberg_k : float
        K of Weinberg's step length ``K (a_max - a_min)^(1/4)`` (m·(m/s²)^(-1/4)),
        calibrated on the ILC site1 training walks (``app.evaluation.pdr_eval``:
        total waypoint distance over total swing^(1/4)).
    step_length_std : float
        σ_d of the step length (m), seed 002.
    heading_std_deg : float
        Standard deviation of a step's heading (degrees) for filters that move
        particles or states by steps: the median absolute heading error on ILC
        site1 segments is about 9.4°, i.e. σ ≈ 9.4 / 0.674 ≈ 14° if Gaussian.
    mag_time_constant_s : float
        Time constant (s) with which the magnetometer corrects the integrated
        gyro heading when there is no rotation vector.
    heading_offset_deg : float
        Added to every heading: the site frame's rotation against magnetic north.
    max_gap_ms : int
        A pause longer than this between samples restarts the filters.
    """

    grid_ms: int = 20
    lowpass_hz: float = 2.5
    lowpass_order: int = 2
    min_step_interval_ms: int = 300
    max_step_ms: int = 1000
    peak_min: float = 0.6
    min_swing: float = 2.0
    gravity: float = 9.80665
    weinberg_k: float = 0.401
    step_length_std: float = 0.1
    heading_std_deg: float = 15.0
    mag_time_constant_s: float = 2.0
    heading_offset_deg: float = 0.0
    max_gap_ms: int = 1000


@dataclass(frozen=True)
class Steps:
    """Detected steps, aligned arrays in time order.

    ``t`` (int64 ms) is the time of the step's acceleration peak, ``length``
    (m), ``heading`` (degrees clockwise from +y in [0, 360), NaN when no
    heading source was available) and ``swing`` = a_max - a_min (m/s²).
    """

    t: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    length: np.ndarray = field(default_factory=lambda: np.zeros(0))
    heading: np.ndarray = field(default_factory=lambda: np.zeros(0))
    swing: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        """Return the number of steps."""
        return int(self.t.size)

    @staticmethod
    def concat(parts: list[Steps]) -> Steps:
        """Join step batches in order."""
        if not parts:
            return Steps()
        return Steps(
            t=np.concatenate([p.t for p in parts]).astype(np.int64),
            length=np.concatenate([p.length for p in parts]),
            heading=np.concatenate([p.heading for p in parts]),
            swing=np.concatenate([p.swing for p in parts]),
        )


def rotation_vector_heading(rot: np.ndarray) -> np.ndarray:
    """Return the azimuth of the phone's +y axis from Android rotation vectors.

    Parameters
    ----------
    rot : ndarray, shape (n, 3) or (n, 4)
        Quaternion x, y, z[, w] rotating the device frame to east-north-up;
        a missing or NaN w is implied as ``sqrt(1 - x² - y² - z²)``.

    Returns
    -------
    ndarray, shape (n,)
        Degrees clockwise from north in [0, 360); NaN where rot is NaN.
    """
    rot = np.asarray(rot, dtype=float)
    x, y, z = rot[:, 0], rot[:, 1], rot[:, 2]
    # w = sqrt(1 - x² - y² - z²) when the sender leaves it out
    implied = np.sqrt(np.clip(1.0 - x * x - y * y - z * z, 0.0, None))
    w = implied if rot.shape[1] < 4 else np.where(np.isnan(rot[:, 3]), implied, rot[:, 3])
    # ψ = atan2(R₀₁, R₁₁) = atan2(2(xy - zw), 1 - 2(x² + z²)), the device y axis in ENU
    psi = np.degrees(np.arctan2(2.0 * (x * y - z * w), 1.0 - 2.0 * (x * x + z * z)))
    return np.mod(psi, 360.0)


def magnetic_heading(acc: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """Return the tilt-compensated magnetic azimuth of the phone's +y axis (Android's method).

    Parameters
    ----------
    acc : ndarray, shape (n, 3)
        Accelerometer (m/s²), taken as the up direction in the device frame.
    mag : ndarray, shape (n, 3)
        Magnetic field (µT) in the device frame.

    Returns
    -------
    ndarray, shape (n,)
        Degrees clockwise from magnetic north in [0, 360); NaN where an input is NaN.
    """
    # H = m × a points east, M = a × H points north (both horizontal)
    east = _cross(mag, acc)
    north = _cross(acc, east)
    # ψ = atan2(Ĥ_y, M̂_y): the device y axis' east and north components
    psi = np.degrees(np.arctan2(east[:, 1] / _norm(east), north[:, 1] / _norm(north)))
    return np.mod(psi, 360.0)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the row-wise cross product of (n, 3) arrays.

    np.cross costs about 20 µs more a call, and the detector calls it twice a batch.
    """
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=1)


def _norm(a: np.ndarray) -> np.ndarray:
    """Return the Euclidean norm of each row of an (n, 3) array."""
    return np.sqrt(np.add.reduce(a * a, axis=1))


def yaw_rate(acc: np.ndarray, gyro: np.ndarray) -> np.ndarray:
    """Return the rotation rate about the vertical, clockwise seen from above (rad/s).

    Parameters
    ----------
    acc : ndarray, shape (n, 3)
        Accelerometer (m/s²), giving the up direction.
    gyro : ndarray, shape (n, 3)
        Angular rate (rad/s), counter-clockwise positive about each device axis.

    Returns
    -------
    ndarray, shape (n,)
    """
    # r = -ω · a / |a|: counter-clockwise about up is a decreasing heading
    return -np.sum(gyro * acc, axis=1) / _norm(acc)


def weinberg_length(swing: np.ndarray, k: float) -> np.ndarray:
    """Return Weinberg step lengths (m) for acceleration swings a_max - a_min (m/s²)."""
    # L = K (a_max - a_min)^(1/4)
    return k * np.power(np.clip(swing, 0.0, None), 0.25)


def lowpass_coefficients(params: PdrParams) -> tuple[np.ndarray, np.ndarray]:
    """Return (b, a) of the Butterworth low-pass applied to |a| on the resampling grid."""
    return _butter(params.lowpass_order, params.lowpass_hz, 1000.0 / params.grid_ms)


@functools.lru_cache(maxsize=16)
def _butter(order: int, cutoff_hz: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Design the filter once per setting: scipy takes 0.3 ms, and every new device needs it."""
    b, a = signal.butter(order, cutoff_hz, fs=fs)
    b, a = np.asarray(b), np.asarray(a)
    # shared by every detector: read-only
    b.setflags(write=False)
    a.setflags(write=False)
    return b, a


def local_maxima(f: np.ndarray) -> np.ndarray:
    """Return indices i with f[i-1] < f[i] >= f[i+1] (interior samples only), shape (k,)."""
    return np.flatnonzero((f[1:-1] > f[:-2]) & (f[1:-1] >= f[2:])) + 1


def forward_fill(x: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Replace each NaN of ``x`` (n, d) by the latest finite value of its column.

    ``last`` (d,) holds each column's value before the first row (NaN if none).
    """
    rows = np.arange(x.shape[0])[:, None]
    # idx_ij = max{k ≤ i : x_kj finite}, -1 before the first
    idx = np.maximum.accumulate(np.where(np.isfinite(x), rows, -1), axis=0)
    filled = np.take_along_axis(x, np.maximum(idx, 0), axis=0)
    return np.where(idx >= 0, filled, last[None, :])


def circular_mean_deg(s: np.ndarray, c: np.ndarray) -> float:
    """Return the direction (degrees in [0, 360)) of the summed finite unit vectors, or NaN."""
    ok = np.isfinite(s) & np.isfinite(c)
    if not ok.any():
        return float("nan")
    # ψ̄ = atan2(Σ sin ψ, Σ cos ψ)
    return float(np.mod(np.degrees(np.arctan2(s[ok].sum(), c[ok].sum())), 360.0))


# Columns of the per-sample channel matrix resampled onto the grid.
_A, _RS, _RC, _R, _MS, _MC = range(6)
_N_CHANNELS = 6


def imu_channels(imu: ImuSamples, compass: bool = True) -> np.ndarray:
    """Return the per-sample channels the detector resamples, shape (n, 6).

    Columns: |a| (m/s²), sin and cos of the rotation-vector heading, yaw rate
    (rad/s, clockwise), sin and cos of the magnetic heading; NaN where the
    source field is absent. Without ``compass`` the last three (what the
    gyro + magnetometer heading needs) are left NaN.
    """
    acc = np.asarray(imu.acc, dtype=float)
    n = acc.shape[0]
    out = np.full((n, _N_CHANNELS), np.nan)
    # |a| = sqrt(ax² + ay² + az²)
    out[:, _A] = _norm(acc)
    rot = np.asarray(imu.rot, dtype=float).reshape(n, -1)
    if rot.shape[1] >= 3:
        psi = np.radians(rotation_vector_heading(rot))
        out[:, _RS], out[:, _RC] = np.sin(psi), np.cos(psi)
    if not compass:
        return out
    gyro = np.asarray(imu.gyro, dtype=float).reshape(n, -1)
    if gyro.shape[1] == 3:
        out[:, _R] = yaw_rate(acc, gyro)
    mag = np.asarray(imu.mag, dtype=float).reshape(n, -1)
    if mag.shape[1] == 3:
        with np.errstate(invalid="ignore", divide="ignore"):
            psi = np.radians(magnetic_heading(acc, mag))
        out[:, _MS], out[:, _MC] = np.sin(psi), np.cos(psi)
    return out


class Pdr:
    """Stateful step detector over a device's IMU stream, fed in batches of any size.

    ``update`` takes the next batch and returns the steps whose peaks it
    confirmed; samples not newer than the last one already seen are dropped
    (counted in ``late``). ``snapshot``/``from_snapshot`` round-trip the state.
    """

    def __init__(self, params: PdrParams | None = None) -> None:
        self.params = params or PdrParams()
        self._b, self._a = lowpass_coefficients(self.params)
        self.late = 0
        self._t_last_step: int | None = None
        # Forward-fill memory of the heading channels (never reset by gaps).
        self._fill = np.full(_N_CHANNELS, np.nan)
        self._reset_stream()

    def _reset_stream(self) -> None:
        """Forget the signal history: used at start and after a pause longer than max_gap_ms."""
        self._t_raw: int | None = None
        self._raw = np.full(_N_CHANNELS, np.nan)
        self._zi_acc: np.ndarray | None = None
        self._zi_head: np.ndarray | None = None
        self._u_last = float("nan")
        self._t_checked: int | None = None
        self._buf_t = np.zeros(0, dtype=np.int64)
        self._buf = np.zeros((0, 3))

    # -- batches -------------------------------------------------------------

    def update(self, imu: ImuSamples) -> Steps:
        """Consume one batch of IMU samples and return the steps it completes.

        Samples without acceleration are ignored; a sample lacking a heading
        field (rotation vector, gyro, magnetometer) reuses that field's last
        value, so a device may send them at a lower rate than the accelerometer.
        """
        t = np.asarray(imu.t, dtype=np.int64)
        compass = not self._rotation_covers(imu)
        if not compass:
            self._forget_compass()
        x = imu_channels(imu, compass)
        order = np.argsort(t, kind="stable")
        t, x = t[order], x[order]
        keep = np.isfinite(x[:, _A])
        # Keep the first sample of a repeated timestamp.
        keep[1:] &= t[1:] != t[:-1]
        if self._t_raw is not None:
            newer = t > self._t_raw
            self.late += int(np.count_nonzero(keep & ~newer))
            keep &= newer
        t, x = t[keep], x[keep]
        if t.size == 0:
            return Steps()
        # a channel with gaps takes its last value; one never sent (nor before) stays NaN
        missing = np.isnan(x[:, 1:])
        gaps = np.flatnonzero(
            missing.any(axis=0) & ~(missing.all(axis=0) & np.isnan(self._fill[1:]))
        )
        if gaps.size:
            x[:, gaps + 1] = forward_fill(x[:, gaps + 1], self._fill[gaps + 1])
        self._fill = x[-1].copy()
        prev = np.concatenate([[self._t_raw if self._t_raw is not None else t[0]], t[:-1]])
        cuts = np.flatnonzero(t - prev > self.params.max_gap_ms)
        if cuts.size == 0:
            if self._t_raw is not None and t[0] - self._t_raw > self.params.max_gap_ms:
                self._reset_stream()
            return self._segment(t, x)
        parts = []
        for seg_t, seg_x in zip(np.split(t, cuts), np.split(x, cuts), strict=True):
            if seg_t.size == 0:
                continue
            if self._t_raw is not None and seg_t[0] - self._t_raw > self.params.max_gap_ms:
                self._reset_stream()
            parts.append(self._segment(seg_t, seg_x))
        return Steps.concat(parts)

    def _rotation_covers(self, imu: ImuSamples) -> bool:
        """Return whether the rotation vector gives every heading of this batch.

        Every sample carries one and so did the last sample before the batch
        (the grid interpolates from it): the gyro + magnetometer heading, a
        third of the detector's work, would go unused.
        """
        rot = np.asarray(imu.rot, dtype=float).reshape(len(imu.t), -1)
        if rot.shape[1] < 3 or not np.isfinite(rot[:, :3]).all():
            return False
        return self._t_raw is None or bool(np.isfinite(self._raw[_RS]))

    def _forget_compass(self) -> None:
        """Drop the gyro + magnetometer heading's state while the rotation vector rules.

        A later stretch without the rotation vector starts that heading afresh
        from the magnetometer.
        """
        self._u_last = float("nan")
        self._zi_head = None
        self._fill[[_R, _MS, _MC]] = np.nan

    def _segment(self, t: np.ndarray, x: np.ndarray) -> Steps:
        """Process samples with no long pause: resample, filter, look for peaks."""
        dt = self.params.grid_ms
        if self._t_raw is None:
            first = -(-int(t[0]) // dt) * dt
            src_t, src_x = t, x
        else:
            first = (self._t_raw // dt + 1) * dt
            src_t, src_x = np.concatenate([[self._t_raw], t]), np.vstack([self._raw, x])
        self._t_raw, self._raw = int(t[-1]), x[-1].copy()
        grid = np.arange(first, int(t[-1]) + 1, dt, dtype=np.int64)
        if grid.size == 0:
            return Steps()
        # Linear interpolation of every channel onto the grid (a channel never sent stays NaN)
        g = np.full((grid.size, _N_CHANNELS), np.nan)
        for j in np.flatnonzero(~np.isnan(src_x).all(axis=0)):
            g[:, j] = np.interp(grid, src_t, src_x[:, j])
        f = self._lowpass(g[:, _A])
        heading = self._heading(g)
        return self._peaks(grid, np.column_stack([f, np.sin(heading), np.cos(heading)]))

    def _lowpass(self, a: np.ndarray) -> np.ndarray:
        """Low-pass |a| with carried filter state, starting in steady state at the first value."""
        if self._zi_acc is None:
            self._zi_acc = signal.lfilter_zi(self._b, self._a) * a[0]
        f, self._zi_acc = signal.lfilter(self._b, self._a, a, zi=self._zi_acc)
        return f

    def _heading(self, g: np.ndarray) -> np.ndarray:
        """Return grid headings (rad, site frame): rotation vector, else gyro + magnetometer."""
        p = self.params
        psi = np.arctan2(g[:, _RS], g[:, _RC])
        comp = np.full(g.shape[0], np.nan)
        mag = np.arctan2(g[:, _MS], g[:, _MC])
        ok = np.flatnonzero(np.isfinite(mag))
        if ok.size:
            i0 = ok[0]
            # u: magnetic heading unwrapped continuously from the previous batch
            seed = self._u_last if np.isfinite(self._u_last) else mag[i0]
            u = np.unwrap(np.concatenate([[seed], mag[i0:]]))[1:]
            self._u_last = float(u[-1])
            alpha = 1.0 - np.exp(-p.grid_ms / (1000.0 * p.mag_time_constant_s))
            r = np.nan_to_num(g[i0:, _R])
            # ψ_k = (1 - α)(ψ_{k-1} + r_k Δt) + α u_k
            drive = (1.0 - alpha) * r * (p.grid_ms / 1000.0) + alpha * u
            den = np.array([1.0, -(1.0 - alpha)])
            if self._zi_head is None:
                self._zi_head = signal.lfilter_zi([1.0], den) * alpha * u[0]
            comp[i0:], self._zi_head = signal.lfilter([1.0], den, drive, zi=self._zi_head)
        psi = np.where(np.isfinite(psi), psi, comp)
        # ψ_site = ψ + offset
        return psi + np.radians(p.heading_offset_deg)

    def _peaks(self, grid: np.ndarray, cols: np.ndarray) -> Steps:
        """Find steps among the new grid samples; ``cols`` is (m, 3): f, sin ψ, cos ψ."""
        p = self.params
        t = np.concatenate([self._buf_t, grid])
        v = np.vstack([self._buf, cols])
        f = v[:, 0]
        cand = local_maxima(f)
        if self._t_checked is not None:
            cand = cand[t[cand] > self._t_checked]
        if t.size >= 2:
            self._t_checked = int(t[-2])
        out_t: list[int] = []
        out_swing: list[float] = []
        out_heading: list[float] = []
        for j in cand:
            tj = int(t[j])
            if f[j] - p.gravity < p.peak_min:
                continue
            if self._t_last_step is not None and tj - self._t_last_step < p.min_step_interval_ms:
                continue
            lo = tj - p.max_step_ms
            if self._t_last_step is not None:
                lo = max(lo, self._t_last_step)
            window = (t > lo) & (t <= tj)
            # swing = a_max - a_min over the step
            swing = f[j] - f[window].min()
            if swing < p.min_swing:
                continue
            out_t.append(tj)
            out_swing.append(float(swing))
            out_heading.append(circular_mean_deg(v[window, 1], v[window, 2]))
            self._t_last_step = tj
        keep = p.max_step_ms // p.grid_ms + 2
        self._buf_t, self._buf = t[-keep:], v[-keep:]
        swing_arr = np.array(out_swing)
        return Steps(
            t=np.array(out_t, dtype=np.int64),
            length=weinberg_length(swing_arr, p.weinberg_k),
            heading=np.array(out_heading),
            swing=swing_arr,
        )

    # -- snapshots -----------------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        """Return the state as a dict of numbers and float/int arrays (no params)."""
        return {
            "late": self.late,
            "t_last_step": self._t_last_step,
            "fill": self._fill.copy(),
            "t_raw": self._t_raw,
            "raw": self._raw.copy(),
            "zi_acc": None if self._zi_acc is None else self._zi_acc.copy(),
            "zi_head": None if self._zi_head is None else self._zi_head.copy(),
            "u_last": self._u_last,
            "t_checked": self._t_checked,
            "buf_t": self._buf_t.copy(),
            "buf": self._buf.copy(),
        }

    @classmethod
    def from_snapshot(cls, state: dict[str, Any], params: PdrParams | None = None) -> Pdr:
        """Rebuild a detector from ``snapshot()`` output (lists are accepted for arrays)."""

        def arr(key: str, dtype: type = float) -> np.ndarray | None:
            value = state[key]
            return None if value is None else np.asarray(value, dtype=dtype)

        def opt_int(key: str) -> int | None:
            value = state[key]
            return None if value is None else int(value)

        pdr = cls(params)
        pdr.late = int(state["late"])
        pdr._t_last_step = opt_int("t_last_step")
        pdr._fill = np.asarray(state["fill"], dtype=float)
        pdr._t_raw = opt_int("t_raw")
        pdr._raw = np.asarray(state["raw"], dtype=float)
        pdr._zi_acc = arr("zi_acc")
        pdr._zi_head = arr("zi_head")
        pdr._u_last = float(state["u_last"])
        pdr._t_checked = opt_int("t_checked")
        pdr._buf_t = np.asarray(state["buf_t"], dtype=np.int64)
        pdr._buf = np.asarray(state["buf"], dtype=float).reshape(-1, 3)
        return pdr


def detect_steps(imu: ImuSamples, params: PdrParams | None = None) -> Steps:
    """Return the steps of a whole recorded stream (one ``Pdr`` fed once)."""
    return Pdr(params).update(imu)
