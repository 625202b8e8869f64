"""Fingerprint radio maps built from survey walks (CN106028450, offline phase).

A map holds, per reference point, each transmitter's RSSI mean, variance and
detection rate. The patent samples a grid of reference points (cells of
0.6–1 m) by standing at each for a while. Survey walks give instead one scan
every ~2 m along the walked line, located by interpolating the surveyed
waypoints in time (the walker moved straight at constant speed between two of
them). A cell therefore pools the scans around it with a Gaussian kernel: its
statistics are the kernel-weighted mean, variance and detection rate of the
scans within ``radius_m``. Cells without a scan within that radius are left
out rather than extrapolated: far from every survey the map would only repeat
its neighbours with more confidence than it has, and the trackers would walk
into areas no one measured. Reference points are kept on the walkable area
only.

Missing signals are evidence: the detection rate says how often a
transmitter was heard in the scans made around a point, so a tracker can
penalise a point where a heard transmitter is never heard, or where a
transmitter always heard there is now absent.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from app.engine.plan import FloorPlan
from app.engine.samples import RssiReadings
from app.engine.scans import ScanParams, scan_ids


@dataclass(frozen=True)
class RadioMapParams:
    """Tunable constants of radio map construction.

    Attributes
    ----------
    cell_m : float
        Side (m) of the reference point grid: the patent's 0.6–1 m.
    bandwidth_m : float
        Standard deviation (m) of the Gaussian kernel pooling scans into a
        point; 0 pools only the scans inside the point's own cell (the
        patent's per-point statistics).
    radius_m : float
        Scans farther than this (m) from a point's centre do not contribute;
        points with no scan that near are left out of the map.
    min_scans : int
        A transmitter enters a floor's map when heard in at least this many
        of the floor's scans; rarer ones carry no usable fingerprint.
    var_prior_db2 : float
        Prior RSSI variance (dB²), the variance of a reading about the mean
        at a point, which few samples cannot estimate (σ = 4 dB).
    var_prior_weight : float
        Pseudo-count of that prior: with n effective scans the variance is
        ``(n s² + k v₀) / (n + k)``.
    var_floor_db2 : float
        No variance is below this (dB²): phones quantise RSSI to 1 dB and the
        walker's position is uncertain by about a metre.
    detect_alpha : float
        Beta prior pseudo-count of detections for the detection rate.
    detect_beta : float
        Beta prior pseudo-count of misses for the detection rate.
    """

    cell_m: float = 1.0
    bandwidth_m: float = 1.0
    radius_m: float = 3.0
    min_scans: int = 5
    var_prior_db2: float = 16.0
    var_prior_weight: float = 2.0
    var_floor_db2: float = 4.0
    detect_alpha: float = 0.1
    detect_beta: float = 1.0


@dataclass(frozen=True)
class Survey:
    """Located survey scans: one row per scan, and the readings of each scan.

    Attributes
    ----------
    scan_t : ndarray of int64, shape (S,)
        Scan times (ms).
    scan_xy : ndarray, shape (S, 2)
        Position (m) of the receiver at each scan.
    scan_floor : ndarray of int32, shape (S,)
        Floor index of each scan.
    scan_walk : ndarray of int32, shape (S,)
        Which walk each scan belongs to (for grouping only).
    reading_scan : ndarray of int32, shape (R,)
        Scan row of each reading; one reading per transmitter per scan.
    reading_tx : ndarray of int32, shape (R,)
        Transmitter index of each reading.
    reading_rssi : ndarray, shape (R,)
        RSSI (dBm).
    """

    scan_t: np.ndarray
    scan_xy: np.ndarray
    scan_floor: np.ndarray
    scan_walk: np.ndarray
    reading_scan: np.ndarray
    reading_tx: np.ndarray
    reading_rssi: np.ndarray

    @property
    def n_scans(self) -> int:
        """Number of scans."""
        return int(self.scan_t.size)

    def reading_xy(self) -> np.ndarray:
        """Return the position (m) of each reading, shape (R, 2)."""
        return self.scan_xy[self.reading_scan]

    def reading_floor(self) -> np.ndarray:
        """Return the floor of each reading, shape (R,)."""
        return self.scan_floor[self.reading_scan]

    def select(self, scans: np.ndarray) -> Survey:
        """Return the survey restricted to the scans selected by a boolean mask (S,)."""
        scans = np.asarray(scans, dtype=bool)
        new_index = np.cumsum(scans) - 1
        keep = scans[self.reading_scan]
        return Survey(
            scan_t=self.scan_t[scans],
            scan_xy=self.scan_xy[scans],
            scan_floor=self.scan_floor[scans],
            scan_walk=self.scan_walk[scans],
            reading_scan=new_index[self.reading_scan[keep]].astype(np.int32),
            reading_tx=self.reading_tx[keep],
            reading_rssi=self.reading_rssi[keep],
        )

    @staticmethod
    def concat(parts: list[Survey]) -> Survey:
        """Join surveys, renumbering scans (walk numbers are kept as given); none: empty."""
        if not parts:
            no_scan = np.zeros(0, dtype=np.int32)
            return Survey(
                np.zeros(0, np.int64), np.zeros((0, 2)), no_scan, no_scan, no_scan, no_scan,
                np.zeros(0),
            )  # fmt: skip
        offsets = np.cumsum([0] + [p.n_scans for p in parts])
        return Survey(
            scan_t=np.concatenate([p.scan_t for p in parts]).astype(np.int64),
            scan_xy=np.concatenate([p.scan_xy for p in parts]).reshape(-1, 2),
            scan_floor=np.concatenate([p.scan_floor for p in parts]).astype(np.int32),
            scan_walk=np.concatenate([p.scan_walk for p in parts]).astype(np.int32),
            reading_scan=np.concatenate(
                [p.reading_scan + o for p, o in zip(parts, offsets, strict=False)]
            ).astype(np.int32),
            reading_tx=np.concatenate([p.reading_tx for p in parts]).astype(np.int32),
            reading_rssi=np.concatenate([p.reading_rssi for p in parts]).astype(float),
        )


def interpolate_waypoints(t: np.ndarray, waypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the positions at times ``t`` on a walk that went straight between waypoints.

    Parameters
    ----------
    t : ndarray of int64, shape (n,)
        Query times (ms).
    waypoints : ndarray, shape (m, 3)
        t (ms), x, y (m) of the surveyed points, sorted by time.

    Returns
    -------
    xy : ndarray, shape (n, 2)
        Linearly interpolated positions (m); NaN outside the waypoints' time span.
    inside : ndarray of bool, shape (n,)
        Whether each time lies within the span (a single waypoint has none).
    """
    t = np.asarray(t, dtype=float)
    wt = waypoints[:, 0]
    inside = (t >= wt[0]) & (t <= wt[-1]) if len(wt) >= 2 else np.zeros(t.shape, dtype=bool)
    xy = np.full((t.size, 2), np.nan)
    if inside.any():
        # p(t) = p_i + (t - t_i) / (t_{i+1} - t_i) (p_{i+1} - p_i)
        xy[inside, 0] = np.interp(t[inside], wt, waypoints[:, 1])
        xy[inside, 1] = np.interp(t[inside], wt, waypoints[:, 2])
    return xy, inside


