"""The measurement preprocessor of Eurasian patent 047000: positioning windows.

The patent's preprocessor cuts a device's continuous stream into
"positioning time ranges"; each one is positioned once. Windows here are
``T_u`` long and aligned on multiples of ``T_u`` of measurement time, so
feeding a stream in any chunking yields the same windows. A window is
released when a later sample shows that it is complete (streams arrive in
time order), or on ``flush``. Steps the dead-reckoning detects after their
window was released are applied in the next window rather than dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.engine.pdr import Steps
from app.engine.samples import Fixes, Pressure, RssiReadings


@dataclass(frozen=True)
class PreprocessParams:
    """Constants of the preprocessor.

    Attributes
    ----------
    window_ms : int
        T_u of the patent (1000 ms): the positioning window, which is also the
        shortest interval between two weight updates of a particle filter.
    """

    window_ms: int = 1000


@dataclass(frozen=True)
class Window:
    """Everything measured in ``[t0, t1)`` (ms), plus late steps carried into it."""

    t0: int
    t1: int
    rssi: RssiReadings = field(default_factory=RssiReadings)
    steps: Steps = field(default_factory=Steps)
    fixes: Fixes = field(default_factory=Fixes)
    pressure: Pressure = field(default_factory=Pressure)

    @property
    def t_last(self) -> int:
        """Time (ms) of the newest measurement in the window; ``t1 - 1`` when it has none."""
        times = [a.t for a in (self.rssi, self.steps, self.fixes, self.pressure) if len(a)]
        return int(max(int(t.max()) for t in times)) if times else self.t1 - 1


def window_start(t: np.ndarray, window_ms: int) -> np.ndarray:
    """Return the start (ms) of the window holding each time ``t`` (ms)."""
    # t₀ = ⌊t / T_u⌋ · T_u
    return (np.asarray(t, dtype=np.int64) // window_ms) * window_ms


def split_sorted(t: np.ndarray, window_ms: int) -> tuple[np.ndarray, np.ndarray]:
    """Split sorted times into windows.

    Returns
    -------
    starts : ndarray of int64, shape (k,)
        Start (ms) of each non-empty window, increasing.
    bounds : ndarray of intp, shape (k + 1,)
        Samples ``bounds[i]:bounds[i + 1]`` fall in window i.
    """
    w = window_start(t, window_ms)
    if w.size == 0:
        return w, np.zeros(1, dtype=np.intp)
    cut = np.flatnonzero(w[1:] != w[:-1]) + 1
    bounds = np.concatenate([[0], cut, [w.size]]).astype(np.intp)
    return w[bounds[:-1]], bounds


def _take(arrays: Any, index: np.ndarray) -> Any:
    """Return a copy of a samples dataclass keeping rows ``index``."""
    return type(arrays)(**{k: v[index] for k, v in vars(arrays).items()})


def _slice(arrays: Any, lo: int, hi: int | None) -> Any:
    """Return a samples dataclass holding rows ``lo:hi`` (views, not copies)."""
    return type(arrays)(**{k: v[lo:hi] for k, v in vars(arrays).items()})


def _head(arrays: Any, n: int) -> Any:
    """Return the first ``n`` rows of a samples dataclass: itself when that is all of it."""
    return arrays if n == len(arrays) else _slice(arrays, 0, n)


def _tail(arrays: Any, n: int) -> Any:
    """Return a samples dataclass without its first ``n`` rows: the shared empty one for none."""
    return _slice(arrays, n, None) if n < len(arrays) else type(arrays)()


def _concat(a: Any, b: Any) -> Any:
    """Concatenate two samples dataclasses of the same type row-wise."""
    return type(a)(**{k: np.concatenate([v, getattr(b, k)]) for k, v in vars(a).items()})


_KINDS = ("rssi", "steps", "fixes", "pressure")
_NEVER = int(np.iinfo(np.int64).min)
"""``newest`` and ``open_from`` before any sample."""
_EMPTY = {"rssi": RssiReadings, "steps": Steps, "fixes": Fixes, "pressure": Pressure}


class Preprocessor:
    """Buffers a device's measurements and releases complete positioning windows.

    Parameters
    ----------
    params : PreprocessParams
    state : dict, optional
        A :meth:`snapshot` to resume from.
    """

    def __init__(self, params: PreprocessParams, state: dict[str, Any] | None = None) -> None:
        self.params = params
        state = state or {}
        self.open_from = int(state.get("open_from", _NEVER))
        self.newest = int(state.get("newest", _NEVER))
        self.pending: dict[str, Any] = {}
        for kind in _KINDS:
            saved = state.get(kind)
            empty = _EMPTY[kind]()
            if saved is None:
                self.pending[kind] = empty
            else:
                self.pending[kind] = type(empty)(
                    **{k: np.asarray(saved[k], dtype=v.dtype) for k, v in vars(empty).items()}
                )

    def snapshot(self) -> dict[str, Any]:
        """Return the pending measurements and window bookkeeping."""
        out: dict[str, Any] = {"open_from": self.open_from, "newest": self.newest}
        for kind in _KINDS:
            out[kind] = dict(vars(self.pending[kind]))
        return out

    def push(
        self,
        *,
        rssi: RssiReadings | None = None,
        steps: Steps | None = None,
        fixes: Fixes | None = None,
        pressure: Pressure | None = None,
    ) -> list[Window]:
        """Add time-ordered measurements; return the windows they complete, oldest first."""
        new = {
            kind: arrays
            for kind, arrays in zip(_KINDS, (rssi, steps, fixes, pressure), strict=True)
            if arrays is not None and len(arrays)
        }
        first = {kind: int(arrays.t.min()) for kind, arrays in new.items()}
        self.newest = max([self.newest] + [int(a.t.max()) for a in new.values()])
        if self.newest == _NEVER:
            return []
        w = self.params.window_ms
        # windows ending at or before the newest sample's window start are complete
        before = self.newest // w * w
        # a device posting each second sends only samples of the window it opens: the
        # windows its last batch left pending are released before they join, not cut out after
        if all(max(t // w * w, self.open_from) >= before for t in first.values()):
            windows = self._release(before)
            self._append(new)
            return windows
        self._append(new)
        return self._release(before)

    def _append(self, new: dict[str, Any]) -> None:
        """Add samples behind the pending ones of their kind."""
        for kind, arrays in new.items():
            old = self.pending[kind]
            self.pending[kind] = _concat(old, arrays) if len(old) else arrays

    def flush(self) -> list[Window]:
        """Release every pending measurement, the last window possibly incomplete."""
        return self._release(np.iinfo(np.int64).max)

    def _release(self, before: int) -> list[Window]:
        w = self.params.window_ms
        kinds = [k for k in _KINDS if len(self.pending[k])]
        if not kinds:
            return []
        # window of each pending sample; late ones join the first open window
        start = {k: np.maximum(window_start(self.pending[k].t, w), self.open_from) for k in kinds}
        one = self._release_one(kinds, start, before)
        if one is not None:
            return one
        all_starts = np.unique(np.concatenate([start[k] for k in kinds]))
        ready = all_starts[all_starts < before]
        if ready.size == 0:
            return []
        windows = []
        for t0 in ready.tolist():
            parts = {k: _take(self.pending[k], np.flatnonzero(start[k] == t0)) for k in kinds}
            windows.append(Window(t0=t0, t1=t0 + w, **parts))
        cut = int(ready[-1]) + w
        for kind in kinds:
            self.pending[kind] = _take(self.pending[kind], np.flatnonzero(start[kind] >= cut))
        self.open_from = cut
        return windows

    def _release_one(
        self, kinds: list[str], start: dict[str, np.ndarray], before: int
    ) -> list[Window] | None:
        """Release the common case by slicing: at most one window complete, windows in order.

        A device posting every second holds the window its last batch completed
        and the one its newest samples opened; slices of in-order samples avoid
        the general path's sort and copies. None when the case does not apply.
        """
        cuts = {}
        first = None
        for kind in kinds:
            s = start[kind]
            if s.size > 1 and (s[1:] < s[:-1]).any():
                return None
            cut = int(np.searchsorted(s, before))
            if cut:
                if s[0] != s[cut - 1] or (first is not None and int(s[0]) != first):
                    return None
                first = int(s[0])
            cuts[kind] = cut
        if first is None:
            return []
        parts = {k: _head(self.pending[k], c) for k, c in cuts.items() if c}
        for kind, cut in cuts.items():
            self.pending[kind] = _tail(self.pending[kind], cut)
        w = self.params.window_ms
        self.open_from = first + w
        return [Window(t0=first, t1=first + w, **parts)]
