"""Accuracy of the WiFi positioning methods on ILC site1's held-out walks.

Site1 (a five-floor mall) is split by walk id with ``walk_split``'s hash
(never by sample: samples of one walk are correlated). Everything the
methods know is learned from the training walks only: the transmitter table
(BSSIDs heard there), the radio maps, each transmitter's calibrated floor,
position and path loss, and the PDR constants (Weinberg's K and the site
frame's heading offset). Each held-out walk is then replayed as the
one-second batches a phone would upload, through:

- ``wknn``: WKNN per WiFi scan on the radio maps, no tracking (the peer baseline);
- ``hmm``: the fingerprint + inertial HMM of seed 002 over the same maps, fed by PDR;
- ``pf``: the particle filter of seed 000 (floor selection, PDR steps, map
  constraint) through ``PositioningEngine`` with the server's default
  parameters, on the transmitters calibrated by ``app.engine.calibration``,
  as on a site without radio maps: floors are chosen on the transmitter
  table alone;
- ``pf-radiomap``: the same where the site has radio maps, as the server
  runs it: the maps' surveyed RSSI in the filters' rasters and in the
  floor evidence.

Each estimate is compared with the waypoints interpolated at its time, only
inside the waypoints' span. Horizontal errors count only where the estimated
floor is right; the floor error is the share of estimates on a wrong floor;
the heading error is against the direction of the waypoint segment being
walked, on segments where the walker moves; "in acc." is the share of the
right-floor errors within the 68% accuracy radius each estimate reported
(68% when the radius is honest). CPU time is per one-second batch
of one device (one device update); the particle filter replays all walks as
devices of one engine, batched as a server worker runs them
(``--pf-unbatched`` replays them one by one: the estimates are identical,
only the CPU per update differs).

``--validation-fraction`` carves a validation set out of the training walks
(``split_ids``) and evaluates on it instead of the test walks: for studying
and tuning the methods without looking at the test walks.

Run ``locus eval ilc`` or ``python -m app.evaluation.ilc_eval``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from app.datasets import data_dir
from app.datasets.ilc import Walk, floor_level, imu_samples, site_walks
from app.engine.calibration import CalibrationParams, TransmitterFit, calibrate, to_emitters
from app.engine.crossval import cross_validate
from app.engine.floors.evidence import FloorEvidence
from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.params import HmmParams
from app.engine.hmm.tracker import HmmTracker
from app.engine.particle.floor_model import FloorModel, build_floor_models
from app.engine.pdr import PdrParams, detect_steps
from app.engine.positioning import (
    ParticleTracker,
    PositioningEngine,
    PositioningParams,
    floor_evidence,
    seed_from_id,
)
from app.engine.radiomap import (
    RadioMap,
    RadioMapParams,
    Survey,
    build_radio_map,
    interpolate_waypoints,
)
from app.engine.samples import Batch, Estimate, RssiReadings
from app.engine.site import Floor, SiteModel
from app.engine.wknn import Fingerprints, WknnParams, WknnTracker
from app.evaluation.pdr_eval import calibrate_k, heading_offset, walk_pdr, wrap_deg
from app.evaluation.plots import plan_figure
from app.evaluation.site1 import SiteData, load_site, split_ids, survey, walk_batches

METHODS = ("wknn", "hmm", "pf", "pf-radiomap")
"""Methods compared. ``pf-radiomap`` is the particle filter whose expected-RSSI
rasters hold the radio maps' surveyed means where the survey went."""

FLOOR_HEIGHT_M = 4.0
"""Storey height of the site model: ILC carries no survey of it (only z0 of outputs uses it)."""

MIN_HEADING_SEGMENT_M = 1.0
"""Waypoint segments shorter than this have no meaningful direction."""

MIN_HEADING_SPEED_MPS = 0.3
"""Below this mean speed on a segment the walker is standing, not walking a direction."""


class Tracker(Protocol):
    """What the replay needs from a method: batches in, estimates out."""

    def process(self, batch: Batch) -> list[Estimate]:
        """Consume one batch; return the estimates it produced."""
        ...


# --- what is learned from the training walks ------------------------------------------


