"""Measure the particle filter on the BLE flat's robot test track, with and without walls.

Everything the filter knows is fitted on the calibration recording only:
each anchor's path loss (A, B, σ by least squares of RSSI on ln r, with r
the 3-D range from the tag 1.3 m above the floor) and the speed prior of the
motion model (Rayleigh scale from the robot's 1 s displacements). The
test track is then replayed as the one-second batches a receiver would
upload. It has no inertial stream, so particles move by the random walk
with that speed prior; the robot's recorded heading is ground truth and is
not used. Each estimate is compared with the tag's position interpolated at
the estimate's time (the newest reading it used), so the error includes the
filter's lag.

Run ``locus eval ble-flat`` (about a minute); ``--plots DIR`` writes the
estimates of one seed over the flat's plan, with and without walls.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from app.datasets import ble_flat
from app.engine.centroid import CentroidParams, WeightedCentroid
from app.engine.particle.params import ParticleFilterParams
from app.engine.pathloss import PathLossParams, fit_pathloss, ranges_3d
from app.engine.positioning import ParticleTracker, PositioningParams
from app.engine.samples import Batch, Estimate
from app.engine.site import Emitters, Floor, SiteModel
from app.evaluation.plots import plan_figure

PLAN_CELL_M = 0.1
"""Raster cell of the flat's plan: its walls are 11 to 17 cm thick and its
narrowest door 0.8 m wide, so a 0.25 m raster would close doorways."""

GRID_CELL_M = 0.25
"""Expected-RSSI raster cell for this small flat (1,000 cells per anchor)."""

SEEDS = (0, 1, 2, 3, 4)
"""Generator seeds: each configuration runs once per seed and errors are pooled."""


@dataclass(frozen=True)
class PathLoss:
    """Per-anchor path-loss fit: A (dBm at 1 m), B (dB per ln-metre), σ (dB), readings used."""

    A: np.ndarray
    B: np.ndarray
    sigma: np.ndarray
    n: np.ndarray


def fit_anchors(track: ble_flat.Track, anchors: ble_flat.Anchors, *, shared: bool) -> PathLoss:
    """Fit the path loss of every anchor on ``track``; ``shared`` fits one model for all."""
    min_range = PathLossParams().min_range_m
    r = ranges_3d(track.xy, anchors.xyz, ble_flat.TAG_HEIGHT_M, min_range)
    heard = np.isfinite(track.rssi)
    k = len(anchors.ids)
    if shared:
        a0, b0, s0 = fit_pathloss(r[heard], track.rssi[heard], min_range)
        return PathLoss(np.full(k, a0), np.full(k, b0), np.full(k, s0), heard.sum(axis=0))
    fits = [
        fit_pathloss(r[heard[:, j], j], track.rssi[heard[:, j], j], min_range) for j in range(k)
    ]
    a, b, s = (np.array(v) for v in zip(*fits, strict=True))
    return PathLoss(a, b, s, heard.sum(axis=0))


def speed_scale(runs: list[ble_flat.Track], window_ms: int = 1000) -> float:
    """Return the Rayleigh scale σ = √(mean v² / 2) of the tag's speed over ``window_ms`` steps."""
    speeds = []
    for run in runs:
        t = np.arange(run.t[0], run.t[-1], window_ms)
        xy = ble_flat.truth_at(run, t)
        speeds.append(np.hypot(*np.diff(xy, axis=0).T) / (window_ms / 1000.0))
    v = np.concatenate(speeds)
    # σ̂ = √(Σ v² / 2n), the maximum-likelihood Rayleigh scale
    return float(np.sqrt(np.mean(v * v) / 2.0))


def flat_site(fit: PathLoss, *, walls: bool) -> SiteModel:
    """Return the flat as a one-floor site with the six anchors as transmitters."""
    anchors = ble_flat.read_anchors()
    plan = ble_flat.floor_plan(ble_flat.read_layout(), PLAN_CELL_M, walls=walls)
    tx = Emitters(
        ids=tuple(str(i) for i in anchors.ids),
        floor=np.zeros(len(anchors.ids), np.int32),
        xyz=anchors.xyz,
        A=fit.A,
        B=fit.B,
        sigma=fit.sigma,
    )
    return SiteModel("ble_flat", (Floor("flat", 0, 3.0, plan),), tx)


