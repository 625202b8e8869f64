"""Pedestrian dead reckoning: steps (time, length, heading) from a phone's IMU stream.

Step detection follows CN106028450: peaks of the low-passed
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

from app.engine import pdr_kernel as kernel
from app.engine.pdr_kernel import NO_TIME, StepRule
from app.engine.samples import ImuSamples, no_times, no_values


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
        step in two: higher cut-offs spread the walked-distance ratios of the
        ILC site1 walks wider (``locus eval pdr`` prints their quartiles).
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
        σ_d of the step length (m), CN106028450.
    heading_std_deg : float
        Standard deviation of a step's heading (degrees) for filters that move
        particles or states by steps: the median absolute heading error on ILC
        site1's test segments is about 10° (``locus eval pdr``), i.e.
        σ ≈ 10 / 0.674 ≈ 15° if Gaussian.
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

    t: np.ndarray = field(default_factory=no_times)
    length: np.ndarray = field(default_factory=no_values)
    heading: np.ndarray = field(default_factory=no_values)
    swing: np.ndarray = field(default_factory=no_values)

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


def weinberg_length(swing: np.ndarray, k: float) -> np.ndarray:
    """Return Weinberg step lengths (m) for acceleration swings a_max - a_min (m/s²)."""
    # L = K (a_max - a_min)^(1/4)
    return k * np.power(np.clip(swing, 0.0, None), 0.25)


def lowpass_coefficients(params: PdrParams) -> tuple[np.ndarray, np.ndarray]:
    """Return (b, a) of the Butterworth low-pass applied to |a| on the resampling grid."""
    return _butter(params.lowpass_order, params.lowpass_hz, 1000.0 / params.grid_ms)


def _lowpass_zi(b: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Return the state that starts ``b / a`` in steady state for a unit input.

    A copy: the compiled filter updates its state in place.
    """
    return _unit_zi(tuple(b), tuple(a)).copy()


@functools.lru_cache(maxsize=16)
def _unit_zi(b: tuple[float, ...], a: tuple[float, ...]) -> np.ndarray:
    """``scipy.signal.lfilter_zi``, once per filter: it costs more than a batch's filtering."""
    return signal.lfilter_zi(np.array(b), np.array(a))


@functools.lru_cache(maxsize=16)
def _butter(order: int, cutoff_hz: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Design the filter once per setting: the design is costly, and every new device needs it."""
    b, a = signal.butter(order, cutoff_hz, fs=fs)
    b, a = np.asarray(b), np.asarray(a)
    # shared by every detector: read-only
    b.setflags(write=False)
    a.setflags(write=False)
    return b, a


# Columns of the per-sample channel matrix resampled onto the grid (``kernel.channels``).
_RS, _R, _MS, _MC = kernel.RS, kernel.R, kernel.MS, kernel.MC
_N_CHANNELS = kernel.N_CHANNELS


def imu_channels(imu: ImuSamples, compass: bool = True) -> np.ndarray:
    """Return the per-sample channels the detector resamples, shape (n, 6) (``kernel.channels``)."""
    n = len(imu.t)

    def columns(values: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(values, dtype=float).reshape(n, -1))

    return kernel.channels(
        columns(imu.acc), columns(imu.rot), columns(imu.gyro), columns(imu.mag), compass
    )


class Pdr:
    """Stateful step detector over a device's IMU stream, fed in batches of any size.

    ``update`` takes the next batch and returns the steps whose peaks it
    confirmed; samples not newer than the last one already seen are dropped
    (counted in ``late``). ``snapshot``/``from_snapshot`` round-trip the state.
    """

    def __init__(self, params: PdrParams | None = None) -> None:
        self.params = params or PdrParams()
        self._b, self._a = lowpass_coefficients(self.params)
        p = self.params
        self._rule = StepRule(
            p.gravity, p.peak_min, p.min_swing, p.min_step_interval_ms, p.max_step_ms
        )
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
        t_raw = NO_TIME if self._t_raw is None else self._t_raw
        t, x, late = kernel.prepare(t, x, t_raw, self._fill)
        self.late += late
        if t.size == 0:
            return Steps()
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
        """Process samples with no long pause: resample, filter, look for peaks (compiled)."""
        p = self.params
        alpha = 1.0 - np.exp(-p.grid_ms / (1000.0 * p.mag_time_constant_s))
        started = np.array([self._zi_acc is not None, self._zi_head is not None], dtype=float)
        # each filter's state, or its unit steady state until it starts
        zi_acc = self._zi_acc if self._zi_acc is not None else _lowpass_zi(self._b, self._a)
        zi_head = (
            self._zi_head
            if self._zi_head is not None
            else _lowpass_zi(np.ones(1), np.array([1.0, alpha - 1.0]))
        )
        step_t, swing, heading, last, checked, self._buf_t, self._buf, self._u_last = (
            kernel.segment(
                t,
                x,
                NO_TIME if self._t_raw is None else self._t_raw,
                self._raw,
                p.grid_ms,
                self._b,
                self._a,
                zi_acc,
                zi_head,
                started,
                self._u_last,
                alpha,
                np.radians(p.heading_offset_deg),
                self._buf_t,
                self._buf,
                NO_TIME if self._t_checked is None else self._t_checked,
                NO_TIME if self._t_last_step is None else self._t_last_step,
                self._rule,
            )
        )
        self._t_raw, self._raw = int(t[-1]), x[-1].copy()
        if started[0]:
            self._zi_acc = zi_acc
        if started[1]:
            self._zi_head = zi_head
        self._t_last_step = None if last == NO_TIME else int(last)
        self._t_checked = None if checked == NO_TIME else int(checked)
        return Steps(
            t=step_t, length=weinberg_length(swing, p.weinberg_k), heading=heading, swing=swing
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
            # a copy: the compiled filters update their state in place
            return None if value is None else np.array(value, dtype=dtype)

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
