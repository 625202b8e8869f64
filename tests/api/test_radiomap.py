"""Radio-map builds through the API: real site1 walks uploaded as surveys, built, stored,
rebuilt to the same result, followed as an asynchronous job, and used by the engine (the
particle filter, and the HMM when the site asks for it). Bad requests change nothing."""

from __future__ import annotations

import time
import uuid
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from app.core.config import Settings
from app.datasets import data_dir
from app.datasets.ilc import Walk, fresh_wifi, imu_samples, read_floor, read_walk, site_walks
from app.engine.hmm.floor_validate import FLOOR_CLASSIFIER_WEIGHT_CANDIDATES
from app.engine.hmm.params import HmmParams
from app.engine.pdr import detect_steps
from app.engine.samples import Estimate
from app.engine.scan_knn import LEVEL_POWERS
from app.engine.scan_knn_cv import FLOOR_CANDIDATES_DBM
from app.engine.smoothing import SmootherParams
from app.engine.trackfit.search import TrackSearchParams
from app.engine.tuning import (
    FLOOR_WEIGHT_CANDIDATES,
    SMOOTHER_FIX_SCALE_CANDIDATES,
    WALK_NOISE_CANDIDATES,
)
from app.engine.wifi_age import AGE_CANDIDATES_MS, DEFAULT_MAX_AGE_MS
from app.evaluation.ilc.ablation import (
    FIXED_LAG,
    FULL,
    LIVE,
    STAGES,
    StageScores,
    load_engines,
    replay_stages,
)
from app.evaluation.ilc.score import estimates_from_positions
from app.evaluation.metrics import truth_at
from app.evaluation.trackfit_eval import as_links, raw_track, server_fitter, simplify
from app.importers.ilc import survey_body, walk_samples
from app.radiomaps.models import CalibratedTransmitter, RadioMapBuild, RadioMapFloor, RadioMapJob
from app.replay import batches_by_time
from app.sites.assembly import site_tuning
from app.sites.models import Site
from app.tracks.schemas import TrackCreate
from app.tracks.service import create_track
from tests.conftest import ADMIN_KEY, make_key

SITE1 = data_dir() / "ilc" / "site1"
FLOOR = "F1"
N_SURVEYS = 4
needs_site1 = pytest.mark.skipif(not SITE1.is_dir(), reason="ILC site1 recordings not present")


@pytest.fixture(scope="module")
def walks() -> list[Path]:
    """The first walks of site1's F1 (by file name): 4 to survey, the 5th to replay."""
    return [p for f, p in site_walks(SITE1) if f == FLOOR][: N_SURVEYS + 1]


@pytest.fixture(scope="module")
def built_site(client: TestClient, walks: list[Path]) -> dict[str, Any]:
    """A site with site1's F1 and 4 of its walks as surveys, built once; its summary."""
    admin = {"Authorization": f"Bearer {ADMIN_KEY}"}
    sid = f"rm-{uuid.uuid4().hex[:8]}"
    assert client.put(f"/v1/sites/{sid}", json={"name": sid}, headers=admin).status_code == 201
    floor = read_floor(SITE1 / FLOOR)
    assert client.put(
        f"/v1/sites/{sid}/floors/{FLOOR}", json=floor.geojson, headers=admin
    ).is_success
    for path in walks[:N_SURVEYS]:
        body = survey_body(read_walk(path, FLOOR), device_id="surveyor")
        r = client.post(f"/v1/sites/{sid}/surveys", json=body, headers=admin)
        assert r.status_code == 201, r.text
    r = client.post(f"/v1/sites/{sid}/radiomap/build", headers=admin)
    assert r.status_code == 200, r.text
    return {"site_id": sid, "summary": r.json()}


