"""WiFi fingerprint + inertial hidden Markov model (CN106028450, seed 002, online phase).

The hidden state is the reference point the phone is at; its distribution over
one floor's reference points is carried from scan to scan:

1. **Initial position** by k-NN in RSSI space (k = 3–5); the distribution
   starts as a Gaussian of ``init_std_m`` around it, times the first scan's
   emission.
2. **Transition** from the PDR steps taken since the last scan: each step's
   length and heading are Gaussian (σ_d = 0.1 m, σ_φ), so the accumulated
   displacement D is Gaussian with covariance Σ = Σ_k (σ_d² u_k u_kᵀ +
   (L_k σ_φ)² n_k n_kᵀ) (u along the step, n across it), plus slow random
   walk for missed steps and the grid's own quantisation. On the regular
   grid this transition is a convolution of the distribution with a shifted
   Gaussian kernel, computed only over the bounding box of the points whose
   probability exceeds P_T; mass moved off the reference points (off the
   walkable, surveyed area) is lost, which is the map constraint.
3. **Emission**: the product over transmitters of Gaussians with the point's
   mean and variance, in the log domain, with the point's detection rate for
   heard and unheard transmitters alike (missing signals are evidence). Each
   transmitter's term is floored so one multipath outlier cannot veto a
   point, and the sum is tempered (readings of one scan are correlated and
   the map is noisy).
4. **Posterior** ∝ transition × emission, normalised; the position is the
   weighted mean, moved on by the steps taken since the scan.

The floor is a second, discrete chain: per scan each floor's marginal
likelihood (emission averaged over its points) updates a floor belief with a
small switching probability; the tracked floor changes only when another
floor's belief passes ``floor_switch_posterior`` (hysteresis), and the
position restarts there from k-NN. When a scan is far better explained
anywhere on the floor than where the distribution is (``relocate_margin``),
the track is lost and restarts the same way.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import signal
from scipy.special import logsumexp

from app.engine.pdr import Pdr, PdrParams, Steps
from app.engine.radiomap import RadioMap
from app.engine.samples import Batch, Estimate
from app.engine.wknn import Fingerprints, scans_of, unique_readings

_PDR_KEYS = tuple(Pdr().snapshot())
"""Keys of a PDR snapshot; those holding None are left out of the HMM's snapshot."""

R68_2D = 1.5096
"""Radius, in σ of an isotropic 2-D Gaussian, holding 68% of it: sqrt(χ²₂(0.68))."""


@dataclass(frozen=True)
class HmmParams:
    """Tunable constants of the fingerprint + inertial HMM.

    Attributes
    ----------
    k : int
        Neighbours of the k-NN initial position (the patent's 3–5).
    missing_dbm : float
        RSSI of a missing reading in the k-NN distance.
    init_std_m : float
        Spread (m) of the initial distribution around the k-NN position.
    step_length_std_m : float
        σ_d of a step's length (m), the patent's 0.1 m.
    heading_std_deg : float
        σ_φ of a step's heading (degrees): PDR headings on ILC site1 are off by
        about 9.4° in median, i.e. σ ≈ 14° if Gaussian.
    walk_noise_m2_per_s : float
        Random-walk variance (m²/s) added between scans: steps PDR missed or
        mis-sized.
    transition_threshold : float
        P_T: reference points whose transition probability falls below this
        are dropped from the distribution (the sparse support).
    kernel_sigmas : float
        The transition kernel is cut at this many standard deviations.
    emission_weight : float
        Exponent tempering the product of per-transmitter likelihoods.
    loglik_floor : float
        Floor (nats) of one heard transmitter's log-likelihood at a point.
    unmapped_dbm : float
        Mean RSSI (dBm) assumed at points where a transmitter was never heard:
        the sensitivity floor.
    unmapped_var_db2 : float
        Variance (dB²) around ``unmapped_dbm``.
    unmapped_detect : float
        Detection rate of a transmitter absent from a floor's map.
    floor_switch_prob : float
        Probability per scan that the floor changes.
    floor_switch_posterior : float
        Belief another floor must reach before the tracked floor changes.
    relocate_margin : float
        Restart from k-NN when the best point of the floor explains the scan
        better than the predicted distribution by more than this (nats,
        tempered).
    emit_every_ms : int
        Without steps or scans, still emit an estimate this often.
    imu_wait_ms : int
        A scan is used once IMU samples this much later have arrived, so the
        steps before it are known.
    imu_timeout_ms : int
        If the IMU stream lags the radio by more than this, scans go ahead without it.
    min_accuracy_m : float
        Smallest accuracy radius reported (m): the grid and the survey's own error.
    accuracy_floor_m : float
        Error (m) added in quadrature to the posterior's 68% radius: the
        posterior knows the maps' noise, not how far the fingerprints
        themselves are from the truth. The server sets it per site to the
        median held-out error of its radio-map build; on ILC site1's
        validation walks that put 69.5% of the errors inside the radius,
        against 11% without.
    """

    k: int = 4
    missing_dbm: float = -100.0
    init_std_m: float = 5.0
    step_length_std_m: float = 0.1
    heading_std_deg: float = 15.0
    walk_noise_m2_per_s: float = 0.05
    transition_threshold: float = 1e-6
    kernel_sigmas: float = 3.0
    emission_weight: float = 0.2
    loglik_floor: float = -8.0
    unmapped_dbm: float = -95.0
    unmapped_var_db2: float = 36.0
    unmapped_detect: float = 0.02
    floor_switch_prob: float = 1e-3
    floor_switch_posterior: float = 0.99
    relocate_margin: float = 10.0
    emit_every_ms: int = 1000
    imu_wait_ms: int = 100
    imu_timeout_ms: int = 3000
    min_accuracy_m: float = 1.0
    accuracy_floor_m: float = 0.0


