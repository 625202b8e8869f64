"""Whether a search's best fit may be returned as the answer, and how far each point may be off.

A fit is only as good as the evidence that singled it out. When the plan (and
the anchors) leave a distinct hypothesis — another rotation, scale or drift —
scoring nearly as well, or the fit had to walk through walls to hold the track
at all, the fitted track is a guess that can be worse than the upload: the
answer is then the uploaded track itself, placed at its start, marked
unfitted with the reason. Either way every point carries a radius that grows
with the distance walked, calibrated so that about 68 % of errors fall
within it. The defaults are starting values, not yet measured: the margin
thresholds follow ``search``'s ambiguity margin and the slopes are a first
guess; they are to be tuned on validation walks and checked for coverage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.engine.trackfit.fit import RELAX_CROSSED
from app.engine.trackfit.search import TrackSearch


@dataclass(frozen=True)
class VerdictParams:
    """Thresholds of a fitted answer and the radius model.

    Attributes
    ----------
    margin_unknown : float
        Least score margin (runner-up's score less the best's, score units of
        ``search``) a fit of a track with no absolute heading needs to be
        returned fitted. Without a heading a wrong rotation that stays in a
        mall's halls scores close to the right one.
    margin_known : float
        The same for a track whose heading is given or measured per link.
    max_relaxed : float
        Largest share of links a fitted track may have placed across a wall
        or by dead reckoning: beyond it the plan does not hold the track.
    radius_base : float
        Radius (m) at the start (the start is given; this is the plan's cell
        and the walker's own extent).
    slope_fitted, slope_placed, slope_unoriented : float
        Growth of the radius per metre walked (m/m) of a fitted track, an
        unfitted track with a known heading, and an unfitted track with none
        (shown in the best rotation found, which may be wrong).
    """

    margin_unknown: float = 1.0
    margin_known: float = 0.0
    max_relaxed: float = 0.25
    radius_base: float = 1.0
    slope_fitted: float = 0.05
    slope_placed: float = 0.08
    slope_unoriented: float = 0.5


@dataclass(frozen=True)
class Verdict:
    """The answer's kind, why, the evidence's margin and the radius of every point."""

    fitted: bool
    reason: str | None
    margin: float
    """Runner-up score less the best's; +inf when no distinct hypothesis survived."""
    radius: np.ndarray
    """Radius (m) of each point, shape (n + 1,)."""


def margin_of(found: TrackSearch) -> float:
    """Return the runner-up's score less the best's (+inf without a distinct runner-up)."""
    if found.runner_up is None or not np.isfinite(found.runner_up.score):
        return float("inf")
    return float(found.runner_up.score - found.best.score)


def judge(
    found: TrackSearch, lengths: np.ndarray, *, oriented: bool, params: VerdictParams
) -> Verdict:
    """Decide whether the best fit is the answer and give each point's radius.

    Parameters
    ----------
    found : TrackSearch
        The search's best fit and runner-up.
    lengths : ndarray, shape (n,)
        Measured link lengths (m).
    oriented : bool
        The track carried an absolute heading (first or per link).
    params : VerdictParams
        Thresholds and radius slopes.
    """
    p = params
    margin = margin_of(found)
    need = p.margin_known if oriented else p.margin_unknown
    relaxed = found.best.fit.relaxed
    walled = int(np.count_nonzero(relaxed >= RELAX_CROSSED))
    reason = None
    if found.ambiguous and not oriented:
        reason = (
            "the plan does not single out one rotation: a distinct track scores within "
            f"{max(margin, 0.0):.2f} of the chosen one"
        )
    elif margin < need:
        reason = (
            f"the plan does not single out one hypothesis: a distinct track scores only "
            f"{max(margin, 0.0):.2f} above the chosen one (needs {need:g})"
        )
    elif relaxed.size and walled > p.max_relaxed * relaxed.size:
        reason = (
            f"the plan does not hold the track: {walled} of {relaxed.size} links "
            "crossed walls or were dead-reckoned"
        )
    fitted = reason is None
    slope = p.slope_fitted if fitted else p.slope_placed if oriented else p.slope_unoriented
    # r_i = r_0 + k Σ_{j ≤ i} l_j
    walked = np.r_[0.0, np.cumsum(np.asarray(lengths, dtype=float))]
    return Verdict(fitted, reason, margin, p.radius_base + slope * walked)
