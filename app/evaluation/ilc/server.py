"""Site1's walk split measured through a running ``locus serve``, as any client sees it.

A fresh server (its own SQLite database in a temporary folder, one filter
worker) is started; the floors and the training walks go in as surveys
through the HTTP API, the radio map is built through it (so the build chooses
the site's constants from those surveys alone), and every held-out walk is
posted as one-second batches with ``?wait=true``. The positions that come
back are scored as the in-process rows are. Nothing of the engine is
assembled here: the figure is the server's.

The same walks then go through the phone engine in process, stage by stage,
on the site read back from the server's own database and assembled as its
workers assemble it (``app.evaluation.ilc.ablation``): its fixed-lag row is
the server's row computed without HTTP, and the rows before it show what
each stage adds.

WiFi goes as phones send it: every reading of every scan, stale cached ones
included, either with the scan's time as ``t`` and the access point's own
``last_seen`` (``scan``), or with each reading's last-seen time as its ``t``
(``reading``), leaving the server to group readings into scans.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.core.config import Settings
from app.datasets import data_dir
from app.datasets.ilc import Walk, read_floor, read_walk, site_walks
from app.evaluation.ilc.ablation import (
    FIXED_LAG,
    FULL,
    LIVE,
    StageScores,
    load_engines,
    replay_stages,
)
from app.evaluation.ilc.experiment import add_split_arguments
from app.evaluation.ilc.knn_baseline import scan_knn_scores
from app.evaluation.ilc.plots import plot_on_plan
from app.evaluation.ilc.recordings import PLAN_CELL_M
from app.evaluation.ilc.score import (
    WalkScore,
    estimates_from_positions,
    score_walk,
    summarise,
)
from app.evaluation.ilc.table import COLUMNS, table_cells
from app.evaluation.markdown import markdown_table
from app.evaluation.split import split_ids, walk_unit
from app.geometry.floormap import parse_floor_map
from app.geometry.raster import floor_plan
from app.importers.ilc import WIFI_TIMES, survey_body, walk_samples
from app.replay import replay_samples

SITE_ID = "eval-site1"
STARTUP_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class ServerRun:
    """What a through-server evaluation measured: the build's summary and each walk's score."""

    build: dict[str, Any]
    scores: list[WalkScore]
    wall_s: float
    positions: dict[str, list[dict[str, Any]]]
    stages: StageScores | None = None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LocalServer:
    """A ``locus serve`` subprocess on a free port with its own database, stopped on exit."""

    def __init__(self, home: Path, workers: int = 1, env: dict[str, str] | None = None) -> None:
        self.port = _free_port()
        self.key = secrets.token_urlsafe(24)
        self.url = f"http://127.0.0.1:{self.port}"
        self.database_url = f"sqlite:///{(home / 'locus.db').resolve()}"
        env = os.environ | {"LOCUS_ADMIN_KEY": self.key} | (env or {})
        command = [sys.executable, "-m", "app.cli", "serve", "--port", str(self.port)]
        command += ["--home", str(home), "--workers", str(workers)]
        self.log = (home / "server.log").open("w")
        self.process = subprocess.Popen(command, env=env, stdout=self.log, stderr=self.log)

    def __enter__(self) -> LocalServer:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                self.log.close()
                raise RuntimeError(f"locus serve exited with {self.process.returncode}")
            try:
                if httpx.get(f"{self.url}/readyz", timeout=1).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        # no __exit__ follows a failed __enter__: stop the server here
        self.__exit__()
        raise RuntimeError(f"locus serve did not become ready in {STARTUP_TIMEOUT_S:.0f} s")

    def __exit__(self, *exc: object) -> None:
        self.process.terminate()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
        self.log.close()


def _upload_site(
    http: httpx.Client, site_dir: Path, floors: Sequence[str], train: Sequence[Walk], wifi: str
) -> None:
    http.put(f"/v1/sites/{SITE_ID}", json={"name": "ILC site1"}).raise_for_status()
    for name in floors:
        geojson = read_floor(site_dir / name).geojson
        http.put(f"/v1/sites/{SITE_ID}/floors/{name}", json=geojson).raise_for_status()

    def body(walk: Walk) -> dict[str, Any]:
        return survey_body(walk, device_id=f"survey-{walk.walk_id}", wifi_times=wifi)

    with ThreadPoolExecutor(max_workers=2) as pool:
        for b in pool.map(body, train):
            r = http.post(f"/v1/sites/{SITE_ID}/surveys", json=b)
            if r.status_code != 201:
                raise RuntimeError(f"survey {b['name']} refused: {r.status_code} {r.text[:300]}")


@contextmanager
def built_site(
    site_dir: Path,
    floors: Sequence[str],
    train: Sequence[Walk],
    *,
    wifi_times: str = "scan",
    tuning: bool = True,
    status: Callable[[str], None] = lambda _: None,
) -> Iterator[tuple[LocalServer, httpx.Client, dict[str, Any]]]:
    """Start a fresh server, survey it with ``train`` and build its radio map through the API;
    yield the server, a client with the admin key and the build's summary."""
    if wifi_times not in WIFI_TIMES:
        raise ValueError(f"wifi_times must be one of {WIFI_TIMES}")
    with (
        tempfile.TemporaryDirectory(prefix="locus-eval-") as home,
        LocalServer(Path(home), env={"LOCUS_RADIOMAP_TUNING": str(tuning).lower()}) as srv,
    ):
        headers = {"Authorization": f"Bearer {srv.key}"}
        with httpx.Client(base_url=srv.url, headers=headers, timeout=1800) as http:
            status(f"uploading {len(floors)} floors and {len(train)} surveys")
            _upload_site(http, site_dir, floors, train, wifi_times)
            status("building the radio map through the API")
            r = http.post(f"/v1/sites/{SITE_ID}/radiomap/build")
            r.raise_for_status()
            yield srv, http, r.json()


