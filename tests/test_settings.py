"""Settings are checked when a node starts: a bad URL or an out-of-range limit stops it with a
message naming the setting and what it accepts, never echoing a password."""

from __future__ import annotations

import secrets
import socket

import pytest

from app.cli import main
from app.core.config import Settings


@pytest.mark.parametrize(
    ("url", "says"),
    [
        ("mysql+pymysql://locus:secret@db/locus", "unsupported scheme 'mysql+pymysql'"),
        ("postgresql://locus:secret@db/locus", "unsupported scheme 'postgresql'"),
        ("locus.db", "is not a database URL"),
    ],
)
def test_a_bad_database_url_names_the_setting_and_the_accepted_forms(url: str, says: str) -> None:
    with pytest.raises(ValueError) as raised:
        Settings(database_url=url)
    message = str(raised.value)
    assert "database_url" in message and says in message
    assert "sqlite:///" in message and "postgresql+psycopg://" in message
    assert "secret" not in message


@pytest.mark.parametrize("url", ["", "sqlite:///var/locus.db", "postgresql+psycopg://u@h:5432/d"])
def test_the_accepted_database_urls_pass(url: str) -> None:
    assert Settings(database_url=url).database_url == url


@pytest.mark.parametrize(
    ("broker", "says"),
    [("kafka://u:secret@k:9092", "a 'kafka' URL"), ("redis-host:6379", "neither")],
)
def test_a_bad_broker_names_the_setting_and_the_accepted_forms(broker: str, says: str) -> None:
    with pytest.raises(ValueError) as raised:
        Settings(broker=broker)
    message = str(raised.value)
    assert "broker" in message and "'memory'" in message and "redis://" in message
    assert says in message and "secret" not in message


@pytest.mark.parametrize("broker", ["memory", "redis://127.0.0.1:6379/0", "rediss://r:6380/1"])
def test_the_accepted_brokers_pass(broker: str) -> None:
    assert Settings(broker=broker).broker == broker


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("ingest_wait_timeout_s", 0),
        ("site_cache_ttl_s", -1),
        ("key_cache_ttl_s", 86_400),
        ("key_cache_size", 0),
        ("planning_max_cells", 0),
        ("radiomap_folds", 1),
        ("radiomap_progress_step", 1.5),
        ("port", 70_000),
        ("max_samples", 0),
        ("shard_backlog", 0),
        ("reorder_window_ms", -1),
        ("job_lease_s", 0),
        ("time_outlier_s", 0),
    ],
)
def test_a_limit_out_of_its_range_is_rejected(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        Settings(**{field: value})


def test_limits_are_read_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("LOCUS_INGEST_WAIT_TIMEOUT_S", "5")
    monkeypatch.setenv("LOCUS_PLANNING_MAX_CELLS", "1000")
    settings = Settings()
    assert settings.ingest_wait_timeout_s == 5.0 and settings.planning_max_cells == 1000
    monkeypatch.setenv("LOCUS_BROKER", "amqp://rabbit")
    with pytest.raises(ValueError, match="broker"):
        Settings()


def test_every_setting_says_what_it_is_for() -> None:
    undocumented = [name for name, field in Settings.model_fields.items() if not field.description]
    assert undocumented == []


def test_the_cli_stops_on_a_bad_setting_with_its_name() -> None:
    with pytest.raises(SystemExit) as raised:
        main(["worker", "--broker", "kafka://k:9092"])
    assert "invalid settings" in str(raised.value) and "broker" in str(raised.value)


@pytest.mark.parametrize(
    ("key", "says"),
    [
        ("change-me", "9 characters, fewer than 24"),
        ("lk_test_admin_key", "17 characters, fewer than 24"),
        ("please-CHANGE-ME-before-production", "the placeholder 'changeme'"),
        ("my-super-secret-admin-key-2026", "the placeholder 'secret'"),
        ("0101010101010101010101010101", "only 2 distinct characters"),
    ],
)
def test_a_weak_admin_key_is_refused_saying_how_to_make_one(
    key: str, says: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    with pytest.raises(ValueError) as raised:
        Settings(admin_key=key)
    message = str(raised.value)
    assert "admin_key (LOCUS_ADMIN_KEY) is too weak" in message and says in message
    assert 'python -c "import secrets; print(secrets.token_urlsafe(32))"' in message
    assert key not in message, "the refused key is not echoed"
    monkeypatch.setenv("LOCUS_ADMIN_KEY", key)
    with pytest.raises(SystemExit) as stopped:
        main(["serve", "--workers", "0"])
    assert "too weak" in str(stopped.value) and "secrets.token_urlsafe" in str(stopped.value)


def test_a_random_admin_key_is_accepted() -> None:
    key = secrets.token_urlsafe(32)
    assert Settings(admin_key=key).admin_key == key
    assert Settings(admin_key="").admin_key is None, "empty means: generate one"


@pytest.mark.parametrize("command", ["serve", "demo"])
def test_a_port_in_use_stops_the_start_saying_what_to_do(command: str, tmp_path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = str(taken.getsockname()[1])
        with pytest.raises(SystemExit) as raised:
            main([command, "--port", port, "--home", str(tmp_path)])
    message = str(raised.value)
    assert f"cannot listen on 127.0.0.1:{port}" in message
    assert "the demo?" in message and "pass --port" in message
    # nothing was started: no database was even created
    assert not list(tmp_path.iterdir())
