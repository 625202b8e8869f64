"""The dashboard in headless Chromium against a real ``locus serve``: the floor drawn from
its map with y up, live markers that follow posted positions, zone events, reconnection,
the accuracy overlay, replay, and a rejected upload listing each problem by feature."""

from __future__ import annotations

import json
import re
import time
import uuid
from pathlib import Path
from typing import Any

import httpx
import pytest
import shapely
from playwright.sync_api import Page, WebSocketRoute, expect

from app.demo import load_map
from app.geometry.floormap import parse_floor_map
from tests.conftest import ADMIN_KEY, LiveServer, floor_doc

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
BOWTIE = {"type": "Polygon", "coordinates": [[[2, 2], [6, 6], [6, 2], [2, 6], [2, 2]]]}
SQUARE = {"type": "Polygon", "coordinates": [[[3, 3], [5, 3], [5, 5], [3, 5], [3, 3]]]}

pytestmark = pytest.mark.browser


@pytest.fixture
def site(server: LiveServer) -> str:
    """A new site with the small test floor 'G' (20 × 10 m, a wall, zone 'Lab', 3 APs)."""
    sid = f"dash-{uuid.uuid4().hex[:8]}"
    with httpx.Client(base_url=server.url, headers=ADMIN) as http:
        assert http.put(f"/v1/sites/{sid}", json={"name": f"Site {sid}"}).status_code == 201
        assert http.put(f"/v1/sites/{sid}/floors/G", json=beacon_floor()).status_code == 201
    return sid


def sign_in(page: Page, server: LiveServer, key: str, site: str) -> None:
    """Open the dashboard, sign in and pick the site and its floor G."""
    page.goto(server.url + "/")
    page.fill("#key", key)
    page.click("#sign-in")
    expect(page.locator(f'#site option[value="{site}"]')).to_have_count(1)
    page.select_option("#site", site)
    expect(page.locator('#floor option[value="G"]')).to_have_count(1)
    page.select_option("#floor", "G")
    expect(page.locator("#plan")).to_have_attribute("data-floor", "G")


# Beacons at the points the tests move devices to: a scan that hears only the beacon at
# (x, y) puts the device exactly there (the site has no path-loss model, so positions
# come from the weighted centroid of the beacons heard).
POINTS = [(2.0, 5.0), (6.0, 5.0), (14.0, 4.0), (3.0, 3.0)] + [(2.0 + 2 * k, 8.5) for k in range(5)]


def beacon_id(x: float, y: float) -> str:
    """Return the id of the test beacon at (x, y)."""
    return f"bb:00:00:00:{int(x):02x}:{int(y * 2):02x}"


def beacon_floor() -> dict:
    """Return the test floor with a beacon at every point the tests use."""
    doc = floor_doc()
    doc["features"] += [
        {
            "type": "Feature",
            "geometry": {"type": "Point", "coordinates": [x, y]},
            "properties": {"kind": "transmitter", "id": beacon_id(x, y), "tech": "ble"},
        }
        for x, y in POINTS
    ]
    return doc


def post_fixes(server: LiveServer, site: str, device: str, points: list[tuple[int, float, float]]):
    """Place the device at each (t, x, y) in turn (one scan of that point's beacon each).

    Points must be more than the centroid's 2 s window apart to be placed exactly.
    """
    scans = [{"t": t, "id": beacon_id(x, y), "rssi": -45.0} for t, x, y in points]
    r = httpx.post(
        f"{server.url}/v1/ingest?wait=true",
        json={"device_id": device, "site_id": site, "ble": scans},
        headers=ADMIN,
        timeout=30,
    )
    assert r.status_code == 200, r.text
    positions = r.json()["positions"]
    assert [(p["x"], p["y"]) for p in positions] == [(x, y) for _, x, y in points]


def view_transform(page: Page) -> tuple[float, float, float]:
    """Return (k, tx, ty) of the plan's world transform: screen = (k·x + tx, ty − k·y)."""
    matrix = page.get_attribute("#plan g.world", "transform") or ""
    a, b, c, d, e, f = (float(v) for v in re.findall(r"-?[\d.e+-]+", matrix))
    assert (b, c, d) == (0.0, 0.0, -a), matrix
    return a, e, f


