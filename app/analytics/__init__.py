"""Analytics on stored positions and zone events: zone occupancy and dwell, floor heatmaps,
and exports of the history."""
