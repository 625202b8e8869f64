"""The documentation stays true to the code: every route of the app's OpenAPI document is in
docs/api.md, every setting in docs/operations.md, every relative link resolves, every table
of figures names a command that exists and takes its options, the README's webhook check
verifies what Locus signs, and nothing points outside the repository."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.core.config import Settings

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *DOCS]
LINK = re.compile(r"\]\(([^)\s]+)\)")
COMMAND = re.compile(r"^Command: `([^`]+)`$", re.M)


def anchors(markdown: str) -> set[str]:
    """Return the GitHub anchors of a page's headings."""
    found = set()
    for heading in re.findall(r"^#+ (.+)$", markdown, flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        found.add(slug)
    return found


def test_every_openapi_path_is_in_the_api_reference(client: TestClient) -> None:
    reference = (ROOT / "docs" / "api.md").read_text()
    paths = client.get("/openapi.json").json()["paths"]
    assert len(paths) > 20
    assert [p for p in paths if f"`{p}`" not in reference] == []


def test_every_setting_is_in_the_operations_page() -> None:
    page = (ROOT / "docs" / "operations.md").read_text()
    fields = Settings.model_fields
    assert [f for f in fields if f"`LOCUS_{f.upper()}`" not in page] == []


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_relative_link_resolves(page: Path) -> None:
    broken = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"^[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path) if path else page
        if not file.exists():
            broken.append(target)
        elif anchor and file.suffix == ".md" and anchor not in anchors(file.read_text()):
            broken.append(target)
    assert broken == []


def command_of(line: str) -> list[str]:
    """Return the argv that runs a documented command with ``--help`` added."""
    words = line.split()
    if words[0] == "locus":
        return [sys.executable, "-m", "app.cli", *words[1:], "--help"]
    assert words[:2] == ["python", "-m"], line
    return [sys.executable, *words[1:], "--help"]


@pytest.mark.parametrize("name", ["accuracy.md", "performance.md"])
def test_every_table_of_figures_names_a_command_that_takes_its_options(name: str) -> None:
    text = (ROOT / "docs" / name).read_text()
    blocks = text.split("\n\n")
    tables = [i for i, b in enumerate(blocks) if b.startswith("| ")]
    assert tables
    for i in tables:
        (line,) = COMMAND.findall("\n\n".join(blocks[max(0, i - 3) : i]))[-1:]
        argv = command_of(line)
        done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, (line, done.stderr[-2000:])
        for option in re.findall(r"--[a-z-]+", line):
            assert option in done.stdout, (line, option)


def test_nothing_points_outside_the_repository() -> None:
    outside = re.compile(r"\bAPI\.md|\bDESIGN\.md|(?i:seeds?/|seed 00\d|release before|one-off)")
    hits = [
        f"{p.relative_to(ROOT)}:{n}"
        for p in [*PAGES, *sorted((ROOT / "app").rglob("*.py"))]
        for n, line in enumerate(p.read_text().splitlines(), 1)
        if outside.search(line)
    ]
    assert hits == []


def test_the_readme_webhook_check_accepts_what_locus_signs_and_nothing_else() -> None:
    from app.outputs.signing import headers, signing_key

    section = (ROOT / "README.md").read_text().split("\n## Positions to MQTT and webhooks\n")[1]
    (snippet,) = re.findall(r"```python\n(.*?)```", section.split("\n## ", 1)[0], flags=re.S)
    assert len([line for line in snippet.splitlines()[2:] if line.strip()]) == 5
    scope: dict[str, object] = {}
    exec(snippet, scope)  # noqa: S102 (the README's own code)
    verify = scope["verify"]
    secret = re.search(r'"secret": "(whsec_[^"]+)"', section).group(1)  # type: ignore[union-attr]
    body = b'{"type":"zone","event":"enter","zone":"Lab","device_id":"tag-1","site_id":"hq"}'
    signed = headers(signing_key(secret), "msg_42", 1_700_000_000, body)
    assert verify(secret, signed, body)  # type: ignore[operator]
    assert not verify(secret, signed, body.replace(b"enter", b"exit"))  # type: ignore[operator]
    assert not verify(secret, signed | {"webhook-id": "msg_43"}, body)  # type: ignore[operator]
    other = "whsec_" + "QUJD" * 8
    assert not verify(other, signed, body)  # type: ignore[operator]
