"""Tunable constants of the fingerprint + inertial HMM (CN106028450)."""

from __future__ import annotations

from dataclasses import dataclass, field

from app.engine.hmm.floor_classifier import FloorClassifierParams
from app.engine.scan_knn import ScanKnnParams
from app.engine.scans import ScanParams


@dataclass(frozen=True)
class HmmParams:
    """Tunable constants of the fingerprint + inertial HMM.

    Attributes
    ----------
    k : int
        Neighbours of the k-NN initial position (the patent's 3–5).
    missing_dbm : float
        RSSI of a missing reading in the k-NN distance.
    init_std_m : float
        Spread (m) of the initial distribution around the k-NN position.
    step_length_std_m : float
        σ_d of a step's length (m), the patent's 0.1 m.
    heading_std_deg : float
        σ_φ of a step's heading (degrees): PDR headings on ILC site1 are off by
        about 10° in median (``locus eval pdr``), i.e. σ ≈ 15° if Gaussian.
    walk_noise_m2_per_s : float
        Random-walk variance (m²/s) added between scans: steps PDR missed or
        mis-sized.
    transition_threshold : float
        P_T: reference points whose transition probability falls below this
        are dropped from the distribution (the sparse support).
    kernel_sigmas : float
        The transition kernel is cut at this many standard deviations.
    emission_weight : float
        Exponent tempering the product of per-transmitter likelihoods.
    floor_weight : float
        Exponent tempering the same likelihoods when they weigh floors
        against each other (a floor's evidence is its mean likelihood);
        chosen apart from ``emission_weight`` since one scan can be sure of
        its floor long before it is sure of its position.
    loglik_floor : float
        Floor (nats) of one heard transmitter's log-likelihood at a point.
    knn_nats_per_db : float
        Where the maps carry their survey scans, a point's untempered
        log-likelihood falls by this much per dB its soft-nearest survey
        scans match the scan worse than the best survey scan anywhere
        (tempered by ``emission_weight``: at 0.2, 1 nat per dB).
    knn_pool_m : float
        Bandwidth (m) of the Gaussian kernel pooling survey scans into a point.
    knn_radius_m : float
        Survey scans farther than this (m) from a point do not describe it.
    reach_m : float
        Points extend this far (m) from the survey scans onto the walkable
        plan, each scored as the survey scans nearest it, so a walker the
        survey never passed can be followed there; 0 keeps the radio map's
        points (within its 3 m). Far enough to cover the walkable plan of a
        surveyed building, so that how far held-out walkers stray from the
        survey is no constant of the site: a shorter reach loses the walkers
        who stray past it, a longer one adds little.
    reach_scans : int
        A point with no survey scan within ``knn_radius_m`` pools this many of
        its nearest scans; the error hardly depends on how many.
    knn_pool_db : float
        Temperature (dB) of the soft minimum of the pooled scans' distances:
        near 1 dB a point is as good as its single best survey scan, a match
        that phone noise (4–6 dB) makes partly luck; at 3 dB the few best
        scans around it count; much wider, poor matches count nearly as much
        as good ones.
    fix_nats : float
        Weight of the per-scan k-NN fix in the emission (before tempering):
        a point's log-likelihood also counts this many times the log-density,
        at the point, of a Gaussian mixture at the scan's k-NN neighbours.
        The pooled emission says how well the survey scans near a point
        match; the fix says where on the floor the best matches are, and
        pulls a track that has drifted into a region of middling matches
        back to them. 0 turns it off. A build replays held-out walks with
        each of ``FIX_WEIGHT_CANDIDATES`` (``app.engine.tuning``); its error
        at each is the build's ``hmm_walk_error_m_by_fix_weight``, which
        ``locus eval ilc`` prints.
    fix_sigma_m : float
        Spread (m) of each neighbour's component: about the per-scan k-NN's
        own error. A site's build sets it to the root mean square of its
        held-out k-NN errors (the default is about what site1's build sets:
        ``locus eval ilc`` prints the build's ``fix_sigma_m``).
    offset_prior_scans : float
        The device's RSSI offset, taken off every scan before matching, is
        the mean level difference of its scans from the survey scans made
        where the posterior is surest, shrunk towards 0 by a prior worth this
        many scans. Phones of different makes hear the same access point
        several dB apart, and one several dB louder or quieter than the
        survey's phones matches the wrong places. The offset takes back part
        of that loss within a walk of a minute or two (a phone tracked longer
        converges further), at a small cost on phones like the survey's;
        ``locus eval ilc --rssi-offset 6`` replays the held-out walks so
        shifted. Scans chosen by match rather than by place hide the offset
        (they are the ones as loud as the phone) and recovered less.
    offset_max_db : float
        The running offset stays within ± this (dB).
    fix_max_nats : float
        The fix's log-density counts at most this far below its peak, so a
        wrong fix cannot rule a point out alone.
    knn_max_db : float
        A point's distance counts at most this much (dB) above the best.
    unmapped_dbm : float
        Mean RSSI (dBm) assumed at points where a transmitter was never heard:
        the sensitivity floor.
    unmapped_var_db2 : float
        Variance (dB²) around ``unmapped_dbm``.
    unmapped_detect : float
        Detection rate of a transmitter absent from a floor's map.
    floor_switch_prob : float
        Probability per scan that the floor changes.
    floor_switch_posterior : float
        Belief another floor must reach before the tracked floor changes. A
        belief nearer 1 follows a change of floor later, with no fewer
        positions on a wrong floor; a lower one costs the positions on the
        right floor some accuracy. ``locus eval ilc-floor-change`` prints how
        soon the engine follows a change of floor.
    floor_classifier_weight : float
        Temper of the per-scan floor classifier's log-probabilities added to
        each scan's floor evidence (``app.engine.hmm.floor_classifier``); 0
        leaves floors to the radio map's evidence alone. A build chooses it
        on held-out walks joined across floors.
    floor_classifier : FloorClassifierParams
        Constants of that classifier.
    relocate_margin : float
        Restart from k-NN when the best point of the floor explains the scan
        better than the predicted distribution by more than this (nats,
        tempered).
    emit_every_ms : int
        Without steps or scans, still emit an estimate this often.
    imu_wait_ms : int
        A scan is used once IMU samples this much later have arrived, so the
        steps before it are known.
    imu_timeout_ms : int
        If the IMU stream lags the radio by more than this, scans go ahead without it.
    min_accuracy_m : float
        Smallest accuracy radius reported (m): the grid and the survey's own error.
    max_reading_age_ms : int
        A reading this much older than the newest one heard is a cached
        repeat (a client sending per-reading last-seen times reports them
        with every scan) and is not used.
    scans : ScanParams
        How readings are grouped into scans.
    references : ScanKnnParams
        The per-scan k-NN over the survey scans behind the emission, the k-NN
        fix and the radius (the site's build chooses its k and weight power).
    accuracy_floor_m : float
        Error (m) added in quadrature to the posterior's 68% radius: the
        posterior knows the maps' noise, not how far the fingerprints
        themselves are from the truth. The server sets it per site to the
        median held-out error of its radio-map build; without it the radius
        holds far fewer than 68% of the errors (``locus eval ilc`` prints the
        share it holds, "in acc.").
    radius_temper : float
        Exponent τ on the posterior before its spread is taken for the radius
        (p_j^τ, renormalised): the emission makes the posterior sharper than
        the fingerprints resolve, so its own spread hardly ranks the errors;
        tempered, with the per-scan k-NN's disagreement added, it ranks them
        better (``locus eval ilc`` prints the radius's rank correlation with
        the error, "acc. rank").
    radius_match_db : float
        The radius grows with the last scan's distance (dB) to its nearest
        survey scan of the floor, relative to this typical distance (ILC
        site1's phones'): a scan unlike any in the survey was heard where the
        survey is sparse or the radio changed, so the radius ranks the errors
        better. And since a denser survey matches closer, a scale calibrated
        on maps built from fewer walks (the build's folds) still holds about
        68% of the errors on the full maps, where without this factor the
        radius comes out too wide there.
    radius_match_min_db : float
        Smallest best-match distance (dB) counted: an exact match is luck.
    radius_match_tau_s : float
        Time constant (s) with which that factor follows the scans (0: the
        last scan's alone): how well a device's scans have been matching the
        survey for the last half minute says more about its errors than the
        last scan does.
    radius_scale : float
        Factor on the posterior's 68% radius before the floor is added: the
        build shrinks it where the posterior's spread alone holds more than
        68% of the held-out errors (a radius too wide says as little as one
        too narrow).
    learn_motion : bool
        Learn the device's heading bias and step-length scale online from its
        scans' k-NN fixes (``motion_fit.MotionFit``) and correct its steps
        by them: a phone carried turned against the walking direction, or a
        stride unlike the survey walkers'.
    motion_prior_m2 : float
        Weight (m² of step-track spread) of the prior that the device's steps
        need no correction.
    motion_gate : float
        A learned rotation or scale counts only as far as it stands out of its
        own noise (the k-NN fix's spread ``fix_sigma_m`` over the track's):
        by c² / (c² + g σ²), so that a phone whose steps need no correction
        keeps them. The learned motion pays most where the steps are wrong:
        ``locus eval ilc --heading-offset 90`` prints the HMM with and
        without it on phones carried turned.
    motion_tau_s : float
        Time constant (s) with which old scans stop counting in that fit.
    motion_min_scale, motion_max_scale : float
        Bounds of the learned step-length scale.
    """

    k: int = 4
    missing_dbm: float = -100.0
    init_std_m: float = 5.0
    step_length_std_m: float = 0.1
    heading_std_deg: float = 15.0
    walk_noise_m2_per_s: float = 0.05
    transition_threshold: float = 1e-6
    kernel_sigmas: float = 3.0
    emission_weight: float = 0.2
    floor_weight: float = 0.2
    loglik_floor: float = -8.0
    knn_nats_per_db: float = 5.0
    knn_pool_m: float = 1.5
    knn_radius_m: float = 3.0
    knn_pool_db: float = 3.0
    reach_m: float = 20.0
    reach_scans: int = 16
    knn_max_db: float = 30.0
    fix_nats: float = 10.0
    fix_sigma_m: float = 8.0
    fix_max_nats: float = 30.0
    offset_prior_scans: float = 10.0
    offset_max_db: float = 15.0
    unmapped_dbm: float = -95.0
    unmapped_var_db2: float = 36.0
    unmapped_detect: float = 0.02
    floor_switch_prob: float = 1e-3
    floor_switch_posterior: float = 0.8
    floor_classifier_weight: float = 0.0
    floor_classifier: FloorClassifierParams = field(default_factory=FloorClassifierParams)
    relocate_margin: float = 10.0
    emit_every_ms: int = 1000
    imu_wait_ms: int = 100
    imu_timeout_ms: int = 3000
    min_accuracy_m: float = 1.0
    accuracy_floor_m: float = 0.0
    radius_temper: float = 0.05
    radius_match_db: float = 6.0
    radius_match_min_db: float = 1.0
    radius_match_tau_s: float = 30.0
    radius_scale: float = 1.0
    max_reading_age_ms: int = 3000
    learn_motion: bool = True
    motion_prior_m2: float = 50.0
    motion_gate: float = 9.0
    motion_tau_s: float = 120.0
    motion_min_scale: float = 0.6
    motion_max_scale: float = 1.6
    scans: ScanParams = field(default_factory=ScanParams)
    references: ScanKnnParams = field(default_factory=ScanKnnParams)
