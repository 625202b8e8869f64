"""A Hypothesis state machine that drives a real server through the API in deep sequences.

Schemathesis sends one request at a time, so its requests rarely reach the
states behind several others: a site with a floor, a device key of it, a
device with positions. This machine builds those states and acts in them in
any order: sites and floors created, replaced and deleted, keys created and
revoked, batches ingested (sound, partly impossible, malformed) with every kind
of key, histories read. After every step it checks what the contract promises
(statuses by role and state, positions of the right device in time order) and
that no answer is a server error.
"""

from __future__ import annotations

import copy
import uuid
from typing import Any, NamedTuple

import httpx
from hypothesis import strategies as st
from hypothesis.stateful import (
    Bundle,
    RuleBasedStateMachine,
    consumes,
    invariant,
    precondition,
    rule,
)

from tests.conftest import ADMIN_KEY, floor_doc

T0 = 1_700_000_000_000
APS = ("aa:00:00:00:00:01", "aa:00:00:00:00:02", "aa:00:00:00:00:03")

ids = st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.:-]{0,20}\Z")
bad_ids = st.sampled_from(["", "-lead", "a b", "x" * 65, "a/b", "é", "a%2Fb"])
rssi = st.one_of(
    st.floats(min_value=-100, max_value=-30, allow_nan=False).map(lambda v: round(v, 1)),
    st.sampled_from([5.0, 0.5, -151.0, "NaN", None, "loud"]),
)


@st.composite
def wifi_scans(draw: st.DrawFn, start: int) -> list[dict[str, Any]]:
    """Return one to three scans of the test floor's access points from ``start`` (ms)."""
    scans = draw(st.integers(min_value=1, max_value=3))
    return [
        {"t": start + 1000 * k + 20 * i, "id": ap, "rssi": draw(rssi)}
        for k in range(scans)
        for i, ap in enumerate(APS)
        if draw(st.booleans()) or i == 0
    ]


def _mutated_floor(kind: str) -> dict[str, Any]:
    """Return the test floor spoiled in one way a map editor gets wrong."""
    doc = copy.deepcopy(floor_doc(pathloss=True))
    features = doc["features"]
    if kind == "no_outline":
        doc["features"] = [f for f in features if f["properties"]["kind"] != "outline"]
    elif kind == "unknown_kind":
        features[1]["properties"]["kind"] = "door"
    elif kind == "open_ring":
        features[0]["geometry"]["coordinates"] = [[[0, 0], [20, 0], [20, 10]]]
    elif kind == "level_text":
        doc["properties"]["level"] = "ground"
    elif kind == "transmitter_no_id":
        del features[3]["properties"]["id"]
    return doc


class Key(NamedTuple):
    """A key the machine created: its secret (empty when refused), role, site and label."""

    secret: str
    role: str
    site: str
    label: str


devices = st.sampled_from(["phone-1", "phone-2", "tag@x"])
MALFORMED = (
    b"{",
    b"[]",
    b'{"device_id": "d", "site_id": "s"}',
    b'{"device_id": "d", "site_id": "s", "wifi": "x"}',
    b'{"device_id": "", "site_id": "s", "ble": [{"t": 1700000000000, "id": "b", "rssi": -50}]}',
    b'{"device_id": "d", "site_id": "s", "imu": [{"t": "soon"}]}',
)
FLOOR_FAULTS = ("no_outline", "unknown_kind", "open_ring", "level_text", "transmitter_no_id")


