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


@dataclass(frozen=True, eq=False)
class FloorWalk:
    """A held-out walk's WiFi readings (site transmitter indices) and its floor index."""

    rssi: RssiReadings
    floor: int


def walk_floor_evidence(
    model: EmissionModel, rssi: RssiReadings, weights: Sequence[float], params: HmmParams
) -> np.ndarray:
    """Return every scan's floor evidence under each weight, (W, S, F), scans in time order.

    Readings are grouped into scans as the tracker groups them, mapped
    transmitters only.
    """
    order = np.argsort(rssi.t, kind="stable")
    t = np.asarray(rssi.t, dtype=np.int64)[order]
    tx = np.asarray(rssi.tx, dtype=np.int32)[order]
    level = np.asarray(rssi.rssi, dtype=float)[order]
    mapped = model.is_mapped(tx)
    t, tx, level = t[mapped], tx[mapped], level[mapped]
    scans = [
        model.floor_log_marginals_by_weight(*unique_readings(tx[g], level[g]), weights)
        for g in group_scans(t, tx, params.scans)
    ]
    if not scans:
        return np.zeros((len(weights), 0, len(model.maps)))
    return np.stack(scans, axis=1)


def floor_pairs(floors: Sequence[int]) -> list[tuple[int, int]]:
    """Return each walk paired with the next one (in order, wrapping) on another floor."""
    n = len(floors)
    out = []
    for i in range(n):
        j = next((k % n for k in range(i + 1, i + n) if floors[k % n] != floors[i]), None)
        if j is not None:
            out.append((i, j))
    return out


def floor_pair_scores(
    model: EmissionModel, walks: Sequence[FloorWalk], weights: Sequence[float], params: HmmParams
) -> dict[float, list[float]]:
    """Return, per floor weight, each joined pair's share of scans followed on a wrong floor.

    Pairs are ``floor_pairs`` of the walks that have scans; empty lists when
    no two of them are on different floors.
    """
    evidence, truth = [], []
    for walk in walks:
        e = walk_floor_evidence(model, walk.rssi, weights, params)
        if e.shape[1]:
            evidence.append(e)
            truth.append(walk.floor)
    floor_of_map = np.asarray(model.floors, dtype=np.int64)
    scores: dict[float, list[float]] = {float(w): [] for w in weights}
    for i, j in floor_pairs(truth):
        joined = np.concatenate([evidence[i], evidence[j]], axis=1)
        expected = np.repeat([truth[i], truth[j]], [evidence[i].shape[1], evidence[j].shape[1]])
        for k, w in enumerate(weights):
            followed = floor_of_map[
                floor_sequence(joined[k], params.floor_switch_prob, params.floor_switch_posterior)
            ]
            scores[float(w)].append(float(np.mean(followed != expected)))
    return scores
