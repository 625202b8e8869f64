"""Particle filter of Eurasian patent 047000 (steps 1–11), batched over many filters.

Each floor a device may be on has its own filter: N particles (x, y, w, α)
with α the particle's walking direction (radians clockwise from +y). One
update, per the patent:

1.  scatter uniformly over the floor's free area when never sampled or when
    the floor had no radio for T_r;
2.  move by the window's steps (or, without an inertial stream, by a random
    walk with a speed prior); a particle whose move would cross a wall or
    barrier or leave the outline stays put and gets a random α; a positional
    measurement pulls particles towards it;
3.  rescatter when fewer than N_a particles are alive (w > ε);
4.  drop readings of transmitters with σ / B > S_q;
5.  update weights at most every T_u;
6.  mutation and centre sampling need N_emin visible transmitters;
7.  rescatter N_m random particles;
8.  the sampling centre is the heard transmitter nearest by the inverse path loss;
9.  put N_c random particles around it, Gaussian with variance d_ce;
10. multiply weights by the Gaussian likelihood of the readings, normalise;
11. when Σ w² > 1 / N_r resample N particles from the weights' CDF at N
    stratified keys (Douc & Cappé 2005), w = 1/N.

Where each part lives (import from the modules; the package exports nothing):

- ``params``: the patent's constants and the motion noise (``ParticleFilterParams``);
- ``floor_model``: what one floor's filters share, built once per site: free
  cells, padded walls, the expected-RSSI raster with the radio map laid over
  it (``build_floor_models``); step 1's uniform ``scatter``;
- ``walls``: the map constraint of step 2, whether a move stays on free cells;
- ``motion``: step 2, moves by steps or a random walk and the pull of fixes;
- ``mutation``: steps 7–9, mutation and sampling around the nearest transmitter;
- ``weights``: steps 3, 10 and 11, live particles, likelihood, resampling;
- ``estimate``: weighted mean, direction and 68% radius of each cloud;
- ``inputs``: one filter's inputs per window and step 4's readings table;
- ``bank``: ``ParticleBank``, the stacked storage of many filters;
- ``kernel``: compiled loops for the per-particle work (moves and the wall
  check, likelihood, resampling, estimate), reproducing the numpy steps
  above bit for bit; ``ParticleFilterParams.kernel`` picks either;
- ``update``: ``update_filters``, steps 1–11 for all due filters of a floor,
  one numpy call or compiled loop per operation (the likelihood a gather
  from the floor's precomputed ``RssiGrid``).
"""