def batches(track: ble_flat.Track, window_ms: int = 1000) -> list[Batch]:
    """Return the track's readings as consecutive batches of ``window_ms``."""
    readings = ble_flat.readings(track)
    key = readings.t // window_ms
    cuts = np.flatnonzero(np.diff(key)) + 1
    out = []
    for idx in np.split(np.arange(key.size), cuts):
        out.append(
            Batch(rssi=type(readings)(readings.t[idx], readings.tx[idx], readings.rssi[idx]))
        )
    return out


def replay_pf(
    track: ble_flat.Track, site: SiteModel, params: PositioningParams, seed: int
) -> list[Estimate]:
    """Run the particle filter over a track; return its estimates."""
    tracker = ParticleTracker(site, params, seed=seed)
    out: list[Estimate] = []
    for batch in batches(track):
        out.extend(tracker.process(batch))
    return out + tracker.flush()


def replay_centroid(track: ble_flat.Track, site: SiteModel) -> list[Estimate]:
    """Run the weighted centroid over a track: the reference without a model."""
    tracker = WeightedCentroid(site, CentroidParams())
    out: list[Estimate] = []
    for batch in batches(track):
        out.extend(tracker.process(batch))
    return out


def errors(track: ble_flat.Track, estimates: list[Estimate]) -> np.ndarray:
    """Return the distance (m) of each estimate from the truth at its time."""
    t = np.array([e.t for e in estimates])
    xy = np.array([[e.x, e.y] for e in estimates])
    return np.hypot(*(xy - ble_flat.truth_at(track, t)).T)


@dataclass(frozen=True)
class Row:
    """Pooled errors of one configuration on the test track and on the calibration runs.

    ``covered`` is the share of test estimates whose error is within their
    reported accuracy, the 68% radius (0.68 when that radius is honest).
    """

    name: str
    test: np.ndarray
    train: np.ndarray
    covered: float


def _stats(e: np.ndarray) -> str:
    """Return mean, median, p75 and p90 of errors as fixed-width text."""
    q = np.percentile(e, [50, 75, 90])
    return f"{e.mean():6.2f} {q[0]:6.2f} {q[1]:6.2f} {q[2]:6.2f}"


def evaluate(
    seeds: tuple[int, ...] = SEEDS, with_train: bool = True
) -> tuple[list[Row], dict[str, object]]:
    """Fit on the calibration recording, then measure every configuration."""
    cal = ble_flat.calibration()
    cal_runs = ble_flat.runs(cal)
    test = ble_flat.test_robot()
    anchors = ble_flat.read_anchors()
    fit = fit_anchors(cal, anchors, shared=False)
    shared = fit_anchors(cal, anchors, shared=True)
    sigma_v = speed_scale(cal_runs)
    loss = PathLossParams(receiver_height_m=ble_flat.TAG_HEIGHT_M, grid_cell_m=GRID_CELL_M)
    base = PositioningParams(filter=ParticleFilterParams(walk_speed_mps=sigma_v, pathloss=loss))
    coarse = replace(base, filter=replace(base.filter, pathloss=replace(loss, grid_cell_m=1.0)))
    configs = [
        ("PF, walls", fit, True, base),
        ("PF, no walls", fit, False, base),
        ("PF, walls, no refinement", fit, True, replace(base, position_gain=1.0)),
        ("PF, walls, shared path loss", shared, True, base),
        ("PF, walls, 1 m RSSI grid", fit, True, coarse),
    ]
    rows = []
    first_seed: dict[str, list[Estimate]] = {}
    for name, f, walls, params in configs:
        site = flat_site(f, walls=walls)
        runs = [replay_pf(test, site, params, s) for s in seeds]
        first_seed[name] = runs[0]
        test_e = np.concatenate([errors(test, r) for r in runs])
        accuracy = np.array([e.accuracy for r in runs for e in r])
        train_e = np.zeros(0)
        if with_train:
            train_e = np.concatenate(
                [errors(r, replay_pf(r, site, params, s)) for r in cal_runs for s in seeds[:1]]
            )
        rows.append(Row(name, test_e, train_e, float(np.mean(test_e <= accuracy))))
    site = flat_site(fit, walls=True)
    centroid = replay_centroid(test, site)
    centroid_e = errors(test, centroid)
    rows.append(
        Row(
            "weighted centroid (reference)",
            centroid_e,
            np.concatenate([errors(r, replay_centroid(r, site)) for r in cal_runs])
            if with_train
            else np.zeros(0),
            float(np.mean(centroid_e <= np.array([e.accuracy for e in centroid]))),
        )
    )
    info = {
        "fit": fit,
        "shared": shared,
        "speed": sigma_v,
        "n_test": len(test),
        "runs": len(cal_runs),
        "estimates": first_seed,
    }
    return rows, info