def marker_screen(page: Page, selector: str) -> tuple[float, float]:
    """Return the screen translation of a pinned marker."""
    transform = page.get_attribute(selector, "transform") or ""
    sx, sy = (float(v) for v in re.findall(r"-?[\d.]+", transform))
    return sx, sy


def test_floor_is_drawn_and_live_marker_follows_positions(
    page: Page, server: LiveServer, site: str
) -> None:
    sign_in(page, server, ADMIN_KEY, site)
    outline = page.locator('#plan [data-layer="map"] [data-kind="outline"]')
    expect(outline).to_have_attribute("d", "M0,0L20,0L20,10L0,10L0,0Z")
    expect(page.locator('#plan [data-layer="map"] [data-kind="wall"]')).to_have_attribute(
        "d", "M10,0L10,7"
    )
    expect(page.locator('#plan [data-kind="transmitter"]')).to_have_count(3 + len(POINTS))
    expect(page.locator("#plan text.label-zone")).to_have_text("Lab")
    expect(page.locator("#connection")).to_have_attribute("data-state", "live")

    t0 = int(time.time() * 1000)
    post_fixes(server, site, "tag-7", [(t0, 2.0, 5.0)])
    marker = '#plan [data-layer="live"] .device[data-device="tag-7"]'
    expect(page.locator(marker)).to_have_attribute("data-x", "2")
    before = marker_screen(page, marker)
    k, tx, ty = view_transform(page)
    # the marker sits where the plan's transform puts (2, 5), y pointing up the screen
    assert before == pytest.approx((k * 2.0 + tx, ty - k * 5.0), abs=0.06)

    # into the Lab, and still there after the zone dwell time (2 s)
    walk = [(t0 + 3000, 6.0, 5.0), (t0 + 6000, 14.0, 4.0), (t0 + 9000, 14.0, 4.0)]
    post_fixes(server, site, "tag-7", walk)
    expect(page.locator(marker)).to_have_attribute("data-t", str(t0 + 9000))
    after = marker_screen(page, marker)
    k, tx, ty = view_transform(page)
    assert after == pytest.approx((k * 14.0 + tx, ty - k * 4.0), abs=0.06)
    # moved 12 m east and 1 m south: right on the screen, and down
    assert after[0] - before[0] == pytest.approx(12 * k, abs=0.1)
    assert after[1] - before[1] == pytest.approx(1 * k, abs=0.1)
    # the engine's path, the pen lifted over the leg from (6, 5) to (14, 4) through the wall
    trail = page.locator('#plan [data-layer="live"] path.trail')
    expect(trail).to_have_attribute("d", "M2,5L6,5M14,4L14,4")
    expect(page.locator('#devices li[data-device="tag-7"] .age')).to_contain_text("s ago")
    entered = page.locator('#zone-events li[data-event="enter"]')
    expect(entered).to_contain_text("Lab")
    expect(entered).to_contain_text("tag-7")


def test_socket_drop_reconnects_with_backoff(page: Page, server: LiveServer, site: str) -> None:
    sockets: list[WebSocketRoute] = []

    def relay(ws: WebSocketRoute) -> None:
        ws.connect_to_server()
        sockets.append(ws)

    page.route_web_socket(re.compile(r".*/v1/ws/positions.*"), relay)
    sign_in(page, server, ADMIN_KEY, site)
    expect(page.locator("#connection")).to_have_attribute("data-state", "live")
    page.evaluate(
        """() => {
          window.states = [];
          const node = document.getElementById("connection");
          new MutationObserver(() => window.states.push(node.dataset.state))
            .observe(node, { attributes: true, attributeFilter: ["data-state"] });
        }"""
    )
    opened = len(sockets)
    sockets[-1].close(code=1011, reason="dropped by the test")
    expect(page.locator("#connection")).to_have_attribute("data-state", "live")
    states = page.evaluate("window.states")
    assert states[0] == "retrying" and states[-1] == "live", states
    assert len(sockets) == opened + 1
    # positions flow again on the new socket
    post_fixes(server, site, "tag-9", [(int(time.time() * 1000), 3.0, 3.0)])
    expect(page.locator('#plan .device[data-device="tag-9"]')).to_have_attribute("data-y", "3")


