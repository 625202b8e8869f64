"""UWB trolley reader: transcribed tables, file layout, attitude convention, truth against fixes."""

from __future__ import annotations

import re

import numpy as np
import pytest

from app.datasets.uwb_trolley import (
    ANCHORS_XYZ,
    BODY_FLIP,
    TAG_LEVER_ARMS,
    body_attitude,
    check_attitude,
    folder,
    parse_wall_times,
    quaternion_matrix,
    read_motion_capture,
    read_ranges,
    tag_positions,
    tag_truth,
    to_ranges,
    trolley_site,
)
from app.engine.lateration.solver import solve

pytestmark = pytest.mark.skipif(not folder().exists(), reason="uwb_trolley recording not present")


def _readme_table(title: str) -> np.ndarray:
    """Rows of numbers of the markdown table under ``title`` in SOURCE_README.md."""
    text = (folder() / "SOURCE_README.md").read_text()
    section = text[text.index(title) :]
    rows = re.findall(r"^\|\s*(?:Tag|Anchor) \d\s*\|(.*)\|\s*$", section, flags=re.MULTILINE)
    return np.array([[float(v) for v in row.split("|")] for row in rows])


@pytest.fixture(scope="module")
def rec():
    return read_ranges()


@pytest.fixture(scope="module")
def mc():
    return read_motion_capture()


def test_tables_are_the_readmes() -> None:
    np.testing.assert_array_equal(_readme_table("Coordinates of UWB anchors")[:8], ANCHORS_XYZ)
    np.testing.assert_array_equal(_readme_table("Coordinates of UWB tags")[:3], TAG_LEVER_ARMS)


def test_wall_times() -> None:
    t = parse_wall_times(["2022-08-15 9:42:24.766", "2022-08-15 10:00:00.5", "2022-08-16 0:00:00"])
    base = np.datetime64("2022-08-15T09:42:24.766", "ms").astype(np.int64)
    assert t[0] == base
    # 10:00:00.500 − 9:42:24.766
    assert t[1] - t[0] == (10 * 3600) * 1000 + 500 - ((9 * 60 + 42) * 60 + 24) * 1000 - 766
    assert t[2] == np.datetime64("2022-08-16", "ms").astype(np.int64)


def test_ranges_layout(rec) -> None:
    first = (folder() / "UWB_dynamic_exp_fast.csv").read_text().splitlines()[0].split(",")
    assert rec.ranges.shape == (len(rec), 8, 3)
    # columns a0-t0, a0-t1, a0-t2, a1-t0, …: anchor-major
    assert rec.ranges[0, 0, 1] == float(first[2]) and rec.ranges[0, 1, 0] == float(first[4])
    assert np.all(np.diff(rec.t) >= 0)
    samples = to_ranges(rec, 2, std=0.1)
    assert samples.range.size == np.isfinite(rec.ranges[:, :, 2]).sum()
    assert samples.anchor.max() == 7 and np.isfinite(samples.range).all()


def test_motion_capture_rows_have_distinct_times(mc) -> None:
    assert np.all(np.diff(mc.t) > 0)
    np.testing.assert_allclose(np.linalg.norm(mc.quaternion, axis=1), 1.0, atol=1e-5)


def test_quaternion_matrix_hand_cases() -> None:
    half = np.sqrt(0.5)
    R = quaternion_matrix(np.array([[1.0, 0, 0, 0], [half, 0, 0, half], [0.0, 1, 0, 0]]))
    np.testing.assert_allclose(R[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R[1] @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # 90° about z
    np.testing.assert_allclose(R[2], np.diag([1.0, -1, -1]), atol=1e-12)  # 180° about x


def test_body_x_points_along_the_motion_and_z_up(mc) -> None:
    check = check_attitude(mc)
    assert check.concentration > 0.99 and abs(check.offset_deg) < 10.0
    assert check.up_z > 0.99 and check.moving > 0.5
    # as documented (w, x, y, z) without the flip the body z axis points down
    assert np.median(quaternion_matrix(mc.quaternion)[:, 2, 2]) < -0.99
    np.testing.assert_allclose(
        body_attitude(mc)[0], quaternion_matrix(mc.quaternion[:1])[0] @ BODY_FLIP
    )


def test_truth_meets_the_fixes_only_with_the_flip(rec, mc) -> None:
    """Over the first 2,000 rows, raw fixes of each tag are 0.16–0.17 m from truth with the flip,
    0.2–0.44 m without it (the tags are then mirrored across the trolley's x axis)."""
    rows = slice(0, 2000)
    flipped = []
    plain = []
    for tag in range(3):
        fix = solve(
            "range", ANCHORS_XYZ, rec.ranges[rows, :, tag], np.full(8, 0.1), height=0.97, dims=2
        )
        truth = tag_truth(mc, tag, rec.t[rows])
        flipped.append(np.sqrt(np.nanmean(np.sum((fix.position[:, :2] - truth[:, :2]) ** 2, 1))))
        mirror = mc.centroid + quaternion_matrix(mc.quaternion) @ TAG_LEVER_ARMS[tag]
        other = np.column_stack([np.interp(rec.t[rows], mc.t, mirror[:, k]) for k in range(2)])
        plain.append(np.sqrt(np.mean(np.sum((fix.position[:, :2] - other) ** 2, 1))))
    assert max(flipped) < 0.2
    assert all(p > f + 0.03 for p, f in zip(plain, flipped, strict=True))
    assert np.mean(plain) > 1.5 * np.mean(flipped)


def test_tag_truth_interpolates_and_marks_outside_times(mc) -> None:
    pos = tag_positions(mc, 1)
    mid = (mc.t[10] + mc.t[11]) / 2
    out = tag_truth(mc, 1, np.array([mc.t[10], mid, mc.t[0] - 5, mc.t[-1] + 5]))
    np.testing.assert_allclose(out[0], pos[10])
    np.testing.assert_allclose(out[1], (pos[10] + pos[11]) / 2)
    assert np.isnan(out[2:]).all()
    shifted = tag_truth(mc, 1, np.array([mc.t[10] - 7]), offset_ms=7)
    np.testing.assert_allclose(shifted[0], pos[10])


def test_site_holds_the_anchors_on_an_open_floor() -> None:
    site = trolley_site()
    np.testing.assert_array_equal(site.anchors.xyz, ANCHORS_XYZ)
    plan = site.floors[0].plan
    assert plan.is_free(ANCHORS_XYZ[:, :2]).all() and plan.free.all()
