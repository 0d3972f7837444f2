"""Service settings, validated once at start-up (environment variables prefixed ``TRYON_``)."""
from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from inference.body import ASSETS_DIR


class Settings(BaseSettings):
    """Every limit the service enforces on a request lives here (documented in openapi.yaml)."""

    model_config = SettingsConfigDict(env_prefix="TRYON_", extra="ignore")

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    assets_dir: Path = ASSETS_DIR
    log_level: str = "info"

    # Request limits (POST /v1/drape)
    max_request_bytes: int = Field(8 * 1024 * 1024, ge=1024, description="largest accepted request body")
    max_frames: int = Field(300, ge=1, description="frames per drape after resampling")
    max_garments: int = Field(4, ge=1, description="garments per request")
    max_bvh_bytes: int = Field(4 * 1024 * 1024, ge=1024, description="largest BVH text")
    max_source_frames: int = Field(20_000, ge=1, description="frames in an uploaded motion before resampling")
    # Concurrent drape computations; further requests wait (bounded) for a slot.
    max_concurrent_drapes: int = Field(2, ge=1)
    max_waiting_drapes: int = Field(16, ge=0, description="requests queued for a slot before 503")
