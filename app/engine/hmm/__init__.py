"""WiFi fingerprint + inertial hidden Markov model (CN106028450, online phase).

The hidden state is the reference point the phone is at; its distribution over
one floor's reference points is carried from scan to scan:

1. **Initial position** by k-NN in RSSI space (k = 3–5); the distribution
   starts as a Gaussian of ``init_std_m`` around it, times the first scan's
   emission.
2. **Transition** from the PDR steps taken since the last scan: each step's
   length and heading are Gaussian (σ_d = 0.1 m, σ_φ), so the accumulated
   displacement D is Gaussian with covariance Σ = Σ_k (σ_d² u_k u_kᵀ +
   (L_k σ_φ)² n_k n_kᵀ) (u along the step, n across it), plus slow random
   walk for missed steps and the grid's own quantisation. On the regular
   grid this transition is a convolution of the distribution with a shifted
   Gaussian kernel, computed only over the bounding box of the points whose
   probability exceeds P_T; mass moved off the reference points (off the
   walkable, surveyed area) is lost, which is the map constraint. Each step
   is first turned and scaled by the device's own heading bias and stride,
   learned online from how its raw step track lies against its scans' k-NN
   fixes (``motion_fit``).
3. **Emission**: the product over transmitters of Gaussians with the point's
   mean and variance, in the log domain, with the point's detection rate for
   heard and unheard transmitters alike (missing signals are evidence). Each
   transmitter's term is floored so one multipath outlier cannot veto a
   point, and the sum is tempered (readings of one scan are correlated and
   the map is noisy). Where the maps carry their survey scans, a point's
   evidence is instead how well the survey scans around it match the scan
   (``app.engine.scan_knn``), plus a Gaussian mixture at the scan's k-NN
   neighbours (the fix), both tempered; the scan is first lowered by the
   device's learned RSSI offset.
4. **Posterior** ∝ transition × emission, normalised; the position is the
   weighted mean, moved on by the steps taken since the scan.

The floor is a second, discrete chain: per scan each floor's marginal
likelihood (emission averaged over its points) updates a floor belief with a
small switching probability; the tracked floor changes only when another
floor's belief passes ``floor_switch_posterior`` (hysteresis), and the
position restarts there from k-NN. When a scan is far better explained
anywhere on the floor than where the distribution is (``relocate_margin``),
the track is lost and restarts the same way. The 68% radius is the tempered
posterior's spread, the steps' since the scan and the k-NN's disagreement
with the posterior, scaled by how far the scan is from its nearest survey
scan and by the site's calibration.

Modules: ``params`` (the tunable constants), ``emission`` (step 3 and the
k-NN of step 1, prepared once per site), ``transition`` (step 2 on the grid),
``motion_fit`` (the device's heading bias and step scale), ``tracker`` (one
device's chain over points and floors: steps 1 and 4).
"""
