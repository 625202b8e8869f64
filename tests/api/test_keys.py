"""Keys: listed without secrets, revocable (a revoked key stops working at once on HTTP and
within a second on open WebSockets, whichever node revoked it), and auth errors that say
what is wrong."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event
from starlette.websockets import WebSocketDisconnect

from app.core.config import Settings
from app.core.db import make_engine, make_sessionmaker, session_scope
from app.core.security import Principal
from app.keys.bootstrap import bootstrap_admin
from app.keys.cache import KeyCache
from app.keys.service import revoke_key
from app.main import create_app
from tests.conftest import ADMIN_KEY, migrated


def _key(client: TestClient, admin: dict, role: str, site: str, label: str) -> tuple[str, int]:
    """Create a key; return it and its id (found in the listing by its label)."""
    r = client.post("/v1/keys", json={"role": role, "site_id": site, "label": label}, headers=admin)
    key = r.json()["key"]
    listed = client.get(f"/v1/keys?site_id={site}&limit=1000", headers=admin).json()["items"]
    (key_id,) = [k["id"] for k in listed if k["label"] == label]
    return key, key_id


def _bearer(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


def test_keys_are_listed_without_secrets(client: TestClient, admin: dict, site_id: str) -> None:
    key, key_id = _key(client, admin, "viewer", site_id, "lobby screen")
    r = client.get(f"/v1/keys?site_id={site_id}", headers=admin)
    assert r.status_code == 200 and key not in r.text
    (listed,) = [k for k in r.json()["items"] if k["id"] == key_id]
    assert set(listed) == {"id", "role", "site_id", "label", "created_at", "revoked_at"}
    assert listed["role"] == "viewer" and listed["site_id"] == site_id
    assert listed["revoked_at"] is None
    assert client.get("/v1/keys", headers=_bearer(key)).status_code == 403


def test_a_revoked_key_is_refused_saying_so(client: TestClient, admin: dict, site_id: str) -> None:
    key, key_id = _key(client, admin, "viewer", site_id, "revoked")
    assert client.get(f"/v1/sites/{site_id}", headers=_bearer(key)).status_code == 200
    assert client.delete(f"/v1/keys/{key_id}", headers=_bearer(key)).status_code == 403
    assert client.delete(f"/v1/keys/{key_id}", headers=admin).status_code == 204
    r = client.get(f"/v1/sites/{site_id}", headers=_bearer(key))
    assert r.status_code == 401 and r.json()["error"]["message"] == "this API key was revoked"
    listed = client.get(f"/v1/keys?site_id={site_id}", headers=admin).json()["items"]
    assert [k["revoked_at"] is not None for k in listed if k["id"] == key_id] == [True]
    assert client.delete(f"/v1/keys/{key_id}", headers=admin).status_code == 204, "idempotent"
    assert client.delete("/v1/keys/999999999", headers=admin).status_code == 404


def _closed_within(ws: Any, seconds: float) -> tuple[int, str, float]:
    """Wait for the server to close ``ws``; return its code, reason and how long it took."""
    started = time.monotonic()
    with pytest.raises(WebSocketDisconnect) as closed:
        while time.monotonic() - started < seconds + 5:
            ws.receive_json()
    return closed.value.code, closed.value.reason, time.monotonic() - started


def test_revoking_a_key_closes_its_open_websockets_within_a_second(
    client: TestClient, admin: dict, site_id: str
) -> None:
    key, key_id = _key(client, admin, "viewer", site_id, "stream")
    device, device_id = _key(client, admin, "device", site_id, "gateway")
    with (
        client.websocket_connect(f"/v1/ws/positions?site_id={site_id}&key={key}") as stream,
        client.websocket_connect(f"/v1/ws/ingest?key={device}") as ingest,
    ):
        revoked_at = time.monotonic()
        assert client.delete(f"/v1/keys/{key_id}", headers=admin).status_code == 204
        assert client.delete(f"/v1/keys/{device_id}", headers=admin).status_code == 204
        for ws in (stream, ingest):
            code, reason, _ = _closed_within(ws, 1.0)
            assert code == 1008 and reason == "this API key was revoked"
        assert time.monotonic() - revoked_at < 1.0


def test_a_key_revoked_by_another_node_stops_working_here_within_a_second(
    client: TestClient, admin: dict, site_id: str
) -> None:
    key, key_id = _key(client, admin, "viewer", site_id, "elsewhere")
    # cached on this node as good
    assert client.get(f"/v1/sites/{site_id}", headers=_bearer(key)).status_code == 200
    with client.websocket_connect(f"/v1/ws/positions?site_id={site_id}&key={key}") as stream:
        # another API node revokes it: only the shared database knows
        with session_scope(client.app.state.locus.sessions) as db:
            revoke_key(db=db, key_id=key_id)
        code, reason, took = _closed_within(stream, 1.0)
    assert code == 1008 and reason == "this API key was revoked" and took < 1.0
    r = client.get(f"/v1/sites/{site_id}", headers=_bearer(key))
    assert r.status_code == 401 and "revoked" in r.json()["error"]["message"]


def test_the_last_working_admin_key_cannot_be_revoked(new_database: Any, tmp_path: Path) -> None:
    settings = Settings(database_url=migrated(new_database()), home=tmp_path, workers=0)
    admin = _bearer(ADMIN_KEY)
    with TestClient(create_app(settings)) as client:
        (bootstrap,) = client.get("/v1/keys", headers=admin).json()["items"]
        r = client.delete(f"/v1/keys/{bootstrap['id']}", headers=admin)
        assert r.status_code == 409 and "last working admin key" in r.json()["error"]["message"]
        second = client.post("/v1/keys", json={"role": "admin"}, headers=admin).json()["key"]
        assert client.delete(f"/v1/keys/{bootstrap['id']}", headers=_bearer(second)).status_code
        assert client.get("/v1/keys", headers=admin).status_code == 401


@pytest.mark.parametrize(
    ("authorization", "says"),
    [
        (None, "missing API key: send 'Authorization: Bearer <key>'"),
        ("Basic dXNlcjpwYXNz", "uses the 'Basic' scheme, not Bearer"),
        ("Token abc", "uses the 'Token' scheme, not Bearer"),
        (ADMIN_KEY, "names no scheme"),
        ("Bearer", "no key after 'Bearer'"),
        ("Bearer lk_nobody_has_this_key", "unknown API key"),
    ],
)
def test_auth_errors_say_what_is_wrong(
    client: TestClient, authorization: str | None, says: str
) -> None:
    headers = {} if authorization is None else {"Authorization": authorization}
    r = client.get("/v1/sites", headers=headers)
    assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
    assert says in r.json()["error"]["message"]
    with pytest.raises(WebSocketDisconnect) as closed:
        with client.websocket_connect("/v1/ws/positions", headers=headers) as ws:
            ws.receive_json()
    assert closed.value.code == 1008 and says[:20] in closed.value.reason


def test_a_revoked_admin_key_given_by_environment_stops_the_start(
    new_database: Any, tmp_path: Path
) -> None:
    url = migrated(new_database())
    settings = Settings(database_url=url, home=tmp_path, workers=0, admin_key=ADMIN_KEY)
    with TestClient(create_app(settings)) as client:
        admin = _bearer(ADMIN_KEY)
        second = client.post("/v1/keys", json={"role": "admin"}, headers=admin).json()["key"]
        bootstrap = client.get("/v1/keys", headers=admin).json()["items"][0]
        assert client.delete(f"/v1/keys/{bootstrap['id']}", headers=_bearer(second)).is_success
    engine = make_engine(url)
    with pytest.raises(ValueError, match="LOCUS_ADMIN_KEY names a revoked key"):
        bootstrap_admin(sessions=make_sessionmaker(engine), settings=settings)
    engine.dispose()


def test_requests_that_find_a_key_expired_together_read_it_from_the_database_once(
    new_database: Any,
) -> None:
    engine = make_engine(migrated(new_database()))
    statements: list[str] = []
    event.listen(engine, "before_cursor_execute", lambda *a: statements.append(a[2]))
    cache = KeyCache(make_sessionmaker(engine), ttl_s=30.0, max_entries=100)

    async def many_at_once() -> list[object]:
        return await asyncio.gather(*(cache.lookup(ADMIN_KEY) for _ in range(50)))

    answers = asyncio.run(many_at_once())
    again = asyncio.run(many_at_once())
    engine.dispose()

    assert all(isinstance(a, Principal) and a.role == "admin" for a in answers + again)
    # one key lookup for the hundred requests: the fifty waiting ones shared it
    assert len([s for s in statements if "api_keys" in s]) == 1
