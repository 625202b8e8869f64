"""Deterministic train, validation and test split of recordings by walk id.

Samples of one walk are strongly correlated (same phone, same path, same
minute), so splitting by sample leaks the test walks into training. The split
hashes each walk id to a number in [0, 1): it is the same on every run and
machine, does not depend on which other walks are present, and a walk never
changes side when recordings are added.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable


def walk_unit(walk_id: str) -> float:
    """Return the walk's position in [0, 1): the first 8 bytes of SHA-1 of its id, scaled."""
    digest = hashlib.sha1(walk_id.encode("utf-8")).digest()
    # u = int(digest[:8]) / 2⁶⁴
    return int.from_bytes(digest[:8], "big") / 2.0**64


def walk_split(walk_ids: Iterable[str], test_fraction: float = 0.2) -> tuple[list[str], list[str]]:
    """Split walk ids into (train, test), each sorted; a walk is test when its unit < fraction.

    Raises
    ------
    ValueError
        When ``test_fraction`` is outside [0, 1].
    """
    if not 0.0 <= test_fraction <= 1.0:
        raise ValueError("test_fraction must be in [0, 1]")
    ids = sorted(set(walk_ids))
    test = [w for w in ids if walk_unit(w) < test_fraction]
    train = [w for w in ids if walk_unit(w) >= test_fraction]
    return train, test


def split_ids(
    walk_ids: Iterable[str], test_fraction: float = 0.2, validation_fraction: float = 0.0
) -> tuple[list[str], list[str], list[str]]:
    """Split walk ids into (train, validation, test), each sorted.

    Test is ``walk_split``'s; validation takes the training walks whose unit
    lies in [test_fraction, test_fraction + validation_fraction), so tuning
    never sees a test walk and a larger validation share only takes from
    training.
    """
    train, test = walk_split(walk_ids, test_fraction)
    upper = test_fraction + validation_fraction
    validation = [w for w in train if walk_unit(w) < upper]
    train = [w for w in train if walk_unit(w) >= upper]
    return train, validation, test
