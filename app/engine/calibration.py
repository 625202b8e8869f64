"""Transmitter calibration from survey walks: floor, position and path loss of each transmitter.

Every transmitter heard in the located survey scans gets the log-distance
model ``rssi = A - B ln r`` (the form of Eurasian patent 047000) fitted by robust least squares,
with ``r`` the 3-D distance from the transmitter, at a nominal height on its
floor, to the phone in the walker's hand. Where the map gives no position,
x and y are fitted too. Three things bias a naive fit and are modelled:

- **censoring**: phones report nothing below their sensitivity (about
  -95 dBm), so far from the transmitter only the lucky, strong readings
  exist and a fit on heard readings alone flattens the slope B. Scans near
  the transmitter that did not hear it enter as censored observations with
  likelihood ``m + (1 - m) Φ((s - rssi_pred) / σ)``: below the sensitivity
  ``s``, or missed anyway with probability ``m`` (scans are incomplete and
  cached repeats are dropped);
- **saturation**: readings at or above ``saturation_dbm`` only say the
  signal was at least that strong (one-sided residual);
- **multipath outliers**: a soft-L1 loss bounds the pull of any single
  reading.

The residual of a censored observation is ``sqrt(-2 ln L)``, so the sum of
squares is the negative log-likelihood of the censored (Tobit) model. σ is
re-estimated from the heard residuals (scaled MAD) and the fit repeated.

A transmitter belongs to the floor where its strongest readings are (mean of
the few strongest, among floors with enough readings); only that floor's
readings are fitted, as the model has no floor-attenuation term.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, fields

import numpy as np
from scipy import optimize, special
from scipy.spatial import cKDTree

from app.engine.pathloss import expected_rssi
from app.engine.radiomap import Survey
from app.engine.site import Emitters

PROGRESS_EVERY = 100
"""Transmitters fitted between two progress reports."""

MAD_TO_STD = 1.4826
"""σ of a Gaussian per unit of median absolute deviation."""


@dataclass(frozen=True)
class CalibrationParams:
    """Tunable constants of transmitter calibration.

    Attributes
    ----------
    tx_height_m : float
        Nominal height (m) of a transmitter above its floor (ceiling mounts).
    rx_height_m : float
        Height (m) of the phone held in front of the walker.
    sensitivity_dbm : float
        Weakest RSSI phones report: an unheard transmitter is below it.
    miss_prob : float
        Probability that a scan misses a transmitter it could hear.
    censor_radius_m : float
        Non-detections count as censored observations only within this
        distance (m) of the initial position; farther, the floor plan and
        walls decide more than distance does.
    max_censored : int
        At most this many censored scans per transmitter (the nearest ones).
    saturation_dbm : float
        Readings at or above this are saturated: only a lower bound.
    f_scale : float
        Soft-L1 scale in units of σ: residuals beyond it count linearly.
    sigma_init_db : float
        σ (dB) of the first fit, before it is estimated from the residuals.
    sigma_min_db : float
        Smallest σ (dB) used in the fit (phones quantise to 1 dB).
    iterations : int
        Fits run, each with σ from the previous one's residuals.
    min_readings : int
        Fewer heard readings on the floor: no fit (not enough data).
    min_spread_m : float
        Position is only fitted when the readings spread at least this far
        (RMS distance from their centroid, m); otherwise B and x, y trade off.
    strongest : int
        The floor and the initial position come from this many strongest readings.
    b_plausible : tuple of float
        Range of B (dB per ln-metre) a sound fit lands in: indoor path-loss
        exponents 2–4 with 10 log10 e ≈ 4.34 dB per ln-metre each, widened.
    b_bounds : tuple of float
        Bounds of B in the solver.
    a_bounds : tuple of float
        Bounds of A (dBm at 1 m) in the solver.
    position_margin_m : float
        A fitted position stays within the readings' bounding box widened by this (m).
    ble_window_ms : int
        BLE advertisements arrive one by one: those a moving receiver heard within one
        window of this length (ms) are taken as one scan, so that a beacon it did not
        hear in the window counts as not heard there.
    """

    tx_height_m: float = 3.0
    rx_height_m: float = 1.2
    sensitivity_dbm: float = -95.0
    miss_prob: float = 0.2
    censor_radius_m: float = 25.0
    max_censored: int = 300
    saturation_dbm: float = -30.0
    f_scale: float = 2.0
    sigma_init_db: float = 6.0
    sigma_min_db: float = 2.0
    iterations: int = 2
    min_readings: int = 10
    min_spread_m: float = 2.0
    strongest: int = 5
    b_plausible: tuple[float, float] = (5.0, 40.0)
    b_bounds: tuple[float, float] = (0.5, 80.0)
    a_bounds: tuple[float, float] = (-120.0, 0.0)
    position_margin_m: float = 15.0
    ble_window_ms: int = 1000


@dataclass(frozen=True)
class TransmitterFit:
    """One transmitter's calibration and its quality figures.

    Attributes
    ----------
    tx : int
        Site transmitter index.
    floor : int
        Floor index it belongs to.
    x, y, z : float
        Position (m, floor frame; z above the floor), fitted or known.
    A : float
        RSSI (dBm) at 1 m.
    B : float
        Slope (dB per ln-metre).
    sigma : float
        Robust standard deviation (dB) of the heard readings about the model.
    n_readings : int
        Heard readings fitted (on ``floor``).
    n_censored : int
        Censored scans (near, on ``floor``, not hearing it) fitted.
    spread_m : float
        RMS distance (m) of the heard readings from their centroid.
    converged : bool
        The solver reported convergence.
    plausible : bool
        Converged, enough readings and spread, B within ``b_plausible``.
    position_known : bool
        x, y came from the map and were not fitted.
    """

    tx: int
    floor: int
    x: float
    y: float
    z: float
    A: float
    B: float
    sigma: float
    n_readings: int
    n_censored: int
    spread_m: float
    converged: bool
    plausible: bool
    position_known: bool


@dataclass(frozen=True)
class PathLossFit:
    """Result of one robust fit: position (m), A, B, σ (dB), convergence."""

    xy: np.ndarray
    A: float
    B: float
    sigma: float
    converged: bool


def distances(tx_xy: np.ndarray, xy: np.ndarray, dz: float | np.ndarray) -> np.ndarray:
    """Return 3-D distances (m) from transmitter(s) ``tx_xy`` (…, 2) to points ``xy`` (…, 2).

    ``dz`` is the height difference (m), a scalar or one per point.
    """
    d = np.asarray(xy, dtype=float) - np.asarray(tx_xy, dtype=float)
    # r = sqrt(Δx² + Δy² + Δz²)
    return np.sqrt(np.sum(d * d, axis=-1) + dz * dz)


def _residuals(
    theta: np.ndarray,
    xy: np.ndarray,
    rssi: np.ndarray,
    censored_xy: np.ndarray,
    sigma: float,
    dz: float,
    known_xy: np.ndarray | None,
    params: CalibrationParams,
) -> np.ndarray:
    """Return the scaled residuals: heard readings, then censored scans."""
    tx_xy, A, B = (
        (known_xy, theta[0], theta[1]) if known_xy is not None else (theta[:2], *theta[2:])
    )
    pred = expected_rssi(distances(tx_xy, xy, dz), A, B)
    # e = (rssi - pred) / σ, one-sided (only pred < rssi counts) for saturated readings
    e = (rssi - pred) / sigma
    e = np.where(rssi >= params.saturation_dbm, np.maximum(e, 0.0), e)
    if censored_xy.shape[0] == 0:
        return e
    pred_c = expected_rssi(distances(tx_xy, censored_xy, dz), A, B)
    m = params.miss_prob
    # L = m + (1 - m) Φ((s - pred) / σ), residual sqrt(-2 ln L)
    log_phi = special.log_ndtr((params.sensitivity_dbm - pred_c) / sigma)
    log_l = np.logaddexp(np.log(m), np.log1p(-m) + log_phi)
    return np.concatenate([e, np.sqrt(np.maximum(-2.0 * log_l, 0.0))])


def _jacobian(
    theta: np.ndarray,
    xy: np.ndarray,
    rssi: np.ndarray,
    censored_xy: np.ndarray,
    sigma: float,
    dz: float,
    known_xy: np.ndarray | None,
    params: CalibrationParams,
) -> np.ndarray:
    """Return ∂ residuals / ∂ θ of ``_residuals``, shape (n + c, len(θ)).

    Analytic, so the solver does not spend len(θ) extra residual evaluations
    per iteration on finite differences (the bulk of a site's calibration time).
    """
    fit_xy = known_xy is None
    tx_xy, A, B = (theta[:2], theta[2], theta[3]) if fit_xy else (known_xy, theta[0], theta[1])

    def pred_and_grad(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = points - tx_xy
        r2 = np.sum(d * d, axis=1) + dz * dz
        # pred = A - B ln r, with ln r = ½ ln r²
        half_ln_r2 = 0.5 * np.log(r2)
        pred = A - B * half_ln_r2
        # ∂pred/∂A = 1, ∂pred/∂B = -ln r, ∂pred/∂t = B (p - t) / r²
        cols = [np.ones(points.shape[0]), -half_ln_r2]
        grad = np.column_stack([B * d / r2[:, None], *cols] if fit_xy else cols)
        return pred, grad

    pred, g = pred_and_grad(xy)
    # ∂e/∂θ = -∂pred/∂θ / σ; zero where a saturated reading's residual is clipped at 0
    jac = -g / sigma
    jac[(rssi >= params.saturation_dbm) & (rssi < pred)] = 0.0
    if censored_xy.shape[0] == 0:
        return jac
    pred_c, g_c = pred_and_grad(censored_xy)
    m = params.miss_prob
    z = (params.sensitivity_dbm - pred_c) / sigma
    log_l = np.logaddexp(np.log(m), np.log1p(-m) + special.log_ndtr(z))
    c = np.sqrt(np.maximum(-2.0 * log_l, 0.0))
    # ∂ln L/∂z = (1 - m) φ(z) / L, computed in logs
    log_pdf = -0.5 * z * z - 0.5 * np.log(2.0 * np.pi)
    dlogl_dz = np.exp(np.log1p(-m) + log_pdf - log_l)
    # c = sqrt(-2 ln L): ∂c = -∂ln L / c, with ∂z = -∂pred / σ
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(c > 1e-12, dlogl_dz / (c * sigma), 0.0)
    return np.vstack([jac, scale[:, None] * g_c])


def fit_path_loss(
    xy: np.ndarray,
    rssi: np.ndarray,
    params: CalibrationParams,
    *,
    censored_xy: np.ndarray | None = None,
    position: np.ndarray | None = None,
) -> PathLossFit:
    """Fit A, B (and the position unless given) to readings of one transmitter on one floor.

    Parameters
    ----------
    xy : ndarray, shape (n, 2)
        Positions (m) of the heard readings.
    rssi : ndarray, shape (n,)
        Their RSSI (dBm).
    params : CalibrationParams
        Heights, censoring, loss and bounds.
    censored_xy : ndarray, shape (c, 2), optional
        Positions of scans nearby that did not hear the transmitter.
    position : ndarray, shape (2,), optional
        Known x, y (m): only A and B are fitted.
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    rssi = np.asarray(rssi, dtype=float)
    cxy = np.zeros((0, 2)) if censored_xy is None else np.asarray(censored_xy, float).reshape(-1, 2)
    dz = params.tx_height_m - params.rx_height_m
    known = None if position is None else np.asarray(position, dtype=float)
    if known is None:
        top = np.argsort(-rssi, kind="stable")[: params.strongest]
        # initial position: power-weighted centroid of the strongest readings, w = 10^(rssi/10)
        w = 10.0 ** ((rssi[top] - rssi[top].max()) / 10.0)
        start_xy = w @ xy[top] / w.sum()
    else:
        start_xy = known
    # initial A, B: least squares of rssi on -ln r
    lnr = np.log(distances(start_xy, xy, dz))
    design = np.column_stack([np.ones_like(lnr), -lnr])
    (a0, b0), *_ = np.linalg.lstsq(design, rssi, rcond=None)
    a0 = float(np.clip(a0, params.a_bounds[0] + 1e-6, params.a_bounds[1] - 1e-6))
    b0 = float(np.clip(b0, params.b_bounds[0] + 1e-6, params.b_bounds[1] - 1e-6))
    if known is None:
        lo_xy = xy.min(axis=0) - params.position_margin_m
        hi_xy = xy.max(axis=0) + params.position_margin_m
        theta = np.array([start_xy[0], start_xy[1], a0, b0])
        lower = np.array([lo_xy[0], lo_xy[1], params.a_bounds[0], params.b_bounds[0]])
        upper = np.array([hi_xy[0], hi_xy[1], params.a_bounds[1], params.b_bounds[1]])
    else:
        theta = np.array([a0, b0])
        lower = np.array([params.a_bounds[0], params.b_bounds[0]])
        upper = np.array([params.a_bounds[1], params.b_bounds[1]])
    sigma = params.sigma_init_db
    converged = False
    for _ in range(params.iterations):
        res = optimize.least_squares(
            _residuals,
            np.clip(theta, lower, upper),
            bounds=(lower, upper),
            jac=_jacobian,
            loss="soft_l1",
            f_scale=params.f_scale,
            args=(xy, rssi, cxy, sigma, dz, known, params),
        )
        theta, converged = res.x, bool(res.success)
        heard = res.fun[: rssi.size] * sigma
        # σ = 1.4826 median |e - median e|
        sigma = max(
            params.sigma_min_db, MAD_TO_STD * float(np.median(np.abs(heard - np.median(heard))))
        )
    if known is None:
        return PathLossFit(theta[:2].copy(), float(theta[2]), float(theta[3]), sigma, converged)
    return PathLossFit(known.copy(), float(theta[0]), float(theta[1]), sigma, converged)


def transmitter_floor(floors: np.ndarray, rssi: np.ndarray, params: CalibrationParams) -> int:
    """Return the floor whose strongest readings are strongest (among floors with enough).

    Parameters
    ----------
    floors : ndarray of int, shape (n,)
        Floor of each reading of one transmitter.
    rssi : ndarray, shape (n,)
        The readings (dBm).
    """
    best, best_score, best_count = -1, -np.inf, 0
    for f in np.unique(floors):
        r = np.sort(rssi[floors == f])[::-1][: params.strongest]
        count = int(np.count_nonzero(floors == f))
        score = float(r.mean())
        enough = count >= params.min_readings
        if (enough, score) > (best_count >= params.min_readings, best_score):
            best, best_score, best_count = int(f), score, count
    return best


def calibrate(
    survey: Survey,
    params: CalibrationParams,
    *,
    known: dict[int, tuple[int, float, float, float]] | None = None,
    progress: Callable[[float], None] | None = None,
) -> list[TransmitterFit]:
    """Calibrate every transmitter with at least ``min_readings`` readings on its floor.

    Parameters
    ----------
    survey : Survey
        Located scans of all floors.
    params : CalibrationParams
        Fitting constants.
    known : dict, optional
        Transmitter index → (floor, x, y, z) from the map; those fit A, B, σ only.
    progress : callable, optional
        Called now and then with the fraction of transmitters done.

    Returns
    -------
    list of TransmitterFit
        One per calibrated transmitter, in transmitter order.
    """
    known = known or {}
    r_floor = survey.reading_floor()
    r_xy = survey.reading_xy()
    order = np.argsort(survey.reading_tx, kind="stable")
    tx_sorted = survey.reading_tx[order]
    cuts = np.flatnonzero(np.diff(tx_sorted)) + 1
    trees = {
        int(f): (
            np.flatnonzero(survey.scan_floor == f),
            cKDTree(survey.scan_xy[survey.scan_floor == f]),
        )
        for f in np.unique(survey.scan_floor)
    }
    out: list[TransmitterFit] = []
    groups = np.split(order, cuts) if order.size else []
    for done, idx in enumerate(groups):
        if progress is not None and done % PROGRESS_EVERY == 0:
            progress(done / len(groups))
        tx = int(survey.reading_tx[idx[0]])
        if tx in known:
            floor, kx, ky, kz = known[tx]
            position = np.array([kx, ky])
        else:
            floor = transmitter_floor(r_floor[idx], survey.reading_rssi[idx], params)
            position, kz = None, params.tx_height_m
        on = idx[r_floor[idx] == floor]
        if on.size < params.min_readings:
            continue
        xy, rssi = r_xy[on], survey.reading_rssi[on]
        # spread = sqrt(mean |p - p̄|²)
        spread = float(np.sqrt(np.mean(np.sum((xy - xy.mean(axis=0)) ** 2, axis=1))))
        if position is None and spread < params.min_spread_m:
            continue
        centre = position if position is not None else xy[np.argmax(rssi)]
        scans, tree = trees[floor]
        near = np.asarray(tree.query_ball_point(centre, params.censor_radius_m), dtype=np.int64)
        near = scans[near]
        heard_scans = survey.reading_scan[on]
        near = near[~np.isin(near, heard_scans)]
        if near.size > params.max_censored:
            d = np.linalg.norm(survey.scan_xy[near] - centre, axis=1)
            near = near[np.argsort(d, kind="stable")[: params.max_censored]]
        p = params
        tx_params = p if position is None else _with_height(p, kz)
        fit = fit_path_loss(
            xy, rssi, tx_params, censored_xy=survey.scan_xy[near], position=position
        )
        plausible = fit.converged and p.b_plausible[0] <= fit.B <= p.b_plausible[1]
        out.append(
            TransmitterFit(
                tx=tx,
                floor=int(floor),
                x=float(fit.xy[0]),
                y=float(fit.xy[1]),
                z=float(kz),
                A=fit.A,
                B=fit.B,
                sigma=fit.sigma,
                n_readings=int(on.size),
                n_censored=int(near.size),
                spread_m=spread,
                converged=fit.converged,
                plausible=bool(plausible),
                position_known=position is not None,
            )
        )
    return out


def _with_height(params: CalibrationParams, z: float) -> CalibrationParams:
    """Return the params with the transmitter height replaced by a known one."""
    values = asdict(params)
    values["tx_height_m"] = float(z)
    return CalibrationParams(**values)


def fits_to_arrays(fits: list[TransmitterFit]) -> dict[str, np.ndarray]:
    """Return the fits as aligned arrays, one per field, for tables and storage."""
    return {
        f.name: np.array([getattr(fit, f.name) for fit in fits]) for f in fields(TransmitterFit)
    }


def predict_rssi(
    fits: dict[str, np.ndarray], tx: np.ndarray, xy: np.ndarray, params: CalibrationParams
) -> np.ndarray:
    """Return the modelled RSSI (dBm) of transmitters ``tx`` (n,) at phone positions ``xy`` (n, 2).

    ``fits`` is ``fits_to_arrays`` output; NaN for transmitters without a fit.
    """
    tx = np.asarray(tx, dtype=np.int64)
    row = np.full(int(max(fits["tx"].max(initial=-1), tx.max(initial=-1))) + 1, -1)
    row[fits["tx"].astype(np.int64)] = np.arange(fits["tx"].size)
    r = row[tx]
    ok = r >= 0
    out = np.full(tx.size, np.nan)
    rr = r[ok]
    dz = fits["z"][rr] - params.rx_height_m
    tx_xy = np.column_stack([fits["x"][rr], fits["y"][rr]])
    out[ok] = expected_rssi(distances(tx_xy, xy[ok], dz), fits["A"][rr], fits["B"][rr])
    return out


def to_emitters(fits: list[TransmitterFit], ids: tuple[str, ...]) -> Emitters:
    """Return the site transmitter table with the fitted floor, position and path loss.

    Rows follow ``ids``; transmitters without a fit get floor -1 and NaN values.
    """
    n = len(ids)
    floor = np.full(n, -1, dtype=np.int32)
    xyz = np.full((n, 3), np.nan)
    A, B, sigma = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    for fit in fits:
        floor[fit.tx] = fit.floor
        xyz[fit.tx] = (fit.x, fit.y, fit.z)
        A[fit.tx], B[fit.tx], sigma[fit.tx] = fit.A, fit.B, fit.sigma
    return Emitters(ids=tuple(ids), floor=floor, xyz=xyz, A=A, B=B, sigma=sigma)
