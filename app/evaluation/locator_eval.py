"""Measure locator-mode tracking on the BLE locator tracks, leave one track out.

For each of the 5 tracks the path loss ``rssi = A − B ln r`` is fitted on the
other 4 (truth positions known there), either per locator or pooled over all
locators ("global"); the tag's known height is the median truth height of the
other tracks. On the held-out track:

* ``lsq``: a 2-D RSSI least-squares fix every 0.5 s from each locator's mean
  RSSI over the last 2 s, started at the centroid of the 3 strongest.
* ``ekf``: :class:`~app.engine.locator_tracker.LocatorTracker` (the same fixes, started
  at the filter's position, then the EKF with course from motion), open floor.
  Its fix σ floor (the model error D does not contain) is calibrated on the
  4 training tracks' raw fixes.
* ``ekf+plan``: the same, positions projected onto the occupancy grid
  (furniture blocked) after each update.

Errors are horizontal distances (m) to the truth interpolated at each
estimate's time. Run ``python -m app.evaluation.locator_eval`` (seconds).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace

import numpy as np

from app.datasets.ble_locator import (
    Locators,
    Track,
    locator_site,
    read_locators,
    read_occupancy,
    read_track,
    track_names,
)
from app.engine.lateration.solver import solve
from app.engine.locator_tracker import (
    LocatorTracker,
    LocatorTrackerParams,
    strongest_centroid,
    window_means,
)
from app.engine.samples import Batch, Sightings
from app.engine.site import SiteModel

BATCH_MS = 1000
"""Sightings reach the tracker in batches of this much measurement time."""

MIN_B = 1.0
"""Fitted path-loss slopes are floored here (dB per ln m): a flat fit carries no range."""


@dataclass(frozen=True)
class PathLoss:
    """Path-loss parameters per locator (K,): A (dBm), B (dB per ln m), sigma (dB)."""

    A: np.ndarray
    B: np.ndarray
    sigma: np.ndarray


def distances(track: Track, locators: Locators) -> np.ndarray:
    """Return the true tag–locator distance (m) of every sighting."""
    return np.linalg.norm(track.truth - locators.xyz[track.locator], axis=1)


def fit_path_loss(tracks: list[Track], locators: Locators, pooled: bool) -> PathLoss:
    """Fit ``rssi = A − B ln d`` by least squares on the tracks' sightings and truth.

    ``pooled``: one (A, B, σ) for all locators; otherwise one per locator.
    """
    d = np.concatenate([distances(tr, locators) for tr in tracks])
    rssi = np.concatenate([tr.rssi for tr in tracks])
    loc = np.concatenate([tr.locator for tr in tracks])
    k = len(locators.ids)
    groups = [np.ones(loc.size, dtype=bool)] if pooled else [loc == i for i in range(k)]
    params = []
    for g in groups:
        X = np.column_stack([np.ones(g.sum()), -np.log(d[g])])
        # [A, B] = argmin Σ (rssi − A + B ln d)²
        (a, b), *_ = np.linalg.lstsq(X, rssi[g], rcond=None)
        sigma = float(np.std(rssi[g] - X @ np.array([a, b])))
        params.append((a, max(b, MIN_B), sigma))
    table = np.array(params * (k if pooled else 1))
    return PathLoss(A=table[:, 0], B=table[:, 1], sigma=table[:, 2])


def truth_at(track: Track, t: np.ndarray) -> np.ndarray:
    """Return the track's truth (M, 2) interpolated at times ``t`` (ms)."""
    return np.column_stack([np.interp(t, track.t, track.truth[:, k]) for k in range(2)])


