"""The positioning loop of Eurasian patent 047000 over many devices at once.

Per device and positioning window (patent, Fig. 2):

1.  measurements go to the preprocessor, which releases complete windows;
2.  the window's readings are split by the floor of their transmitter;
3.  floor selection ranks the active floors; no active floor resets the
    last position and emits nothing. By default a forward filter over floors
    (``floors.forward.FloorFilter``) chooses, on evidence computed for all due
    devices at once (``floors.evidence.FloorEvidence``: the transmitter table,
    and the site's radio maps when it has them); the patent's E_L ranking with
    hysteresis (``floors.patent.PatentFloorSelector``) remains available;
4.  the dead reckoning's steps and any positional measurement of the window
    are handed to the particle filter of each active floor;
5.  the first floor's filter gives x, y;
6.  the position is refined with the previous position and speed (an
    alpha-beta filter with a speed limit);
7.  it is projected onto the floor's free area, and that is the output.

The particle filters of all devices sit in one :class:`ParticleBank`, so one
window of many devices costs one batched filter update per floor. Only the
``max_active_floors`` best floors run a filter: the patent runs every active
floor, which in an atrium can be all of them for little benefit, since the
floor rarely changes to anything but the runner-up.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.engine.floors.evidence import FloorEvidence
from app.engine.floors.params import FloorParams
from app.engine.floors.selection import FloorSelector, floor_selector_class
from app.engine.floors.window import FloorWindow
from app.engine.particle.bank import ParticleBank
from app.engine.particle.estimate import FilterEstimate
from app.engine.particle.floor_model import FloorModel, build_floor_models
from app.engine.particle.inputs import FilterInput
from app.engine.particle.params import ParticleFilterParams
from app.engine.particle.update import update_filters
from app.engine.pdr import Pdr, PdrParams
from app.engine.preprocess import Preprocessor, PreprocessParams, Window
from app.engine.radiomap import RadioMap
from app.engine.samples import Batch, Estimate, Fixes
from app.engine.site import SiteModel


@dataclass(frozen=True)
class PositioningParams:
    """Constants of the positioning loop and of the stages it runs.

    Attributes
    ----------
    filter, preprocess, floors, pdr
        Parameters of the particle filter, the preprocessor, floor selection
        and the dead reckoning.
    max_active_floors : int
        How many of the ranked active floors run their particle filter.
    position_gain : float
        α of the refinement: the share of the filter's innovation taken into
        the position (1 disables refinement). On the BLE flat's calibration
        runs 0.5 to 1 differ by under 4 cm of mean error; 0.7 was best there.
    velocity_gain : float
        β of the refinement: the share of the innovation per second taken
        into the velocity; small, since the filter's positions already lag.
    max_speed_mps : float
        Refined velocity is clamped to this speed (m/s): a brisk walk.
    refine_reset_ms : int
        A gap longer than this between outputs restarts the refinement.
    imu_timeout_ms : int
        Without inertial samples for this long, particles move by the random
        walk instead of steps.
    max_walk_s : float
        Longest random walk (s) applied in one window, after a gap.
    accuracy_floor_m : float
        Error (m) added in quadrature to the particle cloud's 68% radius to
        give the reported accuracy. The cloud measures the filter's
        uncertainty under its own RSSI model, not the model's misfit: on ILC
        site1 it is a small fraction of the errors. The server
        sets it per site to the median held-out error of the site's radio-map
        build (the fingerprints' cross-validation); 0 keeps the cloud's radius.
    """

    filter: ParticleFilterParams = field(default_factory=ParticleFilterParams)
    preprocess: PreprocessParams = field(default_factory=PreprocessParams)
    floors: FloorParams = field(default_factory=FloorParams)
    pdr: PdrParams = field(default_factory=PdrParams)
    max_active_floors: int = 2
    position_gain: float = 0.7
    velocity_gain: float = 0.05
    max_speed_mps: float = 2.5
    refine_reset_ms: int = 5000
    imu_timeout_ms: int = 3000
    max_walk_s: float = 5.0
    accuracy_floor_m: float = 0.0


_PDR_KEYS = tuple(Pdr().snapshot())
"""Fields of a dead-reckoning snapshot."""


def seed_from_id(device_id: str) -> int:
    """Return a 64-bit generator seed derived from a device id (first 8 bytes of SHA-1)."""
    return int.from_bytes(hashlib.sha1(device_id.encode("utf-8")).digest()[:8], "big")


def rng_state(rng: np.random.Generator) -> np.ndarray:
    """Return a PCG64 generator's state as six uint64 words."""
    s = rng.bit_generator.state
    if s["bit_generator"] != "PCG64":
        raise ValueError("only PCG64 generators snapshot")
    mask = (1 << 64) - 1
    state, inc = s["state"]["state"], s["state"]["inc"]
    words = [state >> 64, state & mask, inc >> 64, inc & mask, s["has_uint32"], s["uinteger"]]
    return np.array(words, dtype=np.uint64)


def rng_from_state(words: np.ndarray) -> np.random.Generator:
    """Rebuild the generator saved by :func:`rng_state`."""
    w = [int(v) for v in np.asarray(words, dtype=np.uint64)]
    bit = np.random.PCG64()
    bit.state = {
        "bit_generator": "PCG64",
        "state": {"state": (w[0] << 64) | w[1], "inc": (w[2] << 64) | w[3]},
        "has_uint32": w[4],
        "uinteger": w[5],
    }
    return np.random.Generator(bit)


def refine(
    z: np.ndarray,
    prev: np.ndarray,
    velocity: np.ndarray,
    dt_s: np.ndarray,
    params: PositioningParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Refine filter positions with the previous positions and velocities (alpha-beta filter).

    Parameters
    ----------
    z : ndarray, shape (..., 2)
        The filters' positions (m).
    prev, velocity : ndarray, shape (..., 2)
        Previous outputs (m) and velocities (m/s).
    dt_s : ndarray, shape (...)
        Time since the previous outputs (s), > 0.

    Returns
    -------
    position, velocity : ndarray, shape (..., 2)
        Velocities are clamped to ``max_speed_mps``.
    """
    dt = np.asarray(dt_s, dtype=float)[..., None]
    # x̂⁻ = x + v Δt
    predicted = prev + velocity * dt
    residual = z - predicted
    # x = x̂⁻ + α r, v = v + β r / Δt
    position = predicted + params.position_gain * residual
    velocity = velocity + params.velocity_gain * residual / dt
    speed = np.hypot(velocity[..., 0], velocity[..., 1])[..., None]
    # v ← v · min(1, v_max / |v|)
    velocity = velocity * np.minimum(1.0, params.max_speed_mps / np.maximum(speed, 1e-12))
    return position, velocity


def floor_selector(
    site: SiteModel, params: FloorParams, state: dict[str, Any] | None = None
) -> FloorSelector:
    """Return the floor selector ``params.method`` names, fresh or from a snapshot."""
    levels = np.array([f.level for f in site.floors])
    return floor_selector_class(params)(levels, params, state)


def floor_evidence(
    site: SiteModel, params: FloorParams, radio_maps: Sequence[RadioMap] = ()
) -> FloorEvidence:
    """Return the floor filter's evidence for a site, with its radio maps when it has them."""
    return FloorEvidence(site.transmitters.floor, len(site.floors), params, radio_maps)


def _last_fix(fixes: Fixes, floor: int) -> tuple[float, float, float] | None:
    """Return the window's last positional measurement on ``floor``: x, y (m) and radius (m)."""
    if not len(fixes):
        return None
    on_floor = np.flatnonzero(fixes.floor == floor)
    if not on_floor.size:
        return None
    j = on_floor[-1]
    return float(fixes.xyz[j, 0]), float(fixes.xyz[j, 1]), float(fixes.std[j])


@dataclass(frozen=True)
class HeardByFloor:
    """The transmitters each device heard in a window, per floor: sorted, mean reading, count."""

    tx: np.ndarray
    mean: np.ndarray
    count: np.ndarray
    bounds: list[int]
    """Group g = device · F + floor holds rows ``bounds[g]:bounds[g + 1]``."""
    n_floors: int

    @classmethod
    def of_readings(
        cls,
        device: np.ndarray,
        tx_floor: np.ndarray,
        tx: np.ndarray,
        rssi: np.ndarray,
        n_devices: int,
        n_floors: int,
    ) -> HeardByFloor:
        """Group readings (device row, transmitter floor and index, dBm) by device and floor."""
        placed = tx_floor >= 0
        n_tx = int(tx.max()) + 1 if tx.size else 1
        group = device[placed] * n_floors + tx_floor[placed]
        key, inverse = np.unique(group * n_tx + tx[placed], return_inverse=True)
        count = np.bincount(inverse, minlength=key.size)
        # s̄_m = Σ s_k / n_m over the readings of transmitter m
        mean = np.bincount(inverse, weights=rssi[placed], minlength=key.size) / count
        bounds = np.searchsorted(key // n_tx, np.arange(n_devices * n_floors + 1))
        return cls(key % n_tx, mean, count.astype(float), bounds.tolist(), n_floors)

    def of(self, device: int, floor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return one device's transmitters on one floor, their mean readings and counts."""
        g = device * self.n_floors + floor
        lo, hi = self.bounds[g], self.bounds[g + 1]
        return self.tx[lo:hi], self.mean[lo:hi], self.count[lo:hi]


class DeviceState:
    """One device's positioning state outside the particle bank."""

    def __init__(
        self, site: SiteModel, params: PositioningParams, rng: np.random.Generator
    ) -> None:
        self.rng = rng
        self.pre = Preprocessor(params.preprocess)
        self.floors = floor_selector(site, params.floors)
        self.pdr = Pdr(params.pdr)
        self.slots: dict[int, int] = {}
        self.imu_t = -(2**62)
        self.last_t = -(2**62)
        self.out_t = -(2**62)
        self.out_floor = -1
        self.out_xy = np.zeros(2)
        self.velocity = np.zeros(2)


class PositioningEngine:
    """Positions many devices on one site; their filters share one particle bank.

    Parameters
    ----------
    site : SiteModel
    params : PositioningParams
    models : tuple of FloorModel, optional
        Prebuilt ``build_floor_models(site, params.filter)``, to share between engines.
    evidence : FloorEvidence, optional
        Prebuilt ``floor_evidence(site, params.floors, radio_maps)``, to share
        between engines; by default the transmitter table's alone.
    """

    method = "pf"

    def __init__(
        self,
        site: SiteModel,
        params: PositioningParams,
        models: tuple[FloorModel, ...] | None = None,
        evidence: FloorEvidence | None = None,
    ) -> None:
        self.site = site
        self.params = params
        self.models = models if models is not None else build_floor_models(site, params.filter)
        self.evidence = evidence if evidence is not None else floor_evidence(site, params.floors)
        self.bank = ParticleBank(params.filter.n_particles)
        self.devices: dict[str, DeviceState] = {}
        tx = site.transmitters
        self._tx_floor = np.asarray(tx.floor, dtype=np.intp)
        self._tx_a = np.asarray(tx.A, dtype=float)

    def add(self, device_id: str, seed: int | None = None) -> None:
        """Register a device with a fresh state; its generator is seeded from ``seed`` or its id."""
        seed = seed_from_id(device_id) if seed is None else seed
        self.devices[device_id] = DeviceState(
            self.site, self.params, np.random.Generator(np.random.PCG64(seed))
        )

    def remove(self, device_id: str) -> None:
        """Forget a device and free its filters."""
        dev = self.devices.pop(device_id)
        for slot in dev.slots.values():
            self.bank.release(slot)

    def snapshot(self, device_id: str) -> dict[str, Any]:
        """Return everything needed to resume the device exactly: arrays and scalars only."""
        dev = self.devices[device_id]
        return {
            "rng": rng_state(dev.rng),
            "pre": dev.pre.snapshot(),
            "floors": dev.floors.snapshot(),
            # unset detector fields are None, which snapshots cannot hold: left out
            "pdr": {k: v for k, v in dev.pdr.snapshot().items() if v is not None},
            "filters": {str(f): self.bank.export(s) for f, s in dev.slots.items()},
            "imu_t": dev.imu_t,
            "last_t": dev.last_t,
            "out_t": dev.out_t,
            "out_floor": dev.out_floor,
            "out_xy": dev.out_xy.copy(),
            "velocity": dev.velocity.copy(),
        }

    def restore(self, device_id: str, state: dict[str, Any]) -> None:
        """Register a device from a :meth:`snapshot`."""
        if device_id in self.devices:
            self.remove(device_id)
        dev = DeviceState(self.site, self.params, rng_from_state(state["rng"]))
        p = self.params
        dev.pre = Preprocessor(p.preprocess, state["pre"])
        dev.floors = floor_selector(self.site, p.floors, state["floors"])
        saved = state["pdr"]
        dev.pdr = Pdr.from_snapshot({k: saved.get(k) for k in _PDR_KEYS}, p.pdr)
        dev.slots = {int(f): self.bank.restore(s) for f, s in state.get("filters", {}).items()}
        dev.imu_t = int(state["imu_t"])
        dev.last_t = int(state["last_t"])
        dev.out_t = int(state["out_t"])
        dev.out_floor = int(state["out_floor"])
        dev.out_xy = np.asarray(state["out_xy"], dtype=float).copy()
        dev.velocity = np.asarray(state["velocity"], dtype=float).copy()
        self.devices[device_id] = dev

    def process(self, batches: Mapping[str, Batch]) -> dict[str, list[Estimate]]:
        """Consume one time-ordered batch per device; return each device's new estimates."""
        windows: dict[str, list[Window]] = {}
        for device_id, batch in batches.items():
            windows[device_id] = self._windows(self.devices[device_id], batch)
        return self._run(windows)

    def flush(self, device_ids: list[str]) -> dict[str, list[Estimate]]:
        """Position the devices' last, incomplete windows (end of a recording)."""
        return self._run({d: self.devices[d].pre.flush() for d in device_ids})

    def _windows(self, dev: DeviceState, batch: Batch) -> list[Window]:
        steps = None
        if len(batch.imu):
            steps = dev.pdr.update(batch.imu)
            dev.imu_t = max(dev.imu_t, int(batch.imu.t.max()))
        return dev.pre.push(
            rssi=batch.rssi, steps=steps, fixes=batch.fixes, pressure=batch.pressure
        )

    def _run(self, windows: dict[str, list[Window]]) -> dict[str, list[Estimate]]:
        results: dict[str, list[Estimate]] = {d: [] for d in windows}
        depth = max([len(w) for w in windows.values()] + [0])
        for k in range(depth):
            due = {d: w[k] for d, w in windows.items() if k < len(w)}
            plans = dict(zip(due, self._plan(due), strict=True))
            by_floor: dict[int, list[tuple[str, FilterInput]]] = {}
            for d, (_, inputs) in plans.items():
                for f, inp in inputs:
                    by_floor.setdefault(f, []).append((d, inp))
            estimates: dict[tuple[str, int], FilterEstimate] = {}
            for f in sorted(by_floor):
                pairs = by_floor[f]
                outs = update_filters(
                    self.bank, self.models[f], [inp for _, inp in pairs], self.params.filter
                )
                for (d, _), est in zip(pairs, outs, strict=True):
                    estimates[(d, f)] = est
            chosen = []
            for d, (floor, _) in plans.items():
                if floor < 0:
                    self.devices[d].out_floor = -1
                else:
                    chosen.append((d, floor, estimates[(d, floor)]))
            for d, out in self._outputs(chosen, due):
                results[d].append(out)
        return results

    def _plan(self, due: dict[str, Window]) -> list[tuple[int, list[tuple[int, FilterInput]]]]:
        """Floor selection for the due windows; return each one's floor and filter inputs.

        The readings of all the windows are worked on together: their floors
        and path-loss A looked up once, each transmitter's mean taken once per
        device and floor, the floor selectors updated in one call.
        """
        p = self.params
        devs = [self.devices[d] for d in due]
        wins = list(due.values())
        bounds = np.cumsum([0] + [len(w.rssi) for w in wins])
        tx = np.concatenate([w.rssi.tx for w in wins] + [np.zeros(0, np.int32)]).astype(np.intp)
        rssi = np.concatenate([w.rssi.rssi for w in wins] + [np.zeros(0)])
        device = np.repeat(np.arange(len(wins)), np.diff(bounds))
        tx_floor, tx_a = self._tx_floor[tx], self._tx_a[tx]
        loglik = self._floor_evidence(device, tx, rssi, len(wins))
        selectors = [dev.floors for dev in devs]
        ranked = floor_selector_class(p.floors).update_many(
            selectors,
            [
                FloorWindow(
                    w.t1,
                    tx_floor[lo:hi],
                    rssi[lo:hi],
                    tx_a[lo:hi],
                    loglik[i],
                    w.pressure.hpa,
                )
                for i, (w, lo, hi) in enumerate(zip(wins, bounds[:-1], bounds[1:], strict=True))
            ],
        )
        heard = HeardByFloor.of_readings(
            device, tx_floor, tx, rssi, len(wins), len(self.site.floors)
        )
        plans: list[tuple[int, list[tuple[int, FilterInput]]]] = []
        for i, (dev, win) in enumerate(zip(devs, wins, strict=True)):
            self._release_idle(dev, win.t1)
            if ranked[i].size == 0:
                plans.append((-1, []))
                continue
            no_imu = win.t1 - dev.imu_t > p.imu_timeout_ms
            walk_s = min((win.t1 - dev.last_t) / 1000.0, p.max_walk_s) if no_imu else 0.0
            dev.last_t = win.t1
            inputs = []
            for f in ranked[i][: p.max_active_floors].tolist():
                if f not in dev.slots:
                    dev.slots[f] = self.bank.allocate()
                tx_f, mean, count = heard.of(i, f)
                inputs.append(
                    (
                        f,
                        FilterInput(
                            slot=dev.slots[f],
                            t=win.t1,
                            tx=tx_f,
                            rssi=mean,
                            count=count,
                            rng=dev.rng,
                            step_length=win.steps.length,
                            step_heading=win.steps.heading,
                            walk_s=max(walk_s, 0.0),
                            fix=_last_fix(win.fixes, f),
                        ),
                    )
                )
            plans.append((int(ranked[i][0]), inputs))
        return plans

    def _floor_evidence(
        self, device: np.ndarray, tx: np.ndarray, rssi: np.ndarray, n_devices: int
    ) -> np.ndarray:
        """Return the floor filter's log-likelihoods (D, F) of the due windows' readings."""
        if not floor_selector_class(self.params.floors).uses_evidence:
            return np.zeros((n_devices, len(self.site.floors)))
        return self.evidence.log_likelihood(device, tx, rssi, n_devices)

    def _release_idle(self, dev: DeviceState, t: int) -> None:
        """Free filters of floors silent for longer than T_r: they would rescatter anyway."""
        limit = self.params.filter.rescatter_after_ms
        for f, slot in list(dev.slots.items()):
            if t - int(self.bank.last_radio[slot]) > limit and self.bank.sampled[slot]:
                self.bank.release(slot)
                del dev.slots[f]

    def _outputs(
        self, chosen: list[tuple[str, int, FilterEstimate]], due: dict[str, Window]
    ) -> list[tuple[str, Estimate]]:
        """Refine, project and emit the chosen floors' positions, all devices at once."""
        if not chosen:
            return []
        p = self.params
        devs = [self.devices[d] for d, _, _ in chosen]
        floor = np.array([f for _, f, _ in chosen])
        t = np.array([due[d].t_last for d, _, _ in chosen], dtype=np.int64)
        z = np.array([[e.x, e.y] for _, _, e in chosen])
        prev = np.array([dev.out_xy for dev in devs])
        vel = np.array([dev.velocity for dev in devs])
        dt = (t - np.array([dev.out_t for dev in devs])) / 1000.0
        same = np.array([dev.out_floor for dev in devs]) == floor
        keep = same & (dt > 0.0) & (dt <= p.refine_reset_ms / 1000.0)
        xy, v = refine(z, prev, vel, np.where(keep, dt, 1.0), p)
        xy = np.where(keep[:, None], xy, z)
        v = np.where(keep[:, None], v, 0.0)
        for f in np.unique(floor).tolist():
            on = floor == f
            xy[on] = self.site.floors[f].plan.project(xy[on])
        # converted for all devices at once, then handed out row by row
        radius = np.array([e.radius for _, _, e in chosen])
        accuracy = np.hypot(radius, p.accuracy_floor_m).tolist()
        speed = np.hypot(v[:, 0], v[:, 1]).tolist()
        times, points = t.tolist(), xy.tolist()
        out = []
        for i, (d, f, est) in enumerate(chosen):
            dev = devs[i]
            # rows of this round's arrays, which nothing writes to after
            dev.out_xy, dev.velocity = xy[i], v[i]
            dev.out_t, dev.out_floor = times[i], f
            x, y = points[i]
            height = float(self.site.floors[f].z0)
            estimate = Estimate(
                times[i], x, y, height, f, est.heading, accuracy[i], speed[i], self.method
            )
            out.append((d, estimate))
        return out


class ParticleTracker:
    """One device's positioning behind the worker's ``Tracker`` interface.

    Parameters
    ----------
    site : SiteModel
    params : PositioningParams
    state : dict, optional
        A :meth:`snapshot` to resume from.
    seed : int
        Generator seed of a fresh device (ignored when restoring).
    models : tuple of FloorModel, optional
        Prebuilt floor models shared between trackers of the site.
    evidence : FloorEvidence, optional
        Prebuilt floor evidence shared between trackers of the site.
    """

    _ID = "device"

    def __init__(
        self,
        site: SiteModel,
        params: PositioningParams,
        state: dict[str, Any] | None = None,
        *,
        seed: int = 0,
        models: tuple[FloorModel, ...] | None = None,
        evidence: FloorEvidence | None = None,
    ) -> None:
        self.engine = PositioningEngine(site, params, models, evidence)
        if state is None:
            self.engine.add(self._ID, seed)
        else:
            self.engine.restore(self._ID, state)

    def process(self, batch: Batch) -> list[Estimate]:
        """Consume one time-ordered batch and return the estimates it produced."""
        return self.engine.process({self._ID: batch})[self._ID]

    def flush(self) -> list[Estimate]:
        """Position the last, incomplete window."""
        return self.engine.flush([self._ID])[self._ID]

    def snapshot(self) -> dict[str, Any]:
        """Return the state needed to resume exactly where this tracker stands."""
        return self.engine.snapshot(self._ID)
