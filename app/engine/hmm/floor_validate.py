"""The HMM's floor evidence weight, chosen by replaying held-out walks joined across floors.

How strongly one scan's floor evidence counts (``HmmParams.floor_weight``)
decides how fast the tracker leaves a wrong floor and follows a real change.
Per-scan scores choose too weak a weight where floors sound alike: each scan
is then rightly unsure, yet the tracker's belief, which keeps its floor
between scans, needs many such scans to move, so a walk that starts on the
wrong floor stays there and a change of floor is followed late. Every
survey walk stays on one floor, so a change is made by joining two held-out
walks recorded on different floors; the floor filter
(``app.engine.hmm.floor_filter``) runs over the joined walk's scans under
each candidate weight, and the share of scans it puts on a wrong floor is
the pair's score. Only the floor filter runs (no steps, no positions), so
every held-out walk can be replayed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.floor_filter import floor_sequence
from app.engine.hmm.params import HmmParams
from app.engine.samples import RssiReadings
from app.engine.scans import group_scans
from app.engine.wknn import unique_readings

FLOOR_CLASSIFIER_WEIGHT_CANDIDATES = (0.25, 0.5, 1.0, 2.0)
"""Tempers of the floor classifier's log-probabilities (``HmmParams.floor_classifier_weight``)
a build replays held-out walks, joined in pairs across floors, with, alone and beside each
of the radio map's floor weights."""


@dataclass(frozen=True, eq=False)
class FloorWalk:
    """A held-out walk's WiFi readings (site transmitter indices) and its floor index."""

    rssi: RssiReadings
    floor: int


def walk_floor_evidence(
    model: EmissionModel, rssi: RssiReadings, weights: Sequence[float], params: HmmParams
) -> tuple[np.ndarray, np.ndarray]:
    """Return every scan's floor evidence (W, S, F) and classifier log-probabilities (S, F).

    The evidence is under each of ``weights``; scans are in time order.
    Readings are grouped into scans as the tracker groups them, mapped
    transmitters only.
    """
    order = np.argsort(rssi.t, kind="stable")
    t = np.asarray(rssi.t, dtype=np.int64)[order]
    tx = np.asarray(rssi.tx, dtype=np.int32)[order]
    level = np.asarray(rssi.rssi, dtype=float)[order]
    mapped = model.is_mapped(tx)
    t, tx, level = t[mapped], tx[mapped], level[mapped]
    scans = [unique_readings(tx[g], level[g]) for g in group_scans(t, tx, params.scans)]
    n_floors = len(model.maps)
    if not scans:
        return np.zeros((len(weights), 0, n_floors)), np.zeros((0, n_floors))
    marginals = np.stack([model.floor_log_marginals_by_weight(*s, weights) for s in scans], axis=1)
    classified = np.stack([model.floor_classifier_log_probs(*s) for s in scans])
    return marginals, classified


def floor_pairs(floors: Sequence[int]) -> list[tuple[int, int]]:
    """Return each walk paired with the next one (in order, wrapping) on another floor."""
    n = len(floors)
    out = []
    for i in range(n):
        j = next((k % n for k in range(i + 1, i + n) if floors[k % n] != floors[i]), None)
        if j is not None:
            out.append((i, j))
    return out


@dataclass(frozen=True, eq=False)
class WalkEvidence:
    """A held-out walk's per-scan floor evidence and its true floor index.

    ``marginals`` is the radio map's under each floor weight (W, S, F),
    ``classified`` the classifier's log-probabilities (S, F).
    """

    marginals: np.ndarray
    classified: np.ndarray
    floor: int


def walk_evidence(
    model: EmissionModel, walks: Sequence[FloorWalk], weights: Sequence[float], params: HmmParams
) -> list[WalkEvidence]:
    """Return the floor evidence of every walk that has scans (``walk_floor_evidence``)."""
    out = []
    for walk in walks:
        marginals, classified = walk_floor_evidence(model, walk.rssi, weights, params)
        if marginals.shape[1]:
            out.append(WalkEvidence(marginals, classified, walk.floor))
    return out


def pair_shares(
    evidence: Sequence[WalkEvidence],
    weight: int | None,
    classifier_weight: float,
    floor_of_map: np.ndarray,
    params: HmmParams,
) -> list[float]:
    """Return each joined pair's share of scans followed on a wrong floor.

    The evidence is the radio map's under weight number ``weight`` (None:
    left out, a floor weight of 0) plus ``classifier_weight`` times the
    classifier's.
    """
    shares = []
    truth = [e.floor for e in evidence]

    def scan_evidence(e: WalkEvidence) -> np.ndarray:
        # e = ln mean L^w + c ln p(f | scan)
        radio = 0.0 if weight is None else e.marginals[weight]
        return radio + classifier_weight * e.classified

    for i, j in floor_pairs(truth):
        a, b = evidence[i], evidence[j]
        joined = np.concatenate([scan_evidence(a), scan_evidence(b)])
        expected = np.repeat([a.floor, b.floor], [a.classified.shape[0], b.classified.shape[0]])
        followed = floor_of_map[
            floor_sequence(joined, params.floor_switch_prob, params.floor_switch_posterior)
        ]
        shares.append(float(np.mean(followed != expected)))
    return shares


def floor_pair_scores(
    model: EmissionModel, walks: Sequence[FloorWalk], weights: Sequence[float], params: HmmParams
) -> dict[float, list[float]]:
    """Return, per floor weight, each joined pair's share of scans on a wrong floor.

    The radio map's evidence alone.

    Pairs are ``floor_pairs`` of the walks that have scans; empty lists when
    no two of them are on different floors.
    """
    evidence = walk_evidence(model, walks, weights, params)
    floor_of_map = np.asarray(model.floors, dtype=np.int64)
    return {
        float(w): pair_shares(evidence, k, 0.0, floor_of_map, params) for k, w in enumerate(weights)
    }
