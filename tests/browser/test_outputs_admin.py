"""The Admin tab lists the site's outputs with their delivery status, read again while the
tab is open: a webhook delivering to a real receiver, an MQTT output whose broker does not
answer, and the webhook once its receiver starts refusing."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from playwright.sync_api import Page, expect

from tests.browser.test_dashboard import sign_in
from tests.conftest import ADMIN_KEY, LiveServer, floor_doc, free_port
from tests.receivers import SECRET, Receiver, until

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
T0 = 1_700_000_000_000

pytestmark = pytest.mark.browser


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    server = Receiver()
    yield server
    server.close()


def test_admin_tab_lists_outputs_with_their_status(
    page: Page, server: LiveServer, receiver: Receiver
) -> None:
    site = f"out-{uuid.uuid4().hex[:8]}"
    http = httpx.Client(base_url=server.url, headers=ADMIN, timeout=30)
    assert http.put(f"/v1/sites/{site}", json={"name": site}).status_code == 201
    assert http.put(f"/v1/sites/{site}/floors/G", json=floor_doc()).status_code == 201
    hook = {"kind": "webhook", "url": receiver.url, "secret": SECRET, "events": ["position"]}
    assert http.put(f"/v1/sites/{site}/outputs/hook", json=hook).status_code == 201
    nowhere = {"kind": "mqtt", "url": f"mqtt://127.0.0.1:{free_port()}"}
    assert http.put(f"/v1/sites/{site}/outputs/broker", json=nowhere).status_code == 201
    sent = [0]

    def post() -> None:
        fix = {"t": T0 + 1000 * sent[0], "x": 3.0, "y": 3.0, "floor_id": "G", "std": 0.1}
        sent[0] += 1
        body = {"device_id": "tag", "site_id": site, "uwb_fix": [fix]}
        assert http.post("/v1/ingest?wait=true", json=body).status_code == 200

    def status(output: str) -> dict[str, Any]:
        return dict(http.get(f"/v1/sites/{site}/outputs/{output}").json()["status"])

    # until the workers take the new outputs: a position a poll
    until(lambda: post() or receiver.accepted(), 30, "the webhook delivering")
    until(lambda: status("broker")["last_error"], 30, "the broker's failure noted")
    delivered = until(lambda: (s := status("hook"))["pending"] == 0 and s["delivered"])

    sign_in(page, server, ADMIN_KEY, site)
    page.click("#tab-admin")
    item = page.locator('#outputs li[data-id="hook"]')
    expect(item).to_contain_text("hook · webhook")
    expect(item).to_contain_text(f"{receiver.url} (position)")
    expect(item).to_contain_text(f"{delivered} delivered · 0 waiting · 0 failed")
    expect(item).to_have_attribute("data-health", "ok")
    broker = page.locator('#outputs li[data-id="broker"]')
    expect(broker).to_contain_text("broker · MQTT")
    expect(broker).to_have_attribute("data-health", "failing")
    expect(broker.locator(".error")).to_contain_text("cannot connect")
    assert SECRET not in page.content()

    # the receiver refuses: the open tab shows it on its next read
    receiver.refusing = True
    post()
    until(lambda: status("hook")["last_error"], 30, "the refusal noted")
    expect(item).to_have_attribute("data-health", "failing", timeout=15_000)
    expect(item.locator(".error")).to_contain_text("answered 503")
    expect(item).to_contain_text("1 waiting")
