"""Fit a dead-reckoned track to the floor plan by dynamic programming (Voronov et al.).

A device in energy-saving mode uploads its own dead-reckoned track as links:
a length l_i and the turn from the previous link. Step lengths are off by up
to about 10 % and headings by a few degrees, so the raw polyline crosses
walls. Following Voronov et al., the fitter searches the tracks obtained by
scaling each link by γ ∈ Γ and changing each turn by φ ∈ Φ, rejects those with
a link through a wall, a barrier or the outline, and returns the one that
changed the input least:

    f = C1 Σ |1 - γ_i| + C2 Σ |φ_i|.

The search is the paper's approximate dynamic programme. The plan is cut
into square cells S and, for every link i and cell s, only the best track of
the first i links ending in s survives: its score f_i(s), end point ξ_i(s),
direction ψ_i(s) and predecessor cell ζ_i(s). A backward pass from the best
final cell gives the fitted points. Only reachable free cells are ever alive,
so a link costs O(|S_i| |Γ| |Φ|) with |S_i| the cells the first i links can
reach, bounded by the walkable area divided by the cell area.

Two departures from the paper, both for real phone tracks (site1): the DP
cell shrinks to the median link length when links are shorter than the grid
(``cell_per_link``; per-step links otherwise leave the DP one track per cell
and it turns greedy), and a link no track survives is not the end of the fit:
it is placed by a recovery ladder (wider Γ_w and Φ_w; then crossing a wall
with a free end, for doors the map lacks; then dead reckoning, for walkers
where the map says nobody can be) and flagged in ``TrackFit.relaxed``.
``recover=False, cell_per_link=0`` is the paper's algorithm.

Beyond the paper, ``search`` resolves what the programme cannot: the
rotation of a track whose first heading is unknown (a rotated track fits a
mall's open halls as well as the right one), the walker's step-length scale
and a drifting gyro heading. Each hypothesis is screened as a rigid track and
the best distinct ones are fitted together; the best fit and the runner-up
are reported, flagged ambiguous when their scores are too close. Occasional
WiFi scans along the track (``anchors``) add their fingerprint cost against
the floor's radio map to the score of every hypothesis and track.

Modules: ``fit`` (``fit_track`` and ``fit_tracks``: parameters, the forward
pass over the links with the recovery ladder, the backward pass and the
result), ``step`` (one link of the dynamic programme for every surviving
track), ``grid`` (the DP cells over the plan and the wall test on its raster),
``search`` (the hypotheses, their screening and comparison), ``anchors`` (WiFi
scans as cost rasters).
"""