@dataclass(frozen=True, eq=False)
class Learned:
    """Everything the methods learned from the training walks.

    ``pf_lookup`` maps a site transmitter index to its row in the particle
    filter's transmitter table (-1: not calibrated, unknown to the filter).
    ``fingerprint_error_m`` is the median error of the training scans located
    by WKNN on maps built without their walk's fold, as a radio-map build
    reports it; the server's HMM and particle filter add it to their radius.
    """

    maps: tuple[RadioMap, ...]
    fits: tuple[TransmitterFit, ...]
    pdr: PdrParams
    pf_site: SiteModel
    pf_lookup: np.ndarray
    n_train: int
    fingerprint_error_m: float = 0.0


def pdr_constants(walks: Iterable[Walk], base: PdrParams) -> PdrParams:
    """Return ``base`` with Weinberg's K and the heading offset fitted on ``walks``.

    The offset is the rotation of the site frame against magnetic north, a
    property of the building; K the walkers' step scale.
    """
    results = []
    for walk in walks:
        if walk.waypoints.shape[0] < 2 or walk.acc.shape[0] == 0:
            continue
        steps = detect_steps(imu_samples(walk), base)
        results.append(walk_pdr(walk.walk_id, walk.floor, walk.waypoints, steps))
    return replace(
        base, weinberg_k=calibrate_k(results), heading_offset_deg=heading_offset(results)
    )


def radio_maps(site: SiteData, srv: Survey, params: RadioMapParams) -> tuple[RadioMap, ...]:
    """Build one radio map per floor (on its walkable area) from the training survey."""
    return tuple(
        build_radio_map(srv, f, params, walkable=site.plans[f]) for f in range(len(site.floors))
    )


def pf_site_model(site: SiteData, fits: Sequence[TransmitterFit]) -> tuple[SiteModel, np.ndarray]:
    """Return the particle filter's site (plausible calibrated transmitters only) and the lookup.

    Transmitters whose fit is implausible or missing are not in the table:
    the server only knows transmitters with a path-loss model, and the
    filter's floor selection needs every heard transmitter's floor.
    """
    kept = [f for f in fits if f.plausible]
    lookup = np.full(len(site.tx_ids), -1, dtype=np.int64)
    lookup[[f.tx for f in kept]] = np.arange(len(kept))
    renumbered = [replace(f, tx=i) for i, f in enumerate(kept)]
    emitters = to_emitters(renumbered, tuple(site.tx_ids[f.tx] for f in kept))
    floors = tuple(
        Floor(name, floor_level(name), FLOOR_HEIGHT_M, plan, FLOOR_HEIGHT_M * i)
        for i, (name, plan) in enumerate(zip(site.floors, site.plans, strict=True))
    )
    return SiteModel("ilc-site1", floors, emitters), lookup


def learn(
    site: SiteData,
    train_ids: Sequence[str],
    *,
    map_params: RadioMapParams | None = None,
    calibration: CalibrationParams | None = None,
    pdr: PdrParams | None = None,
    status: Callable[[str], None] = lambda _: None,
) -> Learned:
    """Learn the radio maps, transmitter calibration and PDR constants from ``train_ids``."""
    chosen = set(train_ids)
    status("locating training scans")
    srv = survey(site, chosen)
    status("building radio maps")
    maps = radio_maps(site, srv, map_params or RadioMapParams())
    status("cross-validating the radio maps")
    held = cross_validate(
        srv, dict(enumerate(site.plans)), map_params or RadioMapParams(), WknnParams()
    )
    status("calibrating transmitters")
    fits = tuple(calibrate(srv, calibration or CalibrationParams()))
    status("fitting PDR constants")
    pdr_params = pdr_constants((w for w in site.walks if w.walk_id in chosen), pdr or PdrParams())
    model, lookup = pf_site_model(site, fits)
    error = float(np.median(held.error_m)) if held is not None else 0.0
    return Learned(maps, fits, pdr_params, model, lookup, len(chosen), error)


# --- replay --------------------------------------------------------------------------


def remap(batch: Batch, lookup: np.ndarray) -> Batch:
    """Return the batch with transmitter indices mapped through ``lookup``; -1 dropped."""
    r = batch.rssi
    tx = lookup[r.tx] if r.tx.size else np.zeros(0, np.int64)
    keep = tx >= 0
    readings = RssiReadings(t=r.t[keep], tx=tx[keep].astype(np.int32), rssi=r.rssi[keep])
    return replace(batch, rssi=readings)


