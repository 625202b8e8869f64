"""Fuzzing at depth (``pytest -m slow``): over 10,000 generated requests against one real
server, Schemathesis's every phase plus long runs of the API state machine, and not one
server error."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.conftest import LiveServer
from tests.e2e.test_api_state_machine import run_machine
from tests.e2e.test_schemathesis import run_schemathesis

AT_LEAST = 10_000


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_ten_thousand_generated_requests_without_a_server_error(
    new_database: Any, tmp_path: Path
) -> None:
    server = LiveServer(database_url=new_database(), home=tmp_path, workers=1)
    try:
        # the machine first: Schemathesis may well revoke the admin key the machine uses
        sequences = run_machine(server.url, examples=60, steps=50)
        schema_cases = run_schemathesis(server.url, tmp_path, examples=150, timeout_s=3000)
    finally:
        server.stop()
    log = server.log.read_text()
    total = schema_cases + sequences
    print(
        f"fuzzing at depth: {schema_cases} schemathesis cases + {sequences} state-machine "
        f"requests = {total}; server errors: 0; 'unhandled error' in the log: "
        f"{log.count('unhandled error')}"
    )
    assert total >= AT_LEAST
    assert "unhandled error" not in log
