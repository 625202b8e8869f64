"""Positioning algorithms in pure numpy and scipy: no web framework, no database.

Each module is one algorithm (or one shared data structure) and is usable and
testable on its own; an algorithm that needs several files is a package.
Services and workers call into the engine; the engine never imports them.

Each method's source is cited in docs/algorithms.md: the particle filter with
floor selection and map constraints (Eurasian patent 047000), the UWB +
inertial extended Kalman filter (Brovko's report), the WiFi fingerprint +
inertial HMM (CN106028450), BLE least squares with a-priori accuracy
(Grinyak 2020), the track-to-plan fitter (Voronov et al.).

Shared data
    ``samples``: measurement arrays per kind, a device's batch, an estimate.
    ``site``: a site's floors and emitter tables. ``plan``: floor rasters for
    the point and wall tests of the hot paths. ``tracker``: the interface a
    per-device filter offers the workers. ``gaussian``: the 68 % radius.

RSSI with a path-loss model (Eurasian patent 047000)
    ``pathloss``: ``rssi = A - B ln r``, its inverse, quality filter and the
    likelihood raster. ``preprocess``: positioning windows. ``floors/``
    (package): floor selection, the patent's E_L ranking and a forward filter
    over floors. ``particle/`` (package): the particle filter, batched over
    devices. ``positioning``: the patent's loop over windows, floors and
    filters for many devices. ``calibration``: path loss (and position) of
    each transmitter from survey walks. ``centroid``: weighted centroid, the
    estimator of last resort.

Fingerprints and dead reckoning (CN106028450)
    ``pdr``: steps from a phone's IMU. ``pdr_fit``: its constants fitted to
    survey waypoints. ``scans``: WiFi readings grouped into scans, however
    the client timed them. ``radiomap``: radio maps from survey walks
    (offline phase). ``wknn``: weighted k-NN per scan. ``crossval``:
    held-out accuracy of a radio map on walk-level folds. ``hmm/`` (package):
    the fingerprint + inertial HMM (online phase), and ``hmm/validate`` its
    replay of held-out walks. ``tuning``: a site's building-dependent
    constants chosen from its surveys. ``smoothing``: positions refined
    against the steps that follow them (fixed-lag and full pass).

UWB and fixed locators (Brovko's EKF report, Grinyak 2020)
    ``lateration/`` (package): least-squares fixes and their a-priori
    accuracy (Grinyak 2020). ``accuracy_map``: that accuracy over a floor, for
    planning a layout. ``ekf``: the EKF of position fixes and gyro (Brovko).
    ``uwb_bias``: per-anchor range biases. ``uwb_tracker``: a UWB tag's
    tracker. ``locator_tracker``: a tag heard by fixed locators.

Tracks uploaded by devices (Voronov et al.)
    ``trackfit/`` (package): fitting a dead-reckoned track to the floor plan
    by dynamic programming.
"""
