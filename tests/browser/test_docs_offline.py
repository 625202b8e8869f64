"""The API's documentation pages work on a server without internet: every script, style
and font of /docs and /redoc comes from Locus itself."""

from __future__ import annotations

from urllib.parse import urlsplit

import pytest
from playwright.sync_api import Page, Route, expect

from tests.conftest import LiveServer

pytestmark = pytest.mark.browser

REDOC_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"
"""ReDoc's "API docs by Redocly" badge: hard-coded in its script, hidden when unreachable."""


def block_the_network(page: Page, server: LiveServer) -> list[str]:
    """Abort every request that is not to the server; return the list of what was tried."""
    ours = urlsplit(server.url).netloc
    elsewhere: list[str] = []

    def only_locus(route: Route) -> None:
        if urlsplit(route.request.url).netloc == ours:
            route.continue_()
        else:
            elsewhere.append(route.request.url)
            route.abort("internetdisconnected")

    page.context.route("**/*", only_locus)
    return elsewhere


def test_swagger_ui_renders_with_the_network_blocked(page: Page, server: LiveServer) -> None:
    elsewhere = block_the_network(page, server)
    page.goto(server.url + "/docs")
    expect(page.locator(".swagger-ui .info .title")).to_contain_text("Locus")
    expect(page.locator(".opblock-tag", has_text="ingest").first).to_be_visible()
    expect(page.locator(".opblock-summary-path", has_text="/v1/ingest").first).to_be_visible()
    assert elsewhere == []


def test_redoc_renders_with_the_network_blocked(page: Page, server: LiveServer) -> None:
    elsewhere = block_the_network(page, server)
    page.goto(server.url + "/redoc")
    expect(page.locator("h1").first).to_contain_text("Locus")
    expect(page.get_by_text("/v1/ingest/bulk").first).to_be_attached()
    assert set(elsewhere) <= {REDOC_LOGO}
    expect(page.locator(f'img[src="{REDOC_LOGO}"]')).to_have_count(0)
