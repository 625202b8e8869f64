"""Walk split: by a stable hash of the walk id, never by sample."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from app.evaluation.split import split_ids, walk_split, walk_unit

IDS = [f"5dd9{i:020x}" for i in range(2000)]


def test_walk_unit_is_sha1_of_the_id_scaled_to_the_unit_interval() -> None:
    # sha1("abc") = a9993e364706816a ba3e2571... (FIPS 180-1 test vector)
    assert hashlib.sha1(b"abc").hexdigest().startswith("a9993e364706816a")
    assert walk_unit("abc") == int("a9993e364706816a", 16) / 2.0**64


def test_split_partitions_the_ids_and_is_deterministic() -> None:
    train, test = walk_split(IDS)
    assert sorted(train + test) == sorted(IDS)
    assert not set(train) & set(test)
    assert walk_split(list(reversed(IDS))) == (train, test)
    assert walk_split(IDS + IDS[:10]) == (train, test)


def test_split_fraction_is_close_to_the_requested_one() -> None:
    _, test = walk_split(IDS, test_fraction=0.2)
    # Binomial(2000, 0.2): std ≈ 17.9; 4 std either side.
    assert abs(len(test) - 400) < 72


def test_a_walk_keeps_its_side_when_other_walks_are_added_or_removed() -> None:
    _, test_all = walk_split(IDS)
    _, test_half = walk_split(IDS[::2])
    assert set(test_half) == set(test_all) & set(IDS[::2])


def test_larger_fraction_only_moves_walks_from_train_to_test() -> None:
    _, test_small = walk_split(IDS, 0.1)
    _, test_large = walk_split(IDS, 0.3)
    assert set(test_small) < set(test_large)
    assert walk_split(IDS, 0.0)[1] == [] and walk_split(IDS, 1.0)[0] == []


def test_units_are_uniform() -> None:
    u = np.array([walk_unit(w) for w in IDS])
    counts, _ = np.histogram(u, bins=10, range=(0, 1))
    # Pearson χ² with 9 dof: 27.9 is the 0.999 quantile.
    assert np.sum((counts - 200) ** 2 / 200) < 27.9


@pytest.mark.parametrize("fraction", [-0.1, 1.5])
def test_split_rejects_fractions_outside_the_unit_interval(fraction: float) -> None:
    with pytest.raises(ValueError, match="test_fraction"):
        walk_split(IDS, fraction)


def test_split_puts_no_walk_on_two_sides_and_test_is_walk_splits() -> None:
    train, validation, test = split_ids(IDS[:600], 0.2, 0.1)
    assert not set(train) & set(test)
    assert not set(train) & set(validation)
    assert not set(validation) & set(test)
    assert sorted(train + validation + test) == sorted(IDS[:600])
    assert test == walk_split(IDS[:600], 0.2)[1]
    # validation only takes walks out of training
    train0, _, test0 = split_ids(IDS[:600], 0.2, 0.0)
    assert test0 == test and set(train0) == set(train) | set(validation)
