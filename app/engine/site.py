"""The engine's view of a site: floor rasters and radio/UWB infrastructure tables."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from app.engine.plan import FloorPlan


@dataclass(frozen=True, eq=False)
class Floor:
    """One floor: its id, level (0 ground, -1 first basement), height (m) and raster."""

    floor_id: str
    level: int
    height: float
    plan: FloorPlan
    z0: float = 0.0


@dataclass(frozen=True, eq=False)
class Emitters:
    """Fixed radio infrastructure of one kind (transmitters, anchors or locators).

    Arrays are aligned: row i describes ``ids[i]``. ``floor`` indexes
    ``SiteModel.floors``; ``xyz`` is in the floor's local frame (z above the
    floor surface); ``A`` (dBm at 1 m), ``B`` (dB per ln-metre) and
    ``sigma`` (dB) are the path-loss model ``rssi = A - B ln r``, NaN where
    unknown (anchors have none).
    """

    ids: tuple[str, ...] = ()
    floor: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    A: np.ndarray = field(default_factory=lambda: np.zeros(0))
    B: np.ndarray = field(default_factory=lambda: np.zeros(0))
    sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        """Return the number of emitters."""
        return len(self.ids)

    def index(self) -> dict[str, int]:
        """Return the id → row mapping."""
        return {tx_id: i for i, tx_id in enumerate(self.ids)}


@dataclass(frozen=True, eq=False)
class SiteModel:
    """Everything the filters of one site need, built once per map change."""

    site_id: str
    floors: tuple[Floor, ...]
    transmitters: Emitters = field(default_factory=Emitters)
    anchors: Emitters = field(default_factory=Emitters)
    locators: Emitters = field(default_factory=Emitters)
