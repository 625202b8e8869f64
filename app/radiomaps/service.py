"""Building a site's radio maps and transmitter calibration from its surveys, and storing them.

A build has three phases so the heavy middle one needs no database session:
``load_inputs`` reads the site (floors, map transmitters) and its surveys;
``compute_build`` turns them into per-floor radio maps, transmitter fits and
a summary with a held-out accuracy estimate (pure numpy, deterministic);
``store_build`` replaces the site's stored result in one transaction and bumps
the site's map version, so the workers reload the site and use it at once.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
from sqlalchemy import delete, select
from sqlalchemy.orm import Session, sessionmaker

from app.core.db import session_scope
from app.core.errors import Conflict, NotFound
from app.engine.calibration import CalibrationParams, TransmitterFit, calibrate
from app.engine.crossval import CrossValidation, cross_validate
from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.floor_validate import (
    FLOOR_CLASSIFIER_WEIGHT_CANDIDATES,
    FloorWalk,
    WalkEvidence,
    pair_shares,
    walk_evidence,
)
from app.engine.hmm.params import HmmParams
from app.engine.hmm.validate import (
    HeldWalk,
    WalkResult,
    calibrate_radius,
    candidate_results,
    smoother_scores,
)
from app.engine.pdr import PdrParams
from app.engine.pdr_fit import WalkPdr, measure_walk
from app.engine.plan import FloorPlan
from app.engine.radiomap import (
    RadioMap,
    RadioMapParams,
    Survey,
    build_radio_map,
    locate_scans,
    walkable_cells,
)
from app.engine.samples import ImuSamples, RssiReadings
from app.engine.scan_knn import ScanKnnParams
from app.engine.scan_knn_cv import choose_neighbours, fix_spread, paired_scores, walk_errors
from app.engine.smoothing import SmootherParams
from app.engine.survey_guidance import GuidanceGrid
from app.engine.tuning import (
    EMISSION_WEIGHT_CANDIDATES,
    FIX_WEIGHT_CANDIDATES,
    FLOOR_WEIGHT_CANDIDATES,
    HMM_WEIGHT_CANDIDATES,
    SMOOTHER_FIX_SCALE_CANDIDATES,
    WALK_NOISE_CANDIDATES,
    WKNN_K_CANDIDATES,
    SiteTuning,
    one_move_choice,
    one_standard_error_choice,
    tune_site,
)
from app.engine.wifi_age import AGE_CANDIDATES_MS, DEFAULT_MAX_AGE_MS
from app.engine.wknn import WknnParams
from app.ingest.arrays import imu_arrays, reading_age, wifi_times
from app.radiomaps import guidance
from app.radiomaps.codec import encode_map
from app.radiomaps.models import CalibratedTransmitter, RadioMapBuild, RadioMapFloor, RadioMapJob
from app.sites.assembly import LoadedSite, assemble_site
from app.sites.models import Site
from app.sites.radio_ids import radio_id
from app.sites.service import bump_map_version
from app.surveys.models import SurveyRecord
from app.surveys.service import count_surveys, survey_identity, survey_samples

RADIO_MAP = RadioMapParams()
CALIBRATION = CalibrationParams()
WKNN = WknnParams()

Progress = Callable[[float], None]


@dataclass(frozen=True)
class SurveyInput:
    """One stored survey reduced to what a build reads."""

    identity: str
    """The survey's floor and a digest of its samples: what orders a build's walks, so
    that the same surveys uploaded in any order build the same map."""
    floor_id: str
    waypoints: np.ndarray
    t: np.ndarray
    ids: list[str]
    rssi: np.ndarray
    imu: ImuSamples
    ble: tuple[np.ndarray, list[str], np.ndarray]
    """The BLE readings (t, ids, RSSI): they calibrate beacons, and make no fingerprint."""
    age: np.ndarray
    """How long before its scan's time each WiFi reading was last heard (ms; 0 unless the
    reading carries ``last_seen``)."""

    def wifi(self, index: Mapping[str, int]) -> RssiReadings:
        """Return the WiFi readings with each transmitter as its number in ``index``."""
        tx = np.array([index[i] for i in self.ids], dtype=np.int32)
        return RssiReadings(self.t, tx, self.rssi)

    def heard_within(self, max_age_ms: int) -> SurveyInput:
        """Return the survey with only the WiFi readings last heard within ``max_age_ms``."""
        keep = self.age <= max_age_ms
        return replace(
            self,
            t=self.t[keep],
            ids=[i for i, k in zip(self.ids, keep.tolist(), strict=True) if k],
            rssi=self.rssi[keep],
            age=self.age[keep],
        )


@dataclass(frozen=True, eq=False)
class BuildInputs:
    """What a build reads from the database."""

    site: LoadedSite
    surveys: tuple[SurveyInput, ...]


@dataclass(frozen=True, eq=False)
class BuildResult:
    """What a build stores: maps by floor id, fits, the transmitter ids, the summary and
    the survey guidance by floor id."""

    maps: dict[str, RadioMap]
    fits: list[TransmitterFit]
    tx_ids: tuple[str, ...]
    floor_ids: tuple[str, ...]
    summary: dict[str, Any]
    guidance: dict[str, GuidanceGrid] = field(default_factory=dict)


def check_buildable(*, db: Session, site: Site) -> None:
    """Raise Conflict when the site has no surveys to build from."""
    if count_surveys(db=db, site_id=site.id) == 0:
        raise Conflict(
            f"site '{site.id}' has no surveys: upload survey walks "
            f"(POST /v1/sites/{site.id}/surveys) before building its radio map",
            code="no_surveys",
        )


def _survey_input(row: SurveyRecord) -> SurveyInput:
    samples = survey_samples(row)
    wp = np.array([[w["t"], w["x"], w["y"]] for w in samples["waypoints"]], dtype=float)
    t: list[int] = []
    ids: list[str] = []
    rssi: list[float] = []
    age: list[int] = []
    # WiFi only: a WiFi scan reports every access point heard at one time, the unit a
    # fingerprint is made of; BLE advertisements arrive one by one, each with its own time,
    # and taken as scans they would read as scans that missed every access point.
    wifi = samples.get("wifi", ())
    for s, at in zip(wifi, wifi_times(wifi), strict=True):
        t.append(at)
        ids.append(radio_id(s["id"]))
        rssi.append(float(s["rssi"]))
        age.append(reading_age(s))
    ble = samples.get("ble", ())
    return SurveyInput(
        identity=survey_identity(row),
        floor_id=row.floor_id,
        waypoints=wp.reshape(-1, 3),
        t=np.array(t, dtype=np.int64),
        ids=ids,
        rssi=np.array(rssi, dtype=float),
        imu=_sorted_imu(imu_arrays(samples.get("imu", ()))),
        ble=(
            np.array([s["t"] for s in ble], dtype=np.int64),
            [radio_id(s["id"]) for s in ble],
            np.array([s["rssi"] for s in ble], dtype=float),
        ),
        age=np.array(age, dtype=np.int64),
    )


def _sorted_imu(imu: ImuSamples) -> ImuSamples:
    order = np.argsort(imu.t, kind="stable")
    return ImuSamples(imu.t[order], imu.acc[order], imu.gyro[order], imu.mag[order], imu.rot[order])


def load_inputs(*, db: Session, site: Site, raster_cell: float) -> BuildInputs:
    """Read the site as its floor maps give it (no earlier build) and its surveys, by id."""
    check_buildable(db=db, site=site)
    loaded = assemble_site(db=db, site=site, raster_cell=raster_cell, with_radiomap=False)
    if not loaded.floor_ids:
        raise Conflict(f"site '{site.id}' has no floors", code="no_floors")
    rows = db.scalars(
        select(SurveyRecord).where(SurveyRecord.site_id == site.id).order_by(SurveyRecord.id)
    )
    surveys = sorted(
        (_survey_input(r) for r in rows if r.floor_id in loaded.floor_index),
        key=lambda s: s.identity,
    )
    return BuildInputs(site=loaded, surveys=tuple(surveys))


def _located_survey(inputs: BuildInputs) -> tuple[Survey, Survey, tuple[str, ...]]:
    """Return the WiFi scans of every survey located on its waypoints, its BLE windows
    located the same way, and the transmitter ids."""
    site = inputs.site
    map_ids = site.model.transmitters.ids
    heard = {i for s in inputs.surveys for i in (*s.ids, *s.ble[1])} - set(map_ids)
    tx_ids = tuple(map_ids) + tuple(sorted(heard))
    index = {tx: i for i, tx in enumerate(tx_ids)}
    wifi, ble = [], []
    window = CALIBRATION.ble_window_ms
    for walk, s in enumerate(inputs.surveys):
        floor = site.floor_index[s.floor_id]
        wifi.append(locate_scans(s.wifi(index), s.waypoints, floor=floor, walk=walk))
        t, ids, rssi = s.ble
        if t.size:
            # every advertisement of a window timed at the window's middle: one scan
            start = int(t.min())
            at = start + (t - start) // window * window + window // 2
            beacons = np.array([index[i] for i in ids], dtype=np.int32)
            ble.append(
                locate_scans(RssiReadings(at, beacons, rssi), s.waypoints, floor=floor, walk=walk)
            )
    return Survey.concat(wifi), Survey.concat(ble), tx_ids


def _wifi_age_scores(inputs: BuildInputs, folds: int) -> dict[float, list[float]]:
    """Return, per candidate oldest WiFi reading age (ms), each survey walk's held-out
    per-scan k-NN error, over the walks every candidate scored (``app.engine.wifi_age``)."""
    by_age: dict[float, dict[int, float]] = {}
    for age in AGE_CANDIDATES_MS:
        fresh = replace(inputs, surveys=tuple(s.heard_within(age) for s in inputs.surveys))
        survey, _, tx_ids = _located_survey(fresh)
        by_age[float(age)] = walk_errors(survey, len(tx_ids), folds)[0]
    return paired_scores(by_age) if all(by_age.values()) else {}


def _with_knn(tuning: SiteTuning, knn: ScanKnnParams, spread: float | None) -> SiteTuning:
    """Return ``tuning`` with the per-scan k-NN's constants and, where measured, the spread
    of the HMM's k-NN fix."""
    return replace(
        tuning,
        scan_knn_k=knn.k,
        scan_knn_power=knn.weight_power,
        scan_knn_level_power=knn.level_power,
        scan_knn_floor_dbm=knn.floor_dbm,
        scan_knn_unshared_penalty=knn.unshared_penalty,
        fix_sigma_m=tuning.fix_sigma_m if spread is None else round(spread, 3),
    )