@dataclass
class Replay:
    """One method's estimates on one walk and the CPU time (s) its batches took."""

    estimates: list[Estimate]
    cpu_s: float
    updates: int


def replay(
    tracker: Tracker,
    batches: Iterable[Batch],
    *,
    transform: Callable[[Batch], Batch] | None = None,
    flush: Callable[[], list[Estimate]] | None = None,
) -> Replay:
    """Feed a walk's batches to a tracker, timing only the tracker's own CPU."""
    out: list[Estimate] = []
    cpu = 0.0
    updates = 0
    for batch in batches:
        if transform is not None:
            batch = transform(batch)
        t0 = time.process_time()
        out.extend(tracker.process(batch))
        cpu += time.process_time() - t0
        updates += 1
    if flush is not None:
        t0 = time.process_time()
        out.extend(flush())
        cpu += time.process_time() - t0
    return Replay(out, cpu, updates)


class Runner(Protocol):
    """A method ready to replay walks."""

    def __call__(self, site: SiteData, walk: Walk) -> Replay:
        """Replay one walk."""
        ...


def make_runner(name: str, learned: Learned) -> Runner:
    """Return the replay function of a method, with its shared, prebuilt models."""
    if name == "wknn":
        params = WknnParams()
        prints = Fingerprints(learned.maps, params.missing_dbm)

        def run_wknn(site: SiteData, walk: Walk) -> Replay:
            return replay(WknnTracker(prints, params), walk_batches(site, walk))

        return run_wknn
    if name == "hmm":
        # the radius floor a server takes from its site's radio-map build
        hmm_params = HmmParams(accuracy_floor_m=learned.fingerprint_error_m)
        model = EmissionModel(learned.maps, hmm_params)

        def run_hmm(site: SiteData, walk: Walk) -> Replay:
            tracker = HmmTracker(model, hmm_params, learned.pdr)
            return replay(tracker, walk_batches(site, walk))

        return run_hmm
    if name in ("pf", "pf-radiomap"):
        pf_params = pf_positioning_params(name, learned)
        models = pf_models(name, learned, pf_params)
        evidence = pf_evidence(name, learned, pf_params)

        def run_pf(site: SiteData, walk: Walk) -> Replay:
            tracker = ParticleTracker(
                learned.pf_site,
                pf_params,
                seed=seed_from_id(walk.walk_id),
                models=models,
                evidence=evidence,
            )
            return replay(
                tracker,
                walk_batches(site, walk),
                transform=lambda b: remap(b, learned.pf_lookup),
                flush=tracker.flush,
            )

        return run_pf
    raise ValueError(f"unknown method {name!r}; choose from {', '.join(METHODS)}")


def pf_radio_maps(learned: Learned) -> tuple[RadioMap, ...]:
    """Return the radio maps with their columns renumbered to the particle filter's table."""
    out = []
    for m in learned.maps:
        rows = learned.pf_lookup[m.tx]
        kept = np.flatnonzero(rows >= 0)
        out.append(
            replace(
                m,
                tx=rows[kept].astype(np.int32),
                mean=m.mean[:, kept],
                var=m.var[:, kept],
                detect=m.detect[:, kept],
            )
        )
    return tuple(out)


def pf_positioning_params(name: str, learned: Learned) -> PositioningParams:
    """Return the server's parameters with the learned PDR constants.

    ``pf-radiomap`` also gets the radius floor a server takes from its site's
    radio-map build (``app.workers.trackers.SiteEngines.for_site``).
    """
    floor = learned.fingerprint_error_m if name == "pf-radiomap" else 0.0
    return PositioningParams(pdr=learned.pdr, accuracy_floor_m=floor)


def pf_models(name: str, learned: Learned, params: PositioningParams) -> tuple[FloorModel, ...]:
    """Return the floor models of ``pf`` (path loss only) or ``pf-radiomap``."""
    maps = pf_radio_maps(learned) if name == "pf-radiomap" else ()
    return build_floor_models(learned.pf_site, params.filter, maps)


