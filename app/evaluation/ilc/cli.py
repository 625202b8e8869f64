"""Accuracy of the WiFi positioning methods on ILC site1's held-out walks.

Learns on the training walks, replays the held-out walks through every
method, prints the table and optionally plots a few walks. Run
``locus eval ilc-methods`` or ``python -m app.evaluation.ilc.cli``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path

from app.datasets import data_dir
from app.evaluation.ilc.evaluate import evaluate
from app.evaluation.ilc.experiment import add_split_arguments, prepare_experiment
from app.evaluation.ilc.methods import METHODS
from app.evaluation.ilc.plots import plot_walk
from app.evaluation.ilc.score import summarise
from app.evaluation.ilc.server import evaluate_through_server
from app.evaluation.ilc.table import COLUMNS, table_cells
from app.importers.ilc import WIFI_TIMES


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Parse the options of ``locus eval ilc-methods``."""
    parser = argparse.ArgumentParser(
        prog="locus eval ilc-methods", description=__doc__.splitlines()[0] if __doc__ else None
    )
    add_split_arguments(parser, "evaluate on it instead of the test walks")
    parser.add_argument("--limit", type=int, help="at most this many evaluated walks (id order)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--plots", type=Path, help="folder for PNGs of a few walks")
    parser.add_argument("--n-plots", type=int, default=4)
    parser.add_argument(
        "--through-server",
        action="store_true",
        help="add a last row: the same split replayed through a fresh `locus serve` over HTTP",
    )
    parser.add_argument("--wifi-times", choices=WIFI_TIMES, default="scan")
    parser.add_argument(
        "--pf-unbatched",
        action="store_true",
        help="replay the particle filter walk by walk instead of all walks in one engine",
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    """Learn on the training walks of site1, replay the held-out walks and print the table."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn
    from rich.table import Table

    args = parse_args(argv)
    console = Console(width=max(Console().width, 160))
    t0 = time.perf_counter()
    with console.status("reading site1") as status:
        exp = prepare_experiment(args, status=lambda s: status.update(s))
    learn_s = time.perf_counter() - t0
    learned = exp.learned
    walks = exp.held_out_walks()[: args.limit]
    plotted = [w.walk_id for w in walks[: args.n_plots]] if args.plots else []
    n_plausible = sum(f.plausible for f in learned.fits)
    console.print(
        f"site1: {len(exp.train)} training walks, {len(exp.validation)} validation, "
        f"{len(exp.test)} test; evaluating {len(walks)} {exp.held_out_kind} walks"
    )
    console.print(
        f"learned in {learn_s:.0f} s: {len(exp.site.tx_ids)} transmitters heard, "
        f"{len(learned.fits)} calibrated ({n_plausible} plausible, used by pf), "
        f"{sum(m.n_points for m in learned.maps)} radio-map points, "
        f"chosen on training folds: {learned.tuning.as_dict()}"
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
            exp.site,
            learned,
            walks,
            args.methods,
            keep=plotted,
            batched=not args.pf_unbatched,
            progress=lambda m, i: bar.update(tasks[m], completed=i),
        )
    if args.through_server:
        surveyed = set(exp.train) - set(exp.validation)
        with console.status("through a server") as status:
            run = evaluate_through_server(
                args.site or data_dir() / "ilc" / "site1",
                exp.site.floors,
                [w for w in exp.site.walks if w.walk_id in surveyed],
                walks,
                wifi_times=args.wifi_times,
                status=lambda s: status.update(s),
            )
        console.print(f"the server's build chose: {run.build.get('tuning')}")
        result.rows.append(summarise(f"server ({args.wifi_times})", run.scores, 0.0, 0))
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
            plot_walk(path, exp.site, by_id[walk_id], results)
            console.print(f"wrote {path}")


if __name__ == "__main__":
    main()
