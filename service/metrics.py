"""Prometheus metrics of one app (own registry, so several apps can live in one process)."""
from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

LATENCY_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0)
STAGE_BUCKETS_MS = (1, 2.5, 5, 10, 25, 50, 100, 250, 500, 1000, 2500, 5000, 10000, 30000)
BATCH_BUCKETS = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 64, 128, 256)


class Metrics:
    def __init__(self):
        self.registry = CollectorRegistry()
        r = self.registry
        self.requests = Counter("tryon_http_requests", "HTTP requests by route template, method and status", ["route", "method", "status"], registry=r)
        self.latency = Histogram("tryon_http_request_duration_seconds", "HTTP request latency by route template", ["route", "method"],
                                 buckets=LATENCY_BUCKETS_S, registry=r)
        self.queue_depth = Gauge("tryon_queue_depth", "requests waiting for an inference worker", registry=r)
        self.batch_size = Histogram("tryon_batch_size", "requests per dispatched batch", buckets=BATCH_BUCKETS, registry=r)
        self.batch_frames = Histogram("tryon_batch_frames", "frames per dispatched batch", buckets=(1, 10, 30, 60, 120, 240, 480, 960, 1920, 3840), registry=r)
        self.inference_ms = Histogram("tryon_inference_ms", "pipeline stage time per request, ms, by stage and model version", ["stage", "model"],
                                      buckets=STAGE_BUCKETS_MS, registry=r)
        self.workers_alive = Gauge("tryon_workers_alive", "inference workers up", registry=r)
        self.workers_busy = Gauge("tryon_workers_busy", "inference workers running a batch", registry=r)
        self.worker_restarts = Counter("tryon_worker_restarts", "inference workers replaced after a crash or hang", registry=r)
        self.rejected = Counter("tryon_rejected", "requests refused before inference", ["reason"], registry=r)
        self.cache = Counter("tryon_cache_lookups", "result cache lookups", ["result"], registry=r)
        self.jobs = Gauge("tryon_jobs", "jobs by state", ["state"], registry=r)
