"""One device's HMM: PDR steps and WiFi scans in, positions and floor out (CN106028450)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from app.engine.gaussian import R68_SIGMAS_2D
from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.floor_filter import floor_belief, log_sum_exp, tracked_floor
from app.engine.hmm.kernels import propagate
from app.engine.hmm.motion_fit import MotionFit
from app.engine.hmm.params import HmmParams
from app.engine.hmm.transition import step_displacement, transition_kernel
from app.engine.pdr import Pdr, PdrParams, Steps
from app.engine.samples import Batch, Estimate
from app.engine.scans import group_scans
from app.engine.wknn import unique_readings

_PDR_KEYS = tuple(Pdr().snapshot())
"""Keys of a PDR snapshot; those holding None are left out of the HMM's snapshot."""

_MOTION_KEYS = ("t", "sw", "so", "sf", "soo", "sof")
"""Keys of a motion fit's snapshot, under ``motion.`` in the HMM's."""


class HmmTracker:
    """One device's HMM: PDR steps and WiFi scans in, positions out.

    Parameters
    ----------
    model : EmissionModel
        The site's prepared radio maps (shared by all devices).
    params : HmmParams
        HMM constants.
    pdr_params : PdrParams
        Step detection constants (its heading offset aligns headings with the site).
    state : dict, optional
        A ``snapshot()`` to resume from.
    """

    method = "hmm"

    def __init__(
        self,
        model: EmissionModel,
        params: HmmParams,
        pdr_params: PdrParams | None = None,
        state: dict[str, Any] | None = None,
    ) -> None:
        self.model = model
        self.params = params
        self.pdr_params = pdr_params or PdrParams()
        n_maps = len(model.maps)
        self.motion = MotionFit(
            prior_m2=params.motion_prior_m2,
            tau_s=params.motion_tau_s,
            min_scale=params.motion_min_scale,
            max_scale=params.motion_max_scale,
            fix_sigma_m=params.fix_sigma_m,
            gate=params.motion_gate,
        )
        if state is None:
            self.pdr = Pdr(self.pdr_params)
            self.map = -1
            self.floor_logp = np.full(n_maps, -np.log(n_maps))
            self.prob = np.zeros(0)
            self.summary: tuple[np.ndarray, float] | None = None
            self.d = np.zeros(2)
            self.odometry = np.zeros(2)
            self.raw_odometry = 0j
            self.cov = np.zeros((2, 2))
            self.fix_var = 0.0
            self.match = 1.0
            self.rssi_offset = 0.0
            self.offset_sum = 0.0
            self.offset_scans = 0
            self.t_scan = -1
            self.t_emit = -1
            self.t_imu = -1
            self.t_last = -1
            self.heading = float("nan")
            self.speed = float("nan")
            self.t_step = -1
            self.scan_t = np.zeros(0, dtype=np.int64)
            self.scan_tx = np.zeros(0, dtype=np.int32)
            self.scan_rssi = np.zeros(0)
            self.steps = Steps()
        else:
            self._restore(state)

    # -- state -----------------------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        """Return the state as plain numbers and arrays (PDR state under ``pdr.`` keys)."""
        nz = np.flatnonzero(self.prob)
        state: dict[str, Any] = {
            "map": self.map,
            "floor_logp": self.floor_logp.copy(),
            "n_points": int(self.prob.size),
            "prob_index": nz.astype(np.int32),
            "prob_value": self.prob[nz].copy(),
            "d": self.d.copy(),
            "odometry": self.odometry.copy(),
            "raw_odometry": np.array([self.raw_odometry.real, self.raw_odometry.imag]),
            "cov": self.cov.copy(),
            "fix_var": self.fix_var,
            "match": self.match,
            "rssi_offset": self.rssi_offset,
            "offset_sum": self.offset_sum,
            "offset_scans": self.offset_scans,
            "t_scan": self.t_scan,
            "t_emit": self.t_emit,
            "t_imu": self.t_imu,
            "t_last": self.t_last,
            "heading": self.heading,
            "speed": self.speed,
            "t_step": self.t_step,
            "scan_t": self.scan_t.copy(),
            "scan_tx": self.scan_tx.copy(),
            "scan_rssi": self.scan_rssi.copy(),
            "steps_t": self.steps.t.copy(),
            "steps_length": self.steps.length.copy(),
            "steps_heading": self.steps.heading.copy(),
        }
        for key, value in self.motion.snapshot().items():
            state[f"motion.{key}"] = value
        # None (not yet known) is left out: snapshots hold numbers and arrays only
        for key, value in self.pdr.snapshot().items():
            if value is not None:
                state[f"pdr.{key}"] = value
        return state

    def _restore(self, state: dict[str, Any]) -> None:
        self.pdr = Pdr.from_snapshot({k: state.get(f"pdr.{k}") for k in _PDR_KEYS}, self.pdr_params)
        self.map = int(state["map"])
        self.floor_logp = np.asarray(state["floor_logp"], dtype=float)
        self.prob = np.zeros(int(state["n_points"]))
        self.prob[np.asarray(state["prob_index"], dtype=np.int64)] = state["prob_value"]
        self.summary = None
        self.d = np.asarray(state["d"], dtype=float)
        self.odometry = np.asarray(state.get("odometry", np.zeros(2)), dtype=float)
        self.raw_odometry = complex(*np.asarray(state.get("raw_odometry", np.zeros(2)), float))
        if "motion.t" in state:
            # snapshots before the motion fit start it afresh
            self.motion.restore({k: state[f"motion.{k}"] for k in _MOTION_KEYS})
        self.cov = np.asarray(state["cov"], dtype=float).reshape(2, 2)
        self.fix_var = float(state.get("fix_var", 0.0))
        self.match = float(state.get("match", 1.0))
        self.rssi_offset = float(state.get("rssi_offset", 0.0))
        self.offset_sum = float(state.get("offset_sum", 0.0))
        self.offset_scans = int(state.get("offset_scans", 0))
        self.t_scan = int(state["t_scan"])
        self.t_emit = int(state["t_emit"])
        self.t_imu = int(state["t_imu"])
        self.t_last = int(state["t_last"])
        self.heading = float(state["heading"])
        self.speed = float(state["speed"])
        self.t_step = int(state["t_step"])
        self.scan_t = np.asarray(state["scan_t"], dtype=np.int64)
        self.scan_tx = np.asarray(state["scan_tx"], dtype=np.int32)
        self.scan_rssi = np.asarray(state["scan_rssi"], dtype=float)
        self.steps = Steps(
            t=np.asarray(state["steps_t"], dtype=np.int64),
            length=np.asarray(state["steps_length"], dtype=float),
            heading=np.asarray(state["steps_heading"], dtype=float),
            swing=np.zeros(np.asarray(state["steps_t"]).size),
        )

    @classmethod
    def from_snapshot(
        cls,
        model: EmissionModel,
        params: HmmParams,
        state: dict[str, Any],
        pdr_params: PdrParams | None = None,
    ) -> HmmTracker:
        """Rebuild a tracker from ``snapshot()`` output."""
        return cls(model, params, pdr_params, state)

    # -- processing ------------------------------------------------------------

    def process(self, batch: Batch) -> list[Estimate]:
        """Consume one time-ordered batch; return estimates at steps, scans and each second."""
        if len(batch.imu):
            new = self.pdr.update(batch.imu)
            self.steps = Steps.concat([self.steps, new]) if len(new) else self.steps
            self.t_imu = max(self.t_imu, int(np.max(batch.imu.t)))
            self.t_last = max(self.t_last, self.t_imu)
        r = batch.rssi
        # only mapped transmitters place a device; readings older than the last scan used,
        # or far older than the newest, are cached repeats of what it already said
        newest = max(int(np.max(r.t, initial=-1)), int(np.max(self.scan_t, initial=-1)))
        oldest = max(self.t_scan + 1, newest - self.params.max_reading_age_ms)
        keep = self.model.is_mapped(r.tx) & (np.asarray(r.t) >= oldest)
        if keep.any():
            self.scan_t = np.concatenate([self.scan_t, np.asarray(r.t[keep], dtype=np.int64)])
            self.scan_tx = np.concatenate([self.scan_tx, np.asarray(r.tx[keep], dtype=np.int32)])
            self.scan_rssi = np.concatenate([self.scan_rssi, np.asarray(r.rssi[keep], float)])
            self.t_last = max(self.t_last, int(np.max(r.t[keep])))
        return self._run()

    def _ready_until(self) -> int:
        """Return the latest scan time that may be processed now."""
        p = self.params
        if self.t_imu < 0 or self.t_last - self.t_imu > p.imu_timeout_ms:
            return self.t_last
        return self.t_imu - p.imu_wait_ms

    def _run(self) -> list[Estimate]:
        out: list[Estimate] = []
        ready = self._ready_until()
        groups = group_scans(self.scan_t, self.scan_tx, self.params.scans)
        # a scan is complete at its last reading; the newest one may still be growing
        ends = [int(self.scan_t[g].max()) for g in groups]
        closed = [
            end <= ready and (i + 1 < len(groups) or end + self.params.scans.gap_ms <= ready)
            for i, end in enumerate(ends)
        ]
        done = [g for g, ok in zip(groups, closed, strict=True) if ok]
        waiting_from = min(
            (end for end, ok in zip(ends, closed, strict=True) if not ok), default=None
        )
        step_ok = (
            np.ones(len(self.steps), dtype=bool)
            if waiting_from is None
            else self.steps.t < waiting_from
        )
        events: list[tuple[int, int, Any]] = [
            (int(t), 0, i)
            for i, t in zip(np.flatnonzero(step_ok), self.steps.t[step_ok], strict=True)
        ]
        events += [(end, 1, g) for g, end, ok in zip(groups, ends, closed, strict=True) if ok]
        events.sort(key=lambda e: (e[0], e[1]))
        for t, kind, item in events:
            self._heartbeat(t, out)
            if kind == 0:
                self._step(item, out)
            else:
                self._scan(t, item, out)
        used = np.zeros(self.scan_t.size, dtype=bool)
        for g in done:
            used[g] = True
        self.scan_t, self.scan_tx, self.scan_rssi = (
            self.scan_t[~used],
            self.scan_tx[~used],
            self.scan_rssi[~used],
        )
        keep = ~step_ok
        self.steps = Steps(
            t=self.steps.t[keep],
            length=self.steps.length[keep],
            heading=self.steps.heading[keep],
            swing=self.steps.swing[keep],
        )
        horizon = ready if waiting_from is None else min(ready, waiting_from)
        self._heartbeat(horizon, out)
        return out

    def _heartbeat(self, t: int, out: list[Estimate]) -> None:
        """Emit at every whole ``emit_every_ms`` since the last estimate, up to ``t``."""
        if self.map < 0 or self.t_emit < 0:
            return
        while t - self.t_emit >= self.params.emit_every_ms:
            out.append(self._estimate(self.t_emit + self.params.emit_every_ms))

    def _step(self, i: int, out: list[Estimate]) -> None:
        p = self.params
        length = float(self.steps.length[i])
        heading = float(self.steps.heading[i])
        if math.isfinite(heading):
            # the step as the site's constants see it: L (sin θ, cos θ)
            theta = math.radians(heading)
            self.raw_odometry += complex(length * math.sin(theta), length * math.cos(theta))
        if p.learn_motion:
            # turned counter-clockwise by β (clockwise headings fall by β) and scaled by s
            beta, scale = self.motion.rotation_scale()
            length *= scale
            heading = (heading - math.degrees(beta)) % 360.0
        d, cov = step_displacement(length, heading, p.step_length_std_m, p.heading_std_deg)
        self.d = self.d + d
        self.odometry = self.odometry + d
        self.cov = self.cov + cov
        t = int(self.steps.t[i])
        if self.t_step >= 0 and t > self.t_step:
            # v = L / Δt
            self.speed = length * 1000.0 / (t - self.t_step)
        self.t_step = t
        if math.isfinite(heading):
            self.heading = heading
        if self.map >= 0:
            out.append(self._estimate(t))

    def _scan(self, t: int, index: np.ndarray, out: list[Estimate]) -> None:
        p, model = self.params, self.model
        tx, rssi = unique_readings(self.scan_tx[index], self.scan_rssi[index])
        # as loud as the survey's phones would have heard it
        rssi = rssi - self.rssi_offset
        ll = model.log_likelihoods(tx, rssi)
        marginal = model.floor_log_marginals(tx, rssi)
        if p.floor_classifier_weight > 0:
            # e_f = ln mean_j L_fj^w + c ln p(f | scan)
            marginal = marginal + p.floor_classifier_weight * model.floor_classifier_log_probs(
                tx, rssi
            )
        self.floor_logp = floor_belief(self.floor_logp, marginal, p.floor_switch_prob)
        best = tracked_floor(self.map, self.floor_logp, p.floor_switch_posterior)
        if best != self.map:
            self._start(best, tx, rssi, ll[best])
        else:
            self._update(t, ll[self.map], tx, rssi)
        self.fix_var = self._fix_variance(tx, rssi)
        self._fit_motion(t, tx, rssi)
        self._follow_match(t, self._match_factor(tx, rssi))
        self._learn_offset(tx, rssi)
        self.t_scan = t
        out.append(self._estimate(t))

    def _fix_variance(self, tx: np.ndarray, rssi: np.ndarray) -> float:
        """Return how far the scan's own k-NN disagrees with the posterior (m², per axis).

        Its neighbours' spread and the distance of their mean from the
        posterior's: where the fingerprints are ambiguous or the track has
        drifted from them, the position is less sure than the posterior says.
        """
        near = self.model.scan_neighbours(self.map, tx, rssi)
        if near is None:
            return 0.0
        xy, weight = near
        fix = weight @ xy
        # s² = Σ w |x_i - x̄|² / 2, g² = |x̄ - x̂|²
        spread2 = float(weight @ np.sum((xy - fix) ** 2, axis=1)) / 2.0
        mean, _ = self._posterior()
        return spread2 + float(np.sum((mean - fix) ** 2))

    def _fit_motion(self, t: int, tx: np.ndarray, rssi: np.ndarray) -> None:
        """Count the scan's k-NN fix against the raw step track (``MotionFit``)."""
        if not self.params.learn_motion:
            return
        near = self.model.scan_neighbours(self.map, tx, rssi)
        if near is None:
            return
        xy, weight = near
        fix = weight @ xy
        self.motion.add(t, self.raw_odometry, complex(float(fix[0]), float(fix[1])))

    def _learn_offset(self, tx: np.ndarray, rssi: np.ndarray) -> None:
        """Update the device's RSSI offset with what this scan says it is.

        Phones of different makes hear the same access point several dB apart.
        A scan compared with the survey scans made where the posterior is most
        sure measures the offset (plus what is already taken off); the offset
        is the mean of those measurements shrunk towards 0 by a prior worth
        ``offset_prior_scans`` scans, so a phone like the survey's stays near 0
        and a louder one converges to its offset.
        """
        p = self.params
        measured = self.model.level_offset(self.map, int(np.argmax(self.prob)), tx, rssi)
        if measured is None:
            return
        self.offset_sum += measured + self.rssi_offset
        self.offset_scans += 1
        # o = Σ m_k / (n + n₀), within ±o_max
        shrunk = self.offset_sum / (self.offset_scans + p.offset_prior_scans)
        self.rssi_offset = min(max(shrunk, -p.offset_max_db), p.offset_max_db)

    def _follow_match(self, t: int, match: float) -> None:
        """Move the radius's match factor towards this scan's by how long since the last scan.

        A walk whose scans keep matching the survey poorly is off the surveyed
        paths or heard by an unusual phone for a while, not for one scan: the
        factor follows the scans with time constant ``radius_match_tau_s``.
        """
        tau = self.params.radius_match_tau_s
        if self.t_scan < 0 or tau <= 0:
            self.match = match
            return
        # m̄ ← m̄ + (1 - e^(-Δt/τ)) (m - m̄)
        gain = 1.0 - math.exp(-max(t - self.t_scan, 0) / 1000.0 / tau)
        self.match += gain * (match - self.match)

    def _match_factor(self, tx: np.ndarray, rssi: np.ndarray) -> float:
        """Return the scan's best match on the tracked floor relative to a typical one.

        A scan far in signal space from every survey scan of the floor was
        heard where the survey is sparse or the radio has changed: its position
        is less sure, however sharp the posterior. 1 without survey scans.
        """
        best = self.model.best_match(self.map, tx, rssi)
        if best is None:
            return 1.0
        # m = max(d_min, d_floor) / d_ref
        return max(best, self.params.radius_match_min_db) / self.params.radius_match_db

    def _start(self, f: int, tx: np.ndarray, rssi: np.ndarray, ll: np.ndarray) -> None:
        """(Re)start the position on map ``f``: k-NN prior times the scan's emission."""
        p, model = self.params, self.model
        x0 = model.knn(f, tx, rssi, p.k)
        xy = model.xy[f]
        fix = model.fix_log_density(f, tx, rssi)
        if fix is not None:
            ll = ll + fix
        # ln p₀_j = -|x_j - x₀|² / 2σ₀² + w ln L_j
        logp = -0.5 * np.sum((xy - x0) ** 2, axis=1) / p.init_std_m**2 + ll
        self.map = f
        self.prob = self._normalised(logp)
        self.summary = None
        self.d = np.zeros(2)
        self.cov = np.zeros((2, 2))

    def _update(self, t: int, ll: np.ndarray, tx: np.ndarray, rssi: np.ndarray) -> None:
        """Transition by the steps since the last scan, then weigh by the scan's emission."""
        p, model = self.params, self.model
        m = model.maps[self.map]
        dt = max(t - self.t_scan, 0) / 1000.0 if self.t_scan >= 0 else 0.0
        # Σ = Σ_steps + q Δt I + cell²/6 I (quantisation of source and target cells)
        cov = self.cov + np.eye(2) * (p.walk_noise_m2_per_s * dt + m.cell**2 / 6.0)
        kernel, h = transition_kernel(self.d, cov, m.cell, p.kernel_sigmas)
        prior = propagate(self.prob, model.cells[self.map], model.grids[self.map], kernel, h)
        total = prior.sum()
        if total > 0:
            prior /= total
        # keep points whose transition probability exceeds P_T
        prior[prior < p.transition_threshold] = 0.0
        self.d = np.zeros(2)
        self.cov = np.zeros((2, 2))
        support = np.flatnonzero(prior)
        # w ln L_j on the support, with the k-NN fix where there is one
        ll_support = ll[support]
        fix = model.fix_log_density(self.map, tx, rssi, support)
        if fix is not None:
            ll_support = ll_support + fix
        log_post = np.log(prior[support]) + ll_support
        predictive = log_sum_exp(log_post) if support.size else -np.inf
        if predictive < ll.max() - p.relocate_margin:
            self._start(self.map, tx, rssi, ll)
            return
        self.prob = np.zeros_like(prior)
        self.prob[support] = self._normalised(log_post)
        self.summary = None

    @staticmethod
    def _normalised(logp: np.ndarray) -> np.ndarray:
        # p_j = exp(ln p_j - max) / Σ
        w = np.exp(logp - np.max(logp))
        return w / w.sum()

    def _posterior(self) -> tuple[np.ndarray, float]:
        """Return the posterior's mean (m) and the per-axis variance (m²) of its tempered form.

        Tempered by τ (p_j^τ, renormalised): the emission makes the posterior
        sharper than the fingerprints resolve. Kept until the posterior changes
        (at a scan), as steps and heartbeats emit from the same one.
        """
        if self.summary is None:
            xy = self.model.xy[self.map]
            nz = np.flatnonzero(self.prob)
            # x̂ = Σ p_j x_j
            mean = self.prob[nz] @ xy[nz]
            tempered = self.prob[nz] ** self.params.radius_temper
            tempered /= tempered.sum()
            centre = tempered @ xy[nz]
            var = float(tempered @ np.sum((xy[nz] - centre) ** 2, axis=1)) / 2.0
            self.summary = (mean, var)
        return self.summary

    def _estimate(self, t: int) -> Estimate:
        p, model = self.params, self.model
        mean, var = self._posterior()
        pos = mean + self.d
        # the radius's spread: the tempered posterior's, the steps' since the scan and the
        # per-scan k-NN's disagreement with the posterior,
        var += float(np.trace(self.cov)) / 2.0 + self.fix_var
        # scaled by how well the last scans matched the survey
        radius = max(p.min_accuracy_m, R68_SIGMAS_2D * np.sqrt(var) * self.match)
        # r' = max(r_min, sqrt((s r)² + f²)): the build's calibration of the radius
        accuracy = max(
            p.min_accuracy_m, float(np.hypot(p.radius_scale * radius, p.accuracy_floor_m))
        )
        self.t_emit = t
        return Estimate(
            t=int(t),
            x=float(pos[0]),
            y=float(pos[1]),
            z=0.0,
            floor=int(model.floors[self.map]),
            heading=self.heading,
            accuracy=accuracy,
            speed=self.speed,
            method=self.method,
            odometry=(float(self.odometry[0]), float(self.odometry[1])),
        )