@needs_site1
def test_the_floor_weight_is_the_one_that_follows_walks_joined_across_floors_best(
    client: TestClient,
) -> None:
    admin = {"Authorization": f"Bearer {ADMIN_KEY}"}
    sid = f"rm2-{uuid.uuid4().hex[:8]}"
    assert client.put(f"/v1/sites/{sid}", json={"name": sid}, headers=admin).status_code == 201
    floors = ("F1", "F2")
    for name in floors:
        geojson = read_floor(SITE1 / name).geojson
        assert client.put(f"/v1/sites/{sid}/floors/{name}", json=geojson, headers=admin).is_success
        for path in [p for f, p in site_walks(SITE1) if f == name][:3]:
            body = survey_body(read_walk(path, name), device_id="surveyor")
            assert client.post(f"/v1/sites/{sid}/surveys", json=body, headers=admin).is_success
    r = client.post(f"/v1/sites/{sid}/radiomap/build", headers=admin)
    assert r.status_code == 200, r.text
    tuning, scores = r.json()["tuning"], r.json()["tuning_scores"]
    # every walk with WiFi starts one pair, joined to a walk held out with it on the other
    # floor (walks of one fold only)
    assert 0 < scores["floor_pairs"] <= 6
    by_floor = {float(w): v for w, v in scores["wrong_floor_share_by_floor_weight"].items()}
    by_classifier = {
        float(c): v for c, v in scores["wrong_floor_share_by_floor_classifier_weight"].items()
    }
    assert set(FLOOR_WEIGHT_CANDIDATES) <= set(by_floor) <= {0.0, *FLOOR_WEIGHT_CANDIDATES}
    assert set(FLOOR_CLASSIFIER_WEIGHT_CANDIDATES) <= set(by_classifier)
    assert set(by_classifier) <= {0.0, *FLOOR_CLASSIFIER_WEIGHT_CANDIDATES}
    assert all(0.0 <= v <= 1.0 for v in (*by_floor.values(), *by_classifier.values()))
    # the chosen pair of weights put the fewest scans on a wrong floor along either axis
    assert by_floor[tuning["floor_weight"]] == min(by_floor.values())
    assert by_classifier[tuning["floor_classifier_weight"]] == min(by_classifier.values())


def _stored(client: TestClient, site_id: str) -> dict[str, Any]:
    """Return every stored row of the site's build, as plain values."""
    with client.app.state.locus.sessions() as db:
        maps = db.scalars(select(RadioMapFloor).where(RadioMapFloor.site_id == site_id)).all()
        fits = db.scalars(
            select(CalibratedTransmitter)
            .where(CalibratedTransmitter.site_id == site_id)
            .order_by(CalibratedTransmitter.transmitter_id)
        ).all()
        build = db.get(RadioMapBuild, site_id)
        return {
            "maps": [(m.floor_id, m.n_points, m.transmitters, m.data) for m in maps],
            "fits": [
                {c.name: getattr(f, c.name) for c in CalibratedTransmitter.__table__.columns}
                for f in fits
            ],
            "summary": None if build is None else build.summary,
        }


def _stable(summary: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in summary.items() if k not in ("elapsed_ms", "map_version")}


@needs_site1
def test_build_summary_from_site1_walks(client: TestClient, built_site: dict[str, Any]) -> None:
    s = built_site["summary"]
    assert s["surveys"] == N_SURVEYS and s["scans"] > 20 and s["readings"] > s["scans"]
    [floor] = s["floors"]
    assert floor["floor_id"] == FLOOR and floor["surveys"] == N_SURVEYS
    assert 0 < floor["reference_points"] <= floor["walkable_cells"]
    assert floor["coverage"] == pytest.approx(
        floor["reference_points"] / floor["walkable_cells"], abs=1e-4
    )
    cal = s["calibration"]
    assert 0 < cal["plausible"] <= cal["calibrated"] == len(cal["transmitters"])
    # site1's map has no transmitters: every position is fitted
    assert cal["positions_fitted"] == cal["calibrated"]
    for tx in cal["transmitters"]:
        assert tx["floor_id"] == FLOOR and tx["n_readings"] >= 10 and tx["sigma"] >= 2.0
    acc = s["accuracy"]
    assert acc["method"] == "wknn" and acc["folds"] == N_SURVEYS and acc["scans"] == s["scans"]
    assert 0 < acc["p50_error_m"] <= acc["p90_error_m"] and acc["floor_error_rate"] == 0.0
    stored = _stored(client, built_site["site_id"])
    assert len(stored["maps"]) == 1 and stored["maps"][0][1] == floor["reference_points"]
    assert len(stored["fits"]) == cal["calibrated"]
    assert stored["summary"] == _stable(s)
    admin = {"Authorization": f"Bearer {ADMIN_KEY}"}
    got = client.get(f"/v1/sites/{built_site['site_id']}/radiomap", headers=admin)
    assert got.status_code == 200 and _stable(got.json()) == _stable(s)


