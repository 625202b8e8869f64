"""Absolute headings per link (a phone's compass) fused with the dead-reckoned turns.

A phone knows more than its turns: its rotation vector or magnetometer gives
an absolute heading c_i for each link, noisy (σ_c, a few to tens of degrees
indoors) and offset by a constant bias b (the device's mounting, a
magnetised case, the building's own field). The gyro turns are precise from
link to link but their sum wanders. Written relative to the first link's
dead-reckoned direction, each compass reading observes one slowly varying
offset,

    o_i = c_i - Σ_{k ≤ i} turn_k = θ + e_i + b + v_i,

with θ the true first direction, e_i the integrated gyro error (a random
walk, σ_q² per second) and v_i the compass noise. A fixed-interval smoother
(Kalman forward, Rauch–Tung–Striebel backward) over the unwrapped o_i gives
its estimate õ_i, and the fused direction of link i is Σ turn + õ_i - b: the
turns keep their shape, the compass removes their drift and fixes the
rotation up to b. The bias cannot be told apart from the rotation by the
headings alone, so it is left to the hypothesis search (``search``), where
the plan decides it (a corridor's direction pins it).
"""

from __future__ import annotations

import numpy as np


def wrap(angle: np.ndarray) -> np.ndarray:
    """Return angles (rad) wrapped into [-π, π)."""
    return np.mod(np.asarray(angle, dtype=float) + np.pi, 2 * np.pi) - np.pi


def smooth_offsets(offsets: np.ndarray, q: np.ndarray, r: float) -> np.ndarray:
    """Smooth the unwrapped compass offsets of a random walk, NaN where a link has no reading.

    Parameters
    ----------
    offsets : ndarray, shape (n,)
        o_i (rad), unwrapped; NaN marks a link without a compass reading.
    q : ndarray, shape (n,)
        Variance (rad²) of the random walk's step into each link (``q[0]`` unused).
    r : float
        Variance (rad²) of one compass reading.

    Returns
    -------
    ndarray, shape (n,)
        õ_i, the smoothed offset at every link (a link without a reading
        takes the walk's estimate there).
    """
    n = offsets.size
    x_f = np.empty(n)
    p_f = np.empty(n)
    seen = np.isfinite(offsets)
    x, p = float(offsets[np.argmax(seen)]), 1e6
    for i in range(n):
        # predict: P = P + Q (the first link has no predecessor)
        if i:
            p += q[i]
        if seen[i]:
            # K = P / (P + R),  x = x + K (o - x),  P = (1 - K) P
            k = p / (p + r)
            x += k * (offsets[i] - x)
            p *= 1.0 - k
        x_f[i], p_f[i] = x, p
    out = x_f.copy()
    for i in range(n - 2, -1, -1):
        # RTS: G = P_f,i / (P_f,i + Q),  x_s,i = x_f,i + G (x_s,i+1 - x_f,i)
        g = p_f[i] / (p_f[i] + q[i + 1])
        out[i] = x_f[i] + g * (out[i + 1] - x_f[i])
    return out


def fused_directions(
    turns: np.ndarray, compass: np.ndarray, sigma: float, walk: float, dt: np.ndarray
) -> np.ndarray:
    """Return each link's direction (rad, CCW from +x) from the turns and the compass, bias kept.

    Parameters
    ----------
    turns : ndarray, shape (n,)
        Turns (rad, CCW) between links; ``turns[0]`` is ignored (the first
        link's direction is what the compass sets).
    compass : ndarray, shape (n,)
        Absolute direction of each link (rad, CCW from +x), NaN where unknown;
        at least one must be known.
    sigma : float
        σ_c (rad), the standard deviation of one reading.
    walk : float
        σ_q (rad/√s), how fast the summed turns wander: a link lasting dt
        adds σ_q² dt to their variance.
    dt : ndarray, shape (n,)
        Each link's duration (s).

    Returns
    -------
    ndarray, shape (n,)
        Σ turn + õ_i: the compass bias b is still in it.
    """
    rel = np.cumsum(np.r_[0.0, np.asarray(turns, dtype=float)[1:]])
    raw = np.asarray(compass, dtype=float) - rel
    seen = np.isfinite(raw)
    if not seen.any():
        raise ValueError("at least one link needs a compass heading")
    # unwrap around the first reading so the walk does not jump by 2π
    ref = raw[np.argmax(seen)]
    offsets = np.where(seen, ref + wrap(raw - ref), np.nan)
    # Q_i = σ_q² dt_i, the wander added over link i
    q = walk * walk * np.asarray(dt, dtype=float)
    return rel + smooth_offsets(offsets, q, sigma * sigma)
