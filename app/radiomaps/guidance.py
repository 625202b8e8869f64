"""Survey guidance of a build: where each floor's radio map is thin, computed from the
build's held-out scans (``app.engine.survey_guidance``), summarised, stored one row per
floor, and read back as a JSON grid or a PNG over the floor plan."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict
from datetime import datetime
from typing import Any

import numpy as np
from sqlalchemy import delete
from sqlalchemy.orm import Session

from app.core.errors import NotFound
from app.engine.crossval import HeldOut
from app.engine.plan import FloorPlan
from app.engine.radiomap import Survey
from app.engine.survey_guidance import GuidanceGrid, GuidanceParams, site_guidance
from app.floors.render import grid_png
from app.geometry.floormap import FloorMap
from app.radiomaps.codec import as_stored, decode_guidance, encode_guidance
from app.radiomaps.models import RadioMapBuild, SurveyGuidanceFloor

GUIDANCE = GuidanceParams()

PNG_CMAP = "viridis_r"
"""The accuracy maps' colour map (small errors bright, large dark), so both read alike."""


def compute(
    survey: Survey,
    held: HeldOut,
    plans: Mapping[int, FloorPlan],
    floor_ids: tuple[str, ...],
    params: GuidanceParams = GUIDANCE,
) -> dict[str, GuidanceGrid]:
    """Return every floor's guidance by floor id from the held-out scans of the chosen k, at
    the precision it is stored in, so the build's summary is the stored grids' figures."""
    grids = site_guidance(survey, held, plans, params)
    return {floor_ids[f]: as_stored(g) for f, g in grids.items()}


def _share(cells: np.ndarray, walkable: int) -> float | None:
    return round(float(cells.sum()) / walkable, 4) if walkable else None


def floor_figures(floor_id: str, grid: GuidanceGrid) -> dict[str, Any]:
    """Return one floor's summary: its mean expected error over the surveyed walkable cells,
    and the shares of its walkable cells unsurveyed and above ``high_error_m``."""
    walkable = int(grid.walkable.sum())
    surveyed = grid.error_m[grid.walkable & np.isfinite(grid.error_m)]
    return {
        "floor_id": floor_id,
        "scans": grid.scans,
        "walkable_cells": walkable,
        "mean_expected_error_m": round(float(surveyed.mean()), 3) if surveyed.size else None,
        "unsurveyed_share": _share(grid.unsurveyed, walkable),
        "high_error_share": _share(grid.high, walkable),
        "to_survey_share": _share(grid.unsurveyed | grid.high, walkable),
    }


def summary(grids: Mapping[str, GuidanceGrid], params: GuidanceParams = GUIDANCE) -> dict[str, Any]:
    """Return the build summary's ``guidance``: its parameters and each floor's figures."""
    return asdict(params) | {"floors": [floor_figures(f, g) for f, g in grids.items()]}


def replace_rows(*, db: Session, site_id: str, grids: Mapping[str, GuidanceGrid]) -> None:
    """Replace the site's stored guidance by ``grids`` (none: the site has none)."""
    db.execute(delete(SurveyGuidanceFloor).where(SurveyGuidanceFloor.site_id == site_id))
    for floor_id, grid in grids.items():
        db.add(SurveyGuidanceFloor(site_id=site_id, floor_id=floor_id, data=encode_guidance(grid)))


def get_guidance(*, db: Session, site_id: str, floor_id: str) -> tuple[GuidanceGrid, datetime]:
    """Return the floor's stored guidance and the build's time; NotFound saying why not."""
    build = db.get(RadioMapBuild, site_id)
    if build is None:
        raise NotFound(
            f"site '{site_id}' has no radio map yet, so no survey guidance: upload survey "
            f"walks and build it (POST /v1/sites/{site_id}/radiomap/build)"
        )
    row = db.get(SurveyGuidanceFloor, (site_id, floor_id))
    if row is None:
        raise NotFound(
            f"the latest build of site '{site_id}' has no survey guidance for floor "
            f"'{floor_id}': guidance comes from walks held out of the build, which needs "
            "two survey walks with WiFi or more, and the floor must have been in the site "
            "when it was built"
        )
    return decode_guidance(row.data), build.built_at


def _grid(a: np.ndarray) -> list[list[float | None]]:
    rounded = np.round(a, 2)
    return [[float(v) if np.isfinite(v) else None for v in row] for row in rounded]


def to_json(site_id: str, floor_id: str, grid: GuidanceGrid, built_at: datetime) -> dict[str, Any]:
    """Return the API's guidance document: grids (ny, nx) from row 0 at y0, null where
    there is no value (outside the walkable area; unsurveyed for the expected error)."""
    return {
        "site_id": site_id,
        "floor_id": floor_id,
        "built_at": built_at,
        "origin": [float(grid.origin[0]), float(grid.origin[1])],
        "cell": grid.cell,
        "shape": list(grid.shape),
        "params": asdict(grid.params),
        "summary": floor_figures(floor_id, grid),
        "walkable": grid.walkable.tolist(),
        "expected_error_m": _grid(grid.error_m),
        "distance_m": _grid(grid.distance_m),
    }


def render_png(fmap: FloorMap, grid: GuidanceGrid, *, title: str) -> bytes:
    """Draw the expected error over the floor plan, unsurveyed walkable cells grey; the scale
    runs to twice ``high_error_m`` so the threshold sits in its middle."""
    return grid_png(
        fmap,
        grid.error_m,
        (float(grid.origin[0]), float(grid.origin[1])),
        grid.cell,
        title=title,
        label="expected error (m)",
        cmap=PNG_CMAP,
        vmax=2.0 * grid.params.high_error_m,
        greyed=grid.unsurveyed,
        greyed_label="unsurveyed",
    )
