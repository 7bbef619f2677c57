"""Service settings: environment variables with the ``DST_`` prefix, validated at start-up.

Shared by the API (``app``) and the workers; imports no OCCT.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

LOCAL_BROKER_SCHEMES = ("sqla+sqlite", "memory")


class Settings(BaseSettings):
    """Configuration of ``dst serve`` / ``dst worker``. Every field is ``DST_<NAME>`` in the environment."""

    model_config = SettingsConfigDict(env_prefix="DST_", extra="ignore")

    data_dir: Path = Field(
        Path("dst-data"),
        description="Directory for the job store, the embedded broker and artifacts (default ./dst-data).",
    )
    artifact_dir: Path | None = Field(
        None, description="Where job artifacts (meshes, reports) live; default <data_dir>/artifacts."
    )
    artifact_url: str | None = Field(
        None,
        description="fsspec URL for artifacts shared by every machine (s3://bucket/prefix); jobs then run in "
        "<artifact_dir> as local scratch and upload their files when they finish.",
    )
    artifact_options: dict[str, Any] = Field(
        default_factory=dict,
        description='fsspec storage options as JSON, e.g. {"client_kwargs": {"endpoint_url": "http://minio:9000"}}.',
    )
    database_url: str | None = Field(
        None, description="SQLAlchemy URL of the job store; default sqlite:///<data_dir>/jobs.sqlite."
    )
    broker_url: str | None = Field(
        None,
        description="Celery broker; default the embedded SQLite broker sqla+sqlite:///<data_dir>/broker.sqlite. "
        "Use redis://host:6379/0 to scale out.",
    )
    max_upload_mb: float = Field(200.0, gt=0, le=10_000, description="Largest accepted upload, MB.")
    job_timeout_s: float = Field(900.0, gt=0, le=86_400, description="Wall-clock limit of one job, s.")
    job_memory_mb: int = Field(
        8192,
        ge=1200,
        le=1_000_000,
        description="Address-space limit of one job's process, MB (OCCT needs ~1 GB to load).",
    )
    report_processes: int | None = Field(
        None,
        ge=1,
        le=256,
        description="Helper processes one job's report may fork at once (Linux); `dst worker` sets it "
        "to the CPUs divided by its concurrency unless given.",
    )
    max_attempts: int = Field(
        2, ge=1, le=5, description="Runs of a job interrupted by a crashed worker before it is failed."
    )
    heartbeat_s: float = Field(
        2.0, gt=0, le=60, description="How often a running job reports it is alive, s."
    )
    stale_after_s: float = Field(
        30.0,
        gt=0,
        le=3600,
        description="A running job silent this long on another machine is presumed lost, s.",
    )
    slice_wait_s: float = Field(
        900.0, gt=0, le=86_400, description="How long POST /v1/slice waits for its job, s."
    )
    queue: str = Field("dst", min_length=1, max_length=64, description="Celery queue name.")

    @model_validator(mode="after")
    def _shared_storage_for_remote_workers(self) -> Settings:
        broker = self.effective_broker_url
        given = self.model_fields_set
        shared = (
            "data_dir" in given
            or {"artifact_dir", "database_url"} <= given
            or {"artifact_url", "database_url"} <= given
        )
        if not broker.startswith(LOCAL_BROKER_SCHEMES) and not shared:
            raise ValueError(
                f"DST_BROKER_URL={broker} lets workers run on other machines, but artifacts would be kept in "
                f"the machine-local default {self.data_dir.resolve()}: set DST_DATA_DIR (or DST_ARTIFACT_DIR and "
                "DST_DATABASE_URL, or DST_ARTIFACT_URL=s3://... and DST_DATABASE_URL) to storage every API and "
                "worker machine reaches"
            )
        return self

    @property
    def effective_artifact_dir(self) -> Path:
        return (self.artifact_dir or self.data_dir / "artifacts").resolve()

    @property
    def effective_database_url(self) -> str:
        return self.database_url or f"sqlite:///{(self.data_dir / 'jobs.sqlite').resolve()}"

    @property
    def effective_broker_url(self) -> str:
        return self.broker_url or f"sqla+sqlite:///{(self.data_dir / 'broker.sqlite').resolve()}"

    @property
    def embedded(self) -> bool:
        return self.effective_broker_url.startswith(LOCAL_BROKER_SCHEMES)

    def ensure_dirs(self) -> None:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.effective_artifact_dir.mkdir(parents=True, exist_ok=True)


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    s = Settings()
    s.ensure_dirs()
    return s