def _r(value: float, digits: int = 3) -> float | None:
    return None if not np.isfinite(value) else round(float(value), digits)


def compute_build(
    inputs: BuildInputs,
    *,
    folds: int,
    tune: bool = True,
    hmm_walks: int = 20,
    progress: Progress | None = None,
) -> BuildResult:
    """Build every surveyed floor's radio map, calibrate every heard transmitter, estimate
    the maps' accuracy on held-out walks (``folds`` groups of whole walks held out in turn)
    and, with ``tune``, choose the site's constants on the same folds, replaying up to
    ``hmm_walks`` held-out walks per fold through the HMM (otherwise the engines'
    defaults are kept, with the held-out accuracy floor). Raises Conflict when no scan
    can be located."""
    report = progress or (lambda _: None)
    site = inputs.site
    if not inputs.surveys:
        raise Conflict(f"site '{site.site_id}' has no surveys on its current floors")
    age_scores = _wifi_age_scores(inputs, folds) if tune else {}
    max_age = (
        int(one_standard_error_choice(age_scores, DEFAULT_MAX_AGE_MS))
        if age_scores
        else DEFAULT_MAX_AGE_MS
    )
    inputs = replace(inputs, surveys=tuple(s.heard_within(max_age) for s in inputs.surveys))
    survey, beacons, tx_ids = _located_survey(inputs)
    if survey.reading_rssi.size == 0 and beacons.reading_rssi.size == 0:
        raise Conflict(
            "the surveys hold no WiFi scan and no BLE reading within their waypoints' time span",
            code="no_scans",
        )
    tx = site.model.transmitters
    known = {
        i: (int(tx.floor[i]), float(tx.xyz[i, 0]), float(tx.xyz[i, 1]), float(tx.xyz[i, 2]))
        for i in range(len(tx))
    }
    beacon_fits = calibrate(beacons, CALIBRATION, known=known) if beacons.n_scans else []
    if survey.reading_rssi.size == 0:
        # beacons only: calibrated, with no WiFi fingerprint to map or tune on
        summary = _summary(
            inputs, survey, beacons, [], beacon_fits, tx_ids, None, SiteTuning.defaults(), None
        )
        report(1.0)
        return BuildResult(
            maps={}, fits=beacon_fits, tx_ids=tx_ids, floor_ids=site.floor_ids, summary=summary
        )
    knn, knn_scores = (
        choose_neighbours(survey, len(tx_ids), folds) if tune else (ScanKnnParams(), {})
    )
    spread = fix_spread(survey, len(tx_ids), folds, knn) if tune else None
    report(0.1)
    plans = {i: f.plan for i, f in enumerate(site.model.floors)}
    maps: dict[str, RadioMap] = {}
    floors: list[dict[str, Any]] = []
    for f, floor_id in enumerate(site.floor_ids):
        on = survey.scan_floor == f
        if not on.any():
            continue
        m = build_radio_map(survey, f, RADIO_MAP, walkable=plans[f])
        _, mask = walkable_cells(plans[f], RADIO_MAP.cell_m)
        walkable = int(mask.sum())
        maps[floor_id] = m
        floors.append(
            {
                "floor_id": floor_id,
                "surveys": int(np.unique(survey.scan_walk[on]).size),
                "scans": int(on.sum()),
                "reference_points": m.n_points,
                "walkable_cells": walkable,
                "coverage": _r(m.n_points / walkable if walkable else 0.0, 4),
                "transmitters": int(m.tx.size),
            }
        )
    report(0.25)
    wifi_fits = calibrate(
        survey, CALIBRATION, known=known, progress=lambda x: report(0.25 + 0.4 * x)
    )
    fits = sorted(wifi_fits + beacon_fits, key=lambda f: f.tx)
    report(0.65)
    measured = _measured_walks(inputs)
    base = _with_knn(tune_site(measured, None), knn, spread)
    replays = HmmReplays(inputs, tx_ids, base, hmm_walks if tune else 0, plans)
    floor_replays = FloorReplays(inputs, tx_ids, base.hmm() if tune else None)

    def fold_hook(maps: tuple[RadioMap, ...], test: np.ndarray) -> None:
        if replays.walks:
            replays.on_fold(maps, test, survey.scan_walk)
        floor_replays.on_fold(maps, test, survey.scan_walk)

    validation = cross_validate(
        survey,
        plans,
        RADIO_MAP,
        WKNN,
        folds=folds,
        ks=WKNN_K_CANDIDATES,
        emission=HmmParams(references=knn),
        weights=EMISSION_WEIGHT_CANDIDATES,
        fold_hook=fold_hook if replays.walks or floor_replays.walks else None,
        progress=lambda x: report(0.65 + 0.3 * x),
    )
    chosen = replays.choose()
    floors_chosen = floor_replays.choose()
    tuned = tune_site(
        measured,
        validation,
        chosen[0] if chosen else None,
        floors_chosen[0] if floors_chosen else None,
    )
    if floors_chosen is not None:
        tuned = replace(tuned, floor_classifier_weight=floors_chosen[1])
    tuning = replace(_with_knn(tuned, knn, spread), wifi_max_age_ms=max_age)
    if chosen is not None:
        tuning = replace(tuning, fix_nats=chosen[1], walk_noise_m2_per_s=chosen[2])
    radius = replays.radius_calibration(_replayed_key(tuning))
    smoothers: dict[str, dict[float, list[float]]] = {}
    if radius is not None:
        tuning = replace(tuning, radius_scale=radius[0], accuracy_floor_m=radius[1])
        smoothers = replays.smoother_scores(_replayed_key(tuning), radius)
        default = SmootherParams().fix_scale
        tuning = replace(
            tuning,
            lag_fix_scale=one_standard_error_choice(smoothers["fixed_lag"], default),
            pass_fix_scale=one_standard_error_choice(smoothers["full_pass"], default),
        )
    if not tune:
        defaults = SiteTuning.defaults()
        floor = (
            float(np.median(validation.by_k[defaults.wknn_k].error_m))
            if validation is not None
            else defaults.accuracy_floor_m
        )
        tuning = replace(defaults, accuracy_floor_m=floor)
    report(0.95)
    accuracy: dict[str, Any] | None = None
    grids: dict[str, GuidanceGrid] = {}
    if validation is not None:
        held = validation.by_k[tuning.wknn_k]
        grids = guidance.compute(survey, held, plans, site.floor_ids)
        accuracy = {
            "method": "wknn",
            "k": tuning.wknn_k,
            "folds": held.folds,
            "scans": int(held.error_m.size),
            "mean_error_m": _r(float(np.mean(held.error_m))),
            "p50_error_m": _r(float(np.median(held.error_m))),
            "p90_error_m": _r(float(np.percentile(held.error_m, 90))),
            "floor_error_rate": _r(float(1.0 - np.mean(held.floor_ok)), 4),
        }
        replayed = replays.mean_error(_replayed_key(tuning))
        if replayed is not None:
            # what the server's tracker measured on walks the maps were built without
            accuracy["tracker"] = {
                "method": "hmm",
                "walks": replays.scored,
                "mean_walk_error_m": _r(replayed),
            }
    summary = _summary(
        inputs,
        survey,
        beacons,
        floors,
        fits,
        tx_ids,
        accuracy,
        tuning,
        _tuning_scores(
            validation,
            replays,
            floor_replays.floor_scores(tuning.floor_classifier_weight) if floors_chosen else {},
            floor_replays.classifier_scores(tuning.floor_weight) if floors_chosen else {},
            smoothers,
            age_scores,
            knn_scores,
        ),
    ) | {"guidance": guidance.summary(grids) if grids else None}
    report(1.0)
    return BuildResult(
        maps=maps,
        fits=fits,
        tx_ids=tx_ids,
        floor_ids=site.floor_ids,
        summary=summary,
        guidance=grids,
    )


