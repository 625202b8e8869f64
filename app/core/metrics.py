"""Prometheus metrics of the API process; workers report theirs through stats messages."""

from __future__ import annotations

from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram


class Metrics:
    """All metrics of one API process, in their own registry (one app, one registry)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.requests = Counter(
            "locus_http_requests", "HTTP requests", ["method", "route", "status"], registry=r
        )
        self.request_seconds = Histogram(
            "locus_http_request_seconds", "HTTP request duration", ["route"], registry=r
        )
        self.ingest_samples = Counter(
            "locus_ingest_samples", "Samples accepted by ingest", ["kind"], registry=r
        )
        self.ingest_dropped = Counter(
            "locus_ingest_dropped_samples",
            "Samples (or their optional fields) dropped by the per-sample policy, by reason",
            ["kind", "reason"],
            registry=r,
        )
        self.ingest_rejected = Counter(
            "locus_ingest_rejected_requests", "Ingest requests rejected", ["reason"], registry=r
        )
        self.dropped_samples = Counter(
            "locus_dropped_samples",
            "Accepted samples dropped by the overload policy",
            ["reason"],
            registry=r,
        )
        self.worker_samples = Counter(
            "locus_worker_samples",
            "Samples by outcome in the workers (used, late, duplicate, unknown id, stale WiFi)",
            ["outcome"],
            registry=r,
        )
        self.positions = Counter("locus_positions_emitted", "Positions emitted", registry=r)
        self.zone_events = Counter("locus_zone_events", "Zone enter/exit events", registry=r)
        self.ingest_to_position = Histogram(
            "locus_ingest_to_position_seconds",
            "From accepting a batch to its processing being acknowledged",
            buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
            registry=r,
        )
        self.queue_depth = Gauge(
            "locus_shard_queue_depth",
            "Batches published and not yet acknowledged",
            ["shard"],
            registry=r,
        )
        self.worker_devices = Gauge("locus_worker_devices", "Devices held", ["shard"], registry=r)
        self.worker_update_seconds = Gauge(
            "locus_worker_update_seconds_total",
            "CPU spent processing batches",
            ["shard"],
            registry=r,
        )
        self.worker_restarts = Counter(
            "locus_worker_restarts", "Worker processes restarted", ["shard"], registry=r
        )
        self.ws_subscribers = Gauge("locus_ws_subscribers", "WebSocket subscribers", registry=r)
        self.ws_dropped = Counter(
            "locus_ws_dropped_messages", "Messages dropped for slow subscribers", registry=r
        )

        out = ["site_id", "output_id"]
        self.output_delivered = Counter(
            "locus_output_delivered", "Messages an output acknowledged", out, registry=r
        )
        self.output_retried = Counter(
            "locus_output_retried",
            "Messages whose delivery attempt failed and waits",
            out,
            registry=r,
        )
        self.output_failed = Counter(
            "locus_output_failed", "Messages given up after the retention bound", out, registry=r
        )
        self.output_pending = Gauge(
            "locus_output_pending", "Messages waiting for an output", out, registry=r
        )

    def count_drops(self, drops: list[dict[str, Any]]) -> None:
        """Count the samples or fields the per-sample policy dropped, by kind and reason."""
        for drop in drops:
            self.ingest_dropped.labels(drop["kind"], drop["code"]).inc()
