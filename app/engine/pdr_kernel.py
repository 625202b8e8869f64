"""The step detector's per-batch loops, compiled.

A batch's channels and preparation (sort, screens, heading channels filled)
in one pass; then, for each stretch without a long pause, resampling onto the
time grid, the low-pass of |a|, the heading (rotation vector, else gyro +
magnetometer) and the peak search in another. In numpy they were dozens of
small calls a batch, whose overhead cost far more than the arithmetic on a
second's fifty samples. Compiled once per process
(numba's disk cache); ``load_kernel`` does it before a device needs it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

NO_TIME = np.iinfo(np.int64).min
"""Stands for "none yet" among the detector's times (the compiled loop takes no None)."""

# Columns of the per-sample channel matrix: |a|, sin/cos of the rotation-vector heading,
# yaw rate, sin/cos of the magnetic heading.
A, RS, RC, R, MS, MC = range(6)
N_CHANNELS = 6


class StepRule(NamedTuple):
    """What makes a peak of the low-passed |a| a step (``PdrParams``' fields of the same names)."""

    gravity: float
    peak_min: float
    min_swing: float
    min_step_interval_ms: int
    max_step_ms: int


_DEG = 180.0 / math.pi
"""Degrees per radian, as ``np.degrees`` multiplies."""

_RAD = math.pi / 180.0
"""Radians per degree, as ``np.radians`` multiplies."""


@njit(cache=True)
def rotation_heading(x: float, y: float, z: float, w: float) -> float:  # pragma: no cover
    """Return the azimuth (degrees in [0, 360)) of the phone's +y axis from a rotation vector.

    Android's rotation vector (x, y, z, w) rotates the device frame to
    east-north-up; a NaN ``w`` is implied as ``sqrt(1 - x² - y² - z²)``.
    """
    if math.isnan(w):
        rest = 1.0 - x * x - y * y - z * z
        w = math.sqrt(rest if not rest < 0.0 else 0.0)
    # ψ = atan2(R₀₁, R₁₁) = atan2(2(xy - zw), 1 - 2(x² + z²)), the device y axis in ENU
    return (math.atan2(2.0 * (x * y - z * w), 1.0 - 2.0 * (x * x + z * z)) * _DEG) % 360.0


@njit(cache=True, error_model="numpy")
def magnetic_heading(
    ax: float, ay: float, az: float, mx: float, my: float, mz: float
) -> float:  # pragma: no cover
    """Return the tilt-compensated magnetic azimuth (degrees in [0, 360)) of the phone's +y axis.

    Android's method: the accelerometer (m/s²) gives up, the field (µT) north,
    both in the device frame.
    """
    # H = m × a points east, M = a × H points north (both horizontal)
    ex, ey, ez = my * az - mz * ay, mz * ax - mx * az, mx * ay - my * ax
    nx, ny, nz = ay * ez - az * ey, az * ex - ax * ez, ax * ey - ay * ex
    east = math.sqrt(ex * ex + ey * ey + ez * ez)
    north = math.sqrt(nx * nx + ny * ny + nz * nz)
    # ψ = atan2(Ĥ_y, M̂_y): the device y axis' east and north components
    return (math.atan2(ey / east, ny / north) * _DEG) % 360.0


@njit(cache=True, error_model="numpy")
def yaw_rate(
    ax: float, ay: float, az: float, gx: float, gy: float, gz: float
) -> float:  # pragma: no cover
    """Return the rotation rate about the vertical, clockwise seen from above (rad/s)."""
    # r = -ω · a / |a|: counter-clockwise about up is a decreasing heading
    return -(gx * ax + gy * ay + gz * az) / math.sqrt(ax * ax + ay * ay + az * az)


@njit(cache=True, error_model="numpy")
def channels(
    acc: np.ndarray, rot: np.ndarray, gyro: np.ndarray, mag: np.ndarray, compass: bool
) -> np.ndarray:  # pragma: no cover
    """Return the per-sample channels the detector resamples, shape (n, 6).

    Columns: |a| (m/s²), sin and cos of the rotation-vector heading, yaw rate
    (rad/s, clockwise), sin and cos of the magnetic heading; NaN where the
    source is absent (``rot`` with fewer than 3 columns, ``gyro`` or ``mag``
    without 3). Without ``compass`` the last three (what the gyro +
    magnetometer heading needs) are left NaN.
    """
    n = acc.shape[0]
    out = np.full((n, N_CHANNELS), np.nan)
    for i in range(n):
        ax, ay, az = acc[i, 0], acc[i, 1], acc[i, 2]
        out[i, A] = math.sqrt(ax * ax + ay * ay + az * az)
        if rot.shape[1] >= 3:
            w = rot[i, 3] if rot.shape[1] >= 4 else np.nan
            psi = rotation_heading(rot[i, 0], rot[i, 1], rot[i, 2], w) * _RAD
            out[i, RS], out[i, RC] = math.sin(psi), math.cos(psi)
        if not compass:
            continue
        if gyro.shape[1] == 3:
            out[i, R] = yaw_rate(ax, ay, az, gyro[i, 0], gyro[i, 1], gyro[i, 2])
        if mag.shape[1] == 3:
            psi = magnetic_heading(ax, ay, az, mag[i, 0], mag[i, 1], mag[i, 2]) * _RAD
            out[i, MS], out[i, MC] = math.sin(psi), math.cos(psi)
    return out