def _summary(
    inputs: BuildInputs,
    survey: Survey,
    beacons: Survey,
    floors: list[dict[str, Any]],
    fits: list[TransmitterFit],
    tx_ids: tuple[str, ...],
    accuracy: dict[str, Any] | None,
    tuning: SiteTuning,
    scores: dict[str, Any] | None,
) -> dict[str, Any]:
    """Return a build's summary: what it read, calibrated, mapped, measured and chose."""
    site = inputs.site
    plausible = [f for f in fits if f.plausible]
    heard = np.concatenate([survey.reading_tx, beacons.reading_tx])
    return {
        "site_id": site.site_id,
        "surveys": len(inputs.surveys),
        "scans": survey.n_scans,
        "readings": int(survey.reading_rssi.size),
        "ble_windows": beacons.n_scans,
        "ble_readings": int(beacons.reading_rssi.size),
        "transmitters_heard": int(np.unique(heard).size),
        "floors": floors,
        "calibration": {
            "calibrated": len(fits),
            "plausible": len(plausible),
            "positions_fitted": sum(not f.position_known for f in fits),
            "median_A": _r(float(np.median([f.A for f in plausible])) if plausible else np.nan),
            "median_B": _r(float(np.median([f.B for f in plausible])) if plausible else np.nan),
            "median_sigma_db": _r(
                float(np.median([f.sigma for f in plausible])) if plausible else np.nan
            ),
            "transmitters": [_fit_row(f, tx_ids, site.floor_ids) for f in fits],
        },
        "accuracy": accuracy,
        "tuning": tuning.as_dict(),
        "tuning_scores": scores,
    }