class EmissionModel:
    """Per-floor log-likelihood tables of every reference point, prepared once per site.

    Arrays are stored transmitter-major (T, P) so a scan gathers contiguous rows.

    Parameters
    ----------
    maps : sequence of RadioMap
        One map per floor.
    params : HmmParams
        Unmapped-transmitter constants.
    """

    def __init__(self, maps: Sequence[RadioMap], params: HmmParams) -> None:
        self.maps = tuple(maps)
        self.floors = tuple(m.floor for m in self.maps)
        self.fingerprints = Fingerprints(self.maps, params.missing_dbm)
        self.grids = [m.index_grid() for m in self.maps]
        self.xy = [m.xy for m in self.maps]
        self.mean: list[np.ndarray] = []
        self.inv_var: list[np.ndarray] = []
        self.base: list[np.ndarray] = []
        self.log_miss: list[np.ndarray] = []
        self.absent: list[np.ndarray] = []
        for m in self.maps:
            heard = np.isfinite(m.mean)
            mean = np.where(heard, m.mean, params.unmapped_dbm)
            var = np.where(heard, m.var, params.unmapped_var_db2)
            q = np.clip(m.detect, 1e-6, 1.0 - 1e-6)
            self.mean.append(np.ascontiguousarray(mean.T, dtype=np.float32))
            self.inv_var.append(np.ascontiguousarray((1.0 / var).T, dtype=np.float32))
            # ln q + ln N normaliser: ln q - ½ ln(2π σ²)
            base = np.log(q) - 0.5 * np.log(2.0 * np.pi * var)
            self.base.append(np.ascontiguousarray(base.T, dtype=np.float32))
            log_miss = np.log1p(-q)
            self.log_miss.append(np.ascontiguousarray(log_miss.T, dtype=np.float32))
            # S₀_j = Σ_a ln(1 - q_ja): every mapped transmitter unheard
            self.absent.append(log_miss.sum(axis=1, dtype=np.float64))
        n_tx = max(int(m.tx.max(initial=-1)) for m in self.maps) + 1
        self.columns = self.fingerprints.columns
        self.n_tx = n_tx
        # ln q₀ + ln N(s; s₀, v₀) pieces for transmitters absent from a floor's map
        self.unmapped = (
            np.log(params.unmapped_detect) - 0.5 * np.log(2.0 * np.pi * params.unmapped_var_db2),
            params.unmapped_dbm,
            1.0 / params.unmapped_var_db2,
        )
        self.params = params

    def n_points(self, f: int) -> int:
        """Number of reference points of map ``f`` (position in ``maps``)."""
        return self.maps[f].n_points

    def log_likelihood(self, f: int, tx: np.ndarray, rssi: np.ndarray) -> np.ndarray:
        """Return the tempered log-likelihood of one scan at every point of map ``f``, (P,).

        Parameters
        ----------
        f : int
            Position of the map in ``maps``.
        tx : ndarray of int, shape (n,)
            Unique site transmitter indices heard.
        rssi : ndarray, shape (n,)
            Their RSSI (dBm).
        """
        p = self.params
        tx = np.asarray(tx, dtype=np.int64)
        rssi = np.asarray(rssi, dtype=np.float32)
        lookup = self.columns[f]
        col = np.full(tx.size, -1, dtype=np.int64)
        known = tx < lookup.size
        col[known] = lookup[tx[known]]
        on = col >= 0
        c, s = col[on], rssi[on][:, None]
        # ln q + ln N(s; μ, σ²) = base - ½ (s - μ)² / σ², floored
        term = self.base[f][c] - 0.5 * (s - self.mean[f][c]) ** 2 * self.inv_var[f][c]
        term = np.maximum(term, np.float32(p.loglik_floor))
        # heard ones are not among the unheard: remove their ln(1 - q)
        ll = self.absent[f] + (term - self.log_miss[f][c]).sum(axis=0, dtype=np.float64)
        base0, mean0, inv0 = self.unmapped
        off = rssi[~on].astype(float)
        # transmitters the floor's map lacks: constant over the floor
        ll += np.maximum(base0 - 0.5 * (off - mean0) ** 2 * inv0, p.loglik_floor).sum()
        # tempered: w ln L
        return p.emission_weight * ll

    def knn(self, f: int, tx: np.ndarray, rssi: np.ndarray, k: int) -> np.ndarray:
        """Return the weighted mean position (m) of the k nearest fingerprints on map ``f``."""
        d2 = self.fingerprints.sq_distances(tx, rssi)
        start = sum(m.n_points for m in self.maps[:f])
        d = np.sqrt(d2[start : start + self.maps[f].n_points])
        k = min(k, d.size)
        near = np.argpartition(d, k - 1)[:k]
        # w = 1 / (d + ε)
        w = 1.0 / (d[near] + 1e-3)
        return w @ self.xy[f][near] / w.sum()


