"""Outages told apart from bugs: lost connections are waited out, anything else is raised."""

from __future__ import annotations

import pytest
import redis
from sqlalchemy import create_engine, text
from sqlalchemy.exc import IntegrityError, OperationalError

from app.core import outages


def _refused() -> OperationalError:
    """Return the error SQLAlchemy raises for a database that refuses connections."""
    engine = create_engine("postgresql+psycopg://nobody@127.0.0.1:1/none")
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except OperationalError as exc:
        return exc
    raise AssertionError("port 1 answered")


def test_refused_connections_and_lost_redis_are_outages_constraint_errors_are_not() -> None:
    assert outages.is_outage(_refused())
    assert outages.is_outage(redis.ConnectionError("Connection refused"))
    assert outages.is_outage(redis.BusyLoadingError("loading"))
    assert not outages.is_outage(IntegrityError("insert", {}, Exception("duplicate key")))
    assert not outages.is_outage(redis.ResponseError("WRONGTYPE"))
    assert not outages.is_outage(ValueError("bad"))


def test_work_is_run_again_through_an_outage_until_it_completes() -> None:
    attempts: list[int] = []
    waits: list[int] = []
    refused = _refused()

    def work() -> str:
        attempts.append(1)
        if len(attempts) < 3:
            raise refused
        return "stored"

    assert outages.retry_through_outage(work, what="test", on_wait=lambda: waits.append(1)) == (
        "stored"
    )
    assert len(attempts) == 3 and len(waits) == 2


def test_errors_that_are_not_outages_are_raised_at_once() -> None:
    attempts: list[int] = []

    def work() -> None:
        attempts.append(1)
        raise IntegrityError("insert", {}, Exception("duplicate key"))

    with pytest.raises(IntegrityError):
        outages.retry_through_outage(work, what="test")
    assert attempts == [1]
