"""One filter's inputs for one window, and the tables the batched steps read from them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from app.engine.particle.floor_model import FloorModel


@dataclass(frozen=True, eq=False)
class FilterInput:
    """One filter's inputs for one positioning window.

    Attributes
    ----------
    slot : int
        Row of the filter in the bank.
    t : int
        Window time (ms).
    tx, rssi, count : ndarray, shape (M,)
        Site transmitter index, mean RSSI (dBm) and reading count of each
        transmitter of this floor heard in the window.
    step_length, step_heading : ndarray, shape (K,)
        The window's steps: length (m) and heading (deg clockwise from +y, NaN unknown).
    walk_s : float
        Seconds of random-walk motion to apply when the device has no
        inertial stream; 0 otherwise.
    fix : tuple of float, optional
        Positional measurement (x, y, radius in m), already on this floor.
    rng : np.random.Generator
        The device's generator.
    """

    slot: int
    t: int
    tx: np.ndarray
    rssi: np.ndarray
    count: np.ndarray
    rng: np.random.Generator
    step_length: np.ndarray = field(default_factory=lambda: np.zeros(0))
    step_heading: np.ndarray = field(default_factory=lambda: np.zeros(0))
    walk_s: float = 0.0
    fix: tuple[float, float, float] | None = None

    @property
    def walks(self) -> bool:
        """Whether the window has no steps, so that the particles walk at random."""
        return self.step_length.size == 0


def steps_table(inputs: list[FilterInput]) -> tuple[np.ndarray, np.ndarray]:
    """Return (R, K) step lengths (0 padded) and headings in rad (last heading repeated)."""
    sizes = np.array([i.step_length.size for i in inputs])
    width = max(1, int(sizes.max(initial=0)))
    # each row's k steps, then its last step's heading again up to the width (NaN without one)
    column = np.minimum(np.arange(width), np.maximum(sizes, 1)[:, None] - 1)
    starts = np.cumsum(sizes) - sizes
    heading = np.radians(np.concatenate([i.step_heading for i in inputs] + [[np.nan]]))
    # rows without steps read the NaN appended after every real heading
    flat = np.where(sizes[:, None] > 0, starts[:, None] + column, heading.size - 1)
    length = np.concatenate([i.step_length for i in inputs] + [[0.0]])[flat]
    length[np.arange(width) >= sizes[:, None]] = 0.0
    return length, heading[flat]


def readings_table(
    model: FloorModel, inputs: Sequence[FilterInput]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 4: (D, M) tables of the usable transmitters heard: index, mean RSSI, count, valid."""
    sizes = np.array([i.tx.size for i in inputs])
    tx = np.concatenate([i.tx for i in inputs]).astype(np.intp)
    row = np.repeat(np.arange(len(inputs)), sizes)
    rssi = np.concatenate([i.rssi for i in inputs])
    keep = model.usable[tx] & np.isfinite(rssi)
    tx, row, rssi = tx[keep], row[keep], rssi[keep]
    count = np.concatenate([i.count for i in inputs])[keep]
    kept = np.bincount(row, minlength=len(inputs))
    width = max(1, int(kept.max(initial=0)))
    # column = position of the reading within its row
    col = np.arange(row.size) - np.repeat(np.cumsum(kept) - kept, kept)
    shape = (len(inputs), width)
    tables = (np.zeros(shape, np.intp), np.zeros(shape), np.zeros(shape), np.zeros(shape, bool))
    tables[0][row, col], tables[1][row, col], tables[2][row, col] = tx, rssi, count
    tables[3][row, col] = True
    return tables