def evaluate_through_server(
    site_dir: Path,
    floors: Sequence[str],
    train: Sequence[Walk],
    test: Sequence[Walk],
    *,
    wifi_times: str = "scan",
    tuning: bool = True,
    with_stages: bool = True,
    keep: Sequence[str] = (),
    status: Callable[[str], None] = lambda _: None,
    progress: Callable[[int], None] = lambda _: None,
) -> ServerRun:
    """Start a server, survey and build it from ``train``, replay ``test`` and score it;
    ``with_stages``, also score each stage of the phone engine in process on its build,
    keeping the stages' estimates of the walks named in ``keep``."""
    with built_site(
        site_dir, floors, train, wifi_times=wifi_times, tuning=tuning, status=status
    ) as (srv, http, build):
        status("replaying the held-out walks")
        started = time.perf_counter()
        scores, positions = [], {}
        for i, walk in enumerate(test):
            got = replay_samples(
                http,
                walk_samples(walk, wifi_times=wifi_times),
                site_id=SITE_ID,
                device_id=f"replay-{walk.walk_id}",
                sent_at={"wifi": walk.wifi.t.tolist()},
            )
            positions[walk.walk_id] = got
            estimates = estimates_from_positions(got, floors)
            scores.append(score_walk(walk.waypoints, floors.index(walk.floor), estimates))
            progress(i + 1)
        wall_s = time.perf_counter() - started
        stages = None
        if with_stages:
            status("the same walks in process, stage by stage, on the server's build")
            settings = Settings()
            engines = load_engines(srv.database_url, SITE_ID, settings)
            stages = replay_stages(
                engines,
                SITE_ID,
                test,
                floors,
                wifi_times=wifi_times,
                settings=settings,
                keep=keep,
            )
    return ServerRun(build, scores, wall_s, positions, stages)


def _plot_stages(
    folder: Path, site_dir: Path, floors: Sequence[str], walks: Sequence[Walk], stages: StageScores
) -> None:
    """Draw the kept walks' tracking stages against their truth, one PNG a walk."""
    folder.mkdir(parents=True, exist_ok=True)
    by_id = {w.walk_id: w for w in walks}
    for walk_id, tracks in stages.tracks.items():
        walk = by_id[walk_id]
        f = floors.index(walk.floor)
        plan = floor_plan(
            parse_floor_map(read_floor(site_dir / walk.floor).geojson), cell=PLAN_CELL_M
        )
        shown = {name: tracks[name] for name in (LIVE, FIXED_LAG, FULL)}
        plot_on_plan(folder / f"{walk.floor}_{walk_id}.png", plan, f, walk, shown)


