"""Preprocessor: T_u windows on measurement time, chunking invariance, floors, late steps."""

from __future__ import annotations

import numpy as np

from app.engine.pdr import Steps
from app.engine.preprocess import (
    Preprocessor,
    PreprocessParams,
    Window,
    split_sorted,
)
from app.engine.samples import Fixes, Pressure, RssiReadings


def _stream(seed: int = 2) -> RssiReadings:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(10_300, 17_900, 200)).astype(np.int64)
    return RssiReadings(
        t=t, tx=rng.integers(0, 9, t.size).astype(np.int32), rssi=rng.uniform(-95, -40, t.size)
    )


def _cut(r: RssiReadings, lo: int, hi: int) -> RssiReadings:
    keep = (r.t >= lo) & (r.t < hi)
    return RssiReadings(t=r.t[keep], tx=r.tx[keep], rssi=r.rssi[keep])


def _flat(windows: list[Window]) -> list[tuple[int, int, list[int], list[float]]]:
    return [(w.t0, w.t1, w.rssi.t.tolist(), w.rssi.rssi.tolist()) for w in windows]


def test_split_sorted_matches_window_of_each_sample() -> None:
    t = np.array([999, 1000, 1001, 2999, 3000, 3000, 7000], dtype=np.int64)
    starts, bounds = split_sorted(t, 1000)
    assert starts.tolist() == [0, 1000, 2000, 3000, 7000]
    assert bounds.tolist() == [0, 1, 3, 4, 6, 7]


def test_windows_are_released_when_complete_and_do_not_depend_on_chunking() -> None:
    stream = _stream()
    once = Preprocessor(PreprocessParams())
    whole = once.push(rssi=stream) + once.flush()
    rng = np.random.default_rng(9)
    edges = np.sort(rng.integers(10_000, 18_000, 11))
    chunked = Preprocessor(PreprocessParams())
    parts: list[Window] = []
    lo = 0
    for hi in [*edges.tolist(), 20_000]:
        released = chunked.push(rssi=_cut(stream, lo, hi))
        # nothing released may still receive samples: every window ends before the newest one
        assert all(w.t1 <= chunked.newest for w in released)
        parts += released
        lo = hi
    parts += chunked.flush()
    assert _flat(parts) == _flat(whole)
    assert [w.t0 for w in whole] == list(range(10_000, 18_000, 1000))
    assert sum(len(w.rssi) for w in whole) == len(stream)


def test_the_open_window_waits_for_a_later_sample() -> None:
    pre = Preprocessor(PreprocessParams())
    r = RssiReadings(
        t=np.array([5100, 5900], np.int64), tx=np.zeros(2, np.int32), rssi=np.array([-60.0, -61.0])
    )
    assert pre.push(rssi=r) == []
    later = Pressure(t=np.array([6000], np.int64), hpa=np.array([1001.0]))
    out = pre.push(pressure=later)
    assert [(w.t0, len(w.rssi), len(w.pressure)) for w in out] == [(5000, 2, 0)]
    assert out[0].t_last == 5900
    assert [(w.t0, len(w.pressure)) for w in pre.flush()] == [(6000, 1)]


def test_late_steps_are_applied_in_the_next_window() -> None:
    pre = Preprocessor(PreprocessParams())
    first = RssiReadings(
        t=np.array([1200, 2100], np.int64), tx=np.zeros(2, np.int32), rssi=np.array([-60.0, -62.0])
    )
    assert [w.t0 for w in pre.push(rssi=first)] == [1000]
    late = Steps(
        t=np.array([1500, 2400], np.int64),
        length=np.array([0.7, 0.6]),
        heading=np.array([10.0, 20.0]),
        swing=np.array([3.0, 3.0]),
    )
    fix = Fixes(
        t=np.array([3100], np.int64),
        xyz=np.array([[1.0, 2.0, 0.0]]),
        floor=np.array([0], np.int32),
        std=np.array([0.3]),
    )
    out = pre.push(steps=late, fixes=fix)
    assert [(w.t0, w.steps.length.tolist(), len(w.rssi)) for w in out] == [(2000, [0.7, 0.6], 1)]
    assert [(w.t0, len(w.fixes)) for w in pre.flush()] == [(3000, 1)]


def test_snapshot_resumes_with_pending_samples() -> None:
    stream = _stream(4)
    a = Preprocessor(PreprocessParams())
    a.push(rssi=_cut(stream, 0, 13_500))
    b = Preprocessor(PreprocessParams(), a.snapshot())
    rest = _cut(stream, 13_500, 20_000)
    assert _flat(a.push(rssi=rest) + a.flush()) == _flat(b.push(rssi=rest) + b.flush())


def test_second_by_second_pushes_release_what_one_push_of_everything_does() -> None:
    """A device posting each second (one window complete per push) and a replay posting
    everything at once get the same windows, late steps and a barometer included."""
    stream = _stream(6)
    pressure = Pressure(
        t=np.arange(10_250, 18_000, 500, dtype=np.int64), hpa=np.linspace(1001.0, 1000.2, 16)
    )
    steps = Steps(
        t=np.arange(10_400, 18_000, 600, dtype=np.int64),
        length=np.full(13, 0.7),
        heading=np.linspace(0.0, 120.0, 13),
        swing=np.full(13, 3.0),
    )

    def kinds(w: Window) -> tuple[object, ...]:
        return (
            w.t0,
            w.rssi.t.tolist(),
            w.pressure.hpa.tolist(),
            w.steps.t.tolist(),
            w.steps.heading.tolist(),
        )

    whole = Preprocessor(PreprocessParams())
    expected = whole.push(rssi=stream, pressure=pressure) + whole.push(steps=steps)
    expected += whole.flush()
    live = Preprocessor(PreprocessParams())
    got: list[Window] = []
    for lo in range(10_000, 18_000, 1000):
        got += live.push(
            rssi=_cut(stream, lo, lo + 1000),
            pressure=Pressure(
                t=pressure.t[(pressure.t >= lo) & (pressure.t < lo + 1000)],
                hpa=pressure.hpa[(pressure.t >= lo) & (pressure.t < lo + 1000)],
            ),
        )
    # the steps arrive after all the radio: every one of them is late
    got += live.push(steps=steps) + live.flush()
    assert [kinds(w) for w in got] == [kinds(w) for w in expected]
    assert sum(len(w.steps) for w in got) == len(steps)
