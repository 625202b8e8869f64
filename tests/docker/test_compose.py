"""The container files describe a topology the CLI can run (no Docker engine here)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import yaml

from app.cli import build_parser

DOCKER = Path(__file__).resolve().parents[2] / "docker"


def test_compose_services_and_their_commands() -> None:
    compose = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    services = compose["services"]
    assert {"postgres", "redis", "api1", "api2", "worker", "proxy"} <= set(services)
    assert services["worker"]["deploy"]["replicas"] >= 2
    parser = build_parser()
    for name in ("api1", "api2", "worker"):
        service = services[name]
        command = service["command"]
        assert command[0] == "locus"
        args = parser.parse_args(command[1:])  # exits (fails the test) on an unknown command
        assert args.func is not None
        env = service["environment"]
        assert env["LOCUS_BROKER"].startswith("redis://")
        assert env["LOCUS_DATABASE_URL"].startswith("postgresql+psycopg://")
        assert set(service["depends_on"]) == {"postgres", "redis"}
    api = parser.parse_args(services["api1"]["command"][1:])
    assert api.command == "serve" and api.workers == 0


def test_dockerfile_runs_locus_as_non_root_with_a_healthcheck() -> None:
    text = (DOCKER / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.\d+-slim", text, re.M)
    assert re.search(r"^USER locus$", text, re.M)
    assert "HEALTHCHECK" in text and "/healthz" in text
    cmd = json.loads(re.search(r"^CMD (\[.*\])$", text, re.M).group(1))
    assert cmd[0] == "locus"
    assert build_parser().parse_args(cmd[1:]).command == "serve"
    upstreams = re.findall(r"server (api\d):8000", (DOCKER / "nginx.conf").read_text())
    assert upstreams == ["api1", "api2"]
