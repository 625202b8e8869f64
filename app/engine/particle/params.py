"""Constants of the particle filter: the patent's values, the motion noise, the batching."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from app.engine.pathloss import PathLossParams


@dataclass(frozen=True)
class ParticleFilterParams:
    """Constants of the particle filter; the patent's values are the defaults.

    Attributes
    ----------
    n_particles : int
        N, particles per floor filter.
    dead_weight : float
        ε: a particle with w ≤ ε is dead.
    rescatter_after_ms : int
        T_r: scatter anew when the floor has had no radio for this long.
    min_alive : int
        N_a: fewer live particles than this forces a rescatter.
    quality_threshold : float
        S_q: transmitters with σ / B above it are ignored.
    update_interval_ms : int
        T_u: shortest interval between two weight updates.
    min_transmitters : int
        N_emin: visible transmitters needed for mutation and centre sampling.
    n_mutate : int
        N_m: particles rescattered at every weight update.
    n_centre : int
        N_c: particles placed around the sampling centre.
    centre_variance_m2 : float
        d_ce: the patent calls it the dispersion (variance) of the centre
        sampling, so the standard deviation is √d_ce ≈ 2.24 m.
    resample_n : float
        N_r: resample when Σ w² > 1 / N_r, i.e. when the effective sample size
        1 / Σ w² falls below N_r.
    step_length_std_m : float
        Standard deviation (m) of a step's length per particle: σ_d of the
        dead-reckoning patent (CN106028450).
    heading_std_deg : float
        Standard deviation (deg) of a step's heading per particle: the
        dead-reckoning heading error measured on ILC site1 (``PdrParams``).
    walk_speed_mps : float
        Random-walk motion without an inertial stream: the speed of each
        particle is Rayleigh with this scale σ_v (m/s), i.e. its velocity
        components are N(0, σ_v²) (pedestrians: mean speed σ_v √(π/2) ≈ 1.25 m/s).
    walk_turn_std_deg : float
        Random-walk motion: standard deviation (deg) of a particle's change of
        direction per √s; particles keep their direction between windows, so
        the cloud follows straight motion, and wall hits turn them.
    max_move_m : float
        Longest move (m) of a particle in one update; longer moves (a random
        walk after a gap) are shortened to it. Sets the raster padding.
    pathloss : PathLossParams
        Path-loss constants and the expected-RSSI raster.
    unheard_dbm : float
        RSSI (dBm) the raster takes at a radio map's reference point whose
        survey scans never heard the transmitter: below phones' sensitivity.
    chunk : int
        Filters per numpy call: 64 amortise numpy's per-call cost over
        64 × N particles (measured against 16, 32 and 128 with ``bench.engine``).
    kernel : {"numba", "numpy"}
        Who runs the per-particle loops (moves and the wall check, likelihood,
        resampling, estimate): the compiled ``kernel`` module, or the numpy
        reference it reproduces.
    """

    n_particles: int = 1000
    dead_weight: float = 1e-8
    rescatter_after_ms: int = 45_000
    min_alive: int = 100
    quality_threshold: float = 1.5
    update_interval_ms: int = 1000
    min_transmitters: int = 3
    n_mutate: int = 50
    n_centre: int = 10
    centre_variance_m2: float = 5.0
    resample_n: float = 600.0
    step_length_std_m: float = 0.1
    heading_std_deg: float = 15.0
    walk_speed_mps: float = 1.0
    walk_turn_std_deg: float = 30.0
    max_move_m: float = 10.0
    pathloss: PathLossParams = field(default_factory=PathLossParams)
    unheard_dbm: float = -100.0
    chunk: int = 64
    kernel: Literal["numba", "numpy"] = "numba"
