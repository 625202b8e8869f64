"""Fit a dead-reckoned track to the floor plan: parameters, forward and backward passes, result.

The forward pass runs the dynamic programme link by link (``step``), with the
recovery ladder for a link no track survives; the backward pass follows the
predecessors from the best final cell and replays the chosen lengths and
turns into points.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from app.engine.plan import FloorPlan
from app.engine.trackfit.anchors import AnchorCosts
from app.engine.trackfit.grid import cell_grid
from app.engine.trackfit.step import advance


@dataclass(frozen=True)
class TrackFitParams:
    """Tunable constants of the track fitter (defaults from Voronov et al.).

    Attributes
    ----------
    grid : float
        Side (m) of the square cells S of the dynamic programme; the paper
        uses 1 m. Finer cells keep more tracks alive: closer to the exact
        optimum, slower.
    scales : tuple of float
        Γ, the factors a link's length may be multiplied by.
    turns : tuple of float
        Φ (rad), the changes a turn between two links may receive.
    first_step : float
        Step (rad) of the directions tried for the first link over [-π, π)
        when the initial heading is unknown.
    c1 : float
        C1, weight of the length changes Σ |1 - γ_i|.
    cell_per_link : float
        The DP cell is at most this many median link lengths (and at least one
        raster cell); 0 keeps ``grid`` whatever the links. A link shorter than
        the cell mostly ends in the cell it started from, where only the
        cheapest track survives: the DP keeps one or two tracks and turns
        greedy, and per-step links at a 1 m grid often die at a wall. The
        paper's 1 m grid suits its links of a metre or more; for shorter links
        the cell shrinks with them, at the cost of more cells alive. 1/√2 (the
        cell whose diagonal is a link, which every link leaves) fits per-step
        links closer than 1, but costs a few times the time and takes a long
        track on a large floor past a second (``python -m bench.trackfit``
        times fits by track length and grid), so the default is 1.
    c2 : float
        C2, weight of the turn changes Σ |φ_i|.
    recover : bool
        When no track survives a link, place it by the recovery ladder rather
        than give up (see ``RELAX_*``).
    wide_scales, wide_turns : tuple of float
        Γ_w and Φ_w (rad), the first rung of that ladder, costed by the same
        C1 |1 - γ| + C2 |φ|. Physical range: Γ_w = 0.7–1.3 and Φ_w = ±0.5
        rad (29°) cover how far, on the ILC site1 training walks, the PDR's
        length and heading (after removing each walk's bias) stray from the
        surveyed path between waypoints, most of the time; Γ and Φ do not.
    snap_start : float
        Largest distance (m) a start on a blocked cell is moved to the nearest
        free cell; 0 refuses such a start.
    spread_margin : float
        Score margin of the tracks ``TrackFit.spread`` measures (one Φ step).
    cross_cost, reckon_cost : float
        Score added for a link placed across a wall (``RELAX_CROSSED``) or by
        dead reckoning (``RELAX_DEAD_RECKONED``). Within one fit every track
        takes the same rung, so they change nothing there; they make fits of
        different rotations comparable: one that walks through walls scores
        worse than one that does not. Each is the cost of ten maximal Φ
        changes (2.5 rad of made-up turning).
    anchor_weight : float
        Score per nat of an anchor's log-likelihood below its best position
        (``AnchorCosts``). The likelihood is a mixture over the scan's nearest
        survey scans, not a product of per-reading terms, so it is not
        overconfident and enters untempered: on the site1 validation walks
        weights well below and above 1 fitted worse with the heading unknown
        and hardly differed with it known (``locus eval trackfit
        --validation-fraction 0.2 --anchor-weight W`` prints the errors at W).
    anchor_sigma : float
        Spread (m) of each neighbour's Gaussian in an anchor's mixture: how
        far from a matching survey scan the phone may have scanned. The
        mixture itself widens where the neighbours disagree, so this is the
        spread of one good match: about the per-scan k-NN's median error,
        which fitted the site1 validation walks better than narrower or wider
        (``locus eval trackfit --anchor-sigma S`` tries another).
    anchor_cap : float
        Largest score (after weighting) one anchor adds: a scan that makes a
        position very unlikely is as likely an outlier (a reflection, a
        passer-by) as proof, so it may not outvote the plan alone. Four times
        the relax penalties' scale.
    max_alive : int
        Most tracks one hypothesis keeps after a link (the lowest scores; 0
        keeps all, the paper's programme). On long tracks in large open
        floors the cells alive grow with the area the track could have
        reached, while the tracks far behind the best are those that bent it
        most: cutting them bounds a link's cost without changing the error
        (``bench/trackfit.py`` measures the time and error of long walks on
        site1's largest floor).
    time_limit_s : float
        The forward pass gives up (``failed``) after this much computing time (s).
    """

    grid: float = 1.0
    scales: tuple[float, ...] = (0.9, 1.0, 1.1)
    turns: tuple[float, ...] = (
        -0.25,
        -0.20,
        -0.15,
        -0.10,
        -0.05,
        0.0,
        0.05,
        0.10,
        0.15,
        0.20,
        0.25,
    )
    first_step: float = 0.05
    cell_per_link: float = 1.0
    c1: float = 1.0
    c2: float = 1.0
    recover: bool = True
    wide_scales: tuple[float, ...] = (0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3)
    wide_turns: tuple[float, ...] = tuple(round(0.05 * k, 2) for k in range(-10, 11))
    snap_start: float = 2.0
    spread_margin: float = 0.05
    cross_cost: float = 2.5
    reckon_cost: float = 2.5
    anchor_weight: float = 1.0
    anchor_sigma: float = 5.0
    anchor_cap: float = 10.0
    max_alive: int = 150
    time_limit_s: float = 10.0


@dataclass(frozen=True)
class TrackFit:
    """Result of a fit.

    Attributes
    ----------
    points : ndarray, shape (k + 1, 2)
        Fitted points x_0 … x_k (m); k = n links on success, on failure the
        best fit of the links that could still be placed.
    score : float
        f of the fitted track (of its k links).
    scale : ndarray, shape (k,)
        γ chosen for each link.
    turn : ndarray, shape (k,)
        φ (rad) added to each turn; NaN for the first link when the heading
        was unknown (its direction was searched freely).
    direction : ndarray, shape (k,)
        Direction of each fitted link (rad, counter-clockwise from +x).
    alive : ndarray of int, shape (m,)
        |S_i|, the cells holding a track after each link processed.
    failed : str or None
        Why no complete track was found; None on success.
    relaxed : ndarray of int8, shape (k,)
        How each link was placed: ``RELAX_NONE`` normally, else the rung of
        the recovery ladder that placed it.
    start_shift : float
        Distance (m) the start was moved off a blocked cell.
    cell : float
        Side (m) of the DP cells used: ``grid``, or less for short links
        (``cell_per_link``).
    spread : float
        Largest distance (m) from the fitted last point to the last point of
        any other surviving track scoring within ``spread_margin`` of it. The
        score cannot tell those tracks apart: a large spread (typically with
        the heading unknown in open halls, where any rotation fits) says the
        plan did not determine the fit.
    """

    points: np.ndarray
    score: float
    scale: np.ndarray
    turn: np.ndarray
    direction: np.ndarray
    alive: np.ndarray
    failed: str | None = None
    relaxed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int8))
    start_shift: float = 0.0
    spread: float = 0.0
    cell: float = 0.0


def _ordered(values: tuple[float, ...], centre: float) -> np.ndarray:
    """Return the values sorted by distance from ``centre`` then value: ties prefer less change."""
    arr = np.asarray(values, dtype=float)
    return arr[np.lexsort((arr, np.abs(arr - centre)))]


@dataclass(frozen=True)
class LinkOptions:
    """The candidates tried for one link: γ values, directions relative to ψ, their φ and cost."""

    scales: np.ndarray
    rel: np.ndarray
    phi: np.ndarray
    cost: np.ndarray


def _replay(
    start: np.ndarray,
    psi0: float,
    lengths: np.ndarray,
    turns: np.ndarray,
    options: list[LinkOptions],
    choices: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rebuild points, chosen γ, φ and directions from the per-link choices ``g * A + a``."""
    k = choices.size
    points = np.empty((k + 1, 2))
    points[0] = start
    direction = np.empty(k)
    gamma = np.empty(k)
    phi = np.empty(k)
    psi = psi0
    for i in range(k):
        opt = options[i]
        g, a = divmod(int(choices[i]), opt.rel.size)
        # ψ_i = ψ_{i-1} + turn_i + φ_i,  x_i = x_{i-1} + γ l_i (cos ψ_i, sin ψ_i)
        psi = psi + turns[i] + opt.rel[a]
        step = lengths[i] * opt.scales[g]
        points[i + 1] = points[i] + step * np.array([np.cos(psi), np.sin(psi)])
        direction[i] = psi
        gamma[i] = opt.scales[g]
        phi[i] = opt.phi[a]
    return points, gamma, phi, direction


RELAX_NONE = 0
"""The link was placed with Γ and Φ, clear of every wall."""
RELAX_WIDENED = 1
"""No track survived the link with Γ and Φ: it was placed with the wider Γ_w and Φ_w."""
RELAX_CROSSED = 2
"""Not even Γ_w and Φ_w placed it: the link crosses a wall (Γ, Φ; its end is free)."""
RELAX_DEAD_RECKONED = 3
"""No candidate even ended on free space (the walker is where the plan says nobody
can be): the link keeps its measured length and turn, walls ignored; only an
end off the plan's raster is refused (then the fit fails at that link)."""


def fit_track(
    plan: FloorPlan,
    start: np.ndarray,
    lengths: np.ndarray,
    turns: np.ndarray,
    *,
    heading: float | None = None,
    params: TrackFitParams | None = None,
    anchors: AnchorCosts | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> TrackFit:
    """Fit a track given as links to the plan, starting at ``start``.

    Parameters
    ----------
    plan : FloorPlan
        Free space; no fitted link crosses a blocked raster cell.
    start : ndarray, shape (2,)
        x_0 (m), the first point of the track. A start on a blocked cell (a
        surveyed or radio fix a little inside a barrier) is moved to the
        nearest free cell's centre when that is within ``params.snap_start``.
    lengths : ndarray, shape (n,)
        Link lengths l_i (m), non-negative.
    turns : ndarray, shape (n,)
        Turn (rad, counter-clockwise positive) from the previous link to link
        i; ``turns[0]`` is the turn from ``heading`` and ignored without one.
    heading : float, optional
        Direction (rad, counter-clockwise from +x) before the first link. When
        None, the first link tries every direction of [-π, π) in steps of
        ``first_step`` at no cost, as in the paper.
    params : TrackFitParams, optional
        Γ, Φ, grid, weights, recovery sets and time limit.
    anchors : AnchorCosts, optional
        Absolute evidence on some points (WiFi scans): each adds its cost at
        the candidate end of its point's link to the score of that track.
    clock : callable
        Seconds counter used for the time limit.

    Returns
    -------
    TrackFit
        The fitted track. A link no track survives is placed by the recovery
        steps of ``TrackFit.relaxed`` (with ``params.recover``); ``failed``
        is set, with the best partial track, when the start is blocked beyond
        ``snap_start``, a link dies without recovery, or time runs out.
    """
    return fit_tracks(
        plan,
        start,
        lengths,
        np.asarray(turns, dtype=float).reshape(1, -1),
        headings=None if heading is None else np.array([float(heading)]),
        params=params,
        anchors=anchors,
        clock=clock,
    )[0]


def fit_tracks(
    plan: FloorPlan,
    start: np.ndarray,
    lengths: np.ndarray,
    turns: np.ndarray,
    *,
    headings: np.ndarray | None = None,
    scales: np.ndarray | None = None,
    params: TrackFitParams | None = None,
    anchors: AnchorCosts | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> list[TrackFit]:
    """Fit H hypotheses of one track together, each as ``fit_track`` would alone.

    The hypotheses share the links' measured lengths and differ in their
    first heading, their walker scale and their turns (a drift removed).
    Their tracks never compete for a cell and each has its own recovery
    ladder, so every fit equals its own ``fit_track``; together they cost one
    pass of numpy calls per link instead of H.

    Parameters
    ----------
    plan, start, lengths, params, anchors, clock
        As ``fit_track``.
    turns : ndarray, shape (H, n)
        Each hypothesis' turns; ``turns[h, 0]`` is the turn from ``headings[h]``.
    headings : ndarray, shape (H,), optional
        Each hypothesis' heading before the first link; None (H = 1 only)
        searches the first direction freely, as the paper does.
    scales : ndarray, shape (H,), optional
        Each hypothesis' walker scale on every link (default 1).
    """
    p = params or TrackFitParams()
    t0 = clock()
    start = np.asarray(start, dtype=float).reshape(2)
    lengths = np.asarray(lengths, dtype=float).reshape(-1)
    turns = np.atleast_2d(np.asarray(turns, dtype=float))
    n_h = turns.shape[0]
    scale_h = np.ones(n_h) if scales is None else np.asarray(scales, dtype=float).reshape(n_h)
    if turns.shape[1] != lengths.size:
        raise ValueError("lengths and turns must have the same length")
    if not (np.all(np.isfinite(lengths)) and np.all(lengths >= 0) and np.all(np.isfinite(turns))):
        raise ValueError("lengths must be finite and non-negative, turns finite")
    if p.grid <= 0 or p.first_step <= 0 or not p.scales or not p.turns:
        raise ValueError("grid and first_step must be positive, scales and turns non-empty")
    if headings is None and n_h != 1:
        raise ValueError("an unknown heading is searched for one hypothesis at a time")
    n = lengths.size
    free_first = headings is None
    psi0 = np.zeros(n_h) if headings is None else np.asarray(headings, dtype=float).reshape(n_h)
    # the turn each hypothesis adds before its candidates' φ; none on a free first link
    link_turn = turns.copy()
    if free_first:
        link_turn[:, 0] = 0.0

    def options_for(scale_set: tuple[float, ...], turn_set: tuple[float, ...]) -> LinkOptions:
        """Return the candidates of a link for one (Γ, Φ) pair, relative to ψ + turn."""
        gammas = _ordered(scale_set, 1.0)
        phis = _ordered(turn_set, 0.0)
        # C1 |1 - γ| + C2 |φ| per (γ, φ)
        cost = p.c1 * np.abs(1.0 - gammas)[:, None] + p.c2 * np.abs(phis)[None, :]
        return LinkOptions(gammas, phis, phis, cost)

    normal = options_for(p.scales, p.turns)
    wide = options_for(p.wide_scales or p.scales, p.wide_turns or p.turns)
    straight = LinkOptions(np.ones(1), np.zeros(1), np.zeros(1), np.zeros((1, 1)))
    first_free = first_straight = normal
    if free_first:
        # θ_k = k Δθ ∈ [-π, π), free of charge; 0 and every multiple of the
        # step are tried, so a track on the Φ lattice can be found exactly.
        ks = np.arange(-np.floor(np.pi / p.first_step), np.ceil(np.pi / p.first_step))
        theta = p.first_step * ks
        theta = theta[(theta >= -np.pi) & (theta < np.pi)]
        theta = theta[np.lexsort((theta, np.abs(theta)))]
        free_cost = np.repeat(p.c1 * np.abs(1.0 - normal.scales)[:, None], theta.size, axis=1)
        first_free = LinkOptions(normal.scales, theta, np.full(theta.size, np.nan), free_cost)
        # γ = 1 in any direction for a dead first link of unknown heading
        first_straight = LinkOptions(
            np.ones(1), theta, np.full(theta.size, np.nan), np.zeros((1, theta.size))
        )

    def rungs(i: int) -> list[tuple[int, LinkOptions, bool, bool, float]]:
        """Return link i's rungs: Γ and Φ, then the recovery ladder of a dead link.

        The ladder: Γ_w and Φ_w; walls ignored with the end on free space; pure
        dead reckoning.
        """
        first = free_first and i == 0
        ladder = [(RELAX_NONE, first_free if first else normal, True, True, 0.0)]
        if p.recover:
            ladder += [
                (RELAX_WIDENED, first_free if first else wide, True, True, 0.0),
                (RELAX_CROSSED, first_free if first else normal, True, False, p.cross_cost),
                (
                    RELAX_DEAD_RECKONED,
                    first_straight if first else straight,
                    False,
                    False,
                    p.reckon_cost,
                ),
            ]
        return ladder

    # Longest move tested: the longest candidate link of the largest scale.
    longest = max(max(p.scales), max(p.wide_scales or p.scales), 1.0) * float(scale_h.max())
    cell = p.grid
    if p.cell_per_link > 0 and n:
        # A link shorter than the cell mostly ends in the cell it started from,
        # where only the cheapest track survives: the DP turns greedy. Cells no
        # larger than the typical link keep its alternatives apart.
        cell = min(cell, p.cell_per_link * float(np.median(lengths)) * float(scale_h.min()))
        cell = max(cell, plan.cell)
    grid = cell_grid(plan, cell, longest * float(lengths.max()) if n else 0.0, groups=n_h)
    n_cells = grid.nx * grid.ny
    x0 = start
    if not bool(plan.is_free(start)):
        snapped = plan.project(start)
        if p.snap_start <= 0 or float(np.hypot(*(snapped - start))) > p.snap_start:
            empty = np.zeros(0)
            return [
                TrackFit(
                    start[None, :],
                    0.0,
                    empty,
                    empty,
                    empty,
                    np.zeros(0, dtype=np.int64),
                    "start is not in free space",
                    cell=cell,
                )
                for _ in range(n_h)
            ]
        x0 = snapped

    xi = np.repeat(x0[None, :], n_h, axis=0)
    psi = psi0.copy()
    f = np.zeros(n_h)
    grp = np.arange(n_h)
    live = np.ones(n_h, dtype=bool)
    rung_of = np.zeros((n_h, n), dtype=np.int8)
    used: list[list[LinkOptions]] = [[] for _ in range(n_h)]
    counts: list[np.ndarray] = []
    preds: list[np.ndarray] = []
    choices: list[np.ndarray] = []
    failed: list[str | None] = [None] * n_h
    # per hypothesis: links placed, row of its best track after them, its score, spread
    ends: dict[int, tuple[int, int, float, float]] = {}

    def close(h: int, links: int, why: str | None) -> None:
        """Record hypothesis h's best track after ``links`` links (the current state)."""
        rows = np.flatnonzero(grp == h)
        j = int(rows[np.argmin(f[rows])])
        # Ends of the other tracks that score within the margin: as good an
        # explanation of the input, so the fit is only as certain as they agree.
        near = rows[f[rows] <= f[j] + p.spread_margin]
        ends[h] = (links, j, float(f[j]), float(np.hypot(*(xi[near] - xi[j]).T).max()))
        failed[h] = why
        live[h] = False

    for i in range(n):
        end_cost = (
            None if anchors is None else anchors.for_point(i + 1, p.anchor_weight, p.anchor_cap)
        )
        pending = live.copy()
        parts = []
        for code, opt, free_end, walls, penalty in rungs(i):
            rows = np.flatnonzero(pending[grp])
            if rows.size == 0:
                break
            g_rows = grp[rows]
            cells, xi2, psi2, f2, pred, choice = advance(
                grid,
                xi[rows],
                psi[rows],
                f[rows],
                opt.scales * lengths[i],
                opt.rel,
                opt.cost + penalty,
                free_end=free_end,
                walls=walls,
                end_cost=end_cost,
                group=g_rows,
                link_scale=scale_h[g_rows],
                link_turn=link_turn[g_rows, i],
            )
            placed = np.unique(cells // n_cells)
            for h in placed:
                rung_of[h, i] = code
                used[h].append(opt)
            pending[placed] = False
            parts.append((cells, xi2, psi2, f2, rows[pred], choice))
        for h in np.flatnonzero(pending):
            close(int(h), i, f"no track survives link {i + 1} of {n}")
        if not live.any():
            counts.append(np.zeros(n_h, dtype=np.int64))
            break
        cells, xi, psi, f, pred, choice = (np.concatenate(c) for c in zip(*parts, strict=True))
        order = np.argsort(cells, kind="stable")
        if p.max_alive > 0 and order.size > p.max_alive:
            # rank within each hypothesis by score (then cell); keep the best max_alive
            by = np.lexsort((cells, f, cells // n_cells))
            g_by = cells[by] // n_cells
            rank = np.arange(by.size) - np.searchsorted(g_by, g_by)
            order = np.sort(by[rank < p.max_alive])
        cells, xi, psi, f = cells[order], xi[order], psi[order], f[order]
        grp = cells // n_cells
        counts.append(np.bincount(grp, minlength=n_h))
        preds.append(pred[order].astype(np.int32))
        choices.append(choice[order].astype(np.int32))
        if clock() - t0 > p.time_limit_s and i + 1 < n:
            for h in np.flatnonzero(live):
                close(
                    int(h),
                    i + 1,
                    f"time limit of {p.time_limit_s} s reached after link {i + 1} of {n}",
                )
            break
    for h in np.flatnonzero(live):
        close(int(h), n, None)

    fits = []
    for h in range(n_h):
        k, j, score, spread = ends[h]
        # Backward pass: s*_{i-1} = ζ_i(s*_i) from the best last cell.
        path = np.empty(k, dtype=np.int64)
        for i in range(k - 1, -1, -1):
            path[i] = choices[i][j]
            j = int(preds[i][j])
        points, gamma, phi, direction = _replay(
            x0, psi0[h], lengths[:k] * scale_h[h], link_turn[h, :k], used[h], path
        )
        alive = [int(c[h]) for c in counts[: k + (failed[h] is not None and k < n)]]
        fits.append(
            TrackFit(
                points,
                score,
                gamma,
                phi,
                direction,
                np.array(alive, dtype=np.int64),
                failed[h],
                relaxed=rung_of[h, :k].copy(),
                start_shift=float(np.hypot(*(x0 - start))),
                spread=spread,
                cell=cell,
            )
        )
    return fits
