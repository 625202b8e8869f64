"""Property-based fuzzing of the whole HTTP API from its own OpenAPI document.

Schemathesis generates requests for every operation (valid and invalid bodies,
parameters and headers, with an admin key) against a real ``locus serve`` and
checks that no answer is a server error and every answer matches the schema.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path
from typing import Any

from tests.conftest import ADMIN_KEY, LiveServer

EXAMPLES_PER_OPERATION = 25


def run_schemathesis(url: str, cwd: Path, *, examples: int, timeout_s: float) -> int:
    """Fuzz the server at ``url`` from its OpenAPI document, every phase (the stateful one
    follows the links Schemathesis infers); return the test cases generated, failing on any
    server error or answer outside the schema."""
    run = subprocess.run(
        [
            Path(sys.executable).parent / "schemathesis", "run",
            f"{url}/openapi.json",
            "--header", f"Authorization: Bearer {ADMIN_KEY}",
            "--checks", "not_a_server_error,response_schema_conformance",
            "--phases", "examples,coverage,fuzzing,stateful",
            "--max-examples", str(examples),
            "--seed", "1",
            "--workers", "1",
            "--request-timeout", "30",
        ],
        capture_output=True, text=True, timeout=timeout_s, cwd=cwd,
    )  # fmt: skip
    summary = run.stdout[-3000:]
    assert run.returncode == 0, summary
    generated = re.search(r"(\d+) generated", run.stdout)
    assert generated is not None, summary
    return int(generated.group(1))


def test_no_server_errors_and_every_answer_matches_the_schema(
    new_database: Any, tmp_path: Path
) -> None:
    server = LiveServer(database_url=new_database(), home=tmp_path, workers=1)
    try:
        generated = run_schemathesis(
            server.url, tmp_path, examples=EXAMPLES_PER_OPERATION, timeout_s=600
        )
    finally:
        server.stop()
    assert generated > 500
    print(f"schemathesis: {generated} test cases, no failures")