def pf_evidence(name: str, learned: Learned, params: PositioningParams) -> FloorEvidence:
    """Return the floor evidence of ``pf`` (transmitter table only) or ``pf-radiomap``."""
    maps = pf_radio_maps(learned) if name == "pf-radiomap" else ()
    return floor_evidence(learned.pf_site, params.floors, maps)


def replay_pf_batched(
    site: SiteData,
    learned: Learned,
    walks: Sequence[Walk],
    progress: Callable[[int], None] = lambda _i: None,
    name: str = "pf",
) -> tuple[list[list[Estimate]], float, int]:
    """Replay all walks at once as devices of one ``PositioningEngine``, as a server worker does.

    Walk k's i-th batch goes in the engine's i-th call with every other
    walk's i-th batch, so each call is one batched filter update per floor
    for all devices. A device's filter does not depend on its batch mates,
    so the estimates are those of replaying each walk alone; only the CPU
    per device update differs. Returns each walk's estimates, the engine's
    CPU time (s) and the number of device updates.
    """
    params = pf_positioning_params(name, learned)
    engine = PositioningEngine(
        learned.pf_site,
        params,
        pf_models(name, learned, params),
        pf_evidence(name, learned, params),
    )
    streams = {}
    for walk in walks:
        engine.add(walk.walk_id, seed_from_id(walk.walk_id))
        streams[walk.walk_id] = walk_batches(site, walk)
    out: dict[str, list[Estimate]] = {w.walk_id: [] for w in walks}
    cpu, updates = 0.0, 0
    while streams:
        due: dict[str, Batch] = {}
        for walk_id, stream in list(streams.items()):
            batch = next(stream, None)
            if batch is None:
                del streams[walk_id]
                t0 = time.process_time()
                out[walk_id].extend(engine.flush([walk_id])[walk_id])
                cpu += time.process_time() - t0
                engine.remove(walk_id)
                progress(len(walks) - len(streams))
            else:
                due[walk_id] = remap(batch, learned.pf_lookup)
        if due:
            t0 = time.process_time()
            for walk_id, estimates in engine.process(due).items():
                out[walk_id].extend(estimates)
            cpu += time.process_time() - t0
            updates += len(due)
    return [out[w.walk_id] for w in walks], cpu, updates


# --- scoring -------------------------------------------------------------------------


@dataclass(frozen=True)
class WalkScore:
    """One method's estimates on one walk, scored against the waypoints.

    Arrays cover the estimates inside the waypoints' span: ``floor_ok``
    whether the floor is right, ``error`` the horizontal error (m, NaN on a
    wrong floor), ``heading_error`` the absolute heading error (deg, NaN
    where the estimate has no heading or the walker does not move a direction),
    ``accuracy`` the 68% radius (m) each estimate reported.
    """

    floor_ok: np.ndarray
    error: np.ndarray
    heading_error: np.ndarray
    accuracy: np.ndarray


