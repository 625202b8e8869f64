"""Take the README's dashboard screenshots from a running `locus demo` with Debian's Chromium.

    python scripts/screenshots.py --server http://127.0.0.1:8000 --key ADMIN_KEY --out docs

Writes ``live.png`` (the demo floor with its moving devices, after
``--settle`` seconds of live positions) and ``admin.png`` (a floor map with a
self-intersecting outline and a repeated transmitter id, rejected, its
problems listed and marked).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]

BAD_MAP = {
    "type": "FeatureCollection",
    "properties": {"level": 0, "name": "Broken"},
    "features": [
        {
            "type": "Feature",
            "properties": {"kind": "outline"},
            "geometry": {
                "type": "Polygon",
                "coordinates": [[[0, 0], [30, 0], [0, 20], [30, 20], [0, 0]]],
            },
        },
        {
            "type": "Feature",
            "properties": {"kind": "transmitter", "id": "ap-1", "tech": "wifi"},
            "geometry": {"type": "Point", "coordinates": [5, 5]},
        },
        {
            "type": "Feature",
            "properties": {"kind": "transmitter", "id": "ap-1", "tech": "wifi"},
            "geometry": {"type": "Point", "coordinates": [25, 5]},
        },
    ],
}


def main() -> None:
    """Sign in, watch the live view, then reject a bad map in the admin view."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", default="http://127.0.0.1:8000")
    parser.add_argument("--key", required=True)
    parser.add_argument("--out", type=Path, default=Path("docs"))
    parser.add_argument("--settle", type=float, default=15.0, help="seconds of live positions")
    args = parser.parse_args()
    try:
        # a test tool, not a dependency of the server: --help works without it
        from playwright.sync_api import expect, sync_playwright
    except ModuleNotFoundError:
        raise SystemExit(
            "screenshots.py drives Debian's Chromium with Playwright, a test tool: install it "
            "with `.venv/bin/pip install -e '.[dev]'` (and Chromium with `apt-get install "
            "chromium`)"
        ) from None
    if not Path(CHROMIUM).exists():
        raise SystemExit(f"{CHROMIUM} is missing: `apt-get install chromium`")
    args.out.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1440, "height": 860})
        page.goto(args.server + "/")
        page.fill("#key", args.key)
        page.click("#sign-in")
        expect(page.locator("#plan")).to_have_attribute("data-floor", "F1", timeout=15_000)
        page.wait_for_timeout(args.settle * 1000)
        page.screenshot(path=str(args.out / "live.png"))
        page.click("#tab-admin")
        with tempfile.TemporaryDirectory() as tmp:
            bad = Path(tmp) / "broken-floor.geojson"
            bad.write_text(json.dumps(BAD_MAP))
            page.fill("#upload-floor-id", "F9")
            page.set_input_files("#upload-file", str(bad))
            page.click("#upload")
            expect(page.locator("#upload-result .problem").first).to_be_visible(timeout=15_000)
        page.screenshot(path=str(args.out / "admin.png"))
        browser.close()


if __name__ == "__main__":
    main()
