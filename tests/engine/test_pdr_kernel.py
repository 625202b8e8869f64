"""The step detector's compiled loops against the numpy and scipy calls they replace."""

from __future__ import annotations

import numpy as np
from scipy import signal

from app.engine.pdr_kernel import iir, resample


def test_iir_matches_lfilter_across_chunks() -> None:
    rng = np.random.default_rng(3)
    b, a = signal.butter(2, 2.5, fs=50.0)
    x = rng.normal(9.8, 2.0, 200)
    zi = signal.lfilter_zi(b, a) * x[0]
    want, _ = signal.lfilter(b, a, x, zi=zi)
    state = zi.copy()
    # the state carried in place from one chunk to the next
    got = np.concatenate([iir(b, a, x[:73].copy(), state), iir(b, a, x[73:].copy(), state)])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_resample_matches_np_interp_and_leaves_unsent_channels_nan() -> None:
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.integers(5, 40, 60)).astype(np.int64)
    x = rng.normal(size=(60, 3))
    x[:, 2] = np.nan
    x[:10, 1] = np.nan  # a channel first sent late
    grid = np.arange(t[0] - 30, t[-1] + 30, 20, dtype=np.int64)
    got = resample(t, x, grid)
    for j in (0, 1):
        np.testing.assert_array_equal(got[:, j], np.interp(grid, t, x[:, j]))
    assert np.isnan(got[:, 2]).all()
