"""The compiled particle-filter loops against the numpy reference they reproduce."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.engine.particle import kernel, weights
from app.engine.particle.bank import ParticleBank
from app.engine.particle.estimate import RADIUS_EDGES, FilterEstimate, cloud_estimate
from app.engine.particle.floor_model import build_floor_models
from app.engine.particle.inputs import FilterInput
from app.engine.particle.motion import settle_moves, walk_displacement, window_displacement
from app.engine.particle.params import ParticleFilterParams
from app.engine.particle.update import update_filters
from app.engine.pathloss import expected_rssi, ranges_3d
from app.engine.plan import FloorPlan, burn_segments
from app.engine.site import Emitters, Floor, SiteModel

CELL = 0.25
P = ParticleFilterParams(n_particles=500)


def offices() -> SiteModel:
    """A 30 × 20 m floor: a corridor along y = 10, 5 m rooms either side with 1 m doors."""
    segments = [[0, 0, 30, 0], [30, 0, 30, 20], [30, 20, 0, 20], [0, 20, 0, 0]]
    for y in (8.5, 11.5):
        segments += [[x0, y, x0 + 4.0, y] for x0 in range(0, 30, 5)]
        far = 0.0 if y < 10 else 20.0
        segments += [[x0, y, x0, far] for x0 in range(5, 30, 5)]
    free = np.ones((80, 120), bool)
    burn_segments(free, np.array(segments, float), origin=np.zeros(2), cell=CELL)
    plan = FloorPlan.from_raster(origin=np.zeros(2), cell=CELL, free=free)
    gx, gy = np.meshgrid(np.arange(2.5, 30.0, 5.0), np.array([4.0, 10.0, 16.0]))
    n = gx.size
    rng = np.random.default_rng(3)
    tx = Emitters(
        ids=tuple(f"ap{i}" for i in range(n)),
        floor=np.zeros(n, np.int32),
        xyz=np.column_stack([gx.ravel(), gy.ravel(), np.full(n, 3.0)]),
        A=rng.uniform(-45.0, -35.0, n),
        B=rng.uniform(15.0, 25.0, n),
        sigma=rng.uniform(4.0, 8.0, n),
    )
    return SiteModel("offices", (Floor("F1", 0, 4.0, plan),), tx)


SITE = offices()
MODEL = build_floor_models(SITE, P)[0]


def _window(
    k: int, slots: list[int], rngs: list[np.random.Generator], noise: np.random.Generator
) -> list[FilterInput]:
    """Window k for each device: a walk along the corridor heard from 12 access points.

    Devices differ by turn: two steps with headings, a random walk (moves
    longer than ``max_move_m`` after a 15 s gap), a step without a heading,
    a positional fix, or no radio at all.
    """
    tx = SITE.transmitters
    out = []
    for d, (slot, rng) in enumerate(zip(slots, rngs, strict=True)):
        xy = np.array([[2.0 + 0.7 * k + d, 10.0]])
        rssi = expected_rssi(ranges_3d(xy, tx.xyz, 1.2, 0.5), tx.A, tx.B)[0]
        rssi = rssi + noise.normal(0.0, 6.0, rssi.size)
        heard = np.argsort(-rssi)[:12]
        kind = (k + d) % 5
        extra: dict[str, object] = {}
        if kind in (0, 3):
            extra = {"step_length": np.full(2, 0.7), "step_heading": np.full(2, 90.0)}
        elif kind == 1:
            extra = {"walk_s": 15.0 if k % 4 == 1 else 1.0}
        elif kind == 2:
            extra = {"step_length": np.array([0.7]), "step_heading": np.array([np.nan])}
        if kind == 3:
            extra["fix"] = (float(xy[0, 0]) + 1.0, 10.5, 2.0)
        silent = kind == 4 and k % 2 == 0
        out.append(
            FilterInput(
                slot=slot,
                t=1000 * (k + 1),
                tx=heard[:0] if silent else heard,
                rssi=rssi[heard][:0] if silent else rssi[heard],
                count=np.ones(0 if silent else heard.size),
                rng=rng,
                **extra,  # type: ignore[arg-type]
            )
        )
    return out


def _run(kernel_name: str) -> tuple[list[list[FilterEstimate]], ParticleBank]:
    """Run 24 windows of five devices in chunks of two on non-consecutive slots."""
    params = replace(P, kernel=kernel_name, chunk=2)
    bank = ParticleBank(params.n_particles, 10)
    slots = [bank.allocate() for _ in range(10)][::-2]
    rngs = [np.random.default_rng(100 + d) for d in range(5)]
    noise = np.random.default_rng(0)
    return [
        update_filters(bank, MODEL, _window(k, slots, rngs, noise), params) for k in range(24)
    ], bank


def test_compiled_update_reproduces_the_numpy_reference_on_a_seeded_run() -> None:
    ref_out, ref_bank = _run("numpy")
    out, bank = _run("numba")
    # the particles are bit for bit the reference's: same moves, weights, copies
    for name in ("x", "y", "alpha", "w", "radius", "last_radio", "last_weights"):
        np.testing.assert_array_equal(getattr(bank, name), getattr(ref_bank, name), err_msg=name)
    # the estimates' sums run in another order: within 10⁻⁶ m
    for ref_row, row in zip(ref_out, out, strict=True):
        for a, b in zip(ref_row, row, strict=True):
            assert abs(a.x - b.x) < 1e-6 and abs(a.y - b.y) < 1e-6
            assert a.radius == b.radius and a.resampled == b.resampled
            assert np.isnan(a.heading) == np.isnan(b.heading)
            assert np.isnan(a.heading) or abs(a.heading - b.heading) < 1e-6
    # the run went through rescatter, resampling and the wall check
    assert any(e.resampled for row in out for e in row)


@pytest.mark.parametrize("spread_m", [0.3, 3.0, 30.0])
def test_compiled_moves_agree_with_the_reference_wall_check(spread_m: float) -> None:
    rng = np.random.default_rng(int(spread_m * 10))
    start = MODEL.plan.sample_free(4 * 300, rng).astype(np.float32).reshape(4, 300, 2)
    x, y = start[..., 0], start[..., 1]
    long = np.array([True, False, True, False])
    # only long rows' moves may exceed max_move_m (and the raster's padding)
    spread = np.where(long, spread_m, min(spread_m, 2.0))[:, None]
    dx, dy = (rng.normal(0.0, 1.0, (2, 4, 300)) * spread).astype(np.float32)
    direction, turn = rng.random((2, 4, 300), dtype=np.float32)
    # the reference shortens moves in place
    ref = settle_moves(MODEL, x, y, dx.copy(), dy.copy(), direction, turn, long, 10.0)
    got = kernel.settle_moves(MODEL, x, y, dx.copy(), dy.copy(), direction, turn, long, 10.0)
    for a, b in zip(ref, got, strict=True):
        np.testing.assert_array_equal(a, b)


def test_compiled_moves_agree_with_the_reference_about_the_longest_move() -> None:
    rng = np.random.default_rng(11)
    start = MODEL.plan.sample_free(2 * 400, rng).astype(np.float32).reshape(2, 400, 2)
    x, y = start[..., 0], start[..., 1]
    # lengths either side of max_move_m, where the kernel starts computing |Δ|
    length = np.linspace(9.9, 10.1, 800).reshape(2, 400)
    angle = rng.uniform(0.0, 2.0 * np.pi, (2, 400))
    dx = (length * np.sin(angle)).astype(np.float32)
    dy = (length * np.cos(angle)).astype(np.float32)
    direction, turn = rng.random((2, 2, 400), dtype=np.float32)
    long = np.array([True, True])
    ref = settle_moves(MODEL, x, y, dx.copy(), dy.copy(), direction, turn, long, 10.0)
    got = kernel.settle_moves(MODEL, x, y, dx.copy(), dy.copy(), direction, turn, long, 10.0)
    for a, b in zip(ref, got, strict=True):
        np.testing.assert_array_equal(a, b)


def test_compiled_window_moves_equal_the_reference_displacement() -> None:
    rng = np.random.default_rng(12)
    # windows of one to three steps, padded as steps_table pads them
    length = rng.uniform(0.5, 0.8, (6, 3)) * (np.arange(3) < rng.integers(1, 4, (6, 1)))
    heading = rng.uniform(0.0, 2.0 * np.pi, (6, 3))
    noise = rng.random((6, 2, 700), dtype=np.float32)
    alpha = rng.random((6, 700), dtype=np.float32)
    ref = window_displacement(length, heading, alpha, noise.transpose(1, 0, 2), P)
    got = kernel.window_moves(length, heading, alpha, noise.transpose(1, 0, 2), P)
    for a, b in zip(ref, got, strict=True):
        np.testing.assert_array_equal(a, b)


def test_compiled_walk_moves_equal_the_reference_random_walk() -> None:
    rng = np.random.default_rng(13)
    dt = rng.uniform(0.5, 20.0, (5, 1))
    noise = np.stack(
        [
            rng.standard_exponential((5, 600), dtype=np.float32),
            rng.random((5, 600), dtype=np.float32),
        ],
        axis=1,
    )
    alpha = rng.uniform(-np.pi, np.pi, (5, 600)).astype(np.float32)
    ref = walk_displacement(dt, alpha, noise.transpose(1, 0, 2), P)
    got = kernel.walk_moves(dt, alpha, noise.transpose(1, 0, 2), P)
    for a, b in zip(ref, got, strict=True):
        np.testing.assert_array_equal(a, b)


def test_compiled_resampling_copies_what_the_reference_copies() -> None:
    rng = np.random.default_rng(7)
    w = rng.gamma(0.3, size=(6, 500))
    w /= w.sum(axis=1, keepdims=True)
    x, y, alpha = rng.random((3, 6, 500), dtype=np.float32)
    rows, u = np.array([0, 2, 5]), rng.random(3)
    ref = [a.copy() for a in (x, y, alpha, w)]
    weights.resample_rows(*ref, rows, u)
    got = [a.copy() for a in (x, y, alpha, w)]
    kernel.resample_rows(*got, rows, u)
    for a, b in zip(ref, got, strict=True):
        np.testing.assert_array_equal(a, b)


def test_compiled_likelihood_equals_the_reference_gather() -> None:
    rng = np.random.default_rng(8)
    xy = MODEL.plan.sample_free(3 * 500, rng).astype(np.float32).reshape(3, 500, 2)
    # half of each cloud on a few cells, as after resampling
    xy[:, ::2] = xy[:, :10].repeat(25, axis=1)
    tx = np.stack([rng.choice(18, 6, replace=False) for _ in range(3)])
    rssi = rng.uniform(-90.0, -50.0, (3, 6))
    valid = np.ones((3, 6), bool)
    valid[1, 4:] = False
    count = rng.integers(1, 4, (3, 6)).astype(float)
    args = (MODEL, xy[..., 0], xy[..., 1], tx, rssi, count, valid)
    np.testing.assert_array_equal(kernel.log_likelihood(*args), weights.log_likelihood(*args))


def test_compiled_estimate_matches_the_reference_within_a_micrometre() -> None:
    rng = np.random.default_rng(9)
    x, y = (rng.normal(0.0, 3.0, (2, 4, 500)) + 50.0).astype(np.float32)
    alpha = rng.normal(1.0, 0.5, (4, 500)).astype(np.float32)
    w = rng.random((4, 500))
    w /= w.sum(axis=1, keepdims=True)
    ref = cloud_estimate(x, y, alpha, w)
    got = kernel.cloud_estimate(x, y, alpha, w)
    np.testing.assert_allclose(got[0], ref[0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(got[1], ref[1], rtol=0, atol=1e-6)
    np.testing.assert_allclose(got[2], ref[2], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(got[3], ref[3])


def test_radius_bins_by_the_top_bits_are_the_reference_search_on_and_beside_every_edge() -> None:
    edges = RADIUS_EDGES
    rng = np.random.default_rng(5)
    t = np.concatenate(
        [
            [0.0, np.inf],
            edges,
            np.nextafter(edges, np.float32(-np.inf)),
            np.nextafter(edges, np.float32(np.inf)),
            10.0 ** rng.uniform(-8.0, 6.0, 5000),
        ]
    ).astype(np.float32)[:, None]
    # one particle a row: the row's quantile bin is the particle's bin
    got = kernel._quantile_bins(t, np.ones(t.shape), 0.68, kernel._BIN_BELOW, kernel._EDGES_ABOVE)
    expected = np.searchsorted(edges, t[:, 0], side="right")
    assert got.tolist() == expected.tolist()
