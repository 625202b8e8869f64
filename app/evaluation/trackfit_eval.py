"""Measure the track fitter (Voronov et al., plus hypothesis search) on site1's held-out walks.

A fresh ``locus serve`` is surveyed with the training walks and builds its
radio maps through the API (split by walk, never by sample; the build chooses
the site's k-NN constants from those surveys alone). Every fit is then the
server's own: the body a device would upload goes through the service that
turns a ``POST /v1/tracks`` into a pool job (on the server's database,
nothing stored) and through the fit the pool runs (``run_fit``, which its
processes call before returning their free pages).

For every held-out walk the dead-reckoned track is built from the walk's own
IMU with the engine's PDR (steps with Weinberg length and rotation-vector
heading), starting at the first waypoint at its time; with ``--simulate`` it
is instead simulated from the surveyed path with a phone's errors (a
per-walker step scale, per-step length noise, an initial heading offset and a
slowly drifting gyro bias), seeded by the walk id. The upload is the start
point and the track as links (length, turn), one link per step or steps
merged into straight links between turns (Ramer–Douglas–Peucker).

Four settings: the first heading withheld (the paper's case) or given, and
WiFi anchors or none. Anchors are one of the walk's own scans every
``--scan-every`` seconds (its readings heard within 2 s of the scan), each
ending a link of its own at the step nearest in time (a device ends a
segment where it scans).

Positions are compared with the surveyed waypoints at the waypoints' times
(the first waypoint, the given start, excluded). A fitted link is a scaled
and rotated copy of its raw chord, so the steps inside a merged link are
carried along by the same similarity before interpolating in time. A fit that
fails is scored with the raw track (what a server falls back to) and counted.

Run ``locus eval trackfit [--simulate] [--validation-fraction 0.2]``; the
fitter's constants can be overridden for a study (``--anchor-weight`` …), and
the table then says so.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from app.core.config import Settings
from app.core.db import make_engine, make_sessionmaker
from app.datasets.ilc import Walk, fresh_wifi, imu_samples
from app.engine.pdr import detect_steps
from app.engine.trackfit.search import TrackSearchParams
from app.evaluation.ilc.recordings import MAX_WIFI_AGE_MS
from app.evaluation.ilc.server import SITE_ID, add_site_arguments, built_site, split_site
from app.evaluation.metrics import truth_at
from app.tracks.fitting import run_fit
from app.tracks.schemas import TrackCreate
from app.tracks.service import create_track

MERGE_TOLERANCE_M = 1.0
"""Steps are merged into one link while no step point strays further than
this from the link's chord (Ramer–Douglas–Peucker)."""

SCAN_EVERY_S = 20.0
"""One WiFi scan kept as an anchor this often: an energy-saving phone's 10–30 s."""

SETTINGS = (("unknown", False), ("unknown", True), ("known", False), ("known", True))
"""(first heading, WiFi anchors) of every fit of a walk."""

HYPOTHESES = ("full", "no-scale", "no-drift", "rotation-only")
"""Which motion errors the search hypothesises (``--hypotheses``)."""


@dataclass(frozen=True)
class SimulatedErrors:
    """A phone's dead-reckoning errors for ``--simulate`` (per walk, drawn from its id's seed).

    Attributes
    ----------
    step_m : float
        Step length (m) the true path is cut into.
    scale_sd : float
        Standard deviation of the walker's step-length scale (stride model off for this walker).
    length_sd : float
        Standard deviation of each step's relative length error.
    heading_sd : float
        Standard deviation (rad) of the initial heading offset.
    bias_sd : float
        Standard deviation (rad/s) of the initial gyro bias.
    bias_walk : float
        Random-walk density (rad/s per √s) of the bias: it varies slowly.
    turn_sd : float
        Standard deviation (rad) of each step's heading noise (sway, not accumulated).
    """

    step_m: float = 0.7
    scale_sd: float = 0.08
    length_sd: float = 0.05
    heading_sd: float = float(np.radians(5.0))
    bias_sd: float = float(np.radians(0.2))
    bias_walk: float = float(np.radians(0.02))
    turn_sd: float = float(np.radians(3.0))