def plot_estimates(path: Path, estimates: dict[str, list[Estimate]]) -> None:
    """Save the test track's truth and each configuration's estimates over the walled plan."""
    test = ble_flat.test_robot()
    plan = ble_flat.floor_plan(ble_flat.read_layout(), PLAN_CELL_M, walls=True)
    anchors = ble_flat.read_anchors()
    with plan_figure(path, plan, "BLE flat, robot test track, seed 0", width_in=9.0) as ax:
        ax.plot(test.xy[:, 0], test.xy[:, 1], "k-", lw=2, label="robot (truth)")
        colours = ("tab:blue", "tab:orange")
        for (name, est), colour in zip(estimates.items(), colours, strict=False):
            xy = np.array([[e.x, e.y] for e in est])
            mean = errors(test, est).mean()
            ax.plot(
                xy[:, 0],
                xy[:, 1],
                ".-",
                color=colour,
                lw=0.7,
                ms=3,
                alpha=0.8,
                label=f"{name} (mean error {mean:.2f} m)",
            )
        ax.plot(anchors.xyz[:, 0], anchors.xyz[:, 1], "r^", ms=9, label="anchors")


def format_report(rows: list[Row], info: dict[str, object], seeds: tuple[int, ...]) -> str:
    """Render the fit and the error table as plain text."""
    fit = info["fit"]
    shared = info["shared"]
    assert isinstance(fit, PathLoss) and isinstance(shared, PathLoss)
    lines = [
        f"calibration: {info['runs']} runs; test track: {info['n_test']} rows",
        "path loss per anchor (calibration):  A dBm   B dB   sigma dB  sigma/B  readings",
    ]
    for i in range(fit.A.size):
        lines.append(
            f"  anchor {i + 1:<27d} {fit.A[i]:6.1f} {fit.B[i]:6.2f} {fit.sigma[i]:8.2f}"
            f" {fit.sigma[i] / fit.B[i]:8.2f} {int(fit.n[i]):9d}"
        )
    lines.append(
        f"  {'shared':34s} {shared.A[0]:6.1f} {shared.B[0]:6.2f} {shared.sigma[0]:8.2f}"
        f" {shared.sigma[0] / shared.B[0]:8.2f}"
    )
    lines += [
        f"speed prior (Rayleigh scale, calibration): {info['speed']:.3f} m/s",
        "",
        f"error (m), PF pooled over seeds {list(seeds)};"
        " train = calibration runs (in-sample fit, seed 0)",
        f"{'configuration':32s} {'test: mean':>10s} {'median':>6s} {'p75':>6s} {'p90':>6s}"
        f" {'in acc.':>7s}   {'train: mean':>11s} {'median':>6s} {'p75':>6s} {'p90':>6s}",
    ]
    for row in rows:
        train = _stats(row.train) if row.train.size else ""
        lines.append(f"{row.name:32s}     {_stats(row.test)} {row.covered:7.2f}        {train}")
    lines.append("in acc.: share of test errors within the reported 68% accuracy radius")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Print the fits and the error table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=len(SEEDS), help="number of seeds (0..n-1)")
    parser.add_argument("--no-train", action="store_true", help="skip the calibration-run rows")
    parser.add_argument(
        "--split",
        choices=["walk"],
        default="walk",
        help="by recording: fit on the calibration recording, score the robot test track",
    )
    parser.add_argument("--plots", type=Path, help="folder for a PNG of the test track")
    args = parser.parse_args(argv)
    seeds = tuple(range(args.seeds))
    rows, info = evaluate(seeds, with_train=not args.no_train)
    print(format_report(rows, info, seeds))
    if args.plots:
        args.plots.mkdir(parents=True, exist_ok=True)
        path = args.plots / "ble_flat_test_track.png"
        estimates = info["estimates"]
        assert isinstance(estimates, dict)
        plot_estimates(path, {k: estimates[k] for k in ("PF, walls", "PF, no walls")})
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
