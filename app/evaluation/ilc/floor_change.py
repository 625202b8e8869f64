"""How fast the phone engine follows a change of floor, on joined held-out walks of site1.

Every site1 walk stays on one floor, so a floor change is made by joining
two held-out walks recorded on different floors: the second is shifted in
time to start where the first ends, as if the walker had stepped off an
escalator at the second walk's start. This is harsher than a real change (no
gradual fade of the old floor's access points on the way, no barometer: ILC
recorded none), so the latencies are an upper bound of what a walker sees.
Each walk is paired with the next held-out walk in id order on another floor
that lasts long enough to hear it (``MIN_SECOND_S``).

A fresh server is surveyed with the training walks and builds its radio map
through the API (``built_site``); every joined walk then goes through a
worker's device session on that build (``replay_stages``), the path the
server's workers run. The latency of a stage is the time from the change
until its positions are on the new floor for good (the first position after
which none is on another floor); a change never followed counts apart. The
positions before the change give each stage's share on a wrong floor while
the walker stays on one (every held-out walk is a first walk once).

Run ``locus eval ilc-floor-change [--validation-fraction 0.2] [--limit N]``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import TypeVar

import numpy as np

from app.core.config import Settings
from app.datasets.ilc import BeaconScan, Walk, WifiScan
from app.engine.samples import Estimate
from app.evaluation.ilc.ablation import FIXED_LAG, LIVE, load_engines, replay_stages
from app.evaluation.ilc.server import SITE_ID, add_site_arguments, built_site, split_site
from app.workers.trackers import SiteEngines

STAGES_TIMED = (LIVE, FIXED_LAG)
"""The live positions and the history as served (refined where refined)."""


def _shifted(rows: np.ndarray, dt: int) -> np.ndarray:
    out = rows.copy()
    out[:, 0] += dt
    return out


R = TypeVar("R", WifiScan, BeaconScan)


def _joined_readings(a: R, b: R, end: int, dt: int, times: tuple[str, ...]) -> R:
    """Return ``a``'s readings up to ``end`` then ``b``'s after it, ``b``'s ``times`` fields
    moved by ``dt``; every field is an array aligned with ``t``."""
    keep_a, keep_b = a.t <= end, b.t + dt > end

    def field_of_b(name: str) -> np.ndarray:
        values = getattr(b, name)[keep_b]
        return values + dt if name in times else values

    return replace(
        a,
        **{
            f.name: np.concatenate([getattr(a, f.name)[keep_a], field_of_b(f.name)])
            for f in fields(a)
        },
    )


def joined_walk(first: Walk, second: Walk) -> Walk:
    """Return ``first`` then ``second``, shifted to start at ``first``'s last waypoint.

    Each keeps its samples between its first and last waypoints; the joined
    walk is on ``second``'s floor (its waypoints are both walks').
    """
    end, start = int(first.waypoints[-1, 0]), int(second.waypoints[0, 0])
    dt = end - start

    def rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        b = _shifted(b, dt)
        return np.vstack([a[a[:, 0] <= end], b[b[:, 0] > end]])

    return replace(
        second,
        walk_id=f"{first.walk_id}-{second.walk_id}",
        acc=rows(first.acc, second.acc),
        gyro=rows(first.gyro, second.gyro),
        mag=rows(first.mag, second.mag),
        rot=rows(first.rot, second.rot),
        wifi=_joined_readings(first.wifi, second.wifi, end, dt, ("t", "last_seen")),
        beacons=_joined_readings(first.beacons, second.beacons, end, dt, ("t",)),
        waypoints=np.vstack([first.waypoints, _shifted(second.waypoints[1:], dt)]),
    )


def settle_latency(track: Sequence[Estimate], change_t: int, floor: int) -> float | None:
    """Return the seconds from ``change_t`` until ``track`` is on ``floor`` for good.

    None when its last position is on another floor (the change was never followed).
    """
    after = [e for e in track if e.t > change_t]
    if not after or after[-1].floor != floor:
        return None
    wrong = [e.t for e in after if e.floor != floor]
    if not wrong:
        return (after[0].t - change_t) / 1000.0
    settled = next(e.t for e in after if e.t > wrong[-1])
    return (settled - change_t) / 1000.0


MIN_SECOND_S = 30.0
"""Shortest second walk of a pair (s between its first and last waypoints): a walk of a few
seconds may end before the phone has scanned the new floor at all."""


def floor_pairs(walks: Sequence[Walk], limit: int) -> list[tuple[Walk, Walk]]:
    """Pair each walk (in id order) with the next one on another floor that lasts at least
    ``MIN_SECOND_S``; at most ``limit`` pairs."""
    ordered = sorted(walks, key=lambda w: w.walk_id)
    pairs = []
    for i, first in enumerate(ordered):
        nxt = next(
            (
                w
                for w in ordered[i + 1 :] + ordered[:i]
                if w.floor != first.floor
                and (w.waypoints[-1, 0] - w.waypoints[0, 0]) / 1000.0 >= MIN_SECOND_S
            ),
            None,
        )
        if nxt is not None:
            pairs.append((first, nxt))
    return pairs[:limit]


Quantiles = tuple[float, float, float]
"""Median, 90th percentile and maximum."""


def _quantiles(values: np.ndarray) -> Quantiles:
    """Return median, 90th percentile and maximum of the finite values (NaN for none)."""
    ok = values[np.isfinite(values)]
    if not ok.size:
        return np.nan, np.nan, np.nan
    return float(np.median(ok)), float(np.percentile(ok, 90)), float(ok.max())


@dataclass(frozen=True)
class FloorChanges:
    """Per stage: each joined walk's latency from the change and from the new floor's first
    WiFi scan (s; NaN where the change was never followed), and the positions before the
    change on a wrong floor, of all before it."""

    latency: dict[str, np.ndarray]
    after_scan: dict[str, np.ndarray]
    wrong_before: dict[str, tuple[int, int]]

    def rows(self) -> list[tuple[str, int, Quantiles, Quantiles, int, float]]:
        """Return per stage: name, walks, (p50, p90, max) from the change, the same from the
        first scan, changes never followed, % on a wrong floor before the change."""
        out = []
        for name, lat in self.latency.items():
            wrong, total = self.wrong_before[name]
            out.append(
                (
                    name,
                    int(lat.size),
                    _quantiles(lat),
                    _quantiles(self.after_scan[name]),
                    int(np.isnan(lat).sum()),
                    100.0 * wrong / total if total else np.nan,
                )
            )
        return out


def measure_floor_changes(
    engines: SiteEngines,
    site_id: str,
    pairs: Sequence[tuple[Walk, Walk]],
    floors: Sequence[str],
    *,
    wifi_times: str,
    settings: Settings,
) -> FloorChanges:
    """Replay every joined pair through a device session and time its floor change."""
    latency: dict[str, list[float]] = {name: [] for name in STAGES_TIMED}
    after_scan: dict[str, list[float]] = {name: [] for name in STAGES_TIMED}
    wrong = dict.fromkeys(STAGES_TIMED, 0)
    before = dict.fromkeys(STAGES_TIMED, 0)
    for first, second in pairs:
        walk = joined_walk(first, second)
        run = replay_stages(
            engines,
            site_id,
            [walk],
            floors,
            wifi_times=wifi_times,
            settings=settings,
            keep=[walk.walk_id],
        )
        change_t = int(first.waypoints[-1, 0])
        scans = walk.wifi.t[walk.wifi.t > change_t]
        scan_s = (int(scans.min()) - change_t) / 1000.0 if scans.size else np.nan
        for name in STAGES_TIMED:
            track = run.tracks[walk.walk_id][name]
            got = settle_latency(track, change_t, floors.index(walk.floor))
            latency[name].append(np.nan if got is None else got)
            after_scan[name].append(np.nan if got is None else got - scan_s)
            first_floor = [e.floor for e in track if e.t <= change_t]
            before[name] += len(first_floor)
            wrong[name] += sum(f != floors.index(first.floor) for f in first_floor)
    return FloorChanges(
        {k: np.array(v, dtype=float) for k, v in latency.items()},
        {k: np.array(v, dtype=float) for k, v in after_scan.items()},
        {k: (wrong[k], before[k]) for k in STAGES_TIMED},
    )


def main(argv: Sequence[str] | None = None) -> None:
    """Build a server from the training walks, replay joined held-out walks, print latencies."""
    parser = argparse.ArgumentParser(
        prog="locus eval ilc-floor-change",
        description=__doc__.splitlines()[0] if __doc__ else None,
    )
    add_site_arguments(parser, "join its walks instead of the test walks")
    parser.add_argument("--limit", type=int, default=1000, help="at most this many pairs")
    args = parser.parse_args(argv)
    site_dir, floors, train, held = split_site(args)
    pairs = floor_pairs(held, args.limit)
    print(f"{len(pairs)} pairs of held-out walks on different floors, {len(train)} surveys")
    with built_site(site_dir, floors, train, wifi_times=args.wifi_times) as (srv, _, _):
        settings = Settings()
        engines = load_engines(srv.database_url, SITE_ID, settings)
        changes = measure_floor_changes(
            engines, SITE_ID, pairs, floors, wifi_times=args.wifi_times, settings=settings
        )
    print("latency (s): from the change, and from the new floor's first WiFi scan, until the")
    print("positions stay on the new floor; wrong before: positions on a wrong floor before")
    print("the change (the first walk's, every held-out walk once)")
    print(
        f"{'stage':<26} {'pairs':>5} {'p50':>5} {'p90':>5} {'max':>5}  {'scan p50':>8} "
        f"{'p90':>5} {'max':>5} {'never':>5} {'wrong before':>12}"
    )
    for name, n, change, scan, never, share in changes.rows():
        print(
            f"{name:<26} {n:>5} {change[0]:>5.1f} {change[1]:>5.1f} {change[2]:>5.1f}  "
            f"{scan[0]:>8.1f} {scan[1]:>5.1f} {scan[2]:>5.1f} {never:>5} {share:>11.2f}%"
        )


if __name__ == "__main__":
    main()