HMM_REPLAYED = ("emission_weight", "fix_nats", "walk_noise_m2_per_s")
"""The HMM constants a build chooses by replaying held-out walks, in ``HmmKey`` order."""

HmmKey = tuple[float, float, float]
"""One replayed candidate: its emission weight, k-NN fix weight and transition noise."""


class HmmReplays:
    """Held-out survey walks replayed through the HMM on each fold's maps, per candidate.

    At most ``per_fold`` walks of each fold (those with inertial samples and
    two waypoints, evenly spread) are replayed, with the PDR constants and
    heading noise ``base`` learned from the surveys and no accuracy floor, so
    the replays also calibrate the radius. The candidates step away from the
    defaults one constant at a time (a fold's maps are too large to keep for
    a second round): every emission weight, every k-NN fix weight and every
    transition noise, each with the other two at their defaults. Where more
    than one constant would move, only the move whose replays erred least is
    taken, so the chosen candidate was always replayed.
    """

    def __init__(
        self,
        inputs: BuildInputs,
        tx_ids: tuple[str, ...],
        base: SiteTuning,
        per_fold: int,
        plans: Mapping[int, FloorPlan],
    ) -> None:
        index = {tx: i for i, tx in enumerate(tx_ids)}
        self.plans = plans
        self.walks: dict[int, HeldWalk] = {}
        if per_fold > 0:
            for w, s in enumerate(inputs.surveys):
                if len(s.imu) and s.waypoints.shape[0] >= 2 and s.t.size:
                    floor = inputs.site.floor_index[s.floor_id]
                    self.walks[w] = HeldWalk(s.wifi(index), s.imu, s.waypoints, floor)
        self.per_fold = per_fold
        self.pdr = base.pdr()
        default = HmmParams()
        self.default: HmmKey = (
            default.emission_weight,
            default.fix_nats,
            default.walk_noise_m2_per_s,
        )
        grids = (HMM_WEIGHT_CANDIDATES, FIX_WEIGHT_CANDIDATES, WALK_NOISE_CANDIDATES)
        keys = [self._moved(axis, v) for axis, grid in enumerate(grids) for v in grid]
        self.keys = list(dict.fromkeys(keys))
        self.candidates = [
            replace(
                base.hmm(),
                emission_weight=w,
                fix_nats=f,
                walk_noise_m2_per_s=q,
                accuracy_floor_m=0.0,
                radius_scale=1.0,
            )
            for w, f, q in self.keys
        ]
        self.results: dict[HmmKey, list[WalkResult]] = {k: [] for k in self.keys}

    def _moved(self, axis: int, value: float) -> HmmKey:
        """Return the defaults with one constant (``axis`` of ``HMM_REPLAYED``) set to
        ``value``."""
        key = list(self.default)
        key[axis] = float(value)
        return (key[0], key[1], key[2])

    def on_fold(
        self, maps: tuple[RadioMap, ...], test: np.ndarray, walk_of_scan: np.ndarray
    ) -> None:
        """Replay (some of) the fold's held-out walks on the fold's maps."""
        held = [w for w in np.unique(walk_of_scan[test]).tolist() if w in self.walks]
        if len(held) > self.per_fold:
            held = [held[i] for i in np.linspace(0, len(held) - 1, self.per_fold).astype(int)]
        walks = [self.walks[w] for w in held]
        replayed = candidate_results(maps, walks, self.candidates, self.pdr, self.plans)
        for key, new in zip(self.keys, replayed, strict=True):
            self.results[key] += new

    @property
    def scored(self) -> int:
        """Return the walks replayed (per candidate)."""
        return len(self.results[self.keys[0]]) if self.keys else 0

    def _scores(self, axis: int) -> dict[float, list[float]]:
        """Return each walk's score per value of one constant, the others at their defaults."""
        others = [i for i in range(len(HMM_REPLAYED)) if i != axis]
        return {
            key[axis]: [r.score for r in self.results[key]]
            for key in self.keys
            if all(key[i] == self.default[i] for i in others)
        }

    def mean_errors(self) -> dict[str, dict[float, float]]:
        """Return the mean walk score (m) of each value of each replayed constant, the others
        at their defaults; empty when none was replayed."""
        if not self.scored:
            return {}
        return {
            name: {v: float(np.mean(s)) for v, s in self._scores(axis).items()}
            for axis, name in enumerate(HMM_REPLAYED)
        }

    def choose(self) -> HmmKey | None:
        """Return the candidate chosen one constant at a time (``one_move_choice``); None
        without replays."""
        if not self.scored:
            return None
        w, f, q = one_move_choice(
            [self._scores(axis) for axis in range(len(HMM_REPLAYED))], self.default
        )
        return w, f, q

    def mean_error(self, key: HmmKey) -> float | None:
        """Return the mean walk score (m) of one candidate, None if not replayed."""
        results = self.results.get(key)
        return float(np.mean([r.score for r in results])) if results else None

    def smoother_scores(
        self, key: HmmKey, calibration: tuple[float, float]
    ) -> dict[str, dict[float, list[float]]]:
        """Return one candidate's walk scores under each smoother, per fix scale, its
        radius calibrated by ``calibration``."""
        return smoother_scores(
            self.results.get(key, []),
            calibration,
            HmmParams().min_accuracy_m,
            SMOOTHER_FIX_SCALE_CANDIDATES,
        )

    def radius_calibration(self, key: HmmKey) -> tuple[float, float] | None:
        """Return the radius scale and floor (m) under which the radius holds 68% of one
        candidate's replay errors; None if it was not replayed."""
        results = self.results.get(key)
        if not results:
            return None
        error = np.concatenate([r.error for r in results])
        radius = np.concatenate([r.radius for r in results])
        return calibrate_radius(error, radius, HmmParams().min_accuracy_m)


