"""The HMM's emission (step 3 in ``app.engine.hmm``) and its k-NN start (step 1).

Two emissions, prepared once per site and shared by all devices:

- where the maps carry the survey scans they were pooled from, a point's
  evidence is how well the survey scans around it match the scan, by the
  per-scan k-NN distance (``app.engine.scan_knn``): ``ln L_j = -c (D_j -
  d_min)``, ``D_j`` the soft minimum of the distances of the scans within
  ``knn_radius_m`` of the point, weighted by a Gaussian kernel of distance,
  ``d_min`` the best survey scan's anywhere. It compares scans only on what
  both heard, so a sparse survey does not make unmeasured transmitters
  evidence against a point. The tracker adds the k-NN fix
  (``fix_log_density``): where on the floor the best-matching scans are.
  Given the floor plans, points also reach past the survey onto walkable
  cells (``reach_m``), each pooling the survey scans nearest it;
- otherwise (maps stored without their scans), the seed's per-point
  Gaussian with detection rates.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree
from scipy.special import logsumexp

from app.engine.hmm.floor_classifier import FloorClassifier, fit_floor_classifier
from app.engine.hmm.kernels import mixture_log_density, pooled_emission
from app.engine.hmm.params import HmmParams
from app.engine.plan import FloorPlan
from app.engine.radiomap import RadioMap, extend_onto_plan
from app.engine.scan_knn import ReferenceScans
from app.engine.wknn import Fingerprints

_CAP_MARGIN_DB = 1e-6
"""Margin (dB) past ``knn_max_db`` beyond which a floor's pooled distance is surely capped."""