def step_displacement(
    length: np.ndarray, heading_deg: np.ndarray, length_std: float, heading_std_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Return the summed displacement (2,) and its covariance (2, 2) of a run of steps.

    Parameters
    ----------
    length : ndarray, shape (n,)
        Step lengths (m).
    heading_deg : ndarray, shape (n,)
        Headings (degrees clockwise from +y); a NaN heading moves nothing and
        spreads the step's length isotropically.
    length_std, heading_std_deg : float
        σ_d (m) and σ_φ (degrees) of each step.
    """
    length = np.asarray(length, dtype=float)
    psi = np.radians(np.asarray(heading_deg, dtype=float))
    known = np.isfinite(psi)
    psi = np.where(known, psi, 0.0)
    # u = (sin ψ, cos ψ) along the step, n = (cos ψ, -sin ψ) across it
    u = np.stack([np.sin(psi), np.cos(psi)], axis=1)
    n = np.stack([np.cos(psi), -np.sin(psi)], axis=1)
    # D = Σ L_k u_k
    d = (length[known, None] * u[known]).sum(axis=0)
    var_along = np.full(length.size, length_std**2)
    # across-track variance (L σ_φ)²
    var_across = (length * np.radians(heading_std_deg)) ** 2
    # Σ = Σ_k σ_d² u uᵀ + (L σ_φ)² n nᵀ
    cov = np.einsum("k,ki,kj->ij", var_along * known, u, u)
    cov += np.einsum("k,ki,kj->ij", var_across * known, n, n)
    # unknown heading: the step may go anywhere within its length
    cov += np.eye(2) * float(np.sum((length[~known] ** 2 + length_std**2) / 2.0))
    return d, cov


def transition_kernel(
    d: np.ndarray, cov: np.ndarray, cell: float, n_sigmas: float
) -> tuple[np.ndarray, int]:
    """Return the Gaussian transition kernel on the grid and its half-width (cells).

    ``kernel[h + dr, h + dc]`` is the probability of moving by ``dc`` columns
    (x) and ``dr`` rows (y); it is normalised to sum to 1.

    Parameters
    ----------
    d : ndarray, shape (2,)
        Mean displacement (m).
    cov : ndarray, shape (2, 2)
        Its covariance (m²), including the grid's quantisation.
    cell : float
        Grid cell (m).
    n_sigmas : float
        Truncation radius in standard deviations of the widest axis.
    """
    reach = float(np.hypot(*d) + n_sigmas * np.sqrt(np.linalg.eigvalsh(cov)[-1]))
    h = int(np.ceil(reach / cell))
    off = np.arange(-h, h + 1) * cell
    dx = off[None, :] - d[0]
    dy = off[:, None] - d[1]
    inv = np.linalg.inv(cov)
    # K ∝ exp(-½ (o - D)ᵀ Σ⁻¹ (o - D))
    q = inv[0, 0] * dx * dx + 2.0 * inv[0, 1] * dx * dy + inv[1, 1] * dy * dy
    kernel = np.exp(-0.5 * q)
    return kernel / kernel.sum(), h


def propagate(
    prob: np.ndarray, ij: np.ndarray, grid: np.ndarray, kernel: np.ndarray, h: int
) -> np.ndarray:
    """Move a distribution over reference points by a transition kernel.

    Only the bounding box of the points with non-zero probability is
    convolved; mass landing on cells that are not reference points is lost.

    Parameters
    ----------
    prob : ndarray, shape (P,)
        Probability of each reference point.
    ij : ndarray of int, shape (P, 2)
        Grid row and column of each point.
    grid : ndarray of int, shape (ny, nx)
        Point index of each grid cell, -1 where none.
    kernel : ndarray, shape (2h + 1, 2h + 1)
        From ``transition_kernel``.
    h : int
        Kernel half-width (cells).

    Returns
    -------
    ndarray, shape (P,)
        Σ_i p_i K(x_j - x_i) at every point j (not renormalised).
    """
    active = np.flatnonzero(prob > 0)
    out = np.zeros_like(prob)
    if active.size == 0:
        return out
    r0, c0 = ij[active].min(axis=0)
    r1, c1 = ij[active].max(axis=0)
    image = np.zeros((r1 - r0 + 1, c1 - c0 + 1))
    image[ij[active, 0] - r0, ij[active, 1] - c0] = prob[active]
    # (p * K)[y] = Σ_x p[x] K[y - x]
    moved = signal.convolve(image, kernel, mode="full")
    ny, nx = grid.shape
    lo_r, lo_c = r0 - h, c0 - h
    rr0, cc0 = max(lo_r, 0), max(lo_c, 0)
    rr1, cc1 = min(r1 + h, ny - 1), min(c1 + h, nx - 1)
    sub = grid[rr0 : rr1 + 1, cc0 : cc1 + 1]
    rows, cols = np.nonzero(sub >= 0)
    out[sub[rows, cols]] = moved[rows + rr0 - lo_r, cols + cc0 - lo_c]
    return out


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
        if state is None:
            self.pdr = Pdr(self.pdr_params)
            self.map = -1
            self.floor_logp = np.full(n_maps, -np.log(n_maps))
            self.prob = np.zeros(0)
            self.d = np.zeros(2)
            self.cov = np.zeros((2, 2))
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
            "cov": self.cov.copy(),
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
        self.d = np.asarray(state["d"], dtype=float)
        self.cov = np.asarray(state["cov"], dtype=float).reshape(2, 2)
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
        if len(r):
            self.scan_t = np.concatenate([self.scan_t, np.asarray(r.t, dtype=np.int64)])
            self.scan_tx = np.concatenate([self.scan_tx, np.asarray(r.tx, dtype=np.int32)])
            self.scan_rssi = np.concatenate([self.scan_rssi, np.asarray(r.rssi, dtype=float)])
            self.t_last = max(self.t_last, int(np.max(r.t)))
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
        groups = scans_of(self.scan_t)
        done = [g for g in groups if self.scan_t[g[0]] <= ready]
        waiting_from = min(
            (int(self.scan_t[g[0]]) for g in groups if len(g) and self.scan_t[g[0]] > ready),
            default=None,
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
        events += [(int(self.scan_t[g[0]]), 1, g) for g in done]
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
        length = self.steps.length[i : i + 1]
        heading = self.steps.heading[i : i + 1]
        d, cov = step_displacement(length, heading, p.step_length_std_m, p.heading_std_deg)
        self.d = self.d + d
        self.cov = self.cov + cov
        t = int(self.steps.t[i])
        if self.t_step >= 0 and t > self.t_step:
            # v = L / Δt
            self.speed = float(length[0]) * 1000.0 / (t - self.t_step)
        self.t_step = t
        if np.isfinite(heading[0]):
            self.heading = float(heading[0])
        if self.map >= 0:
            out.append(self._estimate(t))

    def _scan(self, t: int, index: np.ndarray, out: list[Estimate]) -> None:
        p, model = self.params, self.model
        tx, rssi = unique_readings(self.scan_tx[index], self.scan_rssi[index])
        ll = [model.log_likelihood(f, tx, rssi) for f in range(len(model.maps))]
        # per-floor marginal: ln mean_j L_j
        marginal = np.array([logsumexp(v) - np.log(v.size) for v in ll])
        n = marginal.size
        stay = np.exp(self.floor_logp)
        eps = p.floor_switch_prob
        # π_f = (1 - ε) b_f + ε (1 - b_f) / (n - 1)
        prior = (1.0 - eps) * stay + (eps * (1.0 - stay) / (n - 1) if n > 1 else 0.0)
        logp = np.log(np.maximum(prior, 1e-300)) + marginal
        self.floor_logp = logp - logsumexp(logp)
        best = int(np.argmax(self.floor_logp))
        if self.map < 0 or (
            best != self.map and np.exp(self.floor_logp[best]) >= p.floor_switch_posterior
        ):
            self._start(best, tx, rssi, ll[best])
        else:
            self._update(t, ll[self.map], tx, rssi)
        self.t_scan = t
        out.append(self._estimate(t))

    def _start(self, f: int, tx: np.ndarray, rssi: np.ndarray, ll: np.ndarray) -> None:
        """(Re)start the position on map ``f``: k-NN prior times the scan's emission."""
        p, model = self.params, self.model
        x0 = model.knn(f, tx, rssi, p.k)
        xy = model.xy[f]
        # ln p₀_j = -|x_j - x₀|² / 2σ₀² + w ln L_j
        logp = -0.5 * np.sum((xy - x0) ** 2, axis=1) / p.init_std_m**2 + ll
        self.map = f
        self.prob = self._normalised(logp)
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
        prior = propagate(self.prob, m.ij, model.grids[self.map], kernel, h)
        total = prior.sum()
        if total > 0:
            prior /= total
        # keep points whose transition probability exceeds P_T
        prior[prior < p.transition_threshold] = 0.0
        self.d = np.zeros(2)
        self.cov = np.zeros((2, 2))
        with np.errstate(divide="ignore"):
            log_prior = np.log(prior)
        predictive = logsumexp(log_prior + ll) if prior.any() else -np.inf
        if predictive < ll.max() - p.relocate_margin:
            self._start(self.map, tx, rssi, ll)
            return
        self.prob = self._normalised(log_prior + ll)

    @staticmethod
    def _normalised(logp: np.ndarray) -> np.ndarray:
        # p_j = exp(ln p_j - max) / Σ
        w = np.exp(logp - np.max(logp))
        return w / w.sum()

    def _estimate(self, t: int) -> Estimate:
        p, model = self.params, self.model
        xy = model.xy[self.map]
        nz = np.flatnonzero(self.prob)
        w = self.prob[nz]
        # x̂ = Σ p_j x_j + D
        mean = w @ xy[nz]
        dev = xy[nz] - mean
        # C = Σ p_j (x_j - x̂)(x_j - x̂)ᵀ + Σ_D
        cov = np.einsum("n,ni,nj->ij", w, dev, dev) + self.cov
        pos = mean + self.d
        radius = max(p.min_accuracy_m, R68_2D * float(np.sqrt(np.trace(cov) / 2.0)))
        accuracy = float(np.hypot(radius, p.accuracy_floor_m))
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
        )