class FloorReplays:
    """Held-out survey walks joined across floors, their floor followed under each floor
    weight and floor-classifier weight on each fold's maps
    (``app.engine.hmm.floor_validate``); every walk with WiFi is replayed. Without
    ``params`` (no tuning) nothing is."""

    def __init__(
        self, inputs: BuildInputs, tx_ids: tuple[str, ...], params: HmmParams | None
    ) -> None:
        index = {tx: i for i, tx in enumerate(tx_ids)}
        self.params = params or HmmParams()
        self.walks: dict[int, FloorWalk] = {}
        if params is not None:
            for w, s in enumerate(inputs.surveys):
                if s.t.size:
                    self.walks[w] = FloorWalk(s.wifi(index), inputs.site.floor_index[s.floor_id])
        self.evidence: list[WalkEvidence] = []
        self.floor_of_map: list[np.ndarray] = []
        self.folds: list[slice] = []

    def on_fold(
        self, maps: tuple[RadioMap, ...], test: np.ndarray, walk_of_scan: np.ndarray
    ) -> None:
        """Gather the floor evidence of the fold's held-out walks on its maps."""
        held = [w for w in np.unique(walk_of_scan[test]).tolist() if w in self.walks]
        walks = [self.walks[w] for w in held]
        if len({walk.floor for walk in walks}) < 2:
            # nothing to join across floors
            return
        model = EmissionModel(maps, self.params)
        start = len(self.evidence)
        self.evidence += walk_evidence(model, walks, FLOOR_WEIGHT_CANDIDATES, self.params)
        self.folds.append(slice(start, len(self.evidence)))
        self.floor_of_map.append(np.asarray(model.floors, dtype=np.int64))

    def _scores(self, weight: int | None, classifier_weight: float) -> list[float]:
        """Return every fold's pairs' shares of scans on a wrong floor under one setting
        (floor weight number ``weight``, None: the radio map's evidence left out)."""
        out: list[float] = []
        for fold, floors in zip(self.folds, self.floor_of_map, strict=True):
            out += pair_shares(self.evidence[fold], weight, classifier_weight, floors, self.params)
        return out

    @cached_property
    def grid(self) -> dict[tuple[float, float], list[float]]:
        """Return the pairs' shares per (floor weight, classifier weight); a floor weight
        of 0 leaves the radio map's evidence out, and one of the two counts."""
        radio: list[tuple[int | None, float]] = [(None, 0.0)]
        radio += list(enumerate(FLOOR_WEIGHT_CANDIDATES))
        return {
            (w, c): self._scores(k, c)
            for k, w in radio
            for c in (0.0, *FLOOR_CLASSIFIER_WEIGHT_CANDIDATES)
            if k is not None or c > 0.0
        }

    def classifier_scores(self, floor_weight: float) -> dict[float, list[float]]:
        """Return the pairs' shares per classifier weight at ``floor_weight``."""
        return {c: v for (w, c), v in self.grid.items() if w == floor_weight}

    def floor_scores(self, classifier_weight: float) -> dict[float, list[float]]:
        """Return the pairs' shares per floor weight at ``classifier_weight``."""
        return {w: v for (w, c), v in self.grid.items() if c == classifier_weight}

    def choose(self) -> tuple[float, float] | None:
        """Return the floor weight and the classifier weight that put the fewest of the
        pairs' scans on a wrong floor (the smaller weights on a tie); None without pairs.

        Both together: where a floor is thinly surveyed the radio map's floor
        evidence is confidently wrong (hundreds of nats over a walk) and the
        classifier alone does best; where the survey is dense the radio map's
        evidence tells floors apart that the classifier confuses.
        """
        if not self.folds or not all(self.grid.values()):
            return None
        return min(self.grid, key=lambda key: (float(np.mean(self.grid[key])), key))


