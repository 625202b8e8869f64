"""A site's building-dependent constants, learned from its own surveys at radio-map build time.

A building differs from the next in ways no default can know: how its
floor plan is rotated against magnetic north (the PDR heading offset), how
long its walkers' steps are (Weinberg's K), how far apart its fingerprints
are in signal space (the number of WKNN neighbours, the per-scan k-NN's
neighbours and their weights, the HMM's emission weight), how far the
fingerprints themselves are from the truth (the accuracy floor, the spread
of the HMM's k-NN fix) and how far the tracker's positions may be trusted
against its steps (the smoothers' fix scales). A radio-map build chooses
each from the site's survey walks (walk-level folds: no walk both trains and
tests), stores them with the maps, and the site's engines read them from
there; the defaults only seed the choice and stand in where a site has no
surveys.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np

from app.engine.crossval import CrossValidation
from app.engine.hmm.params import HmmParams
from app.engine.pdr import PdrParams
from app.engine.pdr_fit import WalkPdr, fit_pdr_constants, wrap_deg
from app.engine.scan_knn import ScanKnnParams
from app.engine.smoothing import SmootherParams
from app.engine.wifi_age import DEFAULT_MAX_AGE_MS
from app.engine.wknn import WknnParams

HEADING_STD_RANGE_DEG = (5.0, 45.0)
"""Bounds of the learned step heading standard deviation: below, one lucky survey
would make the HMM trust its compass blindly; above, steps say nothing of direction."""

WKNN_K_CANDIDATES = (1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20)
"""Numbers of WKNN neighbours a build cross-validates."""

EMISSION_WEIGHT_CANDIDATES = (0.02, 0.03, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.6, 0.8, 1.0)
"""HMM emission (and floor evidence) weights a build scores on held-out scans."""

HMM_WEIGHT_CANDIDATES = (0.05, 0.1, 0.2, 0.35)
"""Emission weights a build replays held-out walks with."""

FLOOR_WEIGHT_CANDIDATES = (0.05, 0.1, 0.2, 0.4, 0.8, 1.6)
"""Floor evidence weights (``HmmParams.floor_weight``) a build replays held-out walks, joined
in pairs across floors, with (``app.engine.hmm.floor_validate``). Scored on single scans
instead, a small building's floor weight came out so low that the HMM then put many of its
positions on a wrong floor; and the higher the weight, the sooner a change of floor is
followed. The build's share of wrong floors at each candidate is its
``wrong_floor_share_by_floor_weight``, which ``locus eval ilc`` prints."""

FIX_WEIGHT_CANDIDATES = (0.0, 10.0, 20.0)
"""Weights of the per-scan k-NN fix in the HMM's emission a build replays held-out walks
with: on a sparse survey the nearest survey scans can be far from the walker, and the fix
then pulls the track the wrong way."""

WALK_NOISE_CANDIDATES = (0.02, 0.05, 0.15, 0.5)
"""Transition noise (m² per second, ``HmmParams.walk_noise_m2_per_s``) a build replays
held-out walks with: how far the walker may stray from the steps between scans. Phones
whose steps are poorly counted or oriented need more, while well-counted steps lose by it.
The build's HMM error at each candidate is its ``hmm_walk_error_m_by_walk_noise``, which
``locus eval ilc`` prints."""

SMOOTHER_FIX_SCALE_CANDIDATES = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0)
"""Factors on the positions' σ a build scores the fixed-lag and full-pass smoothers with,
on the replayed held-out walks: how much a filter's positions, each carrying the scans
before it, may count against the steps between them."""

MAD_TO_STD = 1.4826
"""Scale of the median absolute deviation to a Gaussian standard deviation."""


@dataclass(frozen=True)
class SiteTuning:
    """Building-dependent constants chosen at build time.

    Attributes
    ----------
    weinberg_k : float
        Step length constant fitted to the surveys' walked distances.
    heading_offset_deg : float
        Rotation (degrees) from PDR headings to the site frame.
    heading_std_deg : float
        Spread (degrees) of survey segments' PDR headings about the truth
        once the offset is applied: the HMM's step heading noise.
    wknn_k : int
        Number of WKNN neighbours.
    emission_weight : float
        Exponent tempering the HMM's per-scan likelihood of positions.
    floor_weight : float
        Exponent tempering it when floors are weighed against each other
        (0: the floors are the floor classifier's alone).
    accuracy_floor_m : float
        Added in quadrature to the radius (m): the floor under which the
        HMM's radius holds 68% of its errors on the replayed held-out walks
        (set by the build), else the median held-out WKNN error.
    pdr_walks : int
        Survey walks the PDR constants were fitted on (0: defaults kept).
    radius_scale : float
        Factor on the HMM posterior's radius (below 1 where the spread alone
        held more than 68% of the replayed walks' errors).
    fix_nats : float
        Weight of the per-scan k-NN fix in the HMM's emission.
    lag_fix_scale : float
        Factor on the positions' σ in the fixed-lag smoother.
    pass_fix_scale : float
        The same in the full backward pass over stored history.
    wifi_max_age_ms : int
        Oldest a WiFi reading's last-seen time may be before its scan's
        time (ms) for the engines to use it (``app.engine.wifi_age``).
    scan_knn_k : int
        Survey scans the per-scan k-NN averages (``app.engine.scan_knn_cv``).
    scan_knn_power : float
        Exponent of its neighbour weights ``(d / d_min)^-p``.
    scan_knn_level_power : int
        Exponent of a shared transmitter's level in its weight in the scan
        distance (``ScanKnnParams.level_power``).
    scan_knn_floor_dbm : float
        Signal level the scan distance counts as nothing (``ScanKnnParams.floor_dbm``).
    scan_knn_unshared_penalty : float
        Scan distance (dB) of two scans sharing nothing
        (``ScanKnnParams.unshared_penalty``).
    fix_sigma_m : float
        Spread (m) of each neighbour of the HMM's k-NN fix: the root mean
        square of the held-out k-NN errors (``app.engine.scan_knn_cv``).
    walk_noise_m2_per_s : float
        The HMM's transition noise beyond the steps' own (m² per second).
    floor_classifier_weight : float
        Temper of the per-scan floor classifier in the HMM's floor evidence
        (0: the radio map's evidence alone).
    """

    weinberg_k: float
    heading_offset_deg: float
    heading_std_deg: float
    wknn_k: int
    emission_weight: float
    floor_weight: float
    accuracy_floor_m: float
    pdr_walks: int = 0
    radius_scale: float = 1.0
    fix_nats: float = HmmParams().fix_nats
    lag_fix_scale: float = SmootherParams().fix_scale
    pass_fix_scale: float = SmootherParams().fix_scale
    wifi_max_age_ms: int = DEFAULT_MAX_AGE_MS
    scan_knn_k: int = ScanKnnParams().k
    scan_knn_power: float = ScanKnnParams().weight_power
    scan_knn_level_power: int = ScanKnnParams().level_power
    scan_knn_floor_dbm: float = ScanKnnParams().floor_dbm
    scan_knn_unshared_penalty: float = ScanKnnParams().unshared_penalty
    fix_sigma_m: float = HmmParams().fix_sigma_m
    walk_noise_m2_per_s: float = HmmParams().walk_noise_m2_per_s
    floor_classifier_weight: float = HmmParams().floor_classifier_weight

    @classmethod
    def defaults(cls) -> SiteTuning:
        """Return the engines' defaults: what a site without a build runs."""
        pdr, hmm = PdrParams(), HmmParams()
        return cls(
            weinberg_k=pdr.weinberg_k,
            heading_offset_deg=pdr.heading_offset_deg,
            heading_std_deg=hmm.heading_std_deg,
            wknn_k=WknnParams().k,
            emission_weight=hmm.emission_weight,
            floor_weight=hmm.floor_weight,
            accuracy_floor_m=hmm.accuracy_floor_m,
        )

    def as_dict(self) -> dict[str, Any]:
        """Return the constants as JSON-ready numbers (stored in the build summary)."""
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> SiteTuning:
        """Return the tuning stored by ``as_dict``; defaults for anything missing."""
        base = asdict(cls.defaults())
        known = {f.name for f in fields(cls)}
        return cls(**(base | {k: v for k, v in (data or {}).items() if k in known}))

    def pdr(self, base: PdrParams | None = None) -> PdrParams:
        """Return PDR constants with the site's step length and heading offset."""
        return replace(
            base or PdrParams(),
            weinberg_k=self.weinberg_k,
            heading_offset_deg=self.heading_offset_deg,
        )

    def hmm(self, base: HmmParams | None = None) -> HmmParams:
        """Return HMM constants with the site's weights, noises and accuracy floor.

        The HMM's k-NN start keeps its own k: the WKNN's best k averages many
        neighbours on a sparse map, a poor place to restart a track.
        """
        return replace(
            base or HmmParams(),
            emission_weight=self.emission_weight,
            floor_weight=self.floor_weight,
            heading_std_deg=self.heading_std_deg,
            accuracy_floor_m=self.accuracy_floor_m,
            radius_scale=self.radius_scale,
            fix_nats=self.fix_nats,
            fix_sigma_m=self.fix_sigma_m,
            walk_noise_m2_per_s=self.walk_noise_m2_per_s,
            floor_classifier_weight=self.floor_classifier_weight,
            references=self.scan_knn((base or HmmParams()).references),
        )

    def scan_knn(self, base: ScanKnnParams | None = None) -> ScanKnnParams:
        """Return per-scan k-NN constants with the site's neighbours, powers and distance."""
        return replace(
            base or ScanKnnParams(),
            k=self.scan_knn_k,
            weight_power=self.scan_knn_power,
            level_power=self.scan_knn_level_power,
            floor_dbm=self.scan_knn_floor_dbm,
            unshared_penalty=self.scan_knn_unshared_penalty,
        )

    def fixed_lag(self, base: SmootherParams | None = None) -> SmootherParams:
        """Return the live fixed-lag smoother's constants with the site's fix scale."""
        return replace(base or SmootherParams(), fix_scale=self.lag_fix_scale)

    def full_pass(self, base: SmootherParams | None = None) -> SmootherParams:
        """Return the history's full-pass smoother constants with the site's fix scale."""
        return replace(base or SmootherParams(), fix_scale=self.pass_fix_scale)

    def wknn(self, base: WknnParams | None = None) -> WknnParams:
        """Return WKNN constants with the site's number of neighbours."""
        return replace(base or WknnParams(), k=self.wknn_k)


def heading_spread(walks: Sequence[WalkPdr], offset_deg: float) -> float | None:
    """Return the robust spread (degrees) of segment heading errors after the offset."""
    errors = np.concatenate([w.segment_error for w in walks]) if walks else np.zeros(0)
    if errors.size < 3:
        return None
    residual = wrap_deg(errors + offset_deg)
    # σ ≈ 1.4826 median |r - median r|
    spread = MAD_TO_STD * float(np.median(np.abs(residual - np.median(residual))))
    return float(np.clip(spread, *HEADING_STD_RANGE_DEG))


def one_standard_error_choice(scores: Mapping[float, Sequence[float]], default: float) -> float:
    """Return the candidate nearest ``default`` that is as good as the best, walk by walk.

    Scores are lower-is-better, one per held-out walk, the same walks in the
    same order for every candidate. A candidate is as good as the best when
    its mean excess over the best's, walk by walk, is within one standard
    error of that excess: comparing on the same walks sets aside how hard each
    walk is (a walk the survey covers poorly is poor under every candidate),
    and what is left is whether the constant helps more than by luck. Nearest
    in ratio (0, meaning off, is farthest from any other value).
    """
    values = {c: np.asarray(v, dtype=float) for c, v in scores.items() if len(v)}
    best = min(values, key=lambda c: float(np.mean(values[c])))

    def as_good(c: float) -> bool:
        excess = values[c] - values[best]
        n = excess.size
        se = float(np.std(excess, ddof=1) / np.sqrt(n)) if n > 1 else 0.0
        return float(np.mean(excess)) <= se

    def distance(c: float) -> float:
        if c == default:
            return 0.0
        return abs(float(np.log(c / default))) if c > 0 and default > 0 else float("inf")

    return min((c for c in values if as_good(c)), key=lambda c: (distance(c), c))


def one_move_choice(
    scores: Sequence[Mapping[float, Sequence[float]]], defaults: Sequence[float]
) -> tuple[float, ...]:
    """Return ``defaults`` with at most one constant moved, by per-walk scores.

    ``scores[i]`` holds the walk scores of constant i's candidates, the
    others at their defaults. Each constant's choice is the one-standard-error
    rule's; where several would move, only the move with the lowest mean score
    is taken, so the result is a candidate that was scored, never an untried
    combination.
    """
    out = tuple(float(d) for d in defaults)
    best: tuple[float, int, float] | None = None
    for i, (by_value, default) in enumerate(zip(scores, defaults, strict=True)):
        if not by_value:
            continue
        chosen = one_standard_error_choice(by_value, default)
        mean = float(np.mean(by_value[chosen]))
        if chosen != default and (best is None or mean < best[0]):
            best = (mean, i, float(chosen))
    if best is None:
        return out
    _, i, value = best
    return out[:i] + (value,) + out[i + 1 :]


def tune_site(
    walks: Sequence[WalkPdr],
    held: CrossValidation | None,
    hmm_weight: float | None = None,
    floor_weight: float | None = None,
) -> SiteTuning:
    """Choose a site's constants from its measured survey walks and cross-validation.

    ``hmm_weight`` and ``floor_weight`` (chosen by replaying held-out walks
    through the HMM, and through its floor filter joined across floors) set
    the emission and floor weights where given; the
    per-scan scores of ``held`` choose them otherwise. The two are chosen
    apart: tied to the emission weight, the floor weight followed it down
    where the replays wanted the steps trusted more, and put more positions on
    a wrong floor.
    """
    base = SiteTuning.defaults()
    pdr = fit_pdr_constants(walks, PdrParams()) if walks else PdrParams()
    spread = heading_spread(walks, pdr.heading_offset_deg)
    k = held.best_k() if held is not None else base.wknn_k
    weight = held.best_emission_weight() if held is not None else None
    if floor_weight is None and held is not None:
        floor_weight = held.best_floor_weight()
    if hmm_weight is not None:
        weight = hmm_weight
    floor = float(np.median(held.by_k[k].error_m)) if held is not None else base.accuracy_floor_m
    return SiteTuning(
        weinberg_k=pdr.weinberg_k,
        heading_offset_deg=pdr.heading_offset_deg,
        heading_std_deg=spread if spread is not None else base.heading_std_deg,
        wknn_k=k,
        emission_weight=weight if weight is not None else base.emission_weight,
        floor_weight=floor_weight if floor_weight is not None else base.floor_weight,
        accuracy_floor_m=floor,
        pdr_walks=len(walks),
    )