def raw_fixes(
    track: Track, site: SiteModel, params: LocatorTrackerParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return times, xy (F, 2) and D_xy (F, 2, 2) of the windowed RSSI fixes, no filter."""
    loc = site.locators
    step = params.step_ms
    times = np.arange((int(track.t[0]) // step + 1) * step, int(track.t[-1]) + 1, step)
    mean, count = window_means(
        track.t, track.locator, track.rssi, len(loc), times, params.window_ms
    )
    std = loc.sigma[None, :] / np.sqrt(np.clip(count, 1, params.max_samples))
    x0 = strongest_centroid(mean, loc.xyz)
    x0[:, 2] = params.tag_height_m
    fix = solve(
        "rssi",
        loc.xyz,
        mean,
        std,
        A=loc.A,
        B=loc.B,
        height=params.tag_height_m,
        dims=2,
        x0=x0,
        params=params.lateration,
    )
    return times[fix.ok], fix.position[fix.ok, :2], fix.covariance[fix.ok, :2, :2]


def calibrate_floor(tracks: list[Track], site: SiteModel, params: LocatorTrackerParams) -> float:
    """Return the σ (m) the fixes miss on ``tracks``: s² = max(0, mean |e|²/2 − mean tr D/2)."""
    sq = []
    var = []
    for tr in tracks:
        t, xy, D = raw_fixes(tr, site, params)
        sq.append(np.sum((xy - truth_at(tr, t)) ** 2, axis=1))
        var.append(np.trace(D, axis1=1, axis2=2))
    # per-coordinate variance of the error minus what D explains
    return float(
        np.sqrt(max(0.0, np.mean(np.concatenate(sq)) / 2 - np.mean(np.concatenate(var)) / 2))
    )


def run_tracker(
    track: Track, site: SiteModel, params: LocatorTrackerParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Feed the track's sightings in 1-s batches; return times, xy and accuracy radii."""
    tracker = LocatorTracker(site, params)
    t_out: list[int] = []
    xy: list[tuple[float, float]] = []
    acc: list[float] = []
    edges = np.arange(track.t[0], track.t[-1] + BATCH_MS, BATCH_MS)
    cut = np.searchsorted(track.t, edges)
    for a, b in zip(cut[:-1], cut[1:], strict=True):
        seen = Sightings(t=track.t[a:b], locator=track.locator[a:b], rssi=track.rssi[a:b])
        for est in tracker.process(Batch(sightings=seen)):
            t_out.append(est.t)
            xy.append((est.x, est.y))
            acc.append(est.accuracy)
    return np.array(t_out, dtype=np.int64), np.array(xy).reshape(-1, 2), np.array(acc)


def main(argv: list[str] | None = None) -> None:
    """Print mean and 75th percentile of the horizontal error per track and method."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--occupancy-cell", type=float, default=0.2)
    args = parser.parse_args(argv)

    locators = read_locators()
    names = track_names()
    tracks = {n: read_track(n, locators) for n in names}
    plan = read_occupancy(args.occupancy_cell)
    methods = [f"{m}/{pl}" for pl in ("loc", "global") for m in ("lsq", "ekf", "ekf+plan")]
    errors: dict[str, dict[str, np.ndarray]] = {m: {} for m in methods}
    coverage: dict[str, list[float]] = {m: [] for m in methods if "ekf" in m}
    floors: dict[str, list[float]] = {"loc": [], "global": []}
    for name in names:
        train = [tracks[n] for n in names if n != name]
        test = tracks[name]
        height = float(np.median(np.concatenate([tr.truth[:, 2] for tr in train])))
        params = LocatorTrackerParams(tag_height_m=height, project_to_plan=False)
        for pooled, tag in ((False, "loc"), (True, "global")):
            pl = fit_path_loss(train, locators, pooled)
            open_site = locator_site(locators, pl.A, pl.B, pl.sigma)
            floor_m = calibrate_floor(train, open_site, params)
            floors[tag].append(floor_m)
            tuned = replace(params, fix_std_floor_m=floor_m)
            t, xy, _ = raw_fixes(test, open_site, tuned)
            errors[f"lsq/{tag}"][name] = np.hypot(*(xy - truth_at(test, t)).T)
            for method, site, p in (
                ("ekf", open_site, tuned),
                (
                    "ekf+plan",
                    locator_site(locators, pl.A, pl.B, pl.sigma, plan),
                    replace(tuned, project_to_plan=True),
                ),
            ):
                t, xy, acc = run_tracker(test, site, p)
                err = np.hypot(*(xy - truth_at(test, t)).T)
                errors[f"{method}/{tag}"][name] = err
                coverage[f"{method}/{tag}"].append(float(np.mean(err <= acc)))

    print("path loss per locator (loc) or pooled (global), fitted on the other 4 tracks")
    for tag, values in floors.items():
        print(
            f"fix σ floor calibrated on the other 4 tracks ({tag}): "
            + ", ".join(f"{v:.2f}" for v in values)
            + " m"
        )
    print("horizontal error mean / p75 (m) per held-out track")
    print(f"{'track':>26} " + " ".join(f"{m:>15}" for m in methods))
    for name in [*names, "all"]:
        cells = []
        for m in methods:
            e = np.concatenate(list(errors[m].values())) if name == "all" else errors[m][name]
            cells.append(f"{np.mean(e):7.2f}/{np.quantile(e, 0.75):.2f}")
        print(f"{name:>26} " + " ".join(f"{c:>15}" for c in cells))
    print()
    print("estimates per track: " + ", ".join(f"{n} {errors['ekf/loc'][n].size}" for n in names))
    print(
        "share of EKF errors within the reported 68 % accuracy radius: "
        + ", ".join(f"{m} {np.mean(c):.2f}" for m, c in coverage.items())
    )


if __name__ == "__main__":
    main()
