"""Deep sequences through the API of a real server: sites, floors, keys, ingest and reads in
any order (``api_machine.ApiMachine``), every answer as the contract says and none a 5xx."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, settings
from hypothesis.stateful import run_state_machine_as_test

from tests.conftest import LiveServer
from tests.e2e.api_machine import ApiMachine


def run_machine(url: str, *, examples: int, steps: int) -> int:
    """Run the machine against the server at ``url``; return the requests it sent."""
    ApiMachine.base_url = url
    ApiMachine.requests = 0
    ApiMachine.server_errors = []
    run_state_machine_as_test(
        ApiMachine,
        settings=settings(
            max_examples=examples,
            stateful_step_count=steps,
            deadline=None,
            database=None,
            derandomize=False,
            suppress_health_check=list(HealthCheck),
        ),
    )
    assert not ApiMachine.server_errors, ApiMachine.server_errors
    return ApiMachine.requests


def test_sequences_of_sites_floors_keys_ingest_and_reads(new_database: Any, tmp_path: Path) -> None:
    server = LiveServer(database_url=new_database(), home=tmp_path, workers=1)
    try:
        sent = run_machine(server.url, examples=8, steps=30)
    finally:
        server.stop()
    assert sent > 100
    print(f"state machine: {sent} requests, no server errors")
