"""The interface every floor selector offers, and the selector a configuration names."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar, Protocol, Self

import numpy as np

from app.engine.floors.forward import FloorFilter
from app.engine.floors.params import FloorParams
from app.engine.floors.patent import PatentFloorSelector
from app.engine.floors.window import FloorWindow


class FloorSelector(Protocol):
    """Chooses one device's floor window by window; its state snapshots to arrays and scalars.

    Parameters
    ----------
    levels : ndarray of int, shape (F,)
        Storey of each floor of the site.
    params : FloorParams
    state : dict, optional
        A :meth:`snapshot` to resume from.
    """

    uses_evidence: ClassVar[bool]
    """Whether :meth:`update` reads the window's ``loglik``: it is computed only then."""

    def __init__(
        self, levels: np.ndarray, params: FloorParams, state: dict[str, Any] | None = None
    ) -> None: ...

    def update(self, window: FloorWindow) -> np.ndarray:
        """Add one window; return the active floors, the chosen floor first, empty for none."""
        ...

    @classmethod
    def update_many(
        cls, selectors: Sequence[Self], windows: Sequence[FloorWindow]
    ) -> list[np.ndarray]:
        """:meth:`update` for many devices of one site, each as if alone."""
        ...

    def snapshot(self) -> dict[str, Any]:
        """Return the state to resume from."""
        ...


SELECTORS: dict[str, type[FloorSelector]] = {"filter": FloorFilter, "patent": PatentFloorSelector}
"""Floor selectors by their name in ``FloorParams.method``."""


def floor_selector_class(params: FloorParams) -> type[FloorSelector]:
    """Return the floor selector ``params.method`` names."""
    try:
        return SELECTORS[params.method]
    except KeyError:
        names = " or ".join(repr(name) for name in SELECTORS)
        raise ValueError(f"unknown floor selection {params.method!r}; choose {names}") from None
