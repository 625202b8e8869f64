"""Replay recordings through a Locus server's HTTP API and score its positions.

This is how a client sees Locus: batches of one second of measurement time
posted with ``?wait=true``, paced at the recording's own rate times a speed
factor (or as fast as the server answers); the positions that come back are
compared with the recording's surveyed truth where it has one.

A recording is either an ILC walk file (``*.txt.gz``, with waypoints) or a
JSON file holding ingest bodies (one object, a list of them, or one per line);
their ``device_id`` and ``site_id`` may be left out and given on the command
line instead.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.datasets.ilc import Walk, read_walk
from app.evaluation.metrics import truth_at
from app.importers.ilc import walk_samples


@dataclass(frozen=True)
class Scored:
    """Positions of one replayed walk with their errors against the truth."""

    positions: list[dict[str, Any]]
    errors: np.ndarray
    floor_ok: np.ndarray


SentAt = dict[str, list[int]]
"""Per sample kind, when each sample left the device (ms), where that is not its ``t``:
a phone reports a WiFi reading when its scan completes, though its ``t`` may be
the access point's older last-seen time."""


def batches_by_time(
    samples: dict[str, list[dict[str, Any]]], *, batch_ms: int, sent_at: SentAt | None = None
) -> list[dict[str, list[dict[str, Any]]]]:
    """Cut sample lists into consecutive windows of ``batch_ms`` by the time each was sent."""
    sent = {
        kind: (sent_at or {}).get(kind) or [s["t"] for s in items]
        for kind, items in samples.items()
    }
    times = [t for ts in sent.values() for t in ts]
    if not times:
        return []
    start = min(times)
    out: dict[int, dict[str, list[dict[str, Any]]]] = {}
    for kind, items in samples.items():
        for s, t in zip(items, sent[kind], strict=True):
            out.setdefault((t - start) // batch_ms, {}).setdefault(kind, []).append(s)
    return [out[k] for k in sorted(out)]


SAMPLE_KINDS = ("wifi", "ble", "imu", "uwb", "uwb_fix", "baro")
"""The sample lists of an ingest body."""


@dataclass(frozen=True)
class Recording:
    """A device's samples by kind, and the walk they came from when it has surveyed truth."""

    samples: dict[str, list[dict[str, Any]]]
    walk: Walk | None = None
    device_id: str | None = None
    site_id: str | None = None


def load_recording(path: Path) -> Recording:
    """Read an ILC walk file or a JSON file of ingest bodies."""
    path = Path(path)
    if path.name.endswith((".txt.gz", ".txt")):
        walk = read_walk(path)
        return Recording(samples=walk_samples(walk), walk=walk, device_id=walk.walk_id)
    text = path.read_text(encoding="utf-8").strip()
    try:
        loaded = json.loads(text)
    except json.JSONDecodeError:
        loaded = [json.loads(line) for line in text.splitlines() if line.strip()]
    bodies = loaded if isinstance(loaded, list) else [loaded]
    samples: dict[str, list[dict[str, Any]]] = {}
    for body in bodies:
        for kind in SAMPLE_KINDS:
            samples.setdefault(kind, []).extend(body.get(kind) or [])
    first = bodies[0] if bodies else {}
    return Recording(
        samples={k: v for k, v in samples.items() if v},
        device_id=first.get("device_id"),
        site_id=first.get("site_id"),
    )


def replay_samples(
    http: httpx.Client,
    samples: dict[str, list[dict[str, Any]]],
    *,
    site_id: str,
    device_id: str,
    batch_ms: int = 1000,
    speed: float = 0.0,
    on_positions: Callable[[list[dict[str, Any]]], None] | None = None,
    sent_at: SentAt | None = None,
) -> list[dict[str, Any]]:
    """Post samples batch by batch with ``?wait=true`` and return every position, by ``t``.

    With ``speed`` > 0 each batch leaves when its measurement time, divided by
    ``speed``, has passed since the first (1.0 is real time); with 0 the next
    batch leaves as soon as the last is answered. ``on_positions`` sees the
    positions of each answer as they come. A paced device can fall silent
    long enough for the server to flush its buffer between two batches; the
    positions of such a flush are in no answer, so the result is read back
    from the device's stored history, and those are passed on at the end.
    """
    chunks = batches_by_time(samples, batch_ms=batch_ms, sent_at=sent_at)
    if not chunks:
        return []
    first_t = [min(s["t"] for items in c.values() for s in items) for c in chunks]
    started = time.monotonic()
    seen: set[int] = set()
    for chunk, t_first in zip(chunks, first_t, strict=True):
        if speed > 0:
            time.sleep(max(0.0, started + (t_first - first_t[0]) / 1000 / speed - time.monotonic()))
        body = {"device_id": device_id, "site_id": site_id, **chunk}
        r = http.post("/v1/ingest?wait=true", json=body)
        r.raise_for_status()
        emitted = r.json()["positions"]
        seen.update(p["t"] for p in emitted)
        if on_positions is not None:
            on_positions(emitted)
    stored = history(http, site_id, device_id, t_from=first_t[0])
    if on_positions is not None:
        on_positions([p for p in stored if p["t"] not in seen])
    return stored


def history(
    http: httpx.Client, site_id: str, device_id: str, *, t_from: int
) -> list[dict[str, Any]]:
    """Return the site's device's stored positions from ``t_from`` on, following the pages."""
    out: list[dict[str, Any]] = []
    cursor: int | None = t_from
    while cursor is not None:
        r = http.get(
            f"/v1/sites/{site_id}/devices/{device_id}/positions",
            params={"from": cursor, "limit": 10_000},
        )
        r.raise_for_status()
        page = r.json()
        out += page["items"]
        cursor = page["next_from"]
    return out


def replay_walk(
    http: httpx.Client, walk: Walk, *, site_id: str, device_id: str, batch_ms: int = 1000
) -> list[dict[str, Any]]:
    """Post the walk's samples batch by batch with ``?wait=true``; return every position."""
    return replay_samples(
        http, walk_samples(walk), site_id=site_id, device_id=device_id, batch_ms=batch_ms
    )


def score(walk: Walk, positions: list[dict[str, Any]]) -> Scored:
    """Return horizontal errors (on the right floor) and the floor hits of positions."""
    inside = [p for p in positions if walk.waypoints[0, 0] <= p["t"] <= walk.waypoints[-1, 0]]
    if not inside:
        return Scored(positions, np.zeros(0), np.zeros(0, dtype=bool))
    t = np.array([p["t"] for p in inside])
    xy = np.array([[p["x"], p["y"]] for p in inside])
    truth, _ = truth_at(walk.waypoints, t)
    floor_ok = np.array([p["floor_id"] == walk.floor for p in inside])
    errors = np.linalg.norm(xy - truth, axis=1)[floor_ok]
    return Scored(inside, errors, floor_ok)
