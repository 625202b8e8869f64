"""Search the motion hypotheses of a track, then fit the most plausible ones to the plan.

The dynamic programme (``fit``) explains a track by small per-link changes of
length (Γ) and turn (Φ). Three errors of a phone's dead reckoning are not
small per link but global, and the programme pays for them on every link or
cannot tell them apart at all:

- the rotation: with the first heading unknown, any rotation of a track that
  stays in a mall's open halls fits with no change, and the programme picks
  one of them silently;
- the walker's step-length scale (a stride model off by 5–20 % for this
  walker), which costs |1 - γ| on every link;
- heading drift, a slowly varying gyro bias β: the heading error grows as
  β t, which the programme pays as a turn change on every link.

Each hypothesis h = (θ, s, β) first turns the raw track into a rigid one
(first direction θ, lengths × s, turns corrected by β Δt) and is screened
cheaply: how far that rigid track leaves the walkable area (m² of track off
the plan, each sample counting its distance to free space up to a cap) plus
the cost of the WiFi anchors at its points. The best screened hypotheses
that are distinct (their tracks lie apart) are then fitted by the dynamic
programme, each with its own anchors, and scored by the fit's score plus a
share of the screening. The best fit is the answer; the runner-up is the best
fit that lies apart from it, and when their scores are within a margin (or
another distinct fit's is, the screening set aside) the answer is flagged
ambiguous rather than picked silently.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from app.engine.plan import FloorPlan
from app.engine.trackfit.anchors import AnchorCosts
from app.engine.trackfit.compass import fused_directions, wrap
from app.engine.trackfit.fit import TrackFit, TrackFitParams, fit_tracks


def _degrees(*values: float) -> tuple[float, ...]:
    return tuple(float(np.radians(v)) for v in values)


@dataclass(frozen=True)
class TrackSearchParams:
    """Hypotheses searched and how they are screened and compared.

    Attributes
    ----------
    fit : TrackFitParams
        The dynamic programme run on each retained hypothesis.
    rotation_step : float
        Step (rad) of the first directions θ tried over [-π, π) when the
        heading is unknown; the programme's Φ (±0.25 rad) on the first link
        covers the gaps between them.
    scales : tuple of float
        Walker step-length scales s. On ILC site1's test walks the summed
        PDR step length over the surveyed length runs 0.955–1.076
        (quartiles, as ``locus eval pdr`` prints them) with longer tails;
        s covers ±20 % in 5 % steps and the programme's Γ the rest.
    drifts : tuple of float
        Heading drift rates β (rad/s): a phone gyroscope's residual bias after
        the OS's own calibration is of the order of 0.1°/s; ±0.3°/s bends a
        minute's walk by up to 18°.
    walking_speed : float
        Speed (m/s) that turns link lengths into durations when the track
        carries no times (a pedestrian's typical 1.2 m/s).
    spacing : float
        Largest distance (m) between screening samples along a track.
    off_cap : float
        A screening sample counts its distance (m) to free space up to this.
    candidates : int
        Distinct hypotheses the programme fits.
    variants : int
        More hypotheses it fits close to the best screened one (its next
        scales and drifts): the rigid screening cannot rank a bent track's
        scale and drift finely, the programme can.
    distinct : float
        Two tracks whose points lie on average more than this apart (m) are
        distinct answers; closer ones are the same answer.
    scale_links : float
        A scale hypothesis costs what the programme pays to rescale this many
        links by Γ: C1 |1 - s| scale_links. Without a prior, hypotheses that
        explain nothing better than s = 1 would win ties at random. On the
        site1 validation walks (one or two minutes, a few merged links each)
        30 links fitted better than fewer or more, with the heading given and
        withheld (``locus eval trackfit --validation-fraction 0.2
        --scale-links N`` prints the errors at N).
    drift_seconds : float
        A drift hypothesis costs what the programme pays to follow that drift
        with turn changes for this long (s): C2 |β| drift_seconds. Drift
        becomes worth hypothesising on walks longer than this. Between one
        and two minutes it hardly matters on the site1 validation walks
        (``locus eval trackfit --drift-seconds S``), and 90 s finds the
        synthetic office walk's 0.2°/s drift within the 0.8 m that
        ``tests/engine/test_trackfit_search.py`` asserts.
    screen_weight : float
        Share of a hypothesis' screening cost (m² off the plan) added to its
        fit's score: the fit itself stays on free space whatever the
        rotation, so how much the rigid track had to be bent back onto the
        plan is the evidence that separates rotations in open halls.
    ambiguity_margin : float
        A runner-up scoring within this of the best makes the answer
        ambiguous (score units: one is four maximal Φ changes); so does a
        distinct fit within this of the best once the screening of their
        rigid tracks is set aside: dead reckoning whose heading wanders leaves
        the plan as a rigid track at the right rotation too, and the
        programme may bend it back as cheaply as a wrong rotation that stays
        on the plan rigid. On the site1 validation walks this second rule
        flags more of the withheld-heading fits, and those left unflagged
        gain more on their raw tracks (``locus eval trackfit`` prints the
        fits flagged and the errors of the others).
    bias_step, bias_range : float
        Compass biases b (rad) tried with per-link headings: every multiple of
        ``bias_step`` within ±``bias_range`` (a phone's compass indoors is
        rarely off by more than a few tens of degrees; the programme's Φ on
        the first link covers the gaps).
    bias_links : float
        A bias hypothesis costs C2 |b| ``bias_links``: without a prior a
        symmetric plan (a straight corridor) would pick among biases at random;
        a few links' worth lets a corridor's direction outvote it.
    compass_walk : float
        σ_q (rad/√s), how fast the summed gyro turns wander from the truth
        (``compass.fused_directions``): 2° per 0.7 m link at walking pace is
        about 2.6°/√s.
    """

    fit: TrackFitParams = field(default_factory=TrackFitParams)
    rotation_step: float = float(np.radians(5.0))
    scales: tuple[float, ...] = (0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15, 1.2)
    drifts: tuple[float, ...] = _degrees(-0.3, -0.15, 0.0, 0.15, 0.3)
    walking_speed: float = 1.2
    spacing: float = 1.0
    off_cap: float = 3.0
    candidates: int = 4
    variants: int = 2
    distinct: float = 3.0
    scale_links: float = 30.0
    drift_seconds: float = 90.0
    screen_weight: float = 0.1
    ambiguity_margin: float = 1.0
    bias_step: float = float(np.radians(5.0))
    bias_range: float = float(np.radians(45.0))
    bias_links: float = 3.0
    compass_walk: float = float(np.radians(2.5))


@dataclass(frozen=True)
class Candidate:
    """One fitted hypothesis.

    Attributes
    ----------
    rotation : float
        θ, direction (rad, counter-clockwise from +x) of the first link before fitting.
    scale : float
        s, the walker scale applied to every link.
    drift : float
        β (rad/s), the heading drift removed from the turns.
    screen : float
        Screening cost: m² of the rigid track off the plan (capped per sample,
        per metre of the measured track).
    fit : TrackFit
        The programme's fit under the hypothesis.
    score : float
        fit score + ``screen_weight`` × screen + the scale and drift priors;
        +inf when the fit failed.
    """

    rotation: float
    scale: float
    drift: float
    screen: float
    fit: TrackFit
    score: float


@dataclass(frozen=True)
class TrackSearch:
    """The best fitted hypothesis, the best distinct one after it, and whether they tie."""

    best: Candidate
    runner_up: Candidate | None
    ambiguous: bool
    screened: int
    """Number of hypotheses screened."""
    bias: float | None = None
    """The compass bias b (rad) of the best fit, when per-link headings were given."""


def durations(lengths: np.ndarray, times: np.ndarray | None, speed: float) -> np.ndarray:
    """Return each link's duration (s): from the times of its ends, else length / speed."""
    if times is None:
        return np.asarray(lengths, dtype=float) / speed
    return np.diff(np.asarray(times, dtype=float))


def hypothesis_turns(turns: np.ndarray, dt: np.ndarray, drift: np.ndarray) -> np.ndarray:
    """Return the turns (H, n) with the drift removed; the first is 0 (θ is the first direction).

    A bias β adds β t to the measured heading, so link i's direction is off
    by β t_i at its middle t_i; between links the turn is off by β (t_i - t_{i-1}).
    """
    mid = np.cumsum(dt) - 0.5 * dt
    # turn'_i = turn_i - β (t_i - t_{i-1}),  turn'_0 = 0
    out = turns[None, :] - drift[:, None] * np.diff(mid, prepend=mid[:1])[None, :]
    out[:, 0] = 0.0
    return out


def rigid_tracks(
    start: np.ndarray,
    lengths: np.ndarray,
    rotation: np.ndarray,
    scale: np.ndarray,
    turns: np.ndarray,
    which: np.ndarray | None = None,
) -> np.ndarray:
    """Dead-reckon every hypothesis: points (H, n + 1) as complex numbers x + iy.

    ψ_i = θ + Σ_{k ≤ i} turn'_k,  x_i = x_0 + s e^{iθ} Σ_{k ≤ i} l_k e^{i(ψ_k - θ)}: the
    shape depends only on the turns, so each row of ``turns`` (D, n) is
    integrated once and hypothesis h takes row ``which[h]`` (default h),
    rotated and scaled.
    """
    shape = np.cumsum(lengths[None, :] * np.exp(1j * np.cumsum(turns, axis=1)), axis=1)
    shape = np.concatenate([np.zeros((shape.shape[0], 1), complex), shape], axis=1)
    rows = np.arange(rotation.size) if which is None else which
    z0 = complex(start[0], start[1])
    return z0 + (scale * np.exp(1j * rotation))[:, None] * shape[rows]


def off_plan(plan: FloorPlan, z: np.ndarray, cap: float) -> np.ndarray:
    """Return each point's distance (m) to the nearest free cell, at most ``cap``."""
    ny, nx = plan.shape
    col = np.floor((z.real - plan.origin[0]) / plan.cell).astype(np.int32)
    row = np.floor((z.imag - plan.origin[1]) / plan.cell).astype(np.int32)
    inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    flat = np.where(inside, row * nx + col, 0)
    # |cell - nearest free cell| in cells, times the cell side
    dr = plan.nearest[0].ravel()[flat] - row
    dc = plan.nearest[1].ravel()[flat] - col
    d = np.sqrt((dr * dr + dc * dc).astype(np.float32)) * np.float32(plan.cell)
    return np.where(inside, np.minimum(d, np.float32(cap)), np.float32(cap))


def screen_costs(
    plan: FloorPlan,
    tracks: np.ndarray,
    lengths: np.ndarray,
    p: TrackSearchParams,
) -> np.ndarray:
    """Return every rigid track's area off the plan (m²), shape (H,).

    Each link is sampled every ``spacing`` (at the largest scale) and each
    sample counts its capped distance to free space times the measured length
    it stands for (so a shrunken track does not look better for being short).
    """
    n = lengths.size
    per_link = np.maximum(1, np.ceil(lengths * max(p.scales) / p.spacing)).astype(np.int64)
    link = np.repeat(np.arange(n), per_link)
    first = np.cumsum(per_link) - per_link
    frac = (np.arange(link.size) - first[link] + 1) / per_link[link]
    # sample = x_{i-1} + f (x_i - x_{i-1})
    a, b = tracks[:, link], tracks[:, link + 1]
    off = off_plan(plan, a + frac[None, :] * (b - a), p.off_cap)
    return off @ (lengths / per_link)[link]


def mean_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the mean distance (m) between track ``a`` (k,) and each track of ``b`` (H, k)."""
    return np.abs(b - a[None, :]).mean(axis=1)


def rival_of(
    best: Candidate, others: list[Candidate], p: TrackSearchParams
) -> tuple[Candidate | None, bool]:
    """Return the runner-up to ``best`` among ``others`` (by score) and whether they tie.

    The runner-up is the best fit whose track lies apart from the best's; the
    answer is ambiguous when it scores within ``ambiguity_margin``, or when any
    fit apart does once their rigid tracks' screening is set aside (that one
    is then the runner-up shown).
    """
    z_best = best.fit.points[:, 0] + 1j * best.fit.points[:, 1]

    def apart(c: Candidate) -> bool:
        z = c.fit.points[:, 0] + 1j * c.fit.points[:, 1]
        return z.shape == z_best.shape and mean_distance(z_best, z[None, :])[0] > p.distinct

    def bent(c: Candidate) -> float:
        return c.score - p.screen_weight * c.screen

    rivals = [c for c in others if apart(c)]
    if not rivals:
        return None, False
    if rivals[0].score - best.score < p.ambiguity_margin:
        return rivals[0], True
    close = [c for c in rivals if bent(c) - bent(best) < p.ambiguity_margin]
    return (close[0], True) if close else (rivals[0], False)


def search_track(
    plan: FloorPlan,
    start: np.ndarray,
    lengths: np.ndarray,
    turns: np.ndarray,
    *,
    heading: float | None = None,
    times: np.ndarray | None = None,
    anchors: AnchorCosts | None = None,
    compass: np.ndarray | None = None,
    compass_sigma: float = float(np.radians(10.0)),
    params: TrackSearchParams | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> TrackSearch:
    """Fit a track under its most plausible rotations, scales and drifts; return the best two.

    Parameters
    ----------
    plan : FloorPlan
        Free space.
    start : ndarray, shape (2,)
        x_0 (m).
    lengths, turns : ndarray, shape (n,)
        Links as ``fit_track`` takes them.
    heading : float, optional
        Direction (rad, CCW from +x) before the first link; the first link's
        direction is then ``heading + turns[0]`` and only scale and drift are
        searched.
    times : ndarray, shape (n + 1,), optional
        Times (s) of the start and of each link's end, for the drift; without
        them links last ``length / walking_speed``.
    anchors : AnchorCosts, optional
        WiFi scans along the track: they screen and score every hypothesis.
    compass : ndarray, shape (n,), optional
        Absolute direction of each link (rad, CCW from +x; NaN where unknown)
        with a constant unknown bias: fused with the turns
        (``compass.fused_directions``), it replaces the drift hypotheses and
        leaves only the bias, the rotation's, to search (``heading`` is then
        not used: a phone's first heading comes from the same compass).
    compass_sigma : float
        σ_c (rad) of one compass reading.
    params : TrackSearchParams, optional
        Hypotheses and comparison constants.
    clock : callable
        Seconds counter for the programme's time limit.
    """
    p = params or TrackSearchParams()
    start = np.asarray(start, dtype=float).reshape(2)
    lengths = np.asarray(lengths, dtype=float).reshape(-1)
    turns = np.asarray(turns, dtype=float).reshape(-1)
    if lengths.shape != turns.shape or lengths.size == 0:
        raise ValueError("lengths and turns must have the same, non-zero length")
    if times is not None and np.asarray(times).shape != (lengths.size + 1,):
        raise ValueError("times must hold the start and every link's end")
    dt = durations(lengths, times, p.walking_speed)
    drift_set = np.asarray(p.drifts, dtype=float)
    scale_set = np.asarray(p.scales, dtype=float)
    fused0 = None
    if compass is not None:
        fused = fused_directions(turns, compass, compass_sigma, p.compass_walk, dt)
        fused0 = float(fused[0])
        k = np.arange(
            -np.floor(p.bias_range / p.bias_step), np.floor(p.bias_range / p.bias_step) + 1
        )
        # θ = ψ̃_0 - b for every bias b tried
        thetas = wrap(fused0 - p.bias_step * k)
        rotation_prior = p.fit.c2 * np.abs(p.bias_step * k) * p.bias_links
        drift_set = np.zeros(1)
        corrected = np.r_[0.0, np.diff(fused)][None, :]
    else:
        if heading is None:
            k = np.arange(int(np.ceil(2 * np.pi / p.rotation_step)))
            thetas = -np.pi + p.rotation_step * k
        else:
            thetas = np.array([heading + turns[0]])
        rotation_prior = np.zeros(thetas.size)
        corrected = hypothesis_turns(turns, dt, drift_set)
    # every (θ, s, β) by index, θ slowest
    ti, si, di = (
        g.ravel()
        for g in np.meshgrid(
            np.arange(thetas.size),
            np.arange(scale_set.size),
            np.arange(drift_set.size),
            indexing="ij",
        )
    )
    theta, scale, drift = thetas[ti], scale_set[si], drift_set[di]
    tracks = rigid_tracks(start, lengths, theta, scale, corrected, di)
    screen = screen_costs(plan, tracks, lengths, p)
    # C1 |1 - s| N_s + C2 |β| T_β (+ C2 |b| N_b for a compass bias)
    prior = p.fit.c1 * np.abs(1.0 - scale) * p.scale_links
    prior += p.fit.c2 * np.abs(drift) * p.drift_seconds + rotation_prior[ti]
    # ranked by what the final score will hold: screening share, priors, anchors
    total = p.screen_weight * screen + prior
    if anchors is not None and len(anchors):
        xy = np.stack([tracks.real, tracks.imag], axis=-1)
        total += anchors.total(xy, p.fit.anchor_weight, p.fit.anchor_cap)

    ranked = np.argsort(total, kind="stable")
    chosen: list[int] = []
    for h in ranked:
        if len(chosen) == p.candidates:
            break
        if all(mean_distance(tracks[c], tracks[h : h + 1])[0] > p.distinct for c in chosen):
            chosen.append(int(h))
    # the best screened answer's next variants (other scales and drifts of about the
    # same track): screening ranks them too roughly to pick among them
    near = ranked[mean_distance(tracks[chosen[0]], tracks[ranked]) <= p.distinct]
    chosen += [int(h) for h in near if h not in chosen][: p.variants]

    picked = np.array(chosen)
    fits = fit_tracks(
        plan,
        start,
        lengths,
        corrected[di[picked]],
        headings=theta[picked],
        scales=scale[picked],
        params=p.fit,
        anchors=anchors,
        clock=clock,
    )
    fitted = [
        Candidate(
            float(theta[h]),
            float(scale[h]),
            float(drift[h]),
            float(screen[h]),
            fit,
            np.inf
            if fit.failed
            else fit.score + p.screen_weight * float(screen[h]) + float(prior[h]),
        )
        for h, fit in zip(picked, fits, strict=True)
    ]
    order = sorted(range(len(fitted)), key=lambda i: (fitted[i].score, i))
    best = fitted[order[0]]
    runner_up, ambiguous = rival_of(best, [fitted[i] for i in order[1:]], p)
    bias = None if fused0 is None else float(wrap(np.array(fused0 - best.rotation)))
    return TrackSearch(best, runner_up, bool(ambiguous), int(theta.size), bias)
