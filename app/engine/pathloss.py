"""Log-distance path loss (Eurasian patent 047000): model, inverse, quality filter, likelihood.

A transmitter heard at range r has mean RSSI ``A - B ln r`` with standard
deviation ``sigma`` (the patent's d). The inverse ``r = exp((A - rssi) / B)``
ranks transmitters by proximity; ``sigma / B`` measures how much a 1-sigma
RSSI error stretches the range estimate, so transmitters above S_q are left out.

The particle filter evaluates the Gaussian likelihood of every reading at
every particle. Computing ``A - B ln r`` there (sqrt, log per particle and
reading) costs about a millisecond per update; :class:`RssiGrid` precomputes
each transmitter's expected RSSI on a raster of the floor once, quantised to
one byte, and the likelihood becomes a gather plus a few multiply-adds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PathLossParams:
    """Constants of the path-loss model and of its precomputed rasters.

    Attributes
    ----------
    min_range_m : float
        Ranges below this are clamped before ``ln r``: the log model diverges at
        the transmitter and nobody carries a phone closer than this to a
        ceiling access point.
    receiver_height_m : float
        Height (m) of the receiving device above the floor; ranges are 3-D
        between it and the transmitter's ``z``. A phone held in hand or worn
        on a lanyard is at 1.0 to 1.4 m.
    grid_cell_m : float
        Cell side (m) of the expected-RSSI rasters: 1 m keeps a
        320 × 232 m floor at 74,000 bytes per transmitter, while the model's
        slope beyond 3 m (B / r ≤ 7 dB/m for B = 20) stays within a σ per cell.
    code_floor_dbm : float
        RSSI (dBm) of code 0 of the one-byte quantisation.
    code_step_db : float
        RSSI step (dB) per code: 0.5 dB spans -150 to -22.5 dBm, and rounding
        adds at most 0.25 dB, far below the 4 to 8 dB of real readings.
    """

    min_range_m: float = 0.5
    receiver_height_m: float = 1.2
    grid_cell_m: float = 1.0
    code_floor_dbm: float = -150.0
    code_step_db: float = 0.5


def expected_rssi(r: np.ndarray, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Return the model RSSI (dBm) at ranges ``r`` (m), broadcasting ``A`` (dBm) and ``B`` (dB)."""
    # rssi(r) = A - B ln r
    return A - B * np.log(r)


