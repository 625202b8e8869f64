"""The BLE flat evaluation on the real recordings: its figures and its plot."""

from __future__ import annotations

from pathlib import Path

import pytest

from app.datasets import ble_flat
from app.evaluation import ble_flat_eval

pytestmark = pytest.mark.skipif(
    not ble_flat.root().is_dir(), reason="ble_flat recordings not present"
)


def test_particle_filter_beats_the_weighted_centroid_and_plots_the_track(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ble_flat_eval.main(["--seeds", "1", "--no-train", "--plots", str(tmp_path)])
    report = capsys.readouterr().out
    rows = {
        line[:32].strip(): float(line[32:].split()[0])
        for line in report.splitlines()
        if line.startswith(("PF, walls ", "weighted centroid"))
    }
    # test-track mean error (m): the filter with walls below the model-free reference
    assert rows["PF, walls"] < rows["weighted centroid (reference)"]
    png = tmp_path / "ble_flat_test_track.png"
    assert png.stat().st_size > 10_000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
