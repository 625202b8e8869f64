"""A device's heading bias and step-length scale, learned online from its own scans.

A phone carried turned against the walking direction (in a pocket, a bag, a
hand held sideways) reports steps whose headings are off by a constant
angle, and a walker whose stride differs from the survey's walkers' has
steps scaled by a constant factor. Both are one similarity of the step
track: a rotation β and a scale s, or one complex factor z = s e^{iβ} in the
plane (x + iy).

The per-scan k-NN fixes say where the device is independently of its steps,
so z is fitted by least squares between the raw step track at each scan (o_k,
complex, the steps' sum with the site's constants) and the fixes (f_k),
translation free: min Σ w_k |f_k − a − z o_k|². Its sufficient statistics
decay with time constant ``tau_s`` (a phone may change pocket), and the fit
is shrunk towards z = 1 by a prior worth ``prior_m2`` of track spread (m²),
separately for the rotation and the scale so that an uncertain rotation does
not shrink the scale:

    β = arg(S_of + λ),  s = (|S_of| + λ) / (S_oo + λ),

with S_oo = Σ w |o − ō|² and S_of = Σ w conj(o − ō)(f − f̄). The fixes err
by metres, so each correction c (β, or s − 1) is then kept only as far as it
stands out of its own noise, σ² = σ_f² / (S_oo + λ) with σ_f the fixes'
spread: by c² / (c² + g σ²). A device that has not walked far, or whose
steps need no correction, keeps z ≈ 1; one walking with its phone turned 90°
is corrected as its track grows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass
class MotionFit:
    """Exponentially weighted least-squares fit of the step track to the scans' fixes.

    Attributes
    ----------
    prior_m2 : float
        λ: the prior's weight (m² of centred track spread) towards z = 1.
    tau_s : float
        Time constant (s) with which old scans stop counting.
    min_scale, max_scale : float
        Bounds of the step-length scale.
    fix_sigma_m : float
        σ_f: how far (m) a fix errs, for the gate; 0 keeps every correction whole.
    gate : float
        g of the gate.
    """

    prior_m2: float
    tau_s: float
    min_scale: float
    max_scale: float
    fix_sigma_m: float = 0.0
    gate: float = 0.0
    t: int = -1
    sw: float = 0.0
    so: complex = 0j
    sf: complex = 0j
    soo: float = 0.0
    sof: complex = 0j
    _fitted: tuple[float, float] = (0.0, 1.0)

    def add(self, t: int, odometry: complex, fix: complex) -> None:
        """Count one scan: the raw step track's position and the scan's fix, at time ``t`` (ms)."""
        # Python complex arithmetic throughout, as the sums come back from a snapshot (numpy's
        # complex division rounds differently)
        odometry, fix = complex(odometry), complex(fix)
        if self.t >= 0 and self.tau_s > 0:
            # every sum decays by e^(-Δt/τ)
            keep = math.exp(-max(t - self.t, 0) / 1000.0 / self.tau_s)
            self.sw *= keep
            self.so *= keep
            self.sf *= keep
            self.soo *= keep
            self.sof *= keep
        self.t = t
        self.sw += 1.0
        self.so += odometry
        self.sf += fix
        self.soo += abs(odometry) ** 2
        self.sof += odometry.conjugate() * fix
        self._fitted = self._fit()

    def rotation_scale(self) -> tuple[float, float]:
        """Return the fitted rotation β (rad, counter-clockwise) and step-length scale s."""
        return self._fitted

    def _fit(self) -> tuple[float, float]:
        """Fit β and s to the sums (kept until the next scan: every step between uses them)."""
        if self.sw <= 0.0 or self.soo + self.prior_m2 <= 0.0:
            return 0.0, 1.0
        # centred sums: S_oo = Σ|o|² - |Σo|²/Σw, S_of = Σ conj(o) f - conj(Σo) Σf / Σw
        soo = max(self.soo - abs(self.so) ** 2 / self.sw, 0.0)
        sof = self.sof - self.so.conjugate() * self.sf / self.sw
        lam = self.prior_m2
        beta = math.atan2((sof + lam).imag, (sof + lam).real)
        scale = (abs(sof) + lam) / (soo + lam)
        if self.fix_sigma_m > 0 and self.gate > 0:
            # each kept as far as it stands out of its noise, σ² = σ_f² / (S_oo + λ)
            noise = self.gate * self.fix_sigma_m**2 / (soo + lam)
            beta = _gated(beta, noise)
            scale = 1.0 + _gated(scale - 1.0, noise)
        return beta, min(max(scale, self.min_scale), self.max_scale)

    def snapshot(self) -> dict[str, Any]:
        """Return the sums as plain numbers."""
        return {
            "t": self.t,
            "sw": self.sw,
            "so": [self.so.real, self.so.imag],
            "sf": [self.sf.real, self.sf.imag],
            "soo": self.soo,
            "sof": [self.sof.real, self.sof.imag],
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Take the sums of a ``snapshot()``."""
        self.t = int(state["t"])
        self.sw = float(state["sw"])
        self.so = complex(*(float(v) for v in state["so"]))
        self.sf = complex(*(float(v) for v in state["sf"]))
        self.soo = float(state["soo"])
        self.sof = complex(*(float(v) for v in state["sof"]))
        self._fitted = self._fit()


def _gated(correction: float, noise: float) -> float:
    """Return the correction c kept as far as it stands out of ``noise`` g σ²: c³ / (c² + g σ²)."""
    return correction * (correction**2 / (correction**2 + noise))