def range_from_rssi(rssi: np.ndarray, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Return the range (m) the model assigns to ``rssi`` (dBm)."""
    # r(rssi) = exp((A - rssi) / B)
    return np.exp((A - rssi) / B)


def reliable(sigma: np.ndarray, B: np.ndarray, s_q: float) -> np.ndarray:
    """Return which transmitters pass the patent's quality filter ``sigma / B <= S_q``.

    Transmitters without a fitted model (NaN or non-positive ``B``) fail.
    """
    sigma = np.asarray(sigma, dtype=float)
    B = np.asarray(B, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        # d / B <= S_q
        ok = (B > 0) & (sigma / B <= s_q)
    return ok & np.isfinite(sigma)


def log_likelihood(rssi: np.ndarray, expected: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Return the Gaussian log-likelihood of readings, summed over the last axis.

    Parameters
    ----------
    rssi, expected, sigma : ndarray, broadcastable, (..., n)
        Measured RSSI s_i (dBm), model RSSI ŝ_i (dBm) and standard deviation σ_i (dB).

    Returns
    -------
    ndarray, shape (...)
        Σ_i ln p_i with p_i = exp(-(s_i - ŝ_i)² / 2σ_i²) / (σ_i √(2π)).
    """
    z = (rssi - expected) / sigma
    # ln p_i = -z_i² / 2 - ln σ_i - ln √(2π)
    return np.sum(-0.5 * z * z - np.log(sigma) - 0.5 * np.log(2.0 * np.pi), axis=-1)


def ranges_3d(
    xy: np.ndarray, tx_xyz: np.ndarray, receiver_height: float, min_range: float
) -> np.ndarray:
    """Return ranges (m) from points on the floor to transmitters.

    Parameters
    ----------
    xy : ndarray, shape (..., 2)
        Receiver positions (m); the receiver is ``receiver_height`` above the floor.
    tx_xyz : ndarray, shape (T, 3)
        Transmitter positions (m), z above the same floor.

    Returns
    -------
    ndarray, shape (..., T)
        max(min_range, |p - tx|).
    """
    d = xy[..., None, :] - tx_xyz[:, :2]
    dz = tx_xyz[:, 2] - receiver_height
    # r = √(Δx² + Δy² + Δz²)
    r = np.sqrt(np.sum(d * d, axis=-1) + dz * dz)
    return np.maximum(r, min_range)


def fit_pathloss(r: np.ndarray, rssi: np.ndarray, min_range: float) -> tuple[float, float, float]:
    """Fit ``rssi = A - B ln r`` by least squares.

    Parameters
    ----------
    r : ndarray, shape (n,)
        Ranges (m) at which the readings were taken, clamped at ``min_range``.
    rssi : ndarray, shape (n,)
        Readings (dBm).

    Returns
    -------
    A, B, sigma
        Intercept (dBm at 1 m), slope (dB per ln-metre) and the residual
        standard deviation (dB, n - 2 degrees of freedom).
    """
    u = -np.log(np.maximum(np.asarray(r, dtype=float), min_range))
    rssi = np.asarray(rssi, dtype=float)
    if rssi.size < 3:
        raise ValueError("need at least three readings to fit A, B and sigma")
    design = np.column_stack([np.ones_like(u), u])
    # [A, B] = argmin |rssi - A - B u|², u = -ln r
    (A, B), *_ = np.linalg.lstsq(design, rssi, rcond=None)
    resid = rssi - (A + B * u)
    # σ² = Σ e² / (n - 2)
    sigma = float(np.sqrt(resid @ resid / (rssi.size - 2)))
    return float(A), float(B), sigma


@dataclass(frozen=True, eq=False)
class RssiGrid:
    """Expected RSSI of a floor's transmitters on a raster, one byte per value.

    Attributes
    ----------
    origin : ndarray, shape (2,)
        x, y (m) of the lower-left corner of cell (0, 0).
    cell : float
        Cell side (m).
    shape : tuple of int
        (ny, nx).
    codes : ndarray of uint8, shape (ny * nx, T)
        Code of the model RSSI of transmitter t at the centre of each cell,
        cells row-major; RSSI = ``floor_dbm + step_db * code``. Cell-major,
        so that the transmitters a particle hears are one cache line or a few
        apart.
    floor_dbm, step_db : float
        Decoding of the codes.
    """

    origin: np.ndarray
    cell: float
    shape: tuple[int, int]
    codes: np.ndarray
    floor_dbm: float
    step_db: float

    @property
    def n_cells(self) -> int:
        """Cells per transmitter plane."""
        return self.shape[0] * self.shape[1]

    def cell_index(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Return the flat cell index (intp) of points ``x``, ``y`` (m), clamped to the raster."""
        ny, nx = self.shape
        inv = 1.0 / self.cell
        # Python floats keep float32 particles in float32
        x0, y0 = float(self.origin[0]), float(self.origin[1])
        # col = ⌊(x - x₀) / c⌋, row = ⌊(y - y₀) / c⌋, both clamped
        col = np.clip(((x - x0) * inv).astype(np.intp), 0, nx - 1)
        row = np.clip(((y - y0) * inv).astype(np.intp), 0, ny - 1)
        # k = row · nx + col
        return row * nx + col

    def decode(self, codes: np.ndarray) -> np.ndarray:
        """Return the RSSI (dBm) of codes."""
        # rssi = floor + step · code
        return self.floor_dbm + self.step_db * codes.astype(float)


def build_rssi_grid(
    bounds: tuple[float, float, float, float],
    tx_xyz: np.ndarray,
    A: np.ndarray,
    B: np.ndarray,
    params: PathLossParams,
) -> RssiGrid:
    """Precompute the expected RSSI of transmitters over a floor's extent.

    Parameters
    ----------
    bounds : (xmin, ymin, xmax, ymax)
        Extent (m) to cover.
    tx_xyz : ndarray, shape (T, 3)
        Transmitter positions (m).
    A, B : ndarray, shape (T,)
        Path-loss parameters; transmitters with NaN get the lowest code.
    """
    xmin, ymin, xmax, ymax = bounds
    c = params.grid_cell_m
    nx = max(1, int(np.ceil((xmax - xmin) / c)))
    ny = max(1, int(np.ceil((ymax - ymin) / c)))
    origin = np.array([xmin, ymin], dtype=float)
    xs = xmin + (np.arange(nx) + 0.5) * c
    ys = ymin + (np.arange(ny) + 0.5) * c
    centres = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    tx_xyz = np.asarray(tx_xyz, dtype=float).reshape(-1, 3)
    codes = np.zeros((ny * nx, tx_xyz.shape[0]), dtype=np.uint8)
    # One transmitter at a time keeps the float temporaries at one plane.
    for t in range(tx_xyz.shape[0]):
        if not (np.isfinite(A[t]) and np.isfinite(B[t])):
            continue
        r = ranges_3d(centres, tx_xyz[t : t + 1], params.receiver_height_m, params.min_range_m)
        rssi = expected_rssi(r[:, 0], A[t], B[t])
        # code = round((rssi - floor) / step), clipped to a byte
        q = np.rint((rssi - params.code_floor_dbm) / params.code_step_db)
        codes[:, t] = np.clip(q, 0, 255).astype(np.uint8)
    return RssiGrid(
        origin=origin,
        cell=c,
        shape=(ny, nx),
        codes=codes,
        floor_dbm=params.code_floor_dbm,
        step_db=params.code_step_db,
    )


def grid_log_likelihood(
    grid: RssiGrid,
    cells: np.ndarray,
    tx: np.ndarray,
    rssi: np.ndarray,
    weight: np.ndarray,
) -> np.ndarray:
    """Return the Gaussian log-likelihood of each particle, up to a per-row constant.

    Particles on the same grid cell share their likelihood, and a converged
    cloud sits on a few dozen cells (plus the handful just mutated or centre
    sampled), so the sum over readings is taken once per distinct cell of
    each row and gathered back: about a tenth of the work of one sum per
    particle.

    Each cell's sum runs over the readings in column order with padding
    adding exact zeros, so a row's result does not depend on how far other
    rows of the batch pad the table: resampling would amplify a last-bit
    difference into a different track depending on the device's batch mates.

    Parameters
    ----------
    grid : RssiGrid
        Expected RSSI of the floor's transmitters.
    cells : ndarray of intp, shape (D, N)
        Flat grid cell of each particle (``grid.cell_index``).
    tx : ndarray of intp, shape (D, M)
        Column of ``grid.codes`` of each heard transmitter; padding may be any valid column.
    rssi : ndarray, shape (D, M)
        Mean RSSI (dBm) of each heard transmitter over the window.
    weight : ndarray, shape (D, M)
        n_m / (2 σ_m²): readings of the transmitter in the window over twice
        its variance (dB⁻²); 0 for padding.

    Returns
    -------
    ndarray of float32, shape (D, N)
        -Σ_m n_m (s̄_m - ŝ_m)² / (2 σ_m²). Summing per reading instead differs
        by Σ (s_k - s̄_m)² / 2σ_m², the same for every particle, so the
        normalised weights are identical.
    """
    d, n = cells.shape
    n_cells, n_tx = grid.codes.shape
    step = grid.step_db
    # key = row · n_cells + cell: equal keys are one row's particles on one cell
    key = (cells + (np.arange(d) * n_cells)[:, None]).ravel()
    order = np.arange(key.size, dtype=np.int32)
    # the last particle written on a cell represents it; only written entries are read
    stamp = np.empty(d * n_cells, np.int32)
    stamp[key] = order
    rep = stamp[key]
    reps = np.flatnonzero(rep == order)
    row = reps // n
    # (R, M) code index of (representative's cell, transmitter m)
    itype = np.int32 if grid.codes.size < 2**31 else np.intp
    cell = cells.ravel()[reps].astype(itype)
    index = tx.astype(itype)[row]
    index += np.multiply(cell, n_tx, dtype=itype)[:, None]
    codes = grid.codes.reshape(-1).take(index)
    # s' = (s̄ - floor) / step: the reading in code units
    s_code = ((rssi - grid.floor_dbm) / step).astype(np.float32)
    # c'_m = -step² n_m / (2 σ_m²) turns code units back into dB
    c = (-weight * step * step).astype(np.float32)
    diff = codes - s_code[row]
    diff *= diff
    diff *= c[row]
    ll = np.zeros(reps.size, np.float32)
    for m in range(diff.shape[1]):
        # reading by reading, in column order: padding adds exact zeros
        ll += diff[:, m]
    value = np.empty(key.size, np.float32)
    value[reps] = ll
    return value[rep].reshape(d, n)