@needs_site1
def test_async_rebuild_reports_progress_and_stores_the_same_result(
    client: TestClient, built_site: dict[str, Any]
) -> None:
    sid, admin = built_site["site_id"], {"Authorization": f"Bearer {ADMIN_KEY}"}
    before = _stored(client, sid)
    r = client.post(f"/v1/sites/{sid}/radiomap/build?async=true", headers=admin)
    assert r.status_code == 202, r.text
    job_id = r.json()["job_id"]
    seen = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        job = client.get(f"/v1/sites/{sid}/radiomap/build/{job_id}", headers=admin).json()
        seen.append((job["status"], job["progress"]))
        if job["status"] in ("done", "failed"):
            break
        time.sleep(0.2)
    assert job["status"] == "done", job
    assert job["progress"] == 1.0 and _stable(job["summary"]) == _stable(built_site["summary"])
    assert all(0.0 <= p <= 1.0 for _, p in seen)
    # idempotent: the second build stored exactly what the first did, and no more rows
    assert _stored(client, sid) == before
    missing = client.get(f"/v1/sites/{sid}/radiomap/build/nope", headers=admin)
    assert missing.status_code == 404 and missing.json()["error"]["code"] == "not_found"


def _replay(
    client: TestClient, site_id: str, device: str, path: Path, shift_ms: int = 0
) -> list[dict[str, Any]]:
    """Post a walk's fresh WiFi (its times moved by ``shift_ms``) and return the positions."""
    wifi = [
        s | {"t": s["t"] + shift_ms, "last_seen": s["last_seen"] + shift_ms}
        for s in walk_samples(read_walk(path, FLOOR))["wifi"]
        if s["t"] - s["last_seen"] <= 2000
    ]
    body = {"device_id": device, "site_id": site_id, "wifi": wifi}
    r = client.post("/v1/ingest?wait=true", json=body, headers=make_admin())
    assert r.status_code == 200, r.text
    return r.json()["positions"]


def make_admin() -> dict[str, str]:
    """Headers of the bootstrap admin key."""
    return {"Authorization": f"Bearer {ADMIN_KEY}"}


@needs_site1
def test_devices_get_positions_from_the_build(
    client: TestClient, built_site: dict[str, Any], walks: list[Path]
) -> None:
    sid, admin = built_site["site_id"], make_admin()
    # a site with a radio map positions WiFi devices with the HMM by default (it measures
    # better on site1); the particle filter gets the calibrated transmitters when chosen
    positions = _replay(client, sid, f"{sid}-hmm", walks[N_SURVEYS])
    assert positions and {p["method"] for p in positions} == {"hmm"}
    # each filter's radius includes the build's accuracy floor
    # (positions are rounded to the millimetre)
    held_out = built_site["summary"]["tuning"]["accuracy_floor_m"] - 1e-3
    assert all(p["floor_id"] == FLOOR and p["accuracy"] >= held_out for p in positions)
    r = client.put(f"/v1/sites/{sid}", json={"name": sid, "engine": "pf"}, headers=admin)
    assert r.status_code == 200 and r.json()["engine"] == "pf"
    assert r.json()["config"] == {"engine": "pf"}
    positions = _replay(client, sid, f"{sid}-pf", walks[N_SURVEYS])
    assert positions and {p["method"] for p in positions} == {"pf"}
    assert {p["floor_id"] for p in positions} == {FLOOR}
    assert all(p["accuracy"] >= held_out for p in positions)
    # the device that started on the HMM moves to the particle filter with the site
    positions = _replay(client, sid, f"{sid}-hmm", walks[N_SURVEYS - 1], shift_ms=86_400_000)
    assert positions and {p["method"] for p in positions} == {"pf"}
    r = client.put(f"/v1/sites/{sid}", json={"name": sid, "engine": "hmm"}, headers=admin)
    assert r.json()["engine"] == "hmm"