class EmissionModel:
    """Per-floor log-likelihood tables of every reference point, prepared once per site.

    Arrays are stored transmitter-major (T, P) so a scan gathers contiguous rows.

    Parameters
    ----------
    maps : sequence of RadioMap
        One map per floor.
    params : HmmParams
        Unmapped-transmitter constants, and how far past the survey points reach.
    plans : mapping of floor index to FloorPlan, optional
        Where the maps carry their survey scans, each floor's walkable cells
        within ``reach_m`` of a scan become points too (after the map's own).
    """

    def __init__(
        self,
        maps: Sequence[RadioMap],
        params: HmmParams,
        plans: Mapping[int, FloorPlan] | None = None,
    ) -> None:
        surveyed = tuple(maps)
        if plans and all(m.references is not None for m in surveyed):
            maps = [
                extend_onto_plan(m, plans[m.floor], params.reach_m) if m.floor in plans else m
                for m in surveyed
            ]
        self.maps = tuple(maps)
        # points [0, n) of map f are its own, pooled from the survey; the rest reach past it
        self.surveyed_points = [m.n_points for m in surveyed]
        self.floors = tuple(m.floor for m in self.maps)
        self.fingerprints = Fingerprints(surveyed, params.missing_dbm)
        self.grids = [m.index_grid() for m in self.maps]
        # grid row and column of each point, typed once for the compiled transition
        self.cells = [np.ascontiguousarray(m.ij, dtype=np.int32) for m in self.maps]
        self.xy = [m.xy for m in self.maps]
        self.mean: list[np.ndarray] = []
        self.inv_var: list[np.ndarray] = []
        self.base: list[np.ndarray] = []
        self.log_miss: list[np.ndarray] = []
        self.absent: list[np.ndarray] = []
        for m in surveyed:
            heard = np.isfinite(m.mean)
            mean = np.where(heard, m.mean, params.unmapped_dbm)
            var = np.where(heard, m.var, params.unmapped_var_db2)
            q = np.clip(m.detect, 1e-6, 1.0 - 1e-6)
            self.mean.append(np.ascontiguousarray(mean.T, dtype=np.float32))
            self.inv_var.append(np.ascontiguousarray((1.0 / var).T, dtype=np.float32))
            # ln q + ln N normaliser: ln q - ½ ln(2π σ²)
            base = np.log(q) - 0.5 * np.log(2.0 * np.pi * var)
            self.base.append(np.ascontiguousarray(base.T, dtype=np.float32))
            log_miss = np.log1p(-q)
            self.log_miss.append(np.ascontiguousarray(log_miss.T, dtype=np.float32))
            # S₀_j = Σ_a ln(1 - q_ja): every mapped transmitter unheard
            self.absent.append(log_miss.sum(axis=1, dtype=np.float64))
        n_tx = max(int(m.tx.max(initial=-1)) for m in self.maps) + 1
        self.columns = self.fingerprints.columns
        self.n_tx = n_tx
        # transmitters some floor's map has: only they are evidence of a position
        self.mapped = np.zeros(n_tx, dtype=bool)
        for lookup in self.columns:
            self.mapped[: lookup.size] |= lookup >= 0
        # ln q₀ + ln N(s; s₀, v₀) pieces for transmitters absent from a floor's map
        self.unmapped = (
            np.log(params.unmapped_detect) - 0.5 * np.log(2.0 * np.pi * params.unmapped_var_db2),
            params.unmapped_dbm,
            1.0 / params.unmapped_var_db2,
        )
        self.params = params
        self.references: ReferenceScans | None = None
        self.ref_blocks: list[slice] = []
        if self.maps and all(m.references is not None for m in self.maps):
            self._prepare_references()
        self._classifier: FloorClassifier | None = None
        self._cache: tuple[bytes, np.ndarray] | None = None
        self._evidence: tuple[bytes, list[np.ndarray], np.ndarray] | None = None
        self._near: tuple[bytes, int, tuple[np.ndarray, np.ndarray] | None] | None = None

    def _prepare_references(self) -> None:
        """Gather the survey scans and each point's kernel over its floor's scans.

        The kernels of every floor's points are one CSR matrix, points stacked
        floor after floor, over all survey scans (floor f's in ``ref_blocks[f]``),
        kept by point and by scan.
        """
        p = self.params
        self.references = ReferenceScans.from_maps(self.maps, self.n_tx, p.references)
        start = 0
        rows, cols, values = [], [], []
        point_start = np.cumsum([0] + [m.n_points for m in self.maps], dtype=np.int64)
        for m, xy, first in zip(self.maps, self.xy, point_start[:-1], strict=True):
            n = m.references.xy.shape[0] if m.references is not None else 0
            block = slice(start, start + n)
            near = cKDTree(xy).sparse_distance_matrix(
                cKDTree(self.references.xy[block]), p.knn_radius_m, output_type="ndarray"
            )
            # K_js = exp(-|x_j - x_s|² / 2b²), rows normalised
            w = np.exp(-0.5 * (near["v"] / p.knn_pool_m) ** 2)
            pool = sparse.csr_matrix((w, (near["i"], near["j"])), shape=(xy.shape[0], n))
            total = np.asarray(pool.sum(axis=1)).ravel()
            pool = sparse.diags(np.where(total > 0, 1.0 / np.maximum(total, 1e-300), 0.0)) @ pool
            far = np.flatnonzero(total == 0)
            if far.size and n:
                pool = pool + self._reach_pool(xy[far], far, self.references.xy[block], xy.shape[0])
            entries = sparse.coo_matrix(pool)
            rows.append(entries.row + first)
            cols.append(entries.col + start)
            values.append(entries.data)
            self.ref_blocks.append(block)
            start += n
        stacked = sparse.csr_matrix(
            (np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
            shape=(int(point_start[-1]), start),
        )
        self.pool_indptr = stacked.indptr.astype(np.int64)
        self.pool_indices = stacked.indices.astype(np.int32)
        self.pool_data = stacked.data.astype(np.float64)
        by_scan = stacked.tocsc()
        self.scan_indptr = by_scan.indptr.astype(np.int64)
        self.scan_points = by_scan.indices.astype(np.int32)
        self.point_start = point_start
        self.surveyed = np.array(self.surveyed_points, dtype=np.int64)

    def _reach_pool(
        self, xy: np.ndarray, rows: np.ndarray, scans: np.ndarray, n_points: int
    ) -> sparse.csr_matrix:
        """Return the pooling rows of points with no survey scan within ``knn_radius_m``.

        Such a point pools its ``reach_scans`` nearest scans by how much farther
        each is than the nearest: it is scored as the survey nearest it. A
        distance penalty per metre past the survey did worse on site1's
        validation walks, the more so the steeper.
        """
        p = self.params
        k = min(p.reach_scans, scans.shape[0])
        dist, idx = cKDTree(scans).query(xy, k=k)
        dist, idx = dist.reshape(len(rows), k), idx.reshape(len(rows), k)
        # K_js = exp(-(d_js - r_j)² / 2b²), r_j the nearest scan's distance; rows normalised
        w = np.exp(-0.5 * ((dist - dist[:, :1]) / p.knn_pool_m) ** 2)
        w /= w.sum(axis=1, keepdims=True)
        return sparse.csr_matrix(
            (w.ravel(), (np.repeat(rows, k), idx.ravel())), shape=(n_points, scans.shape[0])
        )

    def _distances(self, tx: np.ndarray, rssi: np.ndarray) -> np.ndarray:
        """Return the scan's k-NN distance to every survey scan (cached for the last scan).

        The cache is read and replaced whole, so devices positioned from other
        threads on the same model can only miss it, never read another scan's.
        """
        assert self.references is not None
        key = _scan_key(tx, rssi)
        cached = self._cache
        if cached is not None and cached[0] == key:
            return cached[1]
        d = self.references.distances(tx, rssi)
        self._cache = (key, d)
        return d

    def log_likelihoods(self, tx: np.ndarray, rssi: np.ndarray) -> list[np.ndarray]:
        """Return the tempered log-likelihood of one scan at every point of every map."""
        return self._scan_evidence(tx, rssi)[0]

    def floor_log_marginals(self, tx: np.ndarray, rssi: np.ndarray) -> np.ndarray:
        """Return each floor's evidence for a scan, (F,): ln mean_j L_j^(w_f / w).

        Under the floor's own tempering ``floor_weight``, over the surveyed
        points only: those reaching past the survey would weigh floors by its
        gaps.
        """
        return self._scan_evidence(tx, rssi)[1]

    @property
    def floor_classifier(self) -> FloorClassifier | None:
        """Return the floor classifier of the maps' survey scans (fitted on first use).

        None where the maps carry no survey scans.
        """
        refs = self.references
        if refs is None:
            return None
        if self._classifier is None:
            features = sparse.csr_matrix(
                (refs.scan_level, refs.scan_col, refs.scan_start),
                shape=(refs.n_scans, refs.n_usable),
            )
            map_of_floor = {floor: i for i, floor in enumerate(self.floors)}
            labels = np.array([map_of_floor[int(f)] for f in refs.floor], dtype=np.int64)
            self._classifier = fit_floor_classifier(
                features, labels, len(self.maps), refs.column, self.params.floor_classifier
            )
        return self._classifier

    def floor_classifier_log_probs(self, tx: np.ndarray, rssi: np.ndarray) -> np.ndarray:
        """Return the floor classifier's ln p(map | scan), (F,).

        Zeros (no evidence) where there is no classifier.
        """
        classifier = self.floor_classifier
        refs = self.references
        if classifier is None or refs is None:
            return np.zeros(len(self.maps))
        tx, rssi = np.asarray(tx, dtype=np.int64), np.asarray(rssi, dtype=float)
        level = np.maximum(rssi - refs.params.floor_dbm, 0.0)
        return classifier.log_probs(tx, level)

    def floor_log_marginals_by_weight(
        self, tx: np.ndarray, rssi: np.ndarray, weights: Sequence[float]
    ) -> np.ndarray:
        """Return each floor's evidence for a scan under each floor weight, (W, F).

        What ``floor_log_marginals`` returns with ``floor_weight`` set to each
        of ``weights``, from one computation of the scan's likelihoods.
        """
        lls, _ = self._scan_evidence(tx, rssi)
        rescale = np.asarray(weights, dtype=float)[:, None] / self.params.emission_weight
        own = [v[:n] for v, n in zip(lls, self.surveyed_points, strict=True)]
        return np.stack(
            [logsumexp(rescale * v[None, :], axis=1) - np.log(max(v.size, 1)) for v in own],
            axis=1,
        )

    def _scan_evidence(
        self, tx: np.ndarray, rssi: np.ndarray
    ) -> tuple[list[np.ndarray], np.ndarray]:
        """Return ``log_likelihoods`` and ``floor_log_marginals`` of a scan.

        Cached for the last scan, read and replaced whole as ``_distances``' cache.
        """
        key = _scan_key(tx, rssi)
        cached = self._evidence
        if cached is not None and cached[0] == key:
            return cached[1], cached[2]
        p = self.params
        rescale = p.floor_weight / p.emission_weight
        if self.references is None:
            lls = [self.log_likelihood(f, tx, rssi) for f in range(len(self.maps))]
            own = [rescale * v[:n] for v, n in zip(lls, self.surveyed_points, strict=True)]
            marginal = np.array([logsumexp(v) - np.log(v.size) for v in own])
        else:
            d = self._distances(tx, rssi)
            if not np.isfinite(d).any():
                # nothing in common with the survey: no evidence either way
                lls, marginal = [np.zeros(m.n_points) for m in self.maps], np.zeros(len(self.maps))
            else:
                ll, marginal = pooled_emission(
                    d, self.pool_indptr, self.pool_indices, self.pool_data, self.scan_indptr,
                    self.scan_points, self.point_start, self.surveyed, p.knn_pool_db, p.knn_max_db,
                    p.emission_weight * p.knn_nats_per_db, rescale, _CAP_MARGIN_DB,
                )  # fmt: skip
                lls = np.split(ll, self.point_start[1:-1])
        self._evidence = (key, lls, marginal)
        return lls, marginal

    def is_mapped(self, tx: np.ndarray) -> np.ndarray:
        """Return which site transmitter indices some floor's map has, shape (n,)."""
        tx = np.asarray(tx, dtype=np.int64)
        inside = tx < self.n_tx
        out = np.zeros(tx.size, dtype=bool)
        out[inside] = self.mapped[tx[inside]]
        return out

    def n_points(self, f: int) -> int:
        """Return the number of reference points of map ``f`` (position in ``maps``)."""
        return self.maps[f].n_points

    def log_likelihood(self, f: int, tx: np.ndarray, rssi: np.ndarray) -> np.ndarray:
        """Return the tempered log-likelihood of one scan at every point of map ``f``, (P,).

        Parameters
        ----------
        f : int
            Position of the map in ``maps``.
        tx : ndarray of int, shape (n,)
            Unique site transmitter indices heard.
        rssi : ndarray, shape (n,)
            Their RSSI (dBm).
        """
        if self.references is not None:
            return self.log_likelihoods(tx, rssi)[f]
        p = self.params
        tx = np.asarray(tx, dtype=np.int64)
        rssi = np.asarray(rssi, dtype=np.float32)
        lookup = self.columns[f]
        col = np.full(tx.size, -1, dtype=np.int64)
        known = tx < lookup.size
        col[known] = lookup[tx[known]]
        on = col >= 0
        c, s = col[on], rssi[on][:, None]
        # ln q + ln N(s; μ, σ²) = base - ½ (s - μ)² / σ², floored
        term = self.base[f][c] - 0.5 * (s - self.mean[f][c]) ** 2 * self.inv_var[f][c]
        term = np.maximum(term, np.float32(p.loglik_floor))
        # heard ones are not among the unheard: remove their ln(1 - q)
        ll = self.absent[f] + (term - self.log_miss[f][c]).sum(axis=0, dtype=np.float64)
        base0, mean0, inv0 = self.unmapped
        off = rssi[~on].astype(float)
        # transmitters the floor's map lacks: constant over the floor
        ll += np.maximum(base0 - 0.5 * (off - mean0) ** 2 * inv0, p.loglik_floor).sum()
        # tempered: w ln L
        return p.emission_weight * ll

    def _floor_distances(self, f: int, tx: np.ndarray, rssi: np.ndarray) -> np.ndarray | None:
        """Return the scan's distance to each survey scan of map ``f`` (dB).

        None without survey scans or when the scan shares nothing with the floor's.
        """
        if self.references is None:
            return None
        d = self._distances(tx, rssi)[self.ref_blocks[f]]
        return d if np.isfinite(d).any() else None

    def scan_neighbours(
        self, f: int, tx: np.ndarray, rssi: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Return the per-scan k-NN's neighbours on map ``f``: positions (k, 2), weights (k,).

        None without survey scans or when the scan shares nothing with the floor's.
        """
        key = _scan_key(tx, rssi)
        cached = self._near
        if cached is not None and cached[0] == key and cached[1] == f:
            return cached[2]
        d = self._floor_distances(f, tx, rssi)
        near = (
            None
            if d is None or self.references is None
            else self.references.neighbours(d, self.ref_blocks[f])
        )
        # the tracker asks twice a scan (the fix's density, the radius): cached as ``_distances``
        self._near = (key, f, near)
        return near

    def fix_log_density(
        self, f: int, tx: np.ndarray, rssi: np.ndarray, points: np.ndarray | None = None
    ) -> np.ndarray | None:
        """Return the tempered log-density of the scan's k-NN fix at points of map ``f``.

        The fix is a Gaussian mixture at the per-scan k-NN's neighbours (their
        k-NN weights, spread ``fix_sigma_m``): where the pooled emission asks
        how well the survey scans around a point match, this asks where the
        best-matching scans anywhere on the floor are. Relative to the
        mixture's peak (0 there, at most ``fix_max_nats`` below), times
        ``fix_nats`` and the emission weight. None without survey scans or
        when the scan shares nothing with the floor's.

        Parameters
        ----------
        points : ndarray of int, optional
            Point indices to evaluate (default every point of the map).
        """
        p = self.params
        near = self.scan_neighbours(f, tx, rssi) if p.fix_nats != 0.0 else None
        if near is None:
            return None
        centres, weight = near
        xy = self.xy[f] if points is None else self.xy[f][points]
        log_rel = mixture_log_density(
            xy, np.ascontiguousarray(centres), weight, p.fix_sigma_m, p.fix_max_nats
        )
        return p.emission_weight * p.fix_nats * log_rel

    def level_offset(self, f: int, point: int, tx: np.ndarray, rssi: np.ndarray) -> float | None:
        """Return how much louder (dB) the scan heard than the survey scans around a point.

        The survey scans are those point ``point`` of map ``f`` pools, chosen by
        place, not by how well they match: scans chosen by match would be the
        ones as loud as this phone, and hide its offset. None without survey
        scans there or anything shared.
        """
        if self.references is None:
            return None
        row = self.point_start[f] + point
        near = self.pool_indices[self.pool_indptr[row] : self.pool_indptr[row + 1]]
        if near.size == 0:
            return None
        return self.references.level_offset(tx, rssi, near)

    def best_match(self, f: int, tx: np.ndarray, rssi: np.ndarray) -> float | None:
        """Return the scan's distance (dB) to the nearest survey scan of map ``f``.

        None without survey scans or when the scan shares nothing with the floor's.
        """
        d = self._floor_distances(f, tx, rssi)
        return None if d is None else float(d.min())

    def knn(self, f: int, tx: np.ndarray, rssi: np.ndarray, k: int) -> np.ndarray:
        """Return the weighted mean position (m) of the k nearest fingerprints on map ``f``.

        With survey scans, the nearest are scans of the map's floor weighted as
        the per-scan k-NN weighs them; otherwise the map's pooled points.
        """
        d = self._floor_distances(f, tx, rssi)
        if d is not None and self.references is not None:
            return self.references.weighted_mean(d, self.ref_blocks[f], k)
        d2 = self.fingerprints.sq_distances(tx, rssi)
        start = sum(self.surveyed_points[:f])
        d = np.sqrt(d2[start : start + self.surveyed_points[f]])
        k = min(k, d.size)
        near = np.argpartition(d, k - 1)[:k]
        # w = 1 / (d + ε)
        w = 1.0 / (d[near] + 1e-3)
        return w @ self.xy[f][near] / w.sum()


def _scan_key(tx: np.ndarray, rssi: np.ndarray) -> bytes:
    """Return the bytes that identify a scan in the model's last-scan caches."""
    return np.asarray(tx, np.int64).tobytes() + np.asarray(rssi, np.float64).tobytes()