def _replayed_key(tuning: SiteTuning) -> HmmKey:
    """Return the replay candidate a tuning's HMM constants are."""
    return (tuning.emission_weight, tuning.fix_nats, tuning.walk_noise_m2_per_s)


def _measured_walks(inputs: BuildInputs) -> list[WalkPdr]:
    """Return the PDR of every survey with inertial samples against its waypoints."""
    out = []
    for s in inputs.surveys:
        walk = measure_walk(s.identity, s.floor_id, s.waypoints, s.imu, PdrParams())
        if walk is not None:
            out.append(walk)
    return out


def _tuning_scores(
    validation: CrossValidation | None,
    replays: HmmReplays,
    floor_scores: dict[float, list[float]],
    classifier_scores: dict[float, list[float]],
    smoothers: dict[str, dict[float, list[float]]],
    age_scores: dict[float, list[float]],
    knn_scores: dict[str, dict[float, list[float]]],
) -> dict[str, Any] | None:
    """Return the held-out figure of every candidate the tuning chose among."""
    if validation is None:
        return None
    errors = replays.mean_errors()

    def by_value(name: str) -> dict[str, float | None]:
        return {str(v): _r(e) for v, e in errors.get(name, {}).items()}

    def by_scale(name: str) -> dict[str, float | None]:
        return {str(c): _r(float(np.mean(v))) for c, v in smoothers.get(name, {}).items() if v}

    return {
        "hmm_walk_error_m_by_weight": by_value("emission_weight"),
        "hmm_walk_error_m_by_fix_weight": by_value("fix_nats"),
        "hmm_walk_error_m_by_walk_noise": by_value("walk_noise_m2_per_s"),
        "wrong_floor_share_by_floor_weight": {
            str(w): _r(float(np.mean(v)), 4) for w, v in floor_scores.items() if v
        },
        "wrong_floor_share_by_floor_classifier_weight": {
            str(c): _r(float(np.mean(v)), 4) for c, v in classifier_scores.items() if v
        },
        "floor_pairs": min((len(v) for v in floor_scores.values()), default=0),
        "fixed_lag_walk_error_m_by_fix_scale": by_scale("fixed_lag"),
        "full_pass_walk_error_m_by_fix_scale": by_scale("full_pass"),
        "hmm_walks": replays.scored,
        "wknn_mean_error_m_by_k": {
            str(k): _r(float(np.mean(h.error_m))) for k, h in validation.by_k.items()
        },
        "emission_log_score_by_weight": {
            str(w): _r(v, 4) for w, v in validation.emission_score.items()
        },
        "floor_log_score_by_weight": {str(w): _r(v, 4) for w, v in validation.floor_score.items()},
        "emission_scans": validation.emission_scans,
        "knn_walk_error_m_by_wifi_max_age_ms": {
            str(int(a)): _r(float(np.mean(v))) for a, v in age_scores.items() if v
        },
        "knn_walk_error_m_by_weight_power": {
            str(p): _r(float(np.mean(v))) for p, v in knn_scores.get("weight_power", {}).items()
        },
        "knn_walk_error_m_by_floor_dbm": {
            str(f): _r(float(np.mean(v))) for f, v in knn_scores.get("floor_dbm", {}).items()
        },
        "knn_walk_error_m_by_unshared_penalty": {
            str(c): _r(float(np.mean(v))) for c, v in knn_scores.get("unshared_penalty", {}).items()
        },
        "knn_walk_error_m_by_level_power": {
            str(int(g)): _r(float(np.mean(v))) for g, v in knn_scores.get("level_power", {}).items()
        },
        "knn_walk_error_m_by_k": {
            str(int(k)): _r(float(np.mean(v))) for k, v in knn_scores.get("k", {}).items()
        },
    }


