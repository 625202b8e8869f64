"""Zone dwell: a device jittering across a zone's edge gets no enter/exit pair shorter than
the dwell time, and every confirmed crossing is reported at the time it happened; a zone
holds the points shapely says it holds."""

from __future__ import annotations

import numpy as np
import shapely

from app.sites.assembly import Zone
from app.workers.zones import ZoneTracker

DWELL_MS = 2000


def doorway_walk(rng: np.random.Generator) -> list[tuple[int, bool]]:
    """Return (t, inside) at 5 Hz of a device standing in a doorway for 8 s (each position
    in or out at random: a filter's jitter), then inside for 5 s, then outside for 5 s."""
    jitter = [bool(rng.random() < 0.5) for _ in range(40)]
    return [(200 * k, inside) for k, inside in enumerate(jitter + [True] * 25 + [False] * 25)]


def feed(tracker: ZoneTracker, walk: list[tuple[int, bool]]) -> list[tuple[str, str, int]]:
    changes = []
    for t, inside in walk:
        changes += tracker.update(t, frozenset({"Kitchen"} if inside else ()))
    return changes


def test_jitter_at_a_doorway_makes_no_pair_shorter_than_the_dwell() -> None:
    for seed in range(20):
        walk = doorway_walk(np.random.default_rng(seed))
        flicker = feed(ZoneTracker(0), walk)
        changes = feed(ZoneTracker(DWELL_MS), walk)
        assert len(flicker) > 6  # without a dwell the doorway flickers
        events = [event for event, _, _ in changes]
        assert events == ["enter", "exit"] * (len(events) // 2), events
        times = [t for _, _, t in changes]
        assert all(b - a >= DWELL_MS for a, b in zip(times, times[1:], strict=False)), changes
        # the stay inside is confirmed, reported when it began, and its exit when it ended
        assert changes[-1] == ("exit", "Kitchen", 200 * 65)
        assert changes[-2][0] == "enter" and changes[-2][2] <= 200 * 40


def test_a_confirmed_crossing_is_reported_at_the_first_position_across() -> None:
    tracker = ZoneTracker(DWELL_MS)
    assert tracker.update(1000, frozenset({"Lab"})) == []
    assert tracker.update(2500, frozenset({"Lab"})) == []
    assert tracker.update(3000, frozenset({"Lab"})) == [("enter", "Lab", 1000)]
    # leaving Lab for Office at once: both confirmed 2 s later, the exit first
    tracker.update(4000, frozenset({"Office"}))
    assert tracker.update(6000, frozenset({"Office"})) == [
        ("exit", "Lab", 4000),
        ("enter", "Office", 4000),
    ]


def test_pending_crossings_survive_a_snapshot() -> None:
    tracker = ZoneTracker(DWELL_MS)
    tracker.update(1000, frozenset({"Lab"}))
    resumed = ZoneTracker(DWELL_MS)
    resumed.restore(tracker.snapshot())
    assert resumed.update(3000, frozenset({"Lab"})) == [("enter", "Lab", 1000)]
    # a snapshot written before dwell times resumes with its zones and nothing pending
    old = ZoneTracker(DWELL_MS)
    old.restore({"zones": ["Lab"]})
    assert old.inside == {"Lab"} and old.pending == {}


def test_a_zone_contains_what_shapely_says_inside_and_outside_its_bounding_box() -> None:
    # an L: its bounding box holds the missing corner, which the zone does not
    ell = shapely.Polygon([(0, 0), (10, 0), (10, 4), (4, 4), (4, 10), (0, 10)])
    zone = Zone("L", 0, ell)
    rng = np.random.default_rng(3)
    points = np.vstack([rng.uniform(-2.0, 12.0, (400, 2)), [(0.0, 5.0), (7.0, 7.0), (2.0, 2.0)]])

    got = [zone.contains(float(x), float(y)) for x, y in points]

    assert got == shapely.contains_xy(ell, points[:, 0], points[:, 1]).tolist()
    assert got[-3:] == [False, False, True]  # on the edge, in the box's empty corner, inside
