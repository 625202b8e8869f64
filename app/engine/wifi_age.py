"""How old a WiFi reading may be and still count in its scan, chosen from a site's surveys.

A phone's scan lists every access point it still remembers, each with the
time it was last heard (Android's ``ScanResult.timestamp``). Readings heard
a few seconds before the scan completed add access points the scan itself
missed, at the cost of having been heard a few metres back along the walk;
much older ones describe another place. Where the balance lies depends on
how fast people walk there and how often the phones scan, so a build scores
each candidate age by the per-scan k-NN (``app.engine.scan_knn``) on its own
surveys, whole walks held out in turn (``app.engine.scan_knn_cv``), and keeps
the age nearest the default that is as good as the best walk by walk.

On ILC site1 the k-NN errs less the older the readings it keeps, up to the
oldest candidate; ``locus eval ilc`` prints the build's error at each
candidate age (``knn_walk_error_m_by_wifi_max_age_ms``). Longer ages than the
candidates' add readings heard too far back along the walk.
"""

from __future__ import annotations

DEFAULT_MAX_AGE_MS = 5000
"""Oldest last-seen age (ms) a site without a build uses: the strongest published pipelines
on this kind of data dropped readings more than 5 s older than their scan."""

AGE_CANDIDATES_MS = (2000, 3000, 4000, 5000, 6000, 8000)
"""Oldest last-seen age (ms before the scan's time) a build tries."""