def _fit_row(fit: TransmitterFit, tx_ids: tuple[str, ...], floor_ids: tuple[str, ...]) -> dict:
    return {
        "id": tx_ids[fit.tx],
        "floor_id": floor_ids[fit.floor],
        "x": _r(fit.x),
        "y": _r(fit.y),
        "z": _r(fit.z),
        "A": _r(fit.A),
        "B": _r(fit.B),
        "sigma": _r(fit.sigma),
        "n_readings": fit.n_readings,
        "n_censored": fit.n_censored,
        "spread_m": _r(fit.spread_m),
        "converged": fit.converged,
        "plausible": fit.plausible,
        "position_known": fit.position_known,
    }


def store_build(*, db: Session, site: Site, result: BuildResult) -> None:
    """Replace the site's stored radio maps, fits, summary and survey guidance, and bump its
    map version."""
    db.execute(delete(RadioMapFloor).where(RadioMapFloor.site_id == site.id))
    db.execute(delete(CalibratedTransmitter).where(CalibratedTransmitter.site_id == site.id))
    db.execute(delete(RadioMapBuild).where(RadioMapBuild.site_id == site.id))
    guidance.replace_rows(db=db, site_id=site.id, grids=result.guidance)
    db.flush()
    for floor_id, m in result.maps.items():
        db.add(
            RadioMapFloor(
                site_id=site.id,
                floor_id=floor_id,
                n_points=m.n_points,
                transmitters=[result.tx_ids[t] for t in m.tx],
                data=encode_map(m),
            )
        )
    for fit in result.fits:
        db.add(
            CalibratedTransmitter(
                site_id=site.id,
                transmitter_id=result.tx_ids[fit.tx],
                floor_id=result.floor_ids[fit.floor],
                x=fit.x,
                y=fit.y,
                z=fit.z,
                A=fit.A,
                B=fit.B,
                sigma=fit.sigma,
                n_readings=fit.n_readings,
                n_censored=fit.n_censored,
                spread_m=fit.spread_m,
                converged=fit.converged,
                plausible=fit.plausible,
                position_known=fit.position_known,
            )
        )
    db.add(RadioMapBuild(site_id=site.id, summary=result.summary))
    bump_map_version(db=db, site=site)
    db.flush()


