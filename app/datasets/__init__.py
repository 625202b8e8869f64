"""Readers for the public recordings used in tests, evaluation and benchmarks."""

from __future__ import annotations

import os
from pathlib import Path


def data_dir() -> Path:
    """Return the recordings folder: ``$LOCUS_DATA_DIR`` or ``../shared/data`` beside the repo."""
    env = os.environ.get("LOCUS_DATA_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2].parent / "shared" / "data"