def test_rejected_upload_lists_each_problem_at_its_feature(
    page: Page, server: LiveServer, site: str, tmp_path: Path
) -> None:
    doc = floor_doc()
    doc["features"] += [
        {"type": "Feature", "properties": {"kind": "barrier"}, "geometry": BOWTIE},
        {"type": "Feature", "properties": {"kind": "wall"}, "geometry": SQUARE},
    ]
    bad = tmp_path / "bad.geojson"
    bad.write_text(json.dumps(doc))
    sign_in(page, server, ADMIN_KEY, site)
    page.click("#tab-admin")
    expect(page.locator("#upload-floor-id")).to_have_value("G")
    page.set_input_files("#upload-file", str(bad))
    page.click("#upload")

    barrier = page.locator('#upload-result .problem[data-index="6"]')
    expect(barrier).to_contain_text("Feature #6 · barrier")
    expect(barrier).to_contain_text("invalid geometry")
    wall = page.locator('#upload-result .problem[data-index="7"]')
    expect(wall).to_contain_text("Feature #7 · wall")
    expect(wall).to_contain_text("geometry must be")
    # the rejected map is drawn instead of the stored one, the named features marked
    preview = '#plan [data-layer="preview"]'
    expect(page.locator(f'{preview} path[data-index="6"]')).to_have_class(re.compile("problem"))
    expect(page.locator(f'{preview} path[data-index="7"]')).to_have_class(re.compile("problem"))
    expect(page.locator(f'{preview} [data-problem="6"]')).to_have_text("#6")
    expect(page.locator('#plan g.world [data-layer="map"]')).to_be_hidden()
    stored = httpx.get(f"{server.url}/v1/sites/{site}/floors/G", headers=ADMIN).json()
    assert stored == beacon_floor()

    page.click("#preview-back")
    expect(page.locator(f"{preview} path")).to_have_count(0)
    expect(page.locator('#plan g.world [data-layer="map"]')).to_be_visible()

    good = tmp_path / "basement.geojson"
    basement = floor_doc()
    basement["properties"] |= {"level": -1, "name": "Basement"}
    good.write_text(json.dumps(basement))
    page.fill("#upload-floor-id", "B1")
    page.set_input_files("#upload-file", str(good))
    page.click("#upload")
    expect(page.locator("#upload-result")).to_contain_text("Stored floor B1 (Basement)")
    expect(page.locator("#plan")).to_have_attribute("data-floor", "B1")
    expect(page.locator('#floor option[value="B1"]')).to_have_count(1)


def test_admin_creates_a_site_and_selects_it(page: Page, server: LiveServer, site: str) -> None:
    sign_in(page, server, ADMIN_KEY, site)
    page.click("#tab-admin")
    new = f"new-{uuid.uuid4().hex[:6]}"
    page.fill("#new-site-id", new)
    page.fill("#new-site-name", "Warehouse")
    page.click("#site-form button[type=submit]")
    expect(page.locator("#site-result")).to_have_text(f"Site “Warehouse” ({new}) saved.")
    expect(page.locator("#site")).to_have_value(new)
    expect(page.locator("#plan-empty")).to_contain_text("has no floor map yet")
    expect(page.locator("#plan:not([data-floor])")).to_have_count(1)
    site_doc = httpx.get(f"{server.url}/v1/sites/{new}", headers=ADMIN).json()
    assert site_doc["name"] == "Warehouse"


