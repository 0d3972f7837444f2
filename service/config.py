"""Service settings, validated once at start-up (environment variables prefixed ``TRYON_``)."""
from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from inference.body import ASSETS_DIR

REPO_ROOT = Path(__file__).resolve().parents[1]


class Settings(BaseSettings):
    """Every limit the service enforces on a request lives here (documented in openapi.yaml)."""

    model_config = SettingsConfigDict(env_prefix="TRYON_", extra="ignore")

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    assets_dir: Path = ASSETS_DIR
    log_level: str = "info"
    log_json: bool = Field(True, description="one JSON object per log line, with the request id")

    # Request limits (POST /v1/drape)
    max_request_bytes: int = Field(8 * 1024 * 1024, ge=1024, description="largest accepted request body")
    max_frames: int = Field(300, ge=1, description="frames per drape after resampling")
    max_garments: int = Field(4, ge=1, le=8, description="garments per request (at most the schema's cap, 8)")
    max_total_vertices: int = Field(12_000_000, ge=1, description="frames x (garment vertices + body vertices if included)")
    max_bvh_bytes: int = Field(4 * 1024 * 1024, ge=1024, description="largest BVH text")
    max_source_frames: int = Field(20_000, ge=1, le=20_000, description="frames in an uploaded motion before resampling (at most the schema's cap)")
    request_timeout_s: float = Field(60.0, gt=0, description="deadline of a synchronous drape, queueing included (504 after)")

    # Worker pool (service/pool.py): inference runs in `workers` processes (or threads), fed by a
    # scheduler that merges compatible queued requests into batches.
    workers: int = Field(2, ge=1, le=64, description="inference workers")
    worker_mode: Literal["process", "thread"] = Field("process", description="process: crash-isolated workers; thread: in the API process")
    worker_blas_threads: int = Field(1, ge=1, le=64, description="BLAS/OpenMP threads in each worker process (the workers are the parallelism); "
                                     "set for the worker processes' server when the first worker starts")
    max_batch: int = Field(8, ge=1, le=256, description="requests merged into one batch (1: batching off)")
    max_wait_ms: float = Field(5.0, ge=0, le=1000, description="how long a batch waits for more requests once a worker is free, while no other worker is idle")
    max_queue: int = Field(32, ge=0, description="requests queued for a worker before 503 + Retry-After")
    max_queue_wait_s: float = Field(10.0, gt=0, description="503 at once when the expected wait in the queue exceeds this")
    worker_start_timeout_s: float = Field(120.0, gt=0)
    worker_hang_s: float = Field(600.0, gt=0, description="a worker busy with one batch for longer is killed and replaced")
    shutdown_drain_s: float = Field(30.0, ge=0, description="on shutdown, how long queued and running work may finish")

    # Asynchronous jobs (POST /v1/jobs): larger limits, results on disk, never lost once accepted.
    jobs_backend: Literal["sqlite", "redis", "off"] = Field("sqlite", description="sqlite: embedded; redis: RQ queue shared by workers")
    jobs_dir: Path = Field(REPO_ROOT / "build" / "jobs", description="SQLite database and result files")
    redis_url: str = Field("redis://127.0.0.1:6379/0", description="Redis for jobs_backend=redis")
    redis_queue: str = "tryon-jobs"
    job_max_request_bytes: int = Field(32 * 1024 * 1024, ge=1024)
    job_max_frames: int = Field(3000, ge=1)
    job_max_total_vertices: int = Field(120_000_000, ge=1)
    job_chunk_frames: int = Field(120, ge=1, description="frames per progress step of a job")
    job_concurrency: int = Field(1, ge=1, description="jobs run at once by this process (embedded backend)")
    job_timeout_s: float = Field(3600.0, gt=0)
    job_result_ttl_s: float = Field(24 * 3600.0, gt=0, description="results (and finished jobs) expire after this")
    job_lease_s: float = Field(15.0, gt=0, description="a running job whose owner stops renewing this long is re-queued")
    job_max_attempts: int = Field(3, ge=1, description="runs of a job (restarts, worker crashes) before it fails")
    job_poll_s: float = Field(0.5, gt=0)
    job_abandoned_s: float = Field(20.0, ge=10.0, le=50.0, description="Redis backend: a running job whose worker has not "
                                   "heartbeaten (every 5 s) for this long is re-queued (checked every few seconds, so within a minute)")
    job_max_pending: int = Field(256, ge=1, description="queued + running jobs in the store before POST /v1/jobs answers 429")
    job_max_pending_per_key: int = Field(32, ge=1, description="queued + running jobs per API key (per deployment without keys) before 429")

    # Content-addressed result cache (identical request + model versions -> same output)
    cache_max_bytes: int = Field(256 * 1024 * 1024, ge=0, description="in-memory result cache (0: off)")

    # The try-on page (GET /viewer): its three.js files come from the npm package (npm ci --omit=dev)
    viewer_three_dir: Path = Field(REPO_ROOT / "node_modules" / "three", description="the three npm package the /viewer page "
                                   "loads (its build/ and examples/jsm/ files); missing: /viewer answers 503")

    # Security
    api_keys: str = Field("", description="comma-separated API keys; empty (and no file): no auth")
    api_keys_file: Path | None = Field(None, description="file with one API key per line")
    api_key_header: str = "X-API-Key"
    cors_origins: str = Field("", description="comma-separated allowed origins for browsers ('*' for any)")

    @model_validator(mode="after")
    def _check(self) -> "Settings":
        if self.api_keys_file is not None and not self.api_keys_file.is_file():
            raise ValueError(f"api_keys_file {self.api_keys_file} does not exist")
        return self

    def api_key_set(self) -> list[str]:
        """The configured API keys (environment and file); empty: auth off."""
        keys = [k.strip() for k in self.api_keys.split(",")]
        if self.api_keys_file is not None:
            keys += [line.strip() for line in self.api_keys_file.read_text().splitlines() if not line.startswith("#")]
        return [k for k in keys if k]

    def cors_origin_list(self) -> list[str]:
        return [o.strip() for o in self.cors_origins.split(",") if o.strip()]