def louder(walk: Walk, offset_db: float) -> Walk:
    """Return the walk as a phone hearing every access point ``offset_db`` louder hears it."""
    if offset_db == 0.0:
        return walk
    return replace(walk, wifi=replace(walk.wifi, rssi=walk.wifi.rssi + offset_db))


def turned(walk: Walk, offset_deg: float) -> Walk:
    """Return the walk as a phone whose every heading is ``offset_deg`` clockwise of the
    walking direction reports it (carried turned in a pocket or a hand).

    The rotation vector (device to east-north-up, w implied non-negative) is
    turned about the vertical: q' = q_z(-offset) q.
    """
    if offset_deg == 0.0 or not walk.rot.size:
        return walk
    t, x, y, z = walk.rot.T
    w = np.sqrt(np.clip(1.0 - x**2 - y**2 - z**2, 0.0, None))
    half = np.radians(-offset_deg) / 2.0
    c, s = np.cos(half), np.sin(half)
    # (c + s k)(w + x i + y j + z k)
    q = np.stack([c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w])
    q = np.where(q[0] < 0, -q, q)
    return replace(walk, rot=np.column_stack([t, q[1], q[2], q[3]]))


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Parse the options of ``locus eval ilc``."""
    parser = argparse.ArgumentParser(
        prog="locus eval ilc", description=__doc__.splitlines()[0] if __doc__ else None
    )
    add_site_arguments(parser, "evaluate on it instead of the test walks")
    parser.add_argument("--limit", type=int, help="at most this many evaluated walks (id order)")
    parser.add_argument(
        "--no-tuning",
        action="store_true",
        help="the build keeps the engines' hand-set defaults instead of choosing constants",
    )
    parser.add_argument(
        "--rssi-offset",
        type=float,
        default=0.0,
        help="the held-out walks' phones hear WiFi this many dB louder than the survey's "
        "(another make of phone)",
    )
    parser.add_argument(
        "--heading-offset",
        type=float,
        default=0.0,
        help="the held-out walks' phones report every heading this many degrees clockwise "
        "of the walking direction (a phone carried turned)",
    )
    parser.add_argument("--save", type=Path, help="write the positions and summary as JSON")
    parser.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    parser.add_argument("--plots", type=Path, help="folder for PNGs of a few walks' stages")
    parser.add_argument("--n-plots", type=int, default=4, help="walks plotted (evenly spread)")
    return parser.parse_args(argv)


def split_site(args: argparse.Namespace) -> tuple[Path, list[str], list[Walk], list[Walk]]:
    """Return the site folder, its floors (by level), the surveyed training walks and the
    held-out walks (validation or test, at least two waypoints, id order) the options name."""
    site_dir = args.site or data_dir() / "ilc" / "site1"
    pairs = [(f, p) for f, p in site_walks(site_dir) if not args.floors or f in args.floors]
    ids = [path.name.split(".")[0] for _, path in pairs]
    train, validation, test = split_ids(ids, args.test_fraction, args.validation_fraction)
    # an independent hash of the id picks the surveyed share
    train = [w for w in train if walk_unit(f"{w}/survey") < args.train_share]
    held_ids = set(validation if args.validation_fraction > 0 else test)
    surveyed = set(train) - set(validation)
    if args.survey_walks is not None:
        floor_of = {path.name.split(".")[0]: f for f, path in pairs}
        surveyed = set(thin_surveys(sorted(surveyed), floor_of, args.survey_walks))
    walks = [read_walk(path, floor) for floor, path in pairs]
    floors = sorted({f for f, _ in pairs}, key=lambda n: read_floor(site_dir / n).level)
    held = sorted(
        (w for w in walks if w.walk_id in held_ids and w.waypoints.shape[0] >= 2),
        key=lambda w: w.walk_id,
    )
    return site_dir, floors, [w for w in walks if w.walk_id in surveyed], held


def thin_surveys(walk_ids: Sequence[str], floor_of: dict[str, str], per_floor: int) -> list[str]:
    """Return at most ``per_floor`` of the walks of each floor, the same ones on every run.

    Walks are ranked on each floor by an independent hash of their id, so a
    thinner survey is a subset of a thicker one: the walks a site surveyed
    in an afternoon rather than in a week.
    """
    by_floor: dict[str, list[str]] = {}
    for walk_id in sorted(walk_ids, key=lambda w: walk_unit(f"{w}/thin")):
        by_floor.setdefault(floor_of[walk_id], []).append(walk_id)
    return sorted(w for walks in by_floor.values() for w in walks[:per_floor])


def add_site_arguments(parser: argparse.ArgumentParser, validation_use: str) -> None:
    """Add the split, floor subset, surveyed share and WiFi timing options."""
    add_split_arguments(parser, validation_use)
    parser.add_argument("--floors", nargs="+", help="only these floors (a smaller building)")
    parser.add_argument(
        "--train-share",
        type=float,
        default=1.0,
        help="survey only this share of the training walks (by walk id hash)",
    )
    parser.add_argument(
        "--survey-walks",
        type=int,
        default=None,
        metavar="N",
        help="survey at most N training walks a floor (chosen by walk id hash)",
    )
    parser.add_argument("--wifi-times", choices=WIFI_TIMES, default="scan")


def main(argv: Sequence[str] | None = None) -> None:
    """Run site1's walk split through a fresh server and print its row and chosen constants."""
    from rich.console import Console
    from rich.progress import Progress
    from rich.table import Table

    args = parse_args(argv)
    console = Console(width=max(Console().width, 160))
    site_dir, floors, train_walks, held = split_site(args)
    held = [turned(louder(w, args.rssi_offset), args.heading_offset) for w in held[: args.limit]]
    console.print(
        f"{len(floors)} floors, {len(train_walks)} survey walks, {len(held)} held-out walks; "
        f"WiFi timed by {args.wifi_times}, held-out phones {args.rssi_offset:+g} dB, "
        f"headings {args.heading_offset:+g}°"
    )
    plotted = (
        [held[i].walk_id for i in np.linspace(0, len(held) - 1, args.n_plots).astype(int)]
        if args.plots and held
        else []
    )
    with console.status("starting a server") as status, Progress(console=console) as bar:
        task = bar.add_task("replay", total=len(held))
        run = evaluate_through_server(
            site_dir,
            floors,
            train_walks,
            held,
            wifi_times=args.wifi_times,
            tuning=not args.no_tuning,
            keep=plotted,
            status=lambda s: status.update(s),
            progress=lambda i: bar.update(task, completed=i),
        )
    console.print(f"build chose: {run.build.get('tuning')}")
    console.print(f"candidates: {run.build.get('tuning_scores')}")
    console.print(f"build accuracy: {run.build.get('accuracy')}")
    label = f"server ({args.wifi_times}{', defaults' if args.no_tuning else ''})"
    row = summarise(label, run.scores, 0.0, 0)
    rows = []
    if run.stages is not None:
        stages = run.stages.rows()
        rows += [table_cells(replace(s, method=f"in process: {s.method}")) for s in stages]
    rows.append(table_cells(row))
    with console.status("per-scan k-NN on the same split"):
        baseline = scan_knn_scores(floors, train_walks, held)
    rows.append(table_cells(summarise("per-scan k-NN (same surveys)", baseline, 0.0, 0)))
    if args.markdown:
        print(markdown_table(COLUMNS, rows))
    else:
        table = Table(title=f"ILC site1 through locus serve, {len(held)} held-out walks")
        for i, col in enumerate(COLUMNS):
            table.add_column(col, justify="left" if i == 0 else "right", no_wrap=i == 0)
        for cells in rows:
            table.add_row(*cells)
        console.print(table)
    console.print(f"replay wall time {run.wall_s:.0f} s")
    if args.plots and run.stages is not None:
        _plot_stages(args.plots, site_dir, floors, held, run.stages)
    if args.save:
        args.save.write_text(json.dumps({"build": run.build, "positions": run.positions}))


if __name__ == "__main__":
    main()