def _counts(client: TestClient, site_id: str) -> tuple[int, int, int, int, int]:
    with client.app.state.locus.sessions() as db:
        site = db.get(Site, site_id)
        return (
            site.map_version if site else -1,
            db.scalar(select(func.count()).where(RadioMapJob.site_id == site_id)) or 0,
            db.scalar(select(func.count()).where(RadioMapBuild.site_id == site_id)) or 0,
            db.scalar(select(func.count()).where(RadioMapFloor.site_id == site_id)) or 0,
            db.scalar(select(func.count()).where(CalibratedTransmitter.site_id == site_id)) or 0,
        )


def test_bad_build_requests_get_4xx_and_change_nothing(
    client: TestClient, admin: dict, site_id: str
) -> None:
    before = _counts(client, site_id)
    for query in ("", "?async=true"):
        r = client.post(f"/v1/sites/{site_id}/radiomap/build{query}", headers=admin)
        assert r.status_code == 409, r.text
        assert r.json()["error"]["code"] == "no_surveys"
        assert "no surveys" in r.json()["error"]["message"]
    r = client.post("/v1/sites/no-such-site/radiomap/build", headers=admin)
    assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"
    viewer = make_key(client, admin, "viewer", site_id)
    device = make_key(client, admin, "device", site_id)
    for key in (viewer, device):
        assert client.post(f"/v1/sites/{site_id}/radiomap/build", headers=key).status_code == 403
    assert client.post(f"/v1/sites/{site_id}/radiomap/build").status_code == 401
    assert client.get(f"/v1/sites/{site_id}/radiomap", headers=admin).status_code == 404
    r = client.get(f"/v1/sites/{site_id}/radiomap/build/{uuid.uuid4().hex}", headers=admin)
    assert r.status_code == 404
    assert _counts(client, site_id) == before


def test_engine_choice_is_stored_and_validated(
    client: TestClient, admin: dict, site_id: str
) -> None:
    r = client.get(f"/v1/sites/{site_id}", headers=admin)
    assert r.json()["engine"] == "hmm"
    version = r.json()["map_version"]
    for body in (
        {"name": "x", "engine": "kalman"},
        {"name": "x", "engine": "hmm", "config": {"engine": "pf"}},
    ):
        r = client.put(f"/v1/sites/{site_id}", json=body, headers=admin)
        assert r.status_code == 422, r.text
    r = client.put(f"/v1/sites/{site_id}", json={"name": "x", "engine": "pf"}, headers=admin)
    assert r.json()["engine"] == "pf" and r.json()["map_version"] == version + 1
    # leaving the engine out keeps it
    r = client.put(f"/v1/sites/{site_id}", json={"name": "y"}, headers=admin)
    assert r.json()["engine"] == "pf" and r.json()["map_version"] == version + 1


def _replay_walk(
    client: TestClient, site_id: str, device: str, path: Path, wifi_times: str
) -> list[dict[str, Any]]:
    """Post a whole walk (WiFi timed as ``wifi_times`` says, BLE, IMU) in one-second batches,
    each sample in the batch of the time the phone reported it; return the positions."""
    walk = read_walk(path, FLOOR)
    samples = walk_samples(walk, wifi_times=wifi_times)
    out: list[dict[str, Any]] = []
    chunks = batches_by_time(samples, batch_ms=1000, sent_at={"wifi": walk.wifi.t.tolist()})
    for chunk in chunks:
        body = {"device_id": device, "site_id": site_id, **chunk}
        r = client.post("/v1/ingest?wait=true", json=body, headers=make_admin())
        assert r.status_code == 200, r.text
        out += r.json()["positions"]
    return out


