"""The setting every site1 evaluation starts from: the split options, the split and the learning.

Site1 is split by walk id with ``walk_split``'s hash (never by sample:
samples of one walk are correlated). ``--validation-fraction`` carves a
validation set out of the training walks and evaluates on it instead of the
test walks: for studying and tuning the methods without looking at the test
walks.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from app.datasets import data_dir
from app.datasets.ilc import Walk, site_walks
from app.evaluation.ilc.learn import Learned, learn
from app.evaluation.ilc.recordings import SiteRecordings, read_site_recordings
from app.evaluation.split import split_ids


def add_split_arguments(parser: argparse.ArgumentParser, validation_use: str) -> None:
    """Add the site and split options shared by the site1 evaluations."""
    parser.add_argument("--site", type=Path, default=None, help="default: <data>/ilc/site1")
    parser.add_argument(
        "--split",
        choices=["walk"],
        default="walk",
        help="held-out walks by a hash of the walk id (never by sample)",
    )
    parser.add_argument("--test-fraction", type=float, default=0.2)
    parser.add_argument(
        "--validation-fraction",
        type=float,
        default=0.0,
        help=f"carve this share out of training and {validation_use}",
    )


@dataclass(frozen=True, eq=False)
class Experiment:
    """A site split by walk id, what its training walks taught, and which walks are held out.

    ``validating`` says the held-out walks are the validation walks rather
    than the test walks.
    """

    site: SiteRecordings
    learned: Learned
    train: list[str]
    validation: list[str]
    test: list[str]
    validating: bool

    @property
    def held_out_kind(self) -> str:
        """Return "validation" or "test": which walks are held out."""
        return "validation" if self.validating else "test"

    def held_out_walks(self) -> list[Walk]:
        """Return the held-out walks with at least two waypoints, in walk id order."""
        chosen = set(self.validation if self.validating else self.test)
        walks = sorted(self.site.walks, key=lambda w: w.walk_id)
        return [w for w in walks if w.walk_id in chosen and w.waypoints.shape[0] >= 2]


def prepare_experiment(
    args: argparse.Namespace, status: Callable[[str], None] = lambda _: None
) -> Experiment:
    """Split site1's walk ids as ``args`` say, read the site and learn on the training walks."""
    site_dir = args.site or data_dir() / "ilc" / "site1"
    ids = [path.name.split(".")[0] for _, path in site_walks(site_dir)]
    train, validation, test = split_ids(ids, args.test_fraction, args.validation_fraction)
    site = read_site_recordings(site_dir, train_ids=train)
    learned = learn(site, train, status=status)
    return Experiment(site, learned, train, validation, test, args.validation_fraction > 0)
