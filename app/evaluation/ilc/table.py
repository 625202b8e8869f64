"""The printed table of the site1 evaluation: its columns and each row's cells."""

from __future__ import annotations

import numpy as np

from app.evaluation.ilc.score import Row

COLUMNS = (
    "method",
    "walks",
    "n",
    "mean m",
    "p50 m",
    "p75 m",
    "p95 m",
    "floor err",
    "off-floor walks",
    "|hdg err| °",
    "in acc.",
    "acc. rank",
    "CPU/update",
)
"""Column headers, in the order ``table_cells`` returns a row's cells."""


def format_cpu(seconds: float) -> str:
    """Return a CPU time in µs below a millisecond, else in ms."""
    if not np.isfinite(seconds):
        return "—"
    return f"{seconds * 1e6:.0f} µs" if seconds < 1e-3 else f"{seconds * 1e3:.2f} ms"


def table_cells(row: Row) -> list[str]:
    """Return the printed cells of a row, in ``COLUMNS`` order; "—" where there is no figure."""

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
        str(row.walks_off_floor),
        num(row.heading_error, "{:.1f}"),
        num(100.0 * row.in_accuracy, "{:.0f}%"),
        num(row.radius_rank),
        format_cpu(row.cpu_per_update_s),
    ]
