"""The survey guidance overlay in headless Chromium against a real ``locus serve``: real
site1 walks surveyed and built, then the floor's expected-error grid drawn over the plan
cell for cell; before a build, the server's reason shown; one heatmap overlay at a time."""

from __future__ import annotations

import uuid
from typing import Any

import httpx
import pytest
from playwright.sync_api import Page, expect

from app.datasets.ilc import read_floor, read_walk, site_walks
from app.importers.ilc import survey_body
from tests.api.test_radiomap import FLOOR, N_SURVEYS, SITE1, needs_site1
from tests.browser.test_dashboard import sign_in
from tests.conftest import ADMIN_KEY, LiveServer, floor_doc

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
SCREENSHOT = "/tmp/guidance.png"

pytestmark = pytest.mark.browser

# Each drawn cell's pixel, counted by kind: transparent (off the walkable area), unsurveyed
# or coloured from the ramp, told apart by their opacities (drawing through a canvas
# premultiplies alpha, so the colours come back rounded; the opacities exactly).
COUNT_PIXELS = """async ([href, greyAlpha]) => {
  const img = new Image();
  img.src = href;
  await img.decode();
  const c = document.createElement("canvas");
  c.width = img.width; c.height = img.height;
  const g = c.getContext("2d");
  g.drawImage(img, 0, 0);
  const d = g.getImageData(0, 0, c.width, c.height).data;
  const n = { transparent: 0, grey: 0, coloured: 0, width: c.width, height: c.height };
  for (let i = 0; i < d.length; i += 4) {
    if (d[i + 3] === 0) n.transparent++;
    else if (d[i + 3] === greyAlpha) n.grey++;
    else n.coloured++;
  }
  return n;
}"""
UNSURVEYED_ALPHA = 110
"""The opacity of an unsurveyed cell (``NO_VALUE`` in app/web/ramp.js; the ramp's is 165)."""


@pytest.fixture(scope="module")
def built(server: LiveServer) -> tuple[str, dict[str, Any]]:
    """A site with site1's F1 and 4 of its walks surveyed and built; its guidance JSON."""
    if not SITE1.is_dir():
        pytest.skip("ILC site1 recordings not present")
    site = f"sgb-{uuid.uuid4().hex[:8]}"
    walks = [p for f, p in site_walks(SITE1) if f == FLOOR][:N_SURVEYS]
    with httpx.Client(base_url=server.url, headers=ADMIN, timeout=600) as http:
        assert http.put(f"/v1/sites/{site}", json={"name": site}).status_code == 201
        r = http.put(f"/v1/sites/{site}/floors/{FLOOR}", json=read_floor(SITE1 / FLOOR).geojson)
        assert r.is_success, r.text
        for path in walks:
            body = survey_body(read_walk(path, FLOOR), device_id="surveyor")
            assert http.post(f"/v1/sites/{site}/surveys", json=body).status_code == 201
        r = http.post(f"/v1/sites/{site}/radiomap/build")
        assert r.status_code == 200, r.text
        grid = http.get(f"/v1/sites/{site}/floors/{FLOOR}/survey-guidance").json()
    return site, grid


@needs_site1
def test_the_guidance_overlay_draws_the_builds_grid_cell_for_cell(
    page: Page, server: LiveServer, built: tuple[str, dict[str, Any]]
) -> None:
    site, grid = built
    ny, nx = grid["shape"]
    walkable = sum(v for row in grid["walkable"] for v in row)
    unsurveyed = sum(
        w and e is None
        for wr, er in zip(grid["walkable"], grid["expected_error_m"], strict=True)
        for w, e in zip(wr, er, strict=True)
    )
    assert 0 < unsurveyed < walkable
    page.goto(server.url + "/")
    page.fill("#key", ADMIN_KEY)
    page.click("#sign-in")
    expect(page.locator(f'#site option[value="{site}"]')).to_have_count(1)
    page.select_option("#site", site)
    expect(page.locator("#plan")).to_have_attribute("data-floor", FLOOR)
    page.check("#guidance-toggle")
    status = page.locator("#guidance-status")
    expect(status).to_have_attribute("data-state", "shown")
    share = round(100 * grid["summary"]["unsurveyed_share"])
    expect(status).to_contain_text(f"{share}% of the walkable area unsurveyed")
    expect(page.locator("#guidance-scale")).to_be_visible()
    expect(page.locator("#guidance-top")).to_have_text(
        f"≥ {2 * grid['params']['high_error_m']:g} m"
    )

    image = page.locator('#plan [data-layer="heatmap"] image[data-overlay="guidance"]')
    expect(image).to_have_attribute("data-shape", f"{ny}x{nx}")
    expect(image).to_have_attribute("data-cells", str(walkable))
    attrs = image.evaluate("n => ['x', 'y', 'width', 'height'].map(a => +n.getAttribute(a))")
    assert attrs == pytest.approx(
        [grid["origin"][0], grid["origin"][1], nx * grid["cell"], ny * grid["cell"]]
    )
    # one pixel per cell: the walkable cells are drawn, the unsurveyed ones grey
    pixels = page.evaluate(COUNT_PIXELS, [image.get_attribute("href"), UNSURVEYED_ALPHA])
    assert (pixels["width"], pixels["height"]) == (nx, ny)
    assert pixels["grey"] == unsurveyed
    assert pixels["coloured"] == walkable - unsurveyed > 0
    assert pixels["transparent"] == ny * nx - walkable
    page.screenshot(path=SCREENSHOT, full_page=True)


def test_before_a_build_the_overlay_says_why_and_shares_the_layer_with_accuracy(
    page: Page, server: LiveServer
) -> None:
    site = f"sgn-{uuid.uuid4().hex[:8]}"
    with httpx.Client(base_url=server.url, headers=ADMIN) as http:
        assert http.put(f"/v1/sites/{site}", json={"name": site}).status_code == 201
        assert http.put(f"/v1/sites/{site}/floors/G", json=floor_doc()).status_code == 201
    sign_in(page, server, ADMIN_KEY, site)
    page.check("#guidance-toggle")
    status = page.locator("#guidance-status")
    expect(status).to_have_attribute("data-state", "unavailable")
    expect(status).to_contain_text("no radio map yet")
    heatmap = page.locator('#plan [data-layer="heatmap"] image')
    expect(heatmap).to_have_count(0)
    # the accuracy map takes the layer: the guidance is unticked and says nothing
    page.check("#accuracy-toggle")
    expect(page.locator("#accuracy-status")).to_have_attribute("data-state", "shown")
    expect(page.locator("#guidance-toggle")).not_to_be_checked()
    expect(status).to_have_attribute("data-state", "off")
    expect(heatmap).to_have_count(1)
    # and back: the accuracy map goes with its tick, and nothing is drawn in its place
    page.check("#guidance-toggle")
    expect(page.locator("#accuracy-toggle")).not_to_be_checked()
    expect(status).to_have_attribute("data-state", "unavailable")
    expect(heatmap).to_have_count(0)