@njit(cache=True)
def prepare(
    t: np.ndarray, x: np.ndarray, t_raw: int, fill: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:  # pragma: no cover
    """Return a batch's usable samples in time order, heading channels filled, and the late.

    Samples are sorted by time (stable); one without acceleration, one
    repeating an earlier sample's time and one not newer than ``t_raw`` (the
    last sample already used; ``NO_TIME``: none) are left out, the last
    counted as late. A NaN in a heading channel takes that channel's last
    value, ``fill`` before the first sample (NaN: none yet).
    """
    order = np.argsort(t, kind="mergesort")
    n = t.size
    keep = np.zeros(n, dtype=np.bool_)
    late = 0
    for i in range(n):
        j = order[i]
        ok = not math.isnan(x[j, A])
        # the first sample of a repeated time
        if i > 0 and t[j] == t[order[i - 1]]:
            ok = False
        if ok and t_raw != NO_TIME and t[j] <= t_raw:
            late += 1
            ok = False
        keep[i] = ok
    m = 0
    for i in range(n):
        if keep[i]:
            m += 1
    out_t = np.empty(m, dtype=np.int64)
    out_x = np.empty((m, x.shape[1]))
    carry = fill.copy()
    k = 0
    for i in range(n):
        if not keep[i]:
            continue
        j = order[i]
        out_t[k] = t[j]
        out_x[k, A] = x[j, A]
        for c in range(1, x.shape[1]):
            if math.isnan(x[j, c]):
                out_x[k, c] = carry[c]
            else:
                out_x[k, c] = x[j, c]
                carry[c] = x[j, c]
        k += 1
    return out_t, out_x, late


@njit(cache=True)
def _interp(x: float, xp: np.ndarray, fp: np.ndarray, j: int) -> float:  # pragma: no cover
    """Return ``np.interp(x, xp, fp)`` given ``xp[j] <= x < xp[j + 1]`` (numpy's rules)."""
    if x == xp[j]:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    out = slope * (x - xp[j]) + fp[j]
    if math.isnan(out):
        out = slope * (x - xp[j + 1]) + fp[j + 1]
        if math.isnan(out) and fp[j] == fp[j + 1]:
            out = fp[j]
    return out


@njit(cache=True)
def resample(
    src_t: np.ndarray, src_x: np.ndarray, grid: np.ndarray
) -> np.ndarray:  # pragma: no cover
    """Return every channel of ``src_x`` (n, c) linearly interpolated at ``grid`` (m,).

    Outside ``src_t``'s span a channel holds its end value, as ``np.interp``;
    a channel with no finite sample stays NaN.
    """
    n, c = src_x.shape
    out = np.full((grid.size, c), np.nan)
    for ch in range(c):
        sent = False
        for i in range(n):
            if not math.isnan(src_x[i, ch]):
                sent = True
                break
        if not sent:
            continue
        xp = src_t.astype(np.float64)
        fp = np.ascontiguousarray(src_x[:, ch])
        j = 0
        for k in range(grid.size):
            x = float(grid[k])
            if x <= xp[0]:
                out[k, ch] = fp[0]
                continue
            if x >= xp[n - 1]:
                out[k, ch] = fp[n - 1]
                continue
            while xp[j + 1] <= x:
                j += 1
            out[k, ch] = _interp(x, xp, fp, j)
    return out


@njit(cache=True)
def iir(
    b: np.ndarray, a: np.ndarray, x: np.ndarray, z: np.ndarray
) -> np.ndarray:  # pragma: no cover
    """Filter ``x`` by ``b / a`` (``a[0] == 1``) as ``scipy.signal.lfilter`` does.

    Transposed direct form II; ``z`` (len(a) - 1,) is the state, updated in place.
    """
    order = a.size - 1
    bb = np.zeros(order + 1)
    bb[: b.size] = b
    y = np.empty(x.size)
    for k in range(x.size):
        xk = x[k]
        yk = z[0] + bb[0] * xk
        for i in range(order - 1):
            z[i] = z[i + 1] + xk * bb[i + 1] - yk * a[i + 1]
        z[order - 1] = xk * bb[order] - yk * a[order]
        y[k] = yk
    return y


@njit(cache=True)
def _unwrap_from(seed: float, x: np.ndarray) -> np.ndarray:  # pragma: no cover
    """Return ``np.unwrap(concatenate([[seed], x]))[1:]``."""
    out = np.empty(x.size)
    prev = seed
    correction = 0.0
    for k in range(x.size):
        d = x[k] - prev
        wrapped = (d + math.pi) % (2.0 * math.pi) - math.pi
        if wrapped == -math.pi and d > 0:
            wrapped = math.pi
        if abs(d) >= math.pi:
            correction += wrapped - d
        out[k] = x[k] + correction
        prev = x[k]
    return out


@njit(cache=True)
def heading(
    g: np.ndarray,
    zi_head: np.ndarray,
    head_state: np.ndarray,
    u_last: float,
    alpha: float,
    dt_s: float,
    offset_rad: float,
) -> tuple[np.ndarray, float]:  # pragma: no cover
    """Return the grid's headings (rad, site frame) and the magnetic heading's last unwrapped value.

    The rotation vector's where the grid has it, else a complementary filter
    of the yaw rate and the magnetic heading:
    ``ψ_k = (1 - α)(ψ_{k-1} + r_k Δt) + α u_k``. ``head_state[0]`` says whether
    ``zi_head`` (1,) holds that filter's state; it is started in steady state
    at the first magnetic heading (``zi_head`` then holds ``lfilter_zi``'s unit
    state on entry). Both are updated in place.
    """
    m = g.shape[0]
    psi = np.empty(m)
    magnetic = np.empty(m)
    i0 = -1
    for k in range(m):
        psi[k] = math.atan2(g[k, RS], g[k, RC])
        magnetic[k] = math.atan2(g[k, MS], g[k, MC])
        if i0 < 0 and not math.isnan(magnetic[k]):
            i0 = k
    if i0 >= 0:
        mag = magnetic[i0:]
        seed = u_last if not math.isnan(u_last) else mag[0]
        u = _unwrap_from(seed, mag)
        u_last = u[u.size - 1]
        drive = np.empty(u.size)
        for k in range(u.size):
            r = g[i0 + k, R]
            if math.isnan(r):
                r = 0.0
            drive[k] = (1.0 - alpha) * r * dt_s + alpha * u[k]
        if head_state[0] == 0.0:
            zi_head[0] = zi_head[0] * alpha * u[0]
            head_state[0] = 1.0
        comp = iir(np.ones(1), np.array([1.0, -(1.0 - alpha)]), drive, zi_head)
        for k in range(i0, m):
            if math.isnan(psi[k]):
                psi[k] = comp[k - i0]
    for k in range(m):
        psi[k] += offset_rad
    return psi, u_last


@njit(cache=True)
def peaks(
    t: np.ndarray,
    v: np.ndarray,
    t_checked: int,
    t_last_step: int,
    rule: StepRule,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:  # pragma: no cover
    """Return the steps among grid samples ``t`` (n,), ``v`` (n, 3): f, sin ψ, cos ψ.

    A step (``rule``) is a local maximum of f newer than ``t_checked``, ``peak_min``
    above gravity, at least ``min_step_interval_ms`` after the last step and
    ``min_swing`` above the lowest f since the later of that step and
    ``max_step_ms`` before it (``NO_TIME``: none). Returns the steps' times,
    swings (a_max - a_min), headings (degrees in [0, 360): the circular mean
    over the step, NaN without one) and the new last step's time.
    """
    n = t.size
    out_t = np.empty(n, dtype=np.int64)
    out_swing = np.empty(n)
    out_heading = np.empty(n)
    found = 0
    for j in range(1, n - 1):
        if not (v[j - 1, 0] < v[j, 0] and v[j, 0] >= v[j + 1, 0]):
            continue
        tj = t[j]
        if t_checked != NO_TIME and tj <= t_checked:
            continue
        if v[j, 0] - rule.gravity < rule.peak_min:
            continue
        if t_last_step != NO_TIME and tj - t_last_step < rule.min_step_interval_ms:
            continue
        lo = tj - rule.max_step_ms
        if t_last_step != NO_TIME:
            lo = max(lo, t_last_step)
        low = np.inf
        s = 0.0
        c = 0.0
        heard = False
        for i in range(j + 1):
            if t[i] <= lo:
                continue
            low = min(low, v[i, 0])
            if not (math.isnan(v[i, 1]) or math.isnan(v[i, 2])):
                s += v[i, 1]
                c += v[i, 2]
                heard = True
        swing = v[j, 0] - low
        if swing < rule.min_swing:
            continue
        out_t[found] = tj
        out_swing[found] = swing
        out_heading[found] = math.degrees(math.atan2(s, c)) % 360.0 if heard else np.nan
        found += 1
        t_last_step = tj
    return out_t[:found], out_swing[:found], out_heading[:found], t_last_step


@njit(cache=True)
def segment(
    t: np.ndarray,
    x: np.ndarray,
    t_raw: int,
    raw: np.ndarray,
    grid_ms: int,
    b: np.ndarray,
    a: np.ndarray,
    zi_acc: np.ndarray,
    head_zi: np.ndarray,
    started: np.ndarray,
    u_last: float,
    alpha: float,
    offset_rad: float,
    buf_t: np.ndarray,
    buf: np.ndarray,
    t_checked: int,
    t_last_step: int,
    rule: StepRule,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, int, int, np.ndarray, np.ndarray, float
]:  # pragma: no cover
    """Run one stretch of samples without a long pause through the detector.

    ``t`` (n,), ``x`` (n, 6) are the new samples; ``t_raw``, ``raw`` the last
    sample before them (``NO_TIME``: none). They are resampled onto the
    multiples of ``grid_ms`` after ``t_raw``, |a| low-passed by ``b / a``
    (state ``zi_acc``), headed (``heading``; ``head_zi``), and searched for
    steps together with the ``buf_t``, ``buf`` (k, 3) samples kept from before
    (``peaks``). ``started[0]`` / ``started[1]`` say whether ``zi_acc`` /
    ``head_zi`` hold their filter's state; until then they hold its unit steady
    state, scaled here by the first value. The filter states and ``started``
    are updated in place.

    Returns the steps' times, swings and headings, the last step's time, the
    last sample searched, the samples to keep for the next stretch (times,
    rows) and the magnetic heading's last unwrapped value.
    """
    n = t.size
    if t_raw == NO_TIME:
        first = -(-t[0] // grid_ms) * grid_ms
        src_t, src_x = t, x
    else:
        first = (t_raw // grid_ms + 1) * grid_ms
        src_t = np.empty(n + 1, dtype=np.int64)
        src_x = np.empty((n + 1, x.shape[1]))
        src_t[0], src_x[0] = t_raw, raw
        src_t[1:], src_x[1:] = t, x
    m = max((t[n - 1] - first) // grid_ms + 1, 0)
    grid = first + grid_ms * np.arange(m).astype(np.int64)
    if m == 0:
        none = np.zeros(0)
        return none.astype(np.int64), none, none, t_last_step, t_checked, buf_t, buf, u_last
    g = resample(src_t, src_x, grid)
    if started[0] == 0.0:
        # the low-pass starts in steady state at the first value
        for i in range(zi_acc.size):
            zi_acc[i] *= g[0, A]
        started[0] = 1.0
    f = iir(b, a, np.ascontiguousarray(g[:, A]), zi_acc)
    flag = started[1:2]
    psi, u_last = heading(g, head_zi, flag, u_last, alpha, grid_ms / 1000.0, offset_rad)
    k = buf_t.size
    tt = np.empty(k + m, dtype=np.int64)
    v = np.empty((k + m, 3))
    tt[:k], v[:k] = buf_t, buf
    tt[k:] = grid
    for i in range(m):
        v[k + i, 0], v[k + i, 1], v[k + i, 2] = f[i], math.sin(psi[i]), math.cos(psi[i])
    step_t, swing, step_heading, t_last_step = peaks(tt, v, t_checked, t_last_step, rule)
    if tt.size >= 2:
        t_checked = tt[tt.size - 2]
    keep = max(tt.size - (rule.max_step_ms // grid_ms + 2), 0)
    return step_t, swing, step_heading, t_last_step, t_checked, tt[keep:], v[keep:], u_last


def load_kernel() -> None:
    """Run each loop once on a tiny input, so it is compiled before a device needs it.

    The first call in a process compiles it, or reads it from numba's disk cache.
    """
    three = np.ones((2, 3))
    channels(three, np.ones((2, 4)), three, three, True)
    times = np.array([1, 0], dtype=np.int64)
    t, x, _ = prepare(times, three.repeat(2, axis=1), NO_TIME, np.ones(N_CHANNELS))
    one = np.ones(1)
    # compiles the loops it calls too
    segment(
        t, x, NO_TIME, x[0], 20, one, np.array([1.0, 0.0]), np.zeros(1), one, np.zeros(2),
        np.nan, 0.5, 0.0, t, three, NO_TIME, NO_TIME, StepRule(9.8, 0.6, 2.0, 300, 1000),
    )  # fmt: skip
