"""The Analytics tab in headless Chromium against a real ``locus serve``: a walk through the
Lab zone, then the heatmap drawn over the plan and the zone's occupancy chart."""

from __future__ import annotations

import base64
import uuid

import httpx
import pytest
from playwright.sync_api import Page, expect

from tests.browser.test_dashboard import sign_in
from tests.conftest import ADMIN_KEY, LiveServer, floor_doc

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
T0 = 1_700_000_000_000

pytestmark = pytest.mark.browser


def test_analytics_tab_draws_the_heatmap_and_the_occupancy_chart(
    page: Page, server: LiveServer
) -> None:
    site = f"an-{uuid.uuid4().hex[:8]}"
    # east at 1.25 m/s along y = 4 through the Lab (12 ≤ x ≤ 16), a fix every 0.2 s
    fixes = [
        {"t": T0 + 200 * k, "x": 10.5 + 0.25 * k, "y": 4.0, "floor_id": "G", "std": 0.1}
        for k in range(38)
    ]
    with httpx.Client(base_url=server.url, headers=ADMIN) as http:
        assert http.put(f"/v1/sites/{site}", json={"name": site}).status_code == 201
        assert http.put(f"/v1/sites/{site}/floors/G", json=floor_doc()).status_code == 201
        body = {"device_id": "walker", "site_id": site, "uwb_fix": fixes}
        r = http.post("/v1/ingest?wait=true", json=body)
        assert r.status_code == 200 and r.json()["positions"], r.text
        heat = http.get(
            f"/v1/sites/{site}/floors/G/heatmap?from={T0}&to={T0 + 3_600_000}&cell=1"
        ).json()
    expected = sum(v for row in heat["seconds"] for v in row if v is not None)
    assert expected > 0

    sign_in(page, server, ADMIN_KEY, site)
    page.click("#tab-analytics")
    expect(page.locator("#panel-analytics")).to_be_visible()
    # the range inputs take the browser's local time: set them from the epoch times
    page.evaluate(
        """([from, to]) => {
          const local = (ms) => new Date(ms - new Date(ms).getTimezoneOffset() * 60000)
            .toISOString().slice(0, 19);
          document.getElementById("analytics-from").value = local(from);
          document.getElementById("analytics-to").value = local(to);
        }""",
        [T0, T0 + 3_600_000],
    )
    page.select_option("#analytics-bucket", "60")
    expect(page.locator('#analytics-zone option[value="Lab"]')).to_have_count(1)
    page.click("#analytics-form button[type=submit]")
    expect(page.locator("#analytics-status")).to_have_attribute("data-state", "shown")

    image = page.locator('#plan [data-layer="heatmap"] image')
    assert float(image.get_attribute("data-total") or 0) == pytest.approx(expected)
    # the drawn raster has coloured cells, not only transparent ones
    href = image.get_attribute("href") or ""
    coloured = page.evaluate(
        """async (href) => {
          const img = new Image();
          img.src = href;
          await img.decode();
          const c = document.createElement("canvas");
          c.width = img.width; c.height = img.height;
          const g = c.getContext("2d");
          g.drawImage(img, 0, 0);
          const d = g.getImageData(0, 0, c.width, c.height).data;
          let n = 0;
          for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++;
          return n;
        }""",
        href,
    )
    assert coloured > 0 and href.startswith("data:image/png;base64,")
    assert base64.b64decode(href.split(",", 1)[1])[:4] == b"\x89PNG"

    chart = page.locator("#analytics-chart")
    # 60 one-minute buckets in the hour, one device inside in the first
    expect(chart).to_have_attribute("data-points", "60")
    expect(chart).to_have_attribute("data-devices", "1")
    expect(chart.locator(".uplot canvas")).to_have_count(1)
    page.screenshot(path="/tmp/locus-analytics.png", full_page=True)