def test_accuracy_overlay_follows_the_planning_answer(
    page: Page, server: LiveServer, site: str
) -> None:
    sign_in(page, server, ADMIN_KEY, site)
    page.check("#accuracy-toggle")
    expect(page.locator("#accuracy-status")).to_have_attribute("data-state", "shown")
    grid = httpx.get(
        f"{server.url}/v1/sites/{site}/floors/G/accuracy?tech=ble&z=1&cell=0.5", headers=ADMIN
    ).json()
    ny, nx = grid["shape"]
    image = page.locator('#plan [data-layer="heatmap"] image')
    expect(image).to_have_attribute("data-shape", f"{ny}x{nx}")
    attrs = image.evaluate("n => ['x', 'y', 'width', 'height'].map(a => +n.getAttribute(a))")
    assert attrs == pytest.approx(
        [grid["origin"][0], grid["origin"][1], nx * grid["cell"], ny * grid["cell"]]
    )

    # a server without the planning endpoint answers 404: say so, draw nothing
    page.route(
        re.compile(r".*/accuracy\?.*"),
        lambda route: route.fulfill(
            status=404,
            json={"error": {"code": "not_found", "message": "Not Found", "details": []}},
        ),
    )
    page.fill("#accuracy-z", "1.5")
    page.dispatch_event("#accuracy-z", "change")
    status = page.locator("#accuracy-status")
    expect(status).to_have_attribute("data-state", "unavailable")
    expect(status).to_contain_text("not available")
    expect(image).to_have_count(0)


def test_replay_plays_a_device_history(page: Page, server: LiveServer, site: str) -> None:
    t0 = (int(time.time()) - 60) * 1000
    post_fixes(server, site, "walker", [(t0 + 3000 * k, 2.0 + 2 * k, 8.5) for k in range(5)])
    sign_in(page, server, ADMIN_KEY, site)
    page.click("#tab-replay")
    page.fill("#replay-device", "walker")
    page.evaluate(
        """([from, to]) => {
          const local = (ms) =>
            new Date(ms - new Date(ms).getTimezoneOffset() * 60000).toISOString().slice(0, 19);
          document.getElementById("replay-from").value = local(from);
          document.getElementById("replay-to").value = local(to);
        }""",
        [t0 - 5000, t0 + 15_000],
    )
    page.click("#replay-form button[type=submit]")
    expect(page.locator("#replay-status")).to_contain_text("5 positions of walker")
    marker = '#plan [data-layer="replay"] .device[data-device="walker"]'
    expect(page.locator(marker)).to_have_attribute("data-x", "2")
    expect(page.locator('#plan [data-layer="replay"] path.replay-path')).to_have_attribute(
        "d", "M2,8.5L4,8.5L6,8.5L8,8.5L10,8.5"
    )
    page.select_option("#replay-speed", "60")
    page.click("#replay-play")
    expect(page.locator(marker)).to_have_attribute("data-x", "10")
    expect(page.locator("#replay-play")).to_have_text("Play")


def test_viewer_key_sees_no_admin_view(page: Page, server: LiveServer, site: str) -> None:
    r = httpx.post(f"{server.url}/v1/keys", json={"role": "viewer", "site_id": site}, headers=ADMIN)
    sign_in(page, server, r.json()["key"], site)
    expect(page.locator("#role")).to_have_text("viewer")
    expect(page.locator("#tab-admin")).to_be_hidden()
    expect(page.locator("#site option")).to_have_count(1)


def device_colours(page: Page) -> dict[str, str]:
    """Return each live device's colour (its marker's ``--colour``)."""
    return page.evaluate(
        """() => Object.fromEntries(
          [...document.querySelectorAll('#plan [data-layer="live"] .device')].map((n) =>
            [n.dataset.device, n.style.getPropertyValue("--colour")]))"""
    )


def test_each_device_has_its_own_colour_and_its_method_a_shape(
    page: Page, server: LiveServer, site: str
) -> None:
    sign_in(page, server, ADMIN_KEY, site)
    t0 = int(time.time() * 1000)
    phones = {"phone-1": (2.0, 5.0), "phone-2": (6.0, 5.0), "phone-3": (3.0, 3.0)}
    for device, (x, y) in phones.items():
        post_fixes(server, site, device, [(t0, x, y)])
    fix = {"t": t0, "x": 14.0, "y": 4.0, "floor_id": "G", "std": 0.1}
    r = httpx.post(
        f"{server.url}/v1/ingest?wait=true",
        json={"device_id": "tag-1", "site_id": site, "uwb_fix": [fix]},
        headers=ADMIN,
        timeout=30,
    )
    assert r.status_code == 200, r.text
    for device in [*phones, "tag-1"]:
        expect(page.locator(f'#plan .device[data-device="{device}"]')).to_have_count(1)

    colours = device_colours(page)
    assert len(set(colours.values())) == 4, colours
    # the trail and the device list's swatch wear the device's colour
    for device, colour in colours.items():
        trail = page.locator(f'#plan [data-layer="live"] path.trail[data-device="{device}"]')
        assert trail.evaluate("n => n.style.getPropertyValue('--colour')") == colour
        swatch = page.locator(f'#devices li[data-device="{device}"] .swatch path')
        expect(swatch).to_have_attribute("fill", colour)
    # one method, one shape: the three phones alike, the UWB tag's EKF another
    shapes = {
        device: page.get_attribute(f'#plan .device[data-device="{device}"] .dot', "d")
        for device in colours
    }
    assert shapes["phone-1"] == shapes["phone-2"] == shapes["phone-3"] != shapes["tag-1"]