@dataclass(frozen=True)
class RawTrack:
    """A walk's dead-reckoned track from its first waypoint.

    ``t`` (n + 1,) int64 ms and ``xy`` (n + 1, 2) m: the start, then the end
    of each step taken after the first and up to the last waypoint.
    """

    t: np.ndarray
    xy: np.ndarray


def raw_track(
    walk_t: np.ndarray,
    step_t: np.ndarray,
    length: np.ndarray,
    heading_deg: np.ndarray,
    start: np.ndarray,
) -> RawTrack:
    """Dead-reckon steps (length m, heading degrees clockwise from +y) from ``start``.

    ``walk_t`` is (t_first, t_last) of the waypoints; steps outside are dropped.
    """
    keep = (step_t > walk_t[0]) & (step_t <= walk_t[1]) & np.isfinite(heading_deg)
    # θ = π/2 - ψ: counter-clockwise from +x
    theta = np.pi / 2 - np.radians(heading_deg[keep])
    steps = length[keep, None] * np.column_stack([np.cos(theta), np.sin(theta)])
    xy = np.vstack([start, start + np.cumsum(steps, axis=0)])
    return RawTrack(t=np.r_[walk_t[0], step_t[keep]].astype(np.int64), xy=xy)


def simplify(xy: np.ndarray, tolerance: float) -> np.ndarray:
    """Return the indices of the vertices Ramer–Douglas–Peucker keeps, first and last included."""
    keep = np.zeros(len(xy), dtype=bool)
    keep[[0, -1]] = True
    stack = [(0, len(xy) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        a, b = xy[i], xy[j]
        d = b - a
        p = xy[i + 1 : j] - a
        norm = np.hypot(d[0], d[1])
        # distance to the chord: |d × p| / |d|, or |p| when the chord is a point
        dist = np.abs(d[0] * p[:, 1] - d[1] * p[:, 0]) / norm if norm > 0 else np.hypot(*p.T)
        k = int(np.argmax(dist))
        if dist[k] > tolerance:
            m = i + 1 + k
            keep[m] = True
            stack += [(i, m), (m, j)]
    return np.flatnonzero(keep)


def as_links(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return lengths (m), turns (rad, first 0) and directions of a polyline's links."""
    d = np.diff(xy, axis=0)
    direction = np.arctan2(d[:, 1], d[:, 0])
    # turn_i = wrap(θ_i - θ_{i-1}) into [-π, π)
    turn = np.r_[0.0, np.mod(np.diff(direction) + np.pi, 2 * np.pi) - np.pi]
    return np.hypot(d[:, 0], d[:, 1]), turn, direction


def carry_steps(raw: np.ndarray, vertex: np.ndarray, fitted: np.ndarray) -> np.ndarray:
    """Move every raw point by the similarity that maps its link's raw chord to the fitted one.

    Parameters
    ----------
    raw : ndarray, shape (n + 1, 2)
        Raw step points.
    vertex : ndarray of int, shape (k + 1,)
        Indices into ``raw`` of the link ends, from 0 to n.
    fitted : ndarray, shape (k' + 1, 2)
        Fitted link ends, k' ≤ k (fewer when the fit stopped early).

    Returns
    -------
    ndarray, shape (m + 1, 2)
        Fitted step points up to ``vertex[k']``.
    """
    z_raw = raw[:, 0] + 1j * raw[:, 1]
    z_fit = fitted[:, 0] + 1j * fitted[:, 1]
    out = [z_fit[:1]]
    for i in range(len(fitted) - 1):
        a, b = vertex[i], vertex[i + 1]
        chord = z_raw[b] - z_raw[a]
        # z = (x_i - x_{i-1}) / (r_b - r_a): scale and rotation of the link
        z = (z_fit[i + 1] - z_fit[i]) / chord if abs(chord) > 0 else 1.0
        out.append(z_fit[i] + z * (z_raw[a + 1 : b + 1] - z_raw[a]))
    pts = np.concatenate(out)
    return np.column_stack([pts.real, pts.imag])


def position_at(t_points: np.ndarray, xy: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Interpolate a timed polyline at times ``t`` (held at its ends), shape (len(t), 2)."""
    return np.column_stack([np.interp(t, t_points, xy[:, 0]), np.interp(t, t_points, xy[:, 1])])


def simulated_track(waypoints: np.ndarray, errors: SimulatedErrors, seed: int) -> RawTrack:
    """Dead-reckon the surveyed path with a phone's errors, from its first waypoint.

    The path (straight between waypoints, constant speed) is cut into steps of
    ``step_m``; each step keeps its true time, and its length and direction
    get the walker's scale, its own length noise, the heading offset plus the
    integrated drifting bias, and a little sway.
    """
    rng = np.random.default_rng(seed)
    seg = np.hypot(*np.diff(waypoints[:, 1:], axis=0).T)
    s_wp = np.r_[0.0, np.cumsum(seg)]
    s = np.arange(errors.step_m, s_wp[-1], errors.step_m)
    t = np.interp(s, s_wp, waypoints[:, 0])
    truth = np.column_stack(
        [np.interp(s, s_wp, waypoints[:, 1]), np.interp(s, s_wp, waypoints[:, 2])]
    )
    truth = np.vstack([waypoints[0, 1:], truth])
    t = np.r_[waypoints[0, 0], t]
    d = np.diff(truth, axis=0)
    n = d.shape[0]
    dt = np.diff(t) / 1000.0
    # β_k = β_0 + Σ w √dt (random walk); heading error e_k = e_0 + Σ β dt + sway
    bias = rng.normal(0.0, errors.bias_sd) + np.cumsum(
        rng.normal(0.0, errors.bias_walk, n) * np.sqrt(dt)
    )
    err = rng.normal(0.0, errors.heading_sd) + np.cumsum(bias * dt)
    err += rng.normal(0.0, errors.turn_sd, n)
    scale = rng.normal(1.0, errors.scale_sd) * (1.0 + rng.normal(0.0, errors.length_sd, n))
    z = (d[:, 0] + 1j * d[:, 1]) * scale * np.exp(1j * err)
    xy = np.vstack([truth[0], truth[0] + np.column_stack([z.real, z.imag]).cumsum(axis=0)])
    return RawTrack(t=t.astype(np.int64), xy=xy)


@dataclass(frozen=True)
class AnchorScan:
    """One scan a device uploads at raw step ``step``: its readings as the API takes them."""

    step: int
    wifi: list[dict[str, Any]]


def anchor_scans(walk: Walk, step_t: np.ndarray, every_s: float) -> list[AnchorScan]:
    """Return one of the walk's scans every ``every_s``, each at the raw step nearest in time.

    The k-th anchor is the first scan completed at least k·every_s after the
    start (scans before the last step only), with its readings heard within
    2 s of the scan. A device ends a segment where it takes a scan, so each
    anchor observes a link end of its own.
    """
    wifi = fresh_wifi(walk.wifi, MAX_WIFI_AGE_MS)
    out: list[AnchorScan] = []
    target = step_t[0] + every_s * 1000.0
    for t_scan in np.unique(wifi.t):
        if t_scan > step_t[-1]:
            break
        if t_scan < target:
            continue
        step = int(np.argmin(np.abs(step_t - t_scan)))
        if step > 0:
            row = wifi.t == t_scan
            readings = zip(wifi.bssid[row].tolist(), wifi.rssi[row].tolist(), strict=True)
            out.append(AnchorScan(step, [{"id": b, "rssi": float(r)} for b, r in readings]))
        target += every_s * 1000.0
    return out


def track_vertices(raw: RawTrack, links: str, scans: Sequence[AnchorScan]) -> np.ndarray:
    """Return the raw steps that end links: every step, or the merged track's corners, plus
    the step of every anchor scan (the device ends a segment where it scans)."""
    corners = np.arange(len(raw.xy)) if links == "step" else simplify(raw.xy, MERGE_TOLERANCE_M)
    return np.union1d(corners, [s.step for s in scans]).astype(np.int64)


def track_body(
    walk: Walk,
    raw: RawTrack,
    vertex: np.ndarray,
    scans: Sequence[AnchorScan],
    *,
    heading_known: bool,
) -> dict[str, Any]:
    """Return the ``POST /v1/tracks`` body of a raw track cut at ``vertex``, with ``scans`` on
    the links they end and the first link's heading when it is known."""
    lengths, turns, direction = as_links(raw.xy[vertex])
    wifi = {s.step: s.wifi for s in scans}
    segments = [
        {"t": int(raw.t[v]), "length": float(length), "turn": float(turn)}
        | ({"wifi": wifi[int(v)]} if int(v) in wifi else {})
        for v, length, turn in zip(vertex[1:], lengths, turns, strict=True)
    ]
    # engine direction (rad, CCW from +x) → API heading (degrees clockwise from +y, < 360)
    heading = round((90.0 - math.degrees(float(direction[0]))) % 360.0, 6) % 360.0
    return {
        "device_id": f"saver-{walk.walk_id}",
        "site_id": SITE_ID,
        "floor_id": walk.floor,
        "start": {"x": float(raw.xy[0, 0]), "y": float(raw.xy[0, 1])},
        "t0": int(raw.t[0]),
        "heading": heading if heading_known else None,
        "segments": segments,
    }


@dataclass(frozen=True)
class FitResult:
    """Errors (m) at the waypoints after the first, raw and fitted, of one walk and setting."""

    walk_id: str
    floor: str
    heading: str
    anchored: bool
    n_links: int
    n_anchors: int
    raw: np.ndarray
    fitted: np.ndarray
    failed: str | None
    seconds: float
    ambiguous: bool
    scale: float
    drift: float


def search_params(hypotheses: str, base: TrackSearchParams) -> TrackSearchParams:
    """Return ``base`` with the scale or drift hypotheses removed as ``hypotheses`` says."""
    if hypotheses in ("no-scale", "rotation-only"):
        base = replace(base, scales=(1.0,))
    if hypotheses in ("no-drift", "rotation-only"):
        base = replace(base, drifts=(0.0,))
    return base


Fitter = Callable[[dict[str, Any]], dict[str, Any]]
"""Fits one ``POST /v1/tracks`` body and returns the result the server stores."""


def evaluate_walk(
    walk: Walk, raw: RawTrack, vertex: np.ndarray, scans: Sequence[AnchorScan], fit: Fitter
) -> list[FitResult]:
    """Fit one raw track in every setting and return the errors at the waypoints."""
    wp = walk.waypoints
    t_eval = wp[1:, 0]
    truth, _ = truth_at(wp, t_eval)
    raw_err = np.linalg.norm(position_at(raw.t, raw.xy, t_eval) - truth, axis=1)
    out = []
    for heading, anchored in SETTINGS:
        body = track_body(
            walk, raw, vertex, scans if anchored else (), heading_known=heading == "known"
        )
        t0 = time.perf_counter()
        result = fit(body)
        seconds = time.perf_counter() - t0
        failed = (result.get("error") or "failed") if result["status"] != "done" else None
        if failed is None:
            ends = np.array([[p["x"], p["y"]] for p in result["points"]])
            pts = carry_steps(raw.xy, vertex, ends)
            fitted, fit_t = pts, raw.t[: len(pts)]
        else:
            fitted, fit_t = raw.xy, raw.t
        err = np.linalg.norm(position_at(fit_t, fitted, t_eval) - truth, axis=1)
        out.append(
            FitResult(
                walk.walk_id,
                walk.floor,
                heading,
                anchored,
                len(body["segments"]),
                int(result.get("anchors", 0)),
                raw_err,
                err,
                failed,
                seconds,
                bool(result.get("ambiguous", False)),
                float(result.get("scale", 1.0)),
                math.radians(float(result.get("drift", 0.0))),
            )
        )
    return out


def server_fitter(database_url: str, settings: Settings, search: TrackSearchParams) -> Fitter:
    """Return a fitter that makes each body's pool job as ``POST /v1/tracks`` does, on the
    server's database (nothing is stored), and runs it as the pool runs it."""
    sessions = make_sessionmaker(make_engine(database_url))

    def fit(body: dict[str, Any]) -> dict[str, Any]:
        with sessions() as db:
            _, job = create_track(db=db, body=TrackCreate.model_validate(body))
            db.rollback()
        job |= {"cell": settings.raster_cell, "time_limit_s": search.fit.time_limit_s}
        return run_fit(job, search)

    return fit


def format_summary(results: list[FitResult]) -> str:
    """Render raw and fitted mean / p50 / p95 per setting as a plain-text table."""
    header = (
        f"{'heading':<8} {'anchors':<8} {'walks':>5} {'raw mean':>8} {'raw p50':>7} "
        f"{'raw p95':>7} {'fit mean':>8} {'fit p50':>7} {'fit p95':>7} {'fit/raw':>7} "
        f"{'failed':>6} {'ambig':>5} {'sure mean':>9} {'sure raw':>8} {'s med':>6} {'s max':>6}"
    )
    lines = [header, "-" * len(header)]
    for heading, anchored in SETTINGS:
        rs = [r for r in results if r.heading == heading and r.anchored == anchored]
        if not rs:
            continue
        raw = np.concatenate([r.raw for r in rs])
        fit = np.concatenate([r.fitted for r in rs])
        secs = np.array([r.seconds for r in rs])
        sure = [r for r in rs if not r.ambiguous]
        sure_mean = np.concatenate([r.fitted for r in sure]).mean() if sure else np.nan
        sure_raw = np.concatenate([r.raw for r in sure]).mean() if sure else np.nan
        lines.append(
            f"{heading:<8} {'every ' + str(int(SCAN_EVERY_S)) + 's' if anchored else 'none':<8} "
            f"{len(rs):>5} {raw.mean():>8.2f} {np.median(raw):>7.2f} "
            f"{np.percentile(raw, 95):>7.2f} {fit.mean():>8.2f} {np.median(fit):>7.2f} "
            f"{np.percentile(fit, 95):>7.2f} {fit.mean() / raw.mean():>7.2f} "
            f"{sum(r.failed is not None for r in rs):>6} {sum(r.ambiguous for r in rs):>5} "
            f"{sure_mean:>9.2f} {sure_raw:>8.2f} {np.median(secs):>6.2f} {secs.max():>6.2f}"
        )
    return "\n".join(lines)


def per_floor(results: list[FitResult]) -> str:
    """Render fitted / raw mean per floor and setting (the check on more than one floor)."""
    floors = sorted({r.floor for r in results})
    lines = [
        f"{'floor':<6} {'walks':>5} "
        + " ".join(f"{h[:3]}+{'wifi' if a else 'none':<4}" for h, a in SETTINGS)
    ]
    for floor in floors:
        cells = []
        for heading, anchored in SETTINGS:
            rs = [
                r
                for r in results
                if r.floor == floor and (r.heading, r.anchored) == (heading, anchored)
            ]
            raw = np.concatenate([r.raw for r in rs])
            fit = np.concatenate([r.fitted for r in rs])
            cells.append(f"{fit.mean():>4.1f}/{raw.mean():<4.1f}")
        n = len({r.walk_id for r in results if r.floor == floor})
        lines.append(f"{floor:<6} {n:>5} " + " ".join(f"{c:<9}" for c in cells))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Fit every held-out site1 walk in the four settings on a server's build; print the errors."""
    parser = argparse.ArgumentParser(
        prog="locus eval trackfit", description=__doc__.splitlines()[0] if __doc__ else None
    )
    add_site_arguments(parser, "fit its walks instead of the test walks (for tuning)")
    parser.add_argument("--links", choices=("merged", "step"), default="merged")
    parser.add_argument("--scan-every", type=float, default=SCAN_EVERY_S)
    parser.add_argument("--hypotheses", choices=HYPOTHESES, default="full")
    parser.add_argument("--simulate", action="store_true", help="DR simulated from true paths")
    parser.add_argument("--limit", type=int, default=0, help="at most this many walks")
    settings = Settings()
    base = TrackSearchParams()
    parser.add_argument("--time-limit", type=float, default=settings.trackfit_time_limit_s)
    parser.add_argument("--screen-weight", type=float, default=base.screen_weight)
    parser.add_argument("--ambiguity-margin", type=float, default=base.ambiguity_margin)
    parser.add_argument("--scale-links", type=float, default=base.scale_links)
    parser.add_argument("--drift-seconds", type=float, default=base.drift_seconds)
    parser.add_argument("--anchor-weight", type=float, default=base.fit.anchor_weight)
    parser.add_argument("--anchor-sigma", type=float, default=base.fit.anchor_sigma)
    parser.add_argument("--anchor-cap", type=float, default=base.fit.anchor_cap)
    parser.add_argument("--quiet", action="store_true", help="no per-walk lines")
    args = parser.parse_args(argv)

    fit = replace(
        base.fit,
        time_limit_s=args.time_limit,
        anchor_weight=args.anchor_weight,
        anchor_sigma=args.anchor_sigma,
        anchor_cap=args.anchor_cap,
    )
    search = search_params(
        args.hypotheses,
        replace(
            base,
            fit=fit,
            screen_weight=args.screen_weight,
            scale_links=args.scale_links,
            ambiguity_margin=args.ambiguity_margin,
            drift_seconds=args.drift_seconds,
        ),
    )
    site_dir, floors, train, held = split_site(args)
    walks = held[: args.limit] if args.limit else held
    kind = "validation" if args.validation_fraction > 0 else "test"
    print(
        f"site {site_dir.name}: {len(walks)} {kind} walks, "
        f"{'simulated' if args.simulate else 'PDR'} tracks, {args.links} links, hypotheses "
        f"{args.hypotheses}, radio maps built by a server from {len(train)} training walks, "
        f"one scan every {args.scan_every:g} s, raster {settings.raster_cell} m",
        flush=True,
    )
    default_search, default_fit = asdict(base), asdict(base.fit)
    changed = {
        name: value
        for name, value in asdict(search).items()
        if name != "fit" and value != default_search[name]
    } | {
        f"fit.{name}": value
        for name, value in asdict(search.fit).items()
        if name != "time_limit_s" and value != default_fit[name]
    }
    if changed:
        print(f"fitter constants overridden (not the server's): {changed}")
    results: list[FitResult] = []
    with built_site(site_dir, floors, train, status=print) as (srv, _, build):
        print(f"build chose: {build.get('tuning')}", flush=True)
        fitter = server_fitter(srv.database_url, settings, search)
        for walk in walks:
            wp = walk.waypoints
            if args.simulate:
                raw = simulated_track(wp, SimulatedErrors(), seed=int(walk.walk_id[-8:], 16))
            else:
                if walk.acc.shape[0] == 0:
                    continue
                steps = detect_steps(imu_samples(walk))
                raw = raw_track(wp[[0, -1], 0], steps.t, steps.length, steps.heading, wp[0, 1:])
            if len(raw.xy) < 3:
                continue
            scans = anchor_scans(walk, raw.t.astype(float), args.scan_every)
            vertex = track_vertices(raw, args.links, scans)
            found = evaluate_walk(walk, raw, vertex, scans, fitter)
            results += found
            if not args.quiet:
                print(
                    f"{walk.walk_id:<26} {walk.floor:<3} links {found[0].n_links:>4} anchors "
                    f"{len(scans):>2} raw {found[0].raw.mean():>6.2f} fitted "
                    + " ".join(
                        f"{r.fitted.mean():>6.2f}{'?' if r.ambiguous else ' '}" for r in found
                    )
                    + f"  {max(r.seconds for r in found):.2f}s",
                    flush=True,
                )
    print()
    print("errors (m) at the waypoints after the first; failed fits scored with the raw track;")
    print("ambig: fits whose runner-up (a distinct track) scored within the ambiguity margin;")
    print("sure mean / sure raw: fitted / raw mean error of the fits not flagged ambiguous")
    print(format_summary(results))
    for r in results:
        if r.failed:
            print(f"failed: {r.walk_id} ({r.heading} heading, anchors {r.anchored}): {r.failed}")
    print()
    print("fitted / raw mean (m) per floor")
    print(per_floor(results))


if __name__ == "__main__":
    main()
