"""The container files describe a topology the CLI can run (no Docker engine here)."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import yaml
from sqlalchemy.engine import make_url

from app.cli import build_parser
from app.core.config import Settings

DOCKER = Path(__file__).resolve().parents[2] / "docker"
NUMBERS = {"one": 1, "two": 2, "three": 3, "four": 4, "five": 5}


def _compose() -> dict[str, Any]:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def _locus_command(service: dict[str, Any]) -> argparse.Namespace:
    command = service["command"]
    assert command[0] == "locus"
    return build_parser().parse_args(command[1:])  # exits (fails the test) on a bad command


def test_compose_runs_the_topology_the_readme_describes() -> None:
    readme = (DOCKER.parent / "README.md").read_text()
    described = re.search(
        r"\((\w+) API\s+nodes behind nginx, (\w+) workers, PostgreSQL, Redis\)", readme
    )
    assert described, "the README no longer describes the compose topology"
    api_nodes, workers = (NUMBERS[w] for w in described.groups())
    services = _compose()["services"]
    assert {"postgres", "redis", "api1", "api2", "worker", "proxy"} <= set(services)
    commands = {
        name: _locus_command(s).command
        for name, s in services.items()
        if "command" in s and s["command"][0] == "locus"
    }
    assert sorted(commands.values()).count("serve") == api_nodes
    assert [n for n, c in commands.items() if c == "worker"] == ["worker"]
    assert services["worker"]["deploy"]["replicas"] == workers >= 2
    assert services["postgres"]["image"].startswith("postgres:")
    assert services["redis"]["image"].startswith("redis:")
    assert services["proxy"]["image"].startswith("nginx:")
    api_names = sorted(n for n, c in commands.items() if c == "serve")
    assert sorted(services["proxy"]["depends_on"]) == api_names
    upstreams = re.findall(r"server (\w+):8000", (DOCKER / "nginx.conf").read_text())
    assert sorted(upstreams) == api_names


def test_api_nodes_and_workers_share_postgres_and_redis() -> None:
    services = _compose()["services"]
    postgres = services["postgres"]["environment"]
    for name in ("api1", "api2", "worker"):
        service = services[name]
        assert _locus_command(service).command == ("worker" if name == "worker" else "serve")
        env = service["environment"]
        assert env["LOCUS_BROKER"].startswith("redis://")
        assert env["LOCUS_DATABASE_URL"].startswith("postgresql+psycopg://")
        settings = Settings(database_url=env["LOCUS_DATABASE_URL"], broker=env["LOCUS_BROKER"])
        database = make_url(settings.database_url)
        assert database.drivername == "postgresql+psycopg"
        assert (database.host, database.port) == ("postgres", 5432)
        assert database.username == postgres["POSTGRES_USER"]
        assert database.password == postgres["POSTGRES_PASSWORD"]
        assert database.database == postgres["POSTGRES_DB"]
        broker = urlsplit(settings.broker)
        assert (broker.scheme, broker.hostname, broker.port) == ("redis", "redis", 6379)
        assert env["LOCUS_ADMIN_KEY"].startswith("${LOCUS_ADMIN_KEY:?")
        # every node waits until the database and Redis answer their health checks
        assert service["depends_on"] == {
            "postgres": {"condition": "service_healthy"},
            "redis": {"condition": "service_healthy"},
        }
    for dependency in ("postgres", "redis"):
        assert services[dependency]["healthcheck"]["test"]
    for name in ("api1", "api2"):
        api = _locus_command(services[name])
        # API nodes run no workers of their own: the worker service processes their ingest
        assert api.command == "serve" and api.workers == 0 and api.port == 8000


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
