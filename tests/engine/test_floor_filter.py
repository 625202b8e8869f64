"""The HMM's floor filter and the build's replay of it over walks joined across floors."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.floor_filter import floor_belief, floor_sequence, tracked_floor
from app.engine.hmm.floor_validate import FloorWalk, floor_pair_scores, floor_pairs
from app.engine.hmm.params import HmmParams
from app.engine.samples import RssiReadings
from tests.engine.test_hmm import SLOPE_DB, corridor


def test_the_belief_keeps_its_floor_by_the_switch_prior_then_weighs_the_evidence() -> None:
    belief = np.log(np.array([0.9, 0.05, 0.05]))
    evidence = np.array([0.0, 1.0, -1.0])
    got = np.exp(floor_belief(belief, evidence, 0.01))
    # π_f = (1 - ε) b_f + ε (1 - b_f) / (n - 1), times e^{evidence}, normalised
    prior = 0.99 * np.exp(belief) + 0.01 * (1 - np.exp(belief)) / 2
    expected = prior * np.exp(evidence)
    assert got == pytest.approx(expected / expected.sum(), rel=1e-12)


def test_the_followed_floor_changes_only_once_another_is_sure_enough() -> None:
    assert tracked_floor(-1, np.log([0.4, 0.6]), 0.8) == 1
    assert tracked_floor(0, np.log([0.3, 0.7]), 0.8) == 0
    assert tracked_floor(0, np.log([0.1, 0.9]), 0.8) == 1


def test_a_walk_follows_a_change_of_floor_after_enough_evidence() -> None:
    # five scans say floor 0, then five say floor 1, each by 2 nats
    evidence = np.array([[0.0, -2.0]] * 5 + [[-2.0, 0.0]] * 5)
    followed = floor_sequence(evidence, 1e-3, 0.8)
    assert followed[:5].tolist() == [0] * 5
    # the belief built over five scans takes more than one contrary scan to undo
    assert followed[5] == 0 and followed[-1] == 1


def test_each_walk_is_paired_with_the_next_on_another_floor() -> None:
    assert floor_pairs([0, 0, 1, 2]) == [(0, 2), (1, 2), (2, 3), (3, 0)]
    assert floor_pairs([1, 1]) == []


def _quiet(floor: int, offset_db: float) -> object:
    m = corridor(floor, (0, 1))
    return replace(m, mean=m.mean - offset_db)


def _walk(floor: int, offset_db: float, t0: int, cells: range) -> FloorWalk:
    t, tx, rssi = [], [], []
    for k, c in enumerate(cells):
        t += [t0 + 2000 * k] * 2
        tx += [0, 1]
        rssi += [-40.0 - SLOPE_DB * c - offset_db, -40.0 - SLOPE_DB * (29 - c) - offset_db]
    readings = RssiReadings(np.array(t, np.int64), np.array(tx, np.int32), np.array(rssi))
    return FloorWalk(readings, floor)


def test_a_stronger_floor_weight_leaves_a_wrong_floor_sooner_where_floors_sound_alike() -> None:
    # two floors hearing the same access points, the upper 2 dB quieter
    params = HmmParams()
    model = EmissionModel([_quiet(0, 0.0), _quiet(1, 2.0)], params)
    walks = [_walk(0, 0.0, 0, range(5, 25)), _walk(1, 2.0, 100_000, range(5, 25))]
    weights = (0.02, 0.5, 2.0)
    scores = floor_pair_scores(model, walks, weights, params)
    # both walks start a pair; each pair's share is over both walks' 40 scans
    assert all(len(v) == 2 for v in scores.values())
    share = [float(np.mean(scores[w])) for w in weights]
    # too weak, the second walk is never followed; strong enough, within a few scans
    assert share[0] == 0.5 and share[0] > share[1] > share[2]
    assert share[2] < 0.2
    # the weights' evidence is what the tracker's own floor weight gives
    evidence = model.floor_log_marginals_by_weight(
        np.array([0, 1]), np.array([-70.0, -70.0]), weights
    )
    for k, w in enumerate(weights):
        own = EmissionModel(model.maps, replace(params, floor_weight=w))
        assert evidence[k] == pytest.approx(
            own.floor_log_marginals(np.array([0, 1]), np.array([-70.0, -70.0])), abs=1e-9
        )
