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


def test_no_server_errors_and_every_answer_matches_the_schema(
    new_database: Any, tmp_path: Path
) -> None:
    server = LiveServer(database_url=new_database(), home=tmp_path, workers=1)
    try:
        run = subprocess.run(
            [
                Path(sys.executable).parent / "schemathesis", "run",
                f"{server.url}/openapi.json",
                "--header", f"Authorization: Bearer {ADMIN_KEY}",
                "--checks", "not_a_server_error,response_schema_conformance",
                "--phases", "examples,coverage,fuzzing",
                "--max-examples", str(EXAMPLES_PER_OPERATION),
                "--seed", "1",
                "--workers", "1",
                "--request-timeout", "30",
            ],
            capture_output=True, text=True, timeout=600, cwd=tmp_path,
        )  # fmt: skip
    finally:
        server.stop()
    summary = run.stdout[-3000:]
    assert run.returncode == 0, summary
    generated = re.search(r"(\d+) generated", run.stdout)
    assert generated is not None and int(generated.group(1)) > 500, summary
    print(f"schemathesis: {generated.group(0)} test cases, no failures")