def demo_walls() -> Any:
    """Return every line of the demo office a trail may not cross, as one shapely geometry."""
    fmap = parse_floor_map(load_map())
    edges = [fmap.outline.boundary, *fmap.walls, *(b.boundary for b in fmap.barriers)]
    return shapely.union_all(edges)


def drawn_runs(d: str) -> list[list[tuple[float, float]]]:
    """Return the runs of an SVG path of M and L commands, as lists of points."""
    runs: list[list[tuple[float, float]]] = []
    for command, x, y in re.findall(r"([ML])(-?[\d.e+-]+),(-?[\d.e+-]+)", d):
        if command == "M":
            runs.append([])
        runs[-1].append((float(x), float(y)))
    return runs


# A tag placed on beacons in turn, jumping through walls: from the corridor into the room
# above it, over the wall and the no-go area to the next room, back into the corridor,
# along it, into the room below and back out.
OFFICE_ROUTE = [(5, 10), (8, 10), (12, 10), (12, 14), (22, 14), (22, 10), (26, 10), (30, 10)]
OFFICE_ROUTE += [(30, 4), (36, 10)]


def office_with_beacons() -> dict:
    """Return the demo office's map with a beacon at each point of ``OFFICE_ROUTE`` instead
    of its own transmitters, so that a scan hearing one beacon places the device on it."""
    doc = load_map()
    doc["features"] = [f for f in doc["features"] if f["properties"]["kind"] != "transmitter"]
    doc["features"] += [
        {
            "type": "Feature",
            "geometry": {"type": "Point", "coordinates": [x, y]},
            "properties": {"kind": "transmitter", "id": beacon_id(x, y), "tech": "ble"},
        }
        for x, y in OFFICE_ROUTE
    ]
    return doc


def test_a_trail_is_not_drawn_through_the_demo_walls(page: Page, server: LiveServer) -> None:
    sid = f"office-{uuid.uuid4().hex[:8]}"
    with httpx.Client(base_url=server.url, headers=ADMIN) as http:
        assert http.put(f"/v1/sites/{sid}", json={"name": "Demo office"}).status_code == 201
        assert http.put(f"/v1/sites/{sid}/floors/G", json=office_with_beacons()).status_code == 201
    sign_in(page, server, ADMIN_KEY, sid)
    t0 = int(time.time() * 1000)
    post_fixes(
        server, sid, "walker", [(t0 + 3000 * k, x, y) for k, (x, y) in enumerate(OFFICE_ROUTE)]
    )
    marker = page.locator('#plan [data-layer="live"] .device[data-device="walker"]')
    expect(marker).to_have_attribute("data-t", str(t0 + 3000 * (len(OFFICE_ROUTE) - 1)))

    d = page.get_attribute('#plan [data-layer="live"] path.trail', "d") or ""
    runs = drawn_runs(d)
    # every position is drawn, in order: the engine's path, not a route around the walls
    drawn = [c for run in runs for p in run for c in p]
    assert drawn == pytest.approx([c for p in OFFICE_ROUTE for c in p])
    # no drawn leg touches a wall, and only the legs that would are left out
    walls = demo_walls()
    legs = list(zip(OFFICE_ROUTE, OFFICE_ROUTE[1:], strict=False))
    through = [shapely.LineString(leg).intersects(walls) for leg in legs]
    assert sum(through) == len(runs) - 1 >= 4, d
    for run in runs:
        for a, b in zip(run, run[1:], strict=False):
            assert not shapely.LineString([a, b]).intersects(walls), (a, b)