def path_direction(waypoints: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Return the direction (deg clockwise from +y) of the waypoint segment walked at ``t``.

    NaN outside the span, on segments shorter than ``MIN_HEADING_SEGMENT_M``
    or slower than ``MIN_HEADING_SPEED_MPS`` (standing).
    """
    t = np.asarray(t, dtype=float)
    wt, xy = waypoints[:, 0], waypoints[:, 1:3]
    out = np.full(t.shape, np.nan)
    if wt.size < 2:
        return out
    seg = np.clip(np.searchsorted(wt, t, side="right") - 1, 0, wt.size - 2)
    d = xy[seg + 1] - xy[seg]
    length = np.hypot(d[:, 0], d[:, 1])
    dt_s = (wt[seg + 1] - wt[seg]) / 1000.0
    with np.errstate(divide="ignore", invalid="ignore"):
        moving = (length >= MIN_HEADING_SEGMENT_M) & (length / dt_s >= MIN_HEADING_SPEED_MPS)
    ok = moving & (t >= wt[0]) & (t <= wt[-1])
    # φ = atan2(Δx, Δy), clockwise from +y
    out[ok] = np.mod(np.degrees(np.arctan2(d[ok, 0], d[ok, 1])), 360.0)
    return out


def score_walk(waypoints: np.ndarray, floor: int, estimates: Sequence[Estimate]) -> WalkScore:
    """Score a walk's estimates against its waypoints (m, 3: t, x, y) on floor index ``floor``."""
    if not estimates:
        empty = np.zeros(0)
        return WalkScore(np.zeros(0, bool), empty, empty, empty)
    t = np.array([e.t for e in estimates], dtype=np.int64)
    xy = np.array([[e.x, e.y] for e in estimates], dtype=float)
    est_floor = np.array([e.floor for e in estimates])
    heading = np.array([e.heading for e in estimates], dtype=float)
    accuracy = np.array([e.accuracy for e in estimates], dtype=float)
    true_xy, inside = truth_xy(waypoints, t)
    floor_ok = est_floor[inside] == floor
    err = np.hypot(*(xy[inside] - true_xy[inside]).T)
    err = np.where(floor_ok, err, np.nan)
    direction = path_direction(waypoints, t[inside])
    heading_err = np.abs(wrap_deg(heading[inside] - direction))
    return WalkScore(floor_ok, err, heading_err, accuracy[inside])


def truth_xy(waypoints: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the waypoint truth at ``t`` and the inside-span mask (``site1.truth``'s rule)."""
    return interpolate_waypoints(np.asarray(t, dtype=np.int64), waypoints)


@dataclass(frozen=True)
class Row:
    """One table row: a method's figures pooled over the evaluated walks."""

    method: str
    n: int
    mean: float
    p50: float
    p75: float
    p95: float
    floor_error: float
    heading_error: float
    n_heading: int
    in_accuracy: float
    cpu_per_update_s: float
    walks: int


def summarise(method: str, scores: Sequence[WalkScore], cpu_s: float, updates: int) -> Row:
    """Pool walk scores into a row: errors on the right floor only, shares over all estimates."""
    ok = np.concatenate([s.floor_ok for s in scores]) if scores else np.zeros(0, bool)
    err = np.concatenate([s.error for s in scores]) if scores else np.zeros(0)
    hdg = np.concatenate([s.heading_error for s in scores]) if scores else np.zeros(0)
    acc = np.concatenate([s.accuracy for s in scores]) if scores else np.zeros(0)
    right = err[ok]
    # an honest 68% radius holds 68% of the errors on the right floor
    within = right <= acc[ok]
    hdg = hdg[np.isfinite(hdg)]

    def pct(q: float) -> float:
        return float(np.percentile(right, q)) if right.size else float("nan")

    return Row(
        method=method,
        n=int(ok.size),
        mean=float(right.mean()) if right.size else float("nan"),
        p50=pct(50),
        p75=pct(75),
        p95=pct(95),
        floor_error=float(1.0 - ok.mean()) if ok.size else float("nan"),
        heading_error=float(hdg.mean()) if hdg.size else float("nan"),
        n_heading=int(hdg.size),
        in_accuracy=float(within.mean()) if within.size else float("nan"),
        cpu_per_update_s=cpu_s / updates if updates else float("nan"),
        walks=len(scores),
    )


def format_cpu(seconds: float) -> str:
    """Return a CPU time in µs below a millisecond, else in ms."""
    if not np.isfinite(seconds):
        return "—"
    return f"{seconds * 1e6:.0f} µs" if seconds < 1e-3 else f"{seconds * 1e3:.2f} ms"


def table_cells(row: Row) -> list[str]:
    """Return the printed cells of a row, in ``COLUMNS`` order."""

    def num(v: float, fmt: str = "{:.2f}") -> str:
        return "—" if not np.isfinite(v) else fmt.format(v)

    return [
        row.method,
        str(row.walks),
        str(row.n),
        num(row.mean),
        num(row.p50),
        num(row.p75),
        num(row.p95),
        num(100.0 * row.floor_error, "{:.2f}%"),
        num(row.heading_error, "{:.1f}"),
        num(100.0 * row.in_accuracy, "{:.0f}%"),
        format_cpu(row.cpu_per_update_s),
    ]


COLUMNS = (
    "method",
    "walks",
    "n",
    "mean m",
    "p50 m",
    "p75 m",
    "p95 m",
    "floor err",
    "|hdg err| °",
    "in acc.",
    "CPU/update",
)


# --- plots ---------------------------------------------------------------------------


METHOD_COLOURS = {
    "wknn": "tab:orange",
    "hmm": "tab:green",
    "pf": "tab:blue",
    "pf-radiomap": "tab:red",
}
"""Line colour of each method in the walk plots."""


def plot_walk(
    path: Path,
    site: SiteData,
    walk: Walk,
    results: dict[str, list[Estimate]],
) -> None:
    """Save estimate vs truth over the walk's floor plan as a PNG."""
    f = site.floor_index(walk)
    wp = walk.waypoints
    title = f"site1 {walk.floor} walk {walk.walk_id}"
    with plan_figure(path, site.plans[f], title, width_in=10.0) as ax:
        ax.plot(wp[:, 1], wp[:, 2], "k.-", lw=2, ms=6, label="waypoints (truth)")
        for name, estimates in results.items():
            on = [e for e in estimates if e.floor == f]
            off = len(estimates) - len(on)
            if on:
                xy = np.array([[e.x, e.y] for e in on])
                ax.plot(
                    xy[:, 0],
                    xy[:, 1],
                    ".-",
                    color=METHOD_COLOURS.get(name),
                    lw=0.8,
                    ms=3,
                    alpha=0.8,
                    label=f"{name} ({off} of {len(estimates)} on a wrong floor)",
                )
        pad = 15.0
        ax.set_xlim(wp[:, 1].min() - pad, wp[:, 1].max() + pad)
        ax.set_ylim(wp[:, 2].min() - pad, wp[:, 2].max() + pad)


# --- the evaluation ------------------------------------------------------------------


@dataclass
class Evaluation:
    """Rows per method, and the estimates of the walks kept for plotting."""

    rows: list[Row]
    kept: dict[str, dict[str, list[Estimate]]] = field(default_factory=dict)
    learn_s: float = 0.0
    run_s: dict[str, float] = field(default_factory=dict)


def evaluate(
    site: SiteData,
    learned: Learned,
    walks: Sequence[Walk],
    methods: Sequence[str],
    *,
    keep: Iterable[str] = (),
    batched: bool = True,
    progress: Callable[[str, int], None] = lambda _m, _i: None,
) -> Evaluation:
    """Replay ``walks`` through every method; return their rows and the kept walks' estimates.

    ``batched`` runs the particle filter's walks as devices of one engine
    (the server's way, which sets its CPU per update); otherwise walk by walk.
    """
    keep = set(keep)
    rows: list[Row] = []
    kept: dict[str, dict[str, list[Estimate]]] = {w: {} for w in keep}
    run_s: dict[str, float] = {}
    for name in methods:
        started = time.perf_counter()
        if name in ("pf", "pf-radiomap") and batched:
            estimates, cpu, updates = replay_pf_batched(
                site, learned, walks, lambda i, _n=name: progress(_n, i), name
            )
        else:
            runner = make_runner(name, learned)
            estimates, cpu, updates = [], 0.0, 0
            for i, walk in enumerate(walks):
                result = runner(site, walk)
                estimates.append(result.estimates)
                cpu += result.cpu_s
                updates += result.updates
                progress(name, i + 1)
        scores = []
        for walk, est in zip(walks, estimates, strict=True):
            scores.append(score_walk(walk.waypoints, site.floor_index(walk), est))
            if walk.walk_id in keep:
                kept[walk.walk_id][name] = est
        rows.append(summarise(name, scores, cpu, updates))
        run_s[name] = time.perf_counter() - started
    return Evaluation(rows, kept, run_s=run_s)


def add_split_arguments(parser: argparse.ArgumentParser, validation_use: str) -> None:
    """Add the site and split options shared by the site1 evaluations."""
    parser.add_argument("--site", type=Path, default=None, help="default: <data>/ilc/site1")
    parser.add_argument(
        "--split",
        choices=["walk"],
        default="walk",
        help="held-out walks by a hash of the walk id (never by sample)",
    )
    parser.add_argument("--test-fraction", type=float, default=0.2)
    parser.add_argument(
        "--validation-fraction",
        type=float,
        default=0.0,
        help=f"carve this share out of training and {validation_use}",
    )


def split_and_learn(
    site_dir: Path, args: argparse.Namespace, status: Callable[[str], None] = lambda _: None
) -> tuple[SiteData, Learned, list[str], list[str], list[str]]:
    """Split site1's walk ids as ``args`` say, read the site and learn on the training walks.

    Returns the site, what was learned and the training, validation and test ids.
    """
    ids = [p.name.split(".")[0] for _, p in site_walks(site_dir)]
    train, validation, test = split_ids(
        [_IdOnly(i) for i in ids], args.test_fraction, args.validation_fraction
    )
    site = load_site(site_dir, train_ids=train)
    return site, learn(site, train, status=status), train, validation, test


def main(argv: Sequence[str] | None = None) -> None:
    """Learn on the training walks of site1, replay the held-out walks and print the table."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn
    from rich.table import Table

    parser = argparse.ArgumentParser(
        prog="locus eval ilc", description=__doc__.splitlines()[0] if __doc__ else None
    )
    add_split_arguments(parser, "evaluate on it instead of the test walks")
    parser.add_argument("--limit", type=int, help="at most this many evaluated walks (id order)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--plots", type=Path, help="folder for PNGs of a few walks")
    parser.add_argument("--n-plots", type=int, default=4)
    parser.add_argument(
        "--pf-unbatched",
        action="store_true",
        help="replay the particle filter walk by walk instead of all walks in one engine",
    )
    args = parser.parse_args(argv)

    console = Console(width=max(Console().width, 120))
    site_dir = args.site or data_dir() / "ilc" / "site1"
    t0 = time.perf_counter()
    with console.status("reading site1") as status:
        site, learned, train, validation, test = split_and_learn(
            site_dir, args, status=lambda s: status.update(s)
        )
        held_out = validation if args.validation_fraction > 0 else test
    learn_s = time.perf_counter() - t0
    chosen = set(held_out)
    walks = [w for w in sorted(site.walks, key=lambda w: w.walk_id) if w.walk_id in chosen]
    walks = [w for w in walks if w.waypoints.shape[0] >= 2][: args.limit]
    plotted = [w.walk_id for w in walks[: args.n_plots]] if args.plots else []
    n_plausible = sum(f.plausible for f in learned.fits)
    console.print(
        f"site1: {len(train)} training walks, {len(validation)} validation, {len(test)} test; "
        f"evaluating {len(walks)} {'validation' if args.validation_fraction > 0 else 'test'} walks"
    )
    console.print(
        f"learned in {learn_s:.0f} s: {len(site.tx_ids)} transmitters heard, "
        f"{len(learned.fits)} calibrated ({n_plausible} plausible, used by pf), "
        f"{sum(m.n_points for m in learned.maps)} radio-map points, "
        f"PDR K = {learned.pdr.weinberg_k:.4f}, heading offset = "
        f"{learned.pdr.heading_offset_deg:+.2f}°, held-out WKNN median "
        f"{learned.fingerprint_error_m:.2f} m (pf-radiomap's radius floor)"
    )
    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
    ) as bar:
        tasks = {m: bar.add_task(m, total=len(walks)) for m in args.methods}
        result = evaluate(
            site,
            learned,
            walks,
            args.methods,
            keep=plotted,
            batched=not args.pf_unbatched,
            progress=lambda m, i: bar.update(tasks[m], completed=i),
        )
    table = Table(title=f"ILC site1, {len(walks)} held-out walks (split by walk id)")
    for i, col in enumerate(COLUMNS):
        table.add_column(col, justify="left" if i == 0 else "right")
    for row in result.rows:
        table.add_row(*table_cells(row))
    console.print(table)
    console.print(
        "errors on the right floor only, against waypoints interpolated at the estimate's time; "
        "CPU per one-second batch of one device"
        + ("" if args.pf_unbatched else f" (pf: {len(walks)} walks batched in one engine)")
        + "; run times: "
        + ", ".join(f"{m} {s:.0f} s" for m, s in result.run_s.items())
    )
    if args.plots:
        args.plots.mkdir(parents=True, exist_ok=True)
        by_id = {w.walk_id: w for w in walks}
        for walk_id, results in result.kept.items():
            path = args.plots / f"site1_{by_id[walk_id].floor}_{walk_id}.png"
            plot_walk(path, site, by_id[walk_id], results)
            console.print(f"wrote {path}")


@dataclass(frozen=True)
class _IdOnly:
    """A walk reduced to its id, for ``split_ids`` before the walks are read."""

    walk_id: str


if __name__ == "__main__":
    main()
