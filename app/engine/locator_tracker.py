"""A tag heard by fixed locators: windowed RSSI means solved by least squares, then the EKF.

Every ``step_ms`` the readings of the last ``window_ms`` are averaged per
locator and solved as a 2-D fix at the tag's known height (``lateration``);
the fixes, with the path-loss model's location-bound error added, go through
the seed-001 filter (``ekf``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.engine.ekf import EkfParams, PositionEkf, gyro_events, project_onto_plan
from app.engine.lateration.accuracy import path_loss_B
from app.engine.lateration.solver import LaterationParams, LaterationResult, Status, solve
from app.engine.samples import Batch, Estimate
from app.engine.site import SiteModel


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
        exponent, Grinyak's (2020) 5 dB.
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
        path loss, leave one track out; ``locus eval locator`` prints it for
        each held-out track): 1.1–1.4 m.
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
    t: np.ndarray,
    locator: np.ndarray,
    rssi: np.ndarray,
    n_locators: int,
    times: np.ndarray,
    window_ms: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Return mean RSSI (F, K) and sighting counts (F, K) over (τ − window, τ] at each time τ.

    ``t`` must be sorted; means are NaN where a locator did not hear the tag.
    """
    onehot = np.zeros((t.size + 1, n_locators))
    counts = np.zeros((t.size + 1, n_locators))
    onehot[np.arange(1, t.size + 1), locator] = rssi
    counts[np.arange(1, t.size + 1), locator] = 1.0
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

    ``batch.sightings.locator`` indexes ``site.locators``, whose ``A``, ``B``, ``sigma``
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
        self.locator = np.asarray(state.get("locator", np.zeros(0, np.int32)), dtype=np.int32)
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
            "locator": self.locator.copy(),
            "rssi": self.rssi.copy(),
            "next_fix": self.next_fix,
            "floor": self.floor,
        }

    def process(self, batch: Batch) -> list[Estimate]:
        """Consume one batch of sightings (and gyro, if any) and return the estimates."""
        p = self.params
        s = batch.sightings
        if len(s):
            order = np.argsort(s.t, kind="stable")
            self.t = np.concatenate([self.t, s.t[order]])
            self.locator = np.concatenate([self.locator, s.locator[order]])
            self.rssi = np.concatenate([self.rssi, s.rssi[order]])
        events = gyro_events(batch)
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
            self.t, self.locator, self.rssi = self.t[keep], self.locator[keep], self.rssi[keep]
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
                    project_onto_plan(self.site, self.floor, self.ekf)
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
        mean, count = window_means(self.t, self.locator, self.rssi, len(loc), times, p.window_ms)
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
