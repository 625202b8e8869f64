"""A UWB tag's tracker: range epochs solved by least squares (``lateration``), then the EKF."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.engine.ekf import EkfParams, PositionEkf, gyro_events, project_onto_plan
from app.engine.lateration.solver import LaterationParams, LaterationResult, Status, solve
from app.engine.samples import Batch, Estimate
from app.engine.site import SiteModel
from app.engine.uwb_bias import BiasParams, accumulate, solve_biases


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
class Epoch:
    """Ranges of one fix: time (ms), anchor indices, ranges and stds (m)."""

    t: int
    anchors: np.ndarray
    ranges: np.ndarray
    std: np.ndarray


def group_epochs(
    t: np.ndarray, anchors: np.ndarray, ranges: np.ndarray, std: np.ndarray, epoch_ms: int
) -> list[Epoch]:
    """Split time-sorted ranges into fixes: a new one at a repeated anchor or after ``epoch_ms``."""
    out: list[Epoch] = []
    start = 0
    seen: set[int] = set()
    for i in range(t.size + 1):
        if i < t.size and int(anchors[i]) not in seen and t[i] - t[start] <= epoch_ms:
            seen.add(int(anchors[i]))
            continue
        if i > start:
            sl = slice(start, i)
            out.append(Epoch(int(t[i - 1]), anchors[sl], ranges[sl], std[sl]))
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
        events = gyro_events(batch)
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
                    project_onto_plan(self.site, self.floor, self.ekf)
                estimate = self._emit(t)
                if estimate is not None:
                    out.append(estimate)
        return out

    def _laterate(self, epochs: list[Epoch]) -> list[tuple[int, LaterationResult]]:
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