def _stages(settings: Settings, site_id: str, walk: Walk) -> StageScores:
    """Replay ``walk`` stage by stage on the site as a worker assembles it from storage."""
    engines = load_engines(settings.resolved_database_url, site_id, settings)
    return replay_stages(
        engines, site_id, [walk], [FLOOR], wifi_times="scan", settings=settings, keep=[walk.walk_id]
    )


def _by_t(estimates: list[Estimate]) -> dict[int, tuple[float, float]]:
    return {e.t: (e.x, e.y) for e in estimates}


def _same_where_both(a: dict[int, tuple[float, float]], b: dict[int, tuple[float, float]]) -> float:
    """Return the share of ``a``'s times that ``b`` has at the same place (within 2 mm)."""
    same = [t for t in a if t in b and np.allclose(a[t], b[t], atol=2e-3)]
    return len(same) / max(len(a), 1)


@needs_site1
def test_the_in_process_stages_are_the_server_on_its_own_build(
    client: TestClient, settings: Settings, built_site: dict[str, Any], walks: list[Path]
) -> None:
    sid = built_site["site_id"]
    walk = read_walk(walks[N_SURVEYS], FLOOR)
    # the worker loads the site first, so no batch of the walk waits on it
    _replay(client, sid, "warm-up", walks[N_SURVEYS])
    positions = estimates_from_positions(
        _replay_walk(client, sid, "through-http", walks[N_SURVEYS], "scan"), [FLOOR]
    )
    # the evaluation's stages assemble the stored site as a worker does
    stages = _stages(settings, sid, walk)
    assert all(len(stages.scores[name]) == 1 for name in STAGES)
    assert stages.updates > 0 and stages.cpu_s > 0.0
    tracks = stages.tracks[walk.walk_id]
    # the live track is the server's, position for position (a position the server
    # flushed between two batches on a busy machine is in no answer: at most a few)
    live = _by_t([e for e in positions if not e.smoothed])
    mine = _by_t(tracks[LIVE])
    assert len(mine) > 20 and _same_where_both(live, mine) == 1.0
    assert len(live) >= 0.9 * len(mine)
    # so are the refined positions, wherever both refined the same live one
    refined = _by_t([e for e in positions if e.smoothed])
    mine_refined = _by_t([e for e in tracks[FIXED_LAG] if e.smoothed])
    assert len(refined) > 20 and _same_where_both(refined, mine_refined) >= 0.9


@needs_site1
def test_the_history_refines_a_stored_track_by_the_full_backward_pass(
    client: TestClient, settings: Settings, built_site: dict[str, Any], walks: list[Path]
) -> None:
    sid = built_site["site_id"]
    walk = read_walk(walks[N_SURVEYS], FLOOR)
    _replay(client, sid, "warm-up", walks[N_SURVEYS])
    answered = _replay_walk(client, sid, "full-pass", walks[N_SURVEYS], "scan")
    # what only the history keeps is not sent to clients
    assert answered and not any("odometry_x" in p for p in answered)
    url = f"/v1/sites/{sid}/devices/full-pass/positions"
    r = client.get(url, params={"smoothed": "true", "limit": 10_000}, headers=make_admin())
    assert r.status_code == 200, r.text
    refined = estimates_from_positions(r.json()["items"], [FLOOR])
    assert all(e.smoothed for e in refined)
    # it is the engine's full pass over the whole live track, from the odometry stored with it
    stages = _stages(settings, sid, walk)
    tracks = stages.tracks[walk.walk_id]
    assert [e.t for e in refined] == [e.t for e in tracks[LIVE]]
    full = {e.t: (e.x, e.y) for e in tracks[FULL]}
    assert all(np.allclose((e.x, e.y), full[e.t], atol=0.02) for e in refined)
    # and it moved them
    live = _by_t(tracks[LIVE])
    assert any(not np.allclose((e.x, e.y), live[e.t], atol=0.01) for e in refined)
    bad = client.get(url, params={"smoothed": "maybe"}, headers=make_admin())
    assert bad.status_code == 422 and "smoothed" in bad.text