class ApiMachine(RuleBasedStateMachine):
    """Sites, floors, keys and devices of one live server, driven through its HTTP API.

    ``base_url`` is set on the class by the test; ``requests`` and ``server_errors``
    are totals over every run of the machine.
    """

    base_url = ""
    requests = 0
    server_errors: list[str] = []

    sites = Bundle("sites")
    keys = Bundle("keys")

    def __init__(self) -> None:
        super().__init__()
        self.http = httpx.Client(base_url=self.base_url, timeout=60)
        self.run = uuid.uuid4().hex[:6]
        self.with_floor: set[str] = set()
        self.deleted: set[str] = set()
        self.revoked: set[str] = set()
        self.clock: dict[tuple[str, str], int] = {}
        self.positioned: dict[tuple[str, str], int] = {}

    def teardown(self) -> None:
        """Close the client."""
        self.http.close()

    # -- plumbing --------------------------------------------------------------------------

    def call(
        self, method: str, path: str, key: str = ADMIN_KEY, *, raw: bytes | None = None, **kw: Any
    ) -> httpx.Response:
        """Send a request (``raw``: a body sent as JSON, as is); note it, and fail on a server
        error, keeping what caused it."""
        headers = {"Authorization": f"Bearer {key}"}
        if raw is not None:
            kw |= {"content": raw}
            headers["content-type"] = "application/json"
        r = self.http.request(method, path, headers=headers, **kw)
        type(self).requests += 1
        if r.status_code >= 500:
            type(self).server_errors.append(f"{method} {path} -> {r.status_code} {r.text[:300]}")
        assert r.status_code < 500, r.text
        return r

    def live(self, site: str) -> bool:
        return site not in self.deleted

    # -- sites and floors ------------------------------------------------------------------

    @rule(target=sites, name=ids)
    def create_site(self, name: str) -> str:
        site = f"{self.run}-{name}"[:64]
        r = self.call("PUT", f"/v1/sites/{site}", json={"name": name})
        assert r.status_code in (200, 201), r.text
        self.deleted.discard(site)
        return site

    @rule(site=bad_ids)
    def create_site_with_a_bad_id(self, site: str) -> None:
        r = self.call("PUT", f"/v1/sites/{site}", json={"name": "x"})
        assert r.status_code in (404, 405, 422), r.text

    @rule(site=sites, floor=st.sampled_from(["G", "F1"]))
    def put_floor(self, site: str, floor: str) -> None:
        r = self.call("PUT", f"/v1/sites/{site}/floors/{floor}", json=floor_doc(pathloss=True))
        if not self.live(site):
            assert r.status_code == 404, r.text
            return
        assert r.status_code in (200, 201), r.text
        assert r.json()["counts"]["transmitter"] == len(APS)
        self.with_floor.add(site)

    @rule(site=sites, fault=st.sampled_from(FLOOR_FAULTS))
    def put_a_broken_floor(self, site: str, fault: str) -> None:
        r = self.call("PUT", f"/v1/sites/{site}/floors/B", json=_mutated_floor(fault))
        assert r.status_code in ((422,) if self.live(site) else (404, 422)), r.text

    @rule(site=consumes(sites))
    def delete_site(self, site: str) -> None:
        r = self.call("DELETE", f"/v1/sites/{site}")
        assert r.status_code in ((204,) if self.live(site) else (404,)), r.text
        self.deleted.add(site)
        self.with_floor.discard(site)
        assert self.call("GET", f"/v1/sites/{site}").status_code == 404

    # -- keys ------------------------------------------------------------------------------

    @rule(target=keys, site=sites, role=st.sampled_from(["device", "viewer"]))
    def create_key(self, site: str, role: str) -> Key:
        label = uuid.uuid4().hex
        r = self.call("POST", "/v1/keys", json={"role": role, "site_id": site, "label": label})
        if not self.live(site):
            assert r.status_code == 404, r.text
            return Key("", role, site, label)
        assert r.status_code == 201, r.text
        return Key(r.json()["key"], role, site, label)

    @rule(key=keys)
    def revoke_key(self, key: Key) -> None:
        if not key.secret or key.secret in self.revoked:
            return
        listed = self.call("GET", "/v1/keys", params={"limit": 500, "offset": 0})
        assert listed.status_code == 200, listed.text
        found = [k["id"] for k in listed.json()["items"] if k["label"] == key.label]
        if not found:
            return  # beyond the first page
        assert self.call("DELETE", f"/v1/keys/{found[0]}").status_code == 204
        self.revoked.add(key.secret)
        r = self.call("GET", "/v1/keys/self", key=key.secret)
        assert r.status_code == 401 and "revoked" in r.json()["error"]["message"], r.text

    # -- ingest and reads ------------------------------------------------------------------

    @precondition(lambda self: bool(self.with_floor))
    @rule(data=st.data(), key=keys, device=devices, wait=st.booleans())
    def ingest(self, data: st.DataObject, key: Key, device: str, wait: bool) -> None:
        if not key.secret:
            return
        start = self.clock.get((key.site, device), T0)
        wifi = data.draw(wifi_scans(start))
        body = {"device_id": device, "site_id": key.site, "wifi": wifi}
        r = self.call("POST", "/v1/ingest", key=key.secret, params={"wait": wait}, json=body)
        if key.secret in self.revoked:
            assert r.status_code == 401, r.text
            return
        if key.role == "viewer":
            assert r.status_code == 403, r.text
            return
        values = [w["rssi"] for w in wifi]
        sound = [v for v in values if isinstance(v, float) and -150 <= v <= 0]
        # a null or a word where a number belongs breaks the body's structure; impossible
        # values are dropped sample by sample, and a batch left with none is refused; the
        # body is judged before its site is looked up
        if None in values or "loud" in values or not sound:
            assert r.status_code == 422, r.text
            return
        if not self.live(key.site):
            assert r.status_code == 404, r.text
            return
        assert r.status_code == (200 if wait else 202), r.text
        self.clock[(key.site, device)] = max(w["t"] for w in wifi) + 1000
        for p in r.json().get("positions", []):
            assert (p["site_id"], p["device_id"]) == (key.site, device)
            newest = max(self.positioned.get((key.site, device), 0), p["t"])
            self.positioned[(key.site, device)] = newest

    @rule(key=keys, body=st.sampled_from(MALFORMED))
    def ingest_malformed(self, key: Key, body: bytes) -> None:
        r = self.call("POST", "/v1/ingest", key=key.secret or ADMIN_KEY, raw=body)
        # not JSON at all: 400; JSON that is not a batch: 422
        assert r.status_code in (400, 401, 403, 422), r.text

    @rule(site=sites, device=devices)
    def read_history(self, site: str, device: str) -> None:
        r = self.call("GET", f"/v1/sites/{site}/devices/{device}/positions", params={"limit": 1000})
        if not self.live(site) or (site, device) not in self.positioned:
            # a device is known once a batch of it was processed
            assert r.status_code in (200, 404), r.text
            return
        assert r.status_code == 200, r.text
        ts = [p["t"] for p in r.json()["items"]]
        assert ts == sorted(ts)
        assert max(ts) >= self.positioned[(site, device)]

    @rule(key=keys, site=sites)
    def read_as_a_key(self, key: Key, site: str) -> None:
        if not key.secret:
            return
        r = self.call("GET", f"/v1/sites/{site}/devices", key=key.secret)
        if key.secret in self.revoked:
            assert r.status_code == 401, r.text
        elif key.role == "device" or site != key.site:
            assert r.status_code == 403, r.text
        elif not self.live(site):
            assert r.status_code in (403, 404), r.text
        else:
            assert r.status_code == 200, r.text

    @invariant()
    def no_server_error(self) -> None:
        assert not type(self).server_errors, type(self).server_errors