def build_site(
    *,
    sessions: sessionmaker[Session],
    site_id: str,
    raster_cell: float,
    folds: int,
    tune: bool = True,
    hmm_walks: int = 20,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run a whole build (read, compute, store) and return the summary with its duration.

    Meant for a worker thread: each phase opens its own short session.
    """
    started = time.perf_counter()
    with session_scope(sessions) as db:
        site = db.get(Site, site_id)
        if site is None:
            raise NotFound(f"site '{site_id}' not found")
        inputs = load_inputs(db=db, site=site, raster_cell=raster_cell)
    result = compute_build(inputs, folds=folds, tune=tune, hmm_walks=hmm_walks, progress=progress)
    with session_scope(sessions) as db:
        site = db.get(Site, site_id)
        if site is None:
            raise NotFound(f"site '{site_id}' was deleted during the build")
        store_build(db=db, site=site, result=result)
        version = site.map_version
    elapsed_ms = round((time.perf_counter() - started) * 1000.0, 1)
    return result.summary | {"map_version": version, "elapsed_ms": elapsed_ms}


def get_build(*, db: Session, site_id: str) -> RadioMapBuild:
    """Return the site's stored build summary row; NotFound when never built."""
    build = db.get(RadioMapBuild, site_id)
    if build is None:
        raise NotFound(f"site '{site_id}' has no radio map yet: POST .../radiomap/build")
    return build


def create_job(*, db: Session, site_id: str) -> RadioMapJob:
    """Record a queued asynchronous build."""
    job = RadioMapJob(id=uuid.uuid4().hex, site_id=site_id, status="queued", progress=0.0)
    db.add(job)
    db.flush()
    return job


def update_job(
    *,
    sessions: sessionmaker[Session],
    job_id: str,
    status: str | None = None,
    progress: float | None = None,
    summary: dict[str, Any] | None = None,
    error: str | None = None,
) -> None:
    """Record a job's progress or outcome in its own short transaction."""
    with session_scope(sessions) as db:
        job = db.get(RadioMapJob, job_id)
        if job is None:
            return
        if status is not None:
            job.status = status
        if progress is not None:
            job.progress = round(float(progress), 3)
        if summary is not None:
            job.summary = summary
        if error is not None:
            job.error = error


def get_job(*, db: Session, site_id: str, job_id: str) -> RadioMapJob:
    """Return the site's build job; NotFound also when it belongs to another site."""
    job = db.get(RadioMapJob, job_id)
    if job is None or job.site_id != site_id:
        raise NotFound(f"build job '{job_id}' not found in site '{site_id}'")
    return job