def _live(positions: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [p for p in positions if not p["smoothed"]]


@needs_site1
def test_a_walk_gives_the_same_track_whether_wifi_carries_scan_or_reading_times(
    client: TestClient, built_site: dict[str, Any], walks: list[Path]
) -> None:
    sid = built_site["site_id"]
    # a surveyed walk: the four surveys map where it goes (the fifth walk goes elsewhere)
    by_scan = _live(_replay_walk(client, sid, f"{sid}-scan", walks[0], "scan"))
    by_reading = _live(_replay_walk(client, sid, f"{sid}-reading", walks[0], "reading"))
    assert len(by_scan) > 10 and len(by_reading) > 10
    assert {p["floor_id"] for p in by_scan + by_reading} == {FLOOR}
    t = np.array([p["t"] for p in by_reading], dtype=float)
    xy = np.array([[p["x"], p["y"]] for p in by_reading])
    inside = [p for p in by_scan if t[0] <= p["t"] <= t[-1]]
    # the reading-timed track at the scan-timed track's times: the same walk within metres
    at = np.stack([np.interp([p["t"] for p in inside], t, xy[:, i]) for i in (0, 1)], axis=1)
    gap = np.hypot(*(at - np.array([[p["x"], p["y"]] for p in inside])).T)
    assert float(np.median(gap)) < 2.0 and float(gap.max()) < 5.0, np.percentile(gap, [50, 100])
    # and both as close to the surveyed truth (the walk is one of the surveys)
    walk = read_walk(walks[0], FLOOR)
    errors = []
    for track in (by_scan, by_reading):
        truth, on = truth_at(walk.waypoints, np.array([p["t"] for p in track]))
        est = np.array([[p["x"], p["y"]] for p in track])[on]
        errors.append(float(np.mean(np.hypot(*(est - truth[on]).T))))
    assert max(errors) < 3.0, errors


@needs_site1
def test_the_build_chooses_the_sites_constants_from_its_surveys(
    built_site: dict[str, Any],
) -> None:
    summary = built_site["summary"]
    tuning, scores = summary["tuning"], summary["tuning_scores"]
    # every survey carries its IMU: the step length and heading offset are fitted on them
    assert tuning["pdr_walks"] == N_SURVEYS
    assert 0.2 < tuning["weinberg_k"] < 0.7 and -180 <= tuning["heading_offset_deg"] < 180
    # the chosen k and weight are the best of the candidates, as the scores show
    by_k = {int(k): v for k, v in scores["wknn_mean_error_m_by_k"].items()}
    assert by_k[tuning["wknn_k"]] == min(by_k.values())
    # the emission weight comes from replaying held-out survey walks through the HMM: the
    # default unless another erred less by more than the walks' luck
    assert scores["hmm_walks"] > 0
    by_w = {float(w): v for w, v in scores["hmm_walk_error_m_by_weight"].items()}
    default = HmmParams().emission_weight
    assert by_w[tuning["emission_weight"]] <= by_w[default]
    # one floor: no walks to join across floors (a two-floor site's test below)
    assert scores["floor_pairs"] == 0 and not scores["wrong_floor_share_by_floor_weight"]
    # so do the k-NN fix's weight and the transition noise: at most one of the three
    # replayed constants leaves its default, and only for a candidate that erred less
    replayed = {
        "emission_weight": "hmm_walk_error_m_by_weight",
        "fix_nats": "hmm_walk_error_m_by_fix_weight",
        "walk_noise_m2_per_s": "hmm_walk_error_m_by_walk_noise",
    }
    defaults = HmmParams()
    moved = [name for name in replayed if tuning[name] != getattr(defaults, name)]
    assert len(moved) <= 1, moved
    for name, score_key in replayed.items():
        by_value = {float(v): e for v, e in scores[score_key].items()}
        assert by_value[tuning[name]] <= by_value[getattr(defaults, name)]
    assert set(map(float, scores["hmm_walk_error_m_by_walk_noise"])) == set(WALK_NOISE_CANDIDATES)
    assert scores["emission_log_score_by_weight"] and scores["floor_log_score_by_weight"]
    assert summary["accuracy"]["k"] == tuning["wknn_k"]
    # beside the WKNN's, the accuracy says what the tracker measured on those replays: the
    # chosen candidate's
    tracker = summary["accuracy"]["tracker"]
    assert tracker["walks"] == scores["hmm_walks"]
    name = moved[0] if moved else "emission_weight"
    chosen = {float(v): e for v, e in scores[replayed[name]].items()}
    assert tracker["mean_walk_error_m"] == chosen[tuning[name]]
    # the radius floor is calibrated on those replays: 0 or more, never the WKNN median's
    # stand-in when replays exist
    assert tuning["accuracy_floor_m"] >= 0.0
    # and on the same replays each smoother's fix scale: every candidate scored, the
    # chosen one no worse than the default's
    for stage, key in (("fixed_lag", "lag_fix_scale"), ("full_pass", "pass_fix_scale")):
        by_scale = {float(c): v for c, v in scores[f"{stage}_walk_error_m_by_fix_scale"].items()}
        assert set(by_scale) == set(SMOOTHER_FIX_SCALE_CANDIDATES)
        assert by_scale[tuning[key]] <= by_scale[SmootherParams().fix_scale]
    # how old a WiFi reading may be: every candidate age scored by the per-scan k-NN on
    # held-out walks, the chosen one no worse than the default's
    by_age = {int(a): v for a, v in scores["knn_walk_error_m_by_wifi_max_age_ms"].items()}
    assert set(by_age) == set(AGE_CANDIDATES_MS)
    assert by_age[tuning["wifi_max_age_ms"]] <= by_age[DEFAULT_MAX_AGE_MS]
    # the per-scan k-NN's signal floor, penalty, level weighting and weight power: each
    # scored the same way
    for key, score_key, default in (
        ("scan_knn_floor_dbm", "knn_walk_error_m_by_floor_dbm", -100.0),
        ("scan_knn_unshared_penalty", "knn_walk_error_m_by_unshared_penalty", 50.0),
        ("scan_knn_level_power", "knn_walk_error_m_by_level_power", 0),
        ("scan_knn_power", "knn_walk_error_m_by_weight_power", 4.0),
    ):
        by_value = {float(v): e for v, e in scores[score_key].items()}
        assert by_value[float(tuning[key])] <= by_value[default]
    assert set(map(int, scores["knn_walk_error_m_by_level_power"])) == set(LEVEL_POWERS)
    assert set(map(float, scores["knn_walk_error_m_by_floor_dbm"])) == set(FLOOR_CANDIDATES_DBM)


@needs_site1
def test_phones_get_each_position_again_refined_and_history_prefers_the_refined(
    client: TestClient, built_site: dict[str, Any], walks: list[Path]
) -> None:
    sid, device = built_site["site_id"], f"{built_site['site_id']}-smoothed"
    answers = _replay_walk(client, sid, device, walks[0], "scan")
    live = _live(answers)
    refined = [p for p in answers if p["smoothed"]]
    assert live and refined and {p["method"] for p in refined} == {"hmm"}
    # each refined position repeats a live one's time, a few seconds later in the stream
    assert {p["t"] for p in refined} <= {p["t"] for p in live}
    assert [p["t"] for p in answers[:5]] == sorted(p["t"] for p in answers[:5])
    r = client.get(
        f"/v1/devices/{device}/positions", params={"limit": 10_000}, headers=make_admin()
    )
    assert r.status_code == 200, r.text
    items = r.json()["items"]
    times = [p["t"] for p in items]
    # one position per time: the refined one up to the last refined time, live after it
    # (the device's silence after its last upload refined the rest too)
    assert times == sorted(set(times)) and set(times) == {p["t"] for p in live}
    last_refined = max(p["t"] for p in items if p["smoothed"])
    assert last_refined >= max(p["t"] for p in refined)
    assert all(p["smoothed"] == (p["t"] <= last_refined) for p in items)
    latest = client.get(f"/v1/devices/{device}/position", headers=make_admin()).json()
    assert latest["smoothed"] is False and latest["t"] == max(p["t"] for p in live)


def _track_with_scans(walk: Walk, site_id: str, every_ms: int) -> dict[str, Any]:
    """The walk's PDR track as merged links from its first waypoint, heading given, with one
    of its own WiFi scans on the segment ending nearest each ``every_ms``."""
    steps = detect_steps(imu_samples(walk))
    wp = walk.waypoints
    raw = raw_track(wp[[0, -1], 0], steps.t, steps.length, steps.heading, wp[0, 1:])
    vertex = simplify(raw.xy, 1.0)
    lengths, turns, direction = as_links(raw.xy[vertex])
    times = raw.t[vertex]
    segments: list[dict[str, Any]] = [
        {"t": int(t), "length": float(length), "turn": float(turn)}
        for t, length, turn in zip(times[1:], lengths, turns, strict=True)
    ]
    wifi = fresh_wifi(walk.wifi)
    scan_times = np.unique(wifi.t)
    for target in range(int(times[0]) + every_ms, int(times[-1]), every_ms):
        t_scan = scan_times[np.argmin(np.abs(scan_times - target))]
        row = wifi.t == t_scan
        i = int(np.argmin(np.abs(times[1:] - t_scan)))
        segments[i]["wifi"] = [
            {"id": str(b), "rssi": float(r)}
            for b, r in zip(wifi.bssid[row], wifi.rssi[row], strict=True)
        ]
    return {
        "device_id": "saver",
        "site_id": site_id,
        "floor_id": FLOOR,
        "start": {"x": float(wp[0, 1]), "y": float(wp[0, 2])},
        "t0": int(times[0]),
        "heading": float((90.0 - np.degrees(direction[0])) % 360.0),
        "segments": segments,
    }


@needs_site1
def test_a_tracks_wifi_scans_are_scored_against_the_sites_radio_map(
    client: TestClient, built_site: dict[str, Any], walks: list[Path], settings: Settings
) -> None:
    sid, admin = built_site["site_id"], make_admin()
    body = _track_with_scans(read_walk(walks[N_SURVEYS], FLOOR), sid, every_ms=20_000)
    scanned = sum("wifi" in s for s in body["segments"])
    assert scanned >= 2
    r = client.post("/v1/tracks", json=body, headers=admin)
    assert r.status_code == 202, r.text
    track_id = r.json()["track_id"]
    deadline = time.monotonic() + 60
    while (result := client.get(f"/v1/tracks/{track_id}", headers=admin).json())["status"] in (
        "queued",
        "running",
    ):
        assert time.monotonic() < deadline
        time.sleep(0.1)
    assert result["status"] == "done", result
    # every scan reached the fit as an anchor on the floor's radio map
    assert result["anchors"] == scanned
    # and its scans are matched with the per-scan k-NN's constants the site's build chose
    with client.app.state.locus.sessions() as db:
        _, job = create_track(db=db, body=TrackCreate.model_validate(body))
        db.rollback()
        assert job["radiomap"]["knn"] == asdict(site_tuning(db, sid).scan_knn())
        stored = built_site["summary"]["tuning"]
        assert job["radiomap"]["knn"]["floor_dbm"] == stored["scan_knn_floor_dbm"]
    # the track-fit evaluation's fitter is the server's: the same points for the same body
    fitter = server_fitter(settings.resolved_database_url, settings, TrackSearchParams())
    again = fitter(body)
    assert again["points"] == result["points"] and again["anchors"] == result["anchors"]
    assert len(result["points"]) == len(body["segments"]) + 1
