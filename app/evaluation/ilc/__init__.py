"""The WiFi positioning methods evaluated on ILC site1, a five-floor mall.

Everything the methods know is learned from the training walks only; each
held-out walk is then replayed as the one-second batches a phone would
upload and its estimates scored against the surveyed waypoints. One module
per step, each depending only on those above it:

- ``recordings``: the site's floors, transmitter table, surveys and walk batches;
- ``learn``: radio maps, transmitter calibration and PDR constants from the training walks;
- ``replay``: batches through a method, timing its CPU, one walk or many devices at once;
- ``methods``: ``wknn``, ``hmm``, ``pf`` and ``pf-radiomap`` built from what was learned;
- ``score``: estimates against the waypoints, pooled into a row per method;
- ``evaluate``: every method replayed on the held-out walks and scored;
- ``experiment``: the split options, the split and the learning every run starts from;
- ``table`` and ``plots``: the printed table and the walk plots;
- ``cli``: ``locus eval ilc-methods``; ``floor_change``: ``locus eval ilc-floor-change`` (the
  server's phone engine following a change of floor).
"""