def locate_scans(
    readings: RssiReadings,
    waypoints: np.ndarray,
    *,
    floor: int,
    walk: int = 0,
    scans: ScanParams | None = None,
) -> Survey:
    """Group a walk's readings into scans and locate each scan on the waypoints.

    A scan's time is its last reading's; a transmitter repeated within one
    scan keeps the mean of its readings; scans outside the waypoints' time
    span are dropped.

    Parameters
    ----------
    readings : RssiReadings
        The walk's readings, grouped into scans by ``app.engine.scans``.
    waypoints : ndarray, shape (m, 3)
        t (ms), x, y (m), sorted by time.
    floor : int
        Floor index of the walk.
    walk : int
        Number stored in ``scan_walk``.
    scans : ScanParams, optional
        Scan grouping constants.
    """
    t = np.asarray(readings.t, dtype=np.int64)
    scan_of = scan_ids(t, readings.tx, scans or ScanParams())
    by_scan = np.argsort(scan_of, kind="stable")
    firsts = np.flatnonzero(np.diff(scan_of[by_scan], prepend=-1))
    scan_t = np.maximum.reduceat(t[by_scan], firsts) if t.size else np.zeros(0, np.int64)
    xy, inside = interpolate_waypoints(scan_t, waypoints)
    keep = inside[scan_of]
    new_index = np.cumsum(inside) - 1
    scan = new_index[scan_of[keep]]
    tx = np.asarray(readings.tx, dtype=np.int64)[keep]
    rssi = np.asarray(readings.rssi, dtype=float)[keep]
    n_tx = int(tx.max()) + 1 if tx.size else 1
    key, inverse = np.unique(scan * n_tx + tx, return_inverse=True)
    # mean of repeated (scan, tx) readings
    mean = np.bincount(inverse, rssi) / np.bincount(inverse)
    n = int(inside.sum())
    return Survey(
        scan_t=scan_t[inside],
        scan_xy=xy[inside],
        scan_floor=np.full(n, floor, dtype=np.int32),
        scan_walk=np.full(n, walk, dtype=np.int32),
        reading_scan=(key // n_tx).astype(np.int32),
        reading_tx=(key % n_tx).astype(np.int32),
        reading_rssi=mean,
    )


@dataclass(frozen=True, eq=False)
class MapReferences:
    """The survey scans a floor's map was pooled from, kept as reference fingerprints.

    Per-scan k-NN (``app.engine.scan_knn``) compares a scan with each of
    these rather than with the pooled cells.

    Attributes
    ----------
    xy : ndarray of float32, shape (S, 2)
        Surveyed position (m) of each scan.
    walk : ndarray of int32, shape (S,)
        Survey walk of each scan (numbers are only compared, never shown).
    scan : ndarray of int32, shape (R,)
        Scan row of each reading.
    col : ndarray of int32, shape (R,)
        Map column (position in ``RadioMap.tx``) of each reading.
    rssi : ndarray of float32, shape (R,)
        RSSI (dBm) of each reading.
    """

    xy: np.ndarray
    walk: np.ndarray
    scan: np.ndarray
    col: np.ndarray
    rssi: np.ndarray

    KEYS: ClassVar[tuple[str, ...]] = ("xy", "walk", "scan", "col", "rssi")


@dataclass(frozen=True, eq=False)
class RadioMap:
    """The fingerprints of one floor.

    Attributes
    ----------
    floor : int
        Floor index.
    cell : float
        Grid cell side (m).
    origin : ndarray, shape (2,)
        x, y (m) of the lower-left corner of grid cell (0, 0).
    shape : tuple of int
        Grid shape (ny, nx); reference points are a subset of its cells.
    ij : ndarray of int32, shape (P, 2)
        Row and column of each reference point.
    tx : ndarray of int32, shape (T,)
        Site transmitter index of each column.
    mean : ndarray of float32, shape (P, T)
        Mean RSSI (dBm) when heard; NaN where never heard near the point.
    var : ndarray of float32, shape (P, T)
        RSSI variance (dB²) when heard; NaN where never heard.
    detect : ndarray of float32, shape (P, T)
        Probability that a scan at the point hears the transmitter.
    weight : ndarray of float32, shape (P,)
        Kernel weight of the scans pooled into each point (≈ number of scans).
    references : MapReferences, optional
        The scans pooled, for per-scan k-NN; None for maps stored without them.
    """

    floor: int
    cell: float
    origin: np.ndarray
    shape: tuple[int, int]
    ij: np.ndarray
    tx: np.ndarray
    mean: np.ndarray
    var: np.ndarray
    detect: np.ndarray
    weight: np.ndarray
    references: MapReferences | None = None

    @property
    def n_points(self) -> int:
        """Number of reference points."""
        return int(self.ij.shape[0])

    @property
    def xy(self) -> np.ndarray:
        """Reference point positions: the cell centres (m), shape (P, 2)."""
        # x = x₀ + (col + ½) cell, y = y₀ + (row + ½) cell
        return self.origin + (self.ij[:, ::-1] + 0.5) * self.cell

    def index_grid(self) -> np.ndarray:
        """Return the grid (ny, nx) of point indices, -1 where a cell is not a point."""
        grid = np.full(self.shape, -1, dtype=np.int32)
        grid[self.ij[:, 0], self.ij[:, 1]] = np.arange(self.n_points, dtype=np.int32)
        return grid

    def columns(self, tx: np.ndarray) -> np.ndarray:
        """Return the column of each site transmitter index (T',), -1 where not in the map."""
        lookup = np.full(max(int(self.tx.max(initial=-1)), int(np.max(tx, initial=-1))) + 1, -1)
        lookup[self.tx] = np.arange(self.tx.size)
        return lookup[np.asarray(tx, dtype=np.int64)].astype(np.int64)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Return the map as a dict of arrays (for ``np.savez`` or a snapshot store)."""
        return {
            "floor": np.array(self.floor, dtype=np.int32),
            "cell": np.array(self.cell),
            "origin": self.origin.copy(),
            "shape": np.array(self.shape, dtype=np.int64),
            "ij": self.ij,
            "tx": self.tx,
            "mean": self.mean,
            "var": self.var,
            "detect": self.detect,
            "weight": self.weight,
        } | (
            {}
            if self.references is None
            else {f"ref_{k}": getattr(self.references, k) for k in MapReferences.KEYS}
        )

    @classmethod
    def from_arrays(cls, arrays: dict[str, Any]) -> RadioMap:
        """Rebuild a map from ``to_arrays()`` output."""
        shape = np.asarray(arrays["shape"], dtype=np.int64)
        return cls(
            floor=int(arrays["floor"]),
            cell=float(arrays["cell"]),
            origin=np.asarray(arrays["origin"], dtype=float),
            shape=(int(shape[0]), int(shape[1])),
            ij=np.asarray(arrays["ij"], dtype=np.int32).reshape(-1, 2),
            tx=np.asarray(arrays["tx"], dtype=np.int32),
            mean=np.asarray(arrays["mean"], dtype=np.float32),
            var=np.asarray(arrays["var"], dtype=np.float32),
            detect=np.asarray(arrays["detect"], dtype=np.float32),
            weight=np.asarray(arrays["weight"], dtype=np.float32),
            references=MapReferences(
                xy=np.asarray(arrays["ref_xy"], dtype=np.float32).reshape(-1, 2),
                walk=np.asarray(arrays["ref_walk"], dtype=np.int32),
                scan=np.asarray(arrays["ref_scan"], dtype=np.int32),
                col=np.asarray(arrays["ref_col"], dtype=np.int32),
                rssi=np.asarray(arrays["ref_rssi"], dtype=np.float32),
            )
            if "ref_xy" in arrays
            else None,
        )


def walkable_cells(plan: FloorPlan, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the grid origin and a (ny, nx) mask of cells of side ``cell`` holding free space.

    The plan may be finer than the grid: a grid cell is walkable when any free
    plan cell's centre lies in it, so narrow corridors survive coarsening.
    """
    ny, nx = plan.shape
    # grid cells needed to cover the plan's extent
    shape = (int(np.ceil(ny * plan.cell / cell)), int(np.ceil(nx * plan.cell / cell)))
    rows, cols = np.nonzero(plan.free)
    centres = plan.origin + (np.stack([cols, rows], axis=1) + 0.5) * plan.cell
    ij = np.floor((centres - plan.origin) / cell).astype(np.int64)
    mask = np.zeros(shape, dtype=bool)
    mask[np.clip(ij[:, 1], 0, shape[0] - 1), np.clip(ij[:, 0], 0, shape[1] - 1)] = True
    return plan.origin.copy(), mask


def extend_onto_plan(radio_map: RadioMap, plan: FloorPlan, reach_m: float) -> RadioMap:
    """Return the map with walkable cells within ``reach_m`` of a survey scan as points too.

    The added points come after the map's own, with no pooled statistics. A
    tracker confined to the surveyed corridors cannot follow a walker the
    survey never passed; the added points let it, scored by the scans nearest
    them. Unchanged when the map has no scans, ``reach_m`` adds nothing, or the
    map was built on another grid than this plan's.
    """
    refs = radio_map.references
    if refs is None or refs.xy.shape[0] == 0 or reach_m <= 0:
        return radio_map
    origin, mask = walkable_cells(plan, radio_map.cell)
    if mask.shape != radio_map.shape or not np.allclose(origin, radio_map.origin):
        return radio_map
    mask[radio_map.ij[:, 0], radio_map.ij[:, 1]] = False
    cells = np.argwhere(mask)
    centres = origin + (cells[:, ::-1] + 0.5) * radio_map.cell
    dist, _ = cKDTree(refs.xy).query(centres, distance_upper_bound=reach_m)
    added = cells[np.isfinite(dist)].astype(np.int32)
    if added.shape[0] == 0:
        return radio_map
    unknown = np.full((added.shape[0], radio_map.tx.size), np.nan, dtype=np.float32)
    return replace(
        radio_map,
        ij=np.concatenate([radio_map.ij, added]),
        mean=np.concatenate([radio_map.mean, unknown]),
        var=np.concatenate([radio_map.var, unknown]),
        detect=np.concatenate([radio_map.detect, np.zeros_like(unknown)]),
        weight=np.concatenate([radio_map.weight, np.zeros(added.shape[0], np.float32)]),
    )


def pooling_weights(
    points: np.ndarray, scans: np.ndarray, params: RadioMapParams
) -> sparse.csr_matrix:
    """Return the Gaussian kernel weights (P, S) of scans at ``scans`` (S, 2) in points (P, 2).

    Pairs farther apart than ``radius_m`` get no weight.
    """
    near = cKDTree(points).sparse_distance_matrix(
        cKDTree(scans), params.radius_m, output_type="ndarray"
    )
    # w = exp(-d² / 2h²)
    w = np.exp(-0.5 * (near["v"] / params.bandwidth_m) ** 2)
    return sparse.csr_matrix((w, (near["i"], near["j"])), shape=(points.shape[0], scans.shape[0]))


def build_radio_map(
    survey: Survey,
    floor: int,
    params: RadioMapParams,
    *,
    walkable: FloorPlan | None = None,
) -> RadioMap:
    """Build one floor's radio map from the located scans of that floor.

    Parameters
    ----------
    survey : Survey
        Located scans (those of other floors are ignored).
    floor : int
        Floor index to build.
    params : RadioMapParams
        Grid, pooling and prior constants.
    walkable : FloorPlan, optional
        Where positions may be; reference points are kept on its free area.
        Without it the grid covers the scans' extent and every cell near a
        scan is a point.

    Raises
    ------
    ValueError
        When the floor has no scan.
    """
    on_floor = survey.scan_floor == floor
    if not on_floor.any():
        raise ValueError(f"no survey scan on floor {floor}")
    s = survey.select(on_floor)
    cell = params.cell_m
    if walkable is not None:
        origin, mask = walkable_cells(walkable, cell)
    else:
        pad = params.radius_m + cell
        origin = np.floor((s.scan_xy.min(axis=0) - pad) / cell) * cell
        extent = s.scan_xy.max(axis=0) + pad - origin
        mask = np.ones((int(np.ceil(extent[1] / cell)), int(np.ceil(extent[0] / cell))), bool)
    ny, nx = mask.shape
    # cell of each scan: (row, col) = floor((xy - origin) / cell)
    scan_ij = np.floor((s.scan_xy - origin) / cell).astype(np.int64)[:, ::-1]
    in_grid = (scan_ij[:, 0] >= 0) & (scan_ij[:, 0] < ny) & (scan_ij[:, 1] >= 0)
    in_grid &= scan_ij[:, 1] < nx
    if params.bandwidth_m <= 0:
        visited = np.zeros_like(mask)
        visited[scan_ij[in_grid, 0], scan_ij[in_grid, 1]] = True
        candidates = np.argwhere(mask & visited)
    else:
        candidates = np.argwhere(mask)
    centres = origin + (candidates[:, ::-1] + 0.5) * cell
    if params.bandwidth_m > 0:
        dist, _ = cKDTree(s.scan_xy).query(centres, distance_upper_bound=params.radius_m)
        candidates, centres = candidates[np.isfinite(dist)], centres[np.isfinite(dist)]
    if params.bandwidth_m <= 0:
        grid = np.full((ny, nx), -1, dtype=np.int64)
        grid[candidates[:, 0], candidates[:, 1]] = np.arange(candidates.shape[0])
        ok = np.flatnonzero(in_grid)
        point = grid[scan_ij[ok, 0], scan_ij[ok, 1]]
        ok, point = ok[point >= 0], point[point >= 0]
        # own-cell pooling: weight 1 for each scan inside the point's cell
        W = sparse.csr_matrix(
            (np.ones(ok.size), (point, ok)), shape=(candidates.shape[0], s.n_scans)
        )
    else:
        W = pooling_weights(centres, s.scan_xy, params)

    # transmitters heard in at least min_scans scans of the floor
    heard_scans = np.bincount(s.reading_tx, minlength=int(s.reading_tx.max(initial=-1)) + 1)
    tx = np.flatnonzero(heard_scans >= params.min_scans).astype(np.int32)
    col = np.full(heard_scans.size, -1, dtype=np.int64)
    col[tx] = np.arange(tx.size)
    use = col[s.reading_tx] >= 0
    r_scan, r_col, r = s.reading_scan[use], col[s.reading_tx[use]], s.reading_rssi[use]
    shape = (s.n_scans, tx.size)
    H = sparse.csr_matrix((np.ones(r.size), (r_scan, r_col)), shape=shape)
    X = sparse.csr_matrix((r, (r_scan, r_col)), shape=shape)
    X2 = sparse.csr_matrix((r * r, (r_scan, r_col)), shape=shape)
    W2 = W.multiply(W).tocsr()
    # Σ_s w_js, Σ_s w_js h_sa, Σ_s w_js x_sa, Σ_s w_js x_sa², Σ_s w_js² h_sa
    w_all = np.asarray(W.sum(axis=1)).ravel()
    w_heard = (W @ H).toarray()
    sx = (W @ X).toarray()
    sxx = (W @ X2).toarray()
    w2_heard = (W2 @ H).toarray()

    heard = w_heard > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        # μ = Σ w x / Σ w
        mean = np.where(heard, sx / w_heard, np.nan)
        # s² = Σ w x² / Σ w - μ²
        emp_var = np.where(heard, np.maximum(sxx / w_heard - mean**2, 0.0), np.nan)
        # Kish effective count n = (Σ w)² / Σ w²
        n_eff = np.where(heard, w_heard**2 / w2_heard, 0.0)
    k0, v0 = params.var_prior_weight, params.var_prior_db2
    # σ² = max(floor, (n s² + k v₀) / (n + k))
    var = np.maximum((n_eff * emp_var + k0 * v0) / (n_eff + k0), params.var_floor_db2)
    a, b = params.detect_alpha, params.detect_beta
    # q = (Σ w h + α) / (Σ w + α + β)
    detect = (w_heard + a) / (w_all[:, None] + a + b)
    return RadioMap(
        floor=int(floor),
        cell=float(cell),
        origin=np.asarray(origin, dtype=float),
        shape=(int(ny), int(nx)),
        ij=candidates.astype(np.int32),
        tx=tx,
        mean=mean.astype(np.float32),
        var=np.where(heard, var, np.nan).astype(np.float32),
        detect=detect.astype(np.float32),
        weight=w_all.astype(np.float32),
        references=MapReferences(
            xy=s.scan_xy.astype(np.float32),
            walk=s.scan_walk.astype(np.int32),
            scan=r_scan.astype(np.int32),
            col=r_col.astype(np.int32),
            rssi=r.astype(np.float32),
        ),
    )
