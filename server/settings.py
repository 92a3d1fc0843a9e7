"""Server settings from the environment (pydantic-settings); every default lives under one data directory."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from server.object_store import LocalStore, ObjectStore, is_store_url, open_store

SUBMISSIONS_PREFIX, METRIC_CACHE_PREFIX = "submissions", "metric-cache"


class Settings(BaseSettings):
    """Where the server keeps its state and which splits it serves; each field reads the env var of its name."""

    model_config = SettingsConfigDict(
        env_file=".env", env_file_encoding="utf-8", extra="ignore", populate_by_name=True
    )

    data_dir: Path = Field(Path(".navsim-lb"), validation_alias="DATA_DIR")
    # Defaults below are derived from data_dir when left empty.
    database_url: str = Field("", validation_alias="DATABASE_URL")
    broker_url: str = Field("", validation_alias="BROKER_URL")
    # An object store shared by the API and every worker, s3://bucket/prefix (server.object_store; endpoint,
    # keys and region from the AWS_* variables): uploads under submissions/, published metric caches under
    # metric-cache/. Empty: uploads in storage_dir, caches only in cache_dir (one machine, or a shared disk).
    storage_url: str = Field("", validation_alias="STORAGE_URL")
    # The most this machine keeps of the scenes of splits registered from an object store (server.split_store).
    split_cache_bytes: int = Field(8 * 2**30, ge=0, validation_alias="SPLIT_CACHE_BYTES")
    # Where uploads and metric caches live, as configured (None: under data_dir; see the properties).
    storage_dir_option: Path | None = Field(None, validation_alias="STORAGE_DIR")
    cache_dir_option: Path | None = Field(None, validation_alias="CACHE_DIR")
    # Split directories registered at startup: JSON object name -> directory.
    splits: dict[str, Path] = Field(default_factory=dict, validation_alias="SPLITS")
    max_upload_bytes: int = Field(256 * 1024 * 1024, validation_alias="MAX_UPLOAD_BYTES")
    # Where failed logins and uploads are counted (server.rate_limits): memory:// for one API process,
    # redis://host:port/db to share the counts between API processes.
    rate_limit_storage: str = Field("memory://", validation_alias="RATE_LIMIT_STORAGE")
    bootstrap_samples: int = Field(2000, validation_alias="BOOTSTRAP_SAMPLES")
    # The public leaderboard is served from memory for this long (0 disables the cache).
    leaderboard_cache_seconds: float = Field(2.0, validation_alias="LEADERBOARD_CACHE_SECONDS")
    # Workers: the broker queue shared by API and workers, and how a submission is cut into tasks.
    queue_name: str = Field("navsim-lb", validation_alias="QUEUE_NAME")
    # (token, seed) pairs per chunk task. Fewer make each scoring call less efficient (a navtest-size run with 3
    # seeds took 1.39x the engine's time at 128, 1.25x at 384: benchmarks/service.py; since, 1.18x at 384 and
    # 1.17x at 768); more cost memory (about 270-360 MiB per pool process at 384, 390-420 at 768) and work lost
    # with a killed process.
    chunk_size: int = Field(384, ge=1, validation_alias="CHUNK_SIZE")
    # Hard limit of one task; a chunk's soft limit (its own clean failure) comes 30 s earlier (worker.app).
    task_time_limit: float = Field(600.0, gt=30, validation_alias="TASK_TIME_LIMIT")
    # A pass costs a few queries: often enough that a lost chunk is re-sent within seconds of its last beat.
    reaper_interval: float = Field(10.0, gt=0, validation_alias="REAPER_INTERVAL")
    # Claims of one run (first try, then re-queues of a run left with nothing in flight) before it fails.
    max_attempts: int = Field(3, ge=1, validation_alias="MAX_ATTEMPTS")

    @model_validator(mode="after")
    def _derive_defaults(self) -> Settings:
        if not self.database_url:
            self.database_url = f"sqlite:///{self.data_dir / 'navsim-lb.sqlite'}"
        if not self.broker_url:
            # kombu's SQLAlchemy transport: a broker in an SQLite file, no server to run.
            self.broker_url = f"sqla+sqlite:///{self.data_dir / 'broker.sqlite'}"
        if self.storage_url and not is_store_url(self.storage_url):
            raise ValueError(f"STORAGE_URL {self.storage_url!r}: an object store is s3://bucket/prefix")
        return self

    @property
    def storage_dir(self) -> Path:
        """Where uploaded files are stored without an object store."""
        return self.storage_dir_option or self.data_dir / "submissions"

    @property
    def submission_store(self) -> ObjectStore:
        """Where uploaded files are stored: the object store's submissions/, else storage_dir."""
        if self.storage_url:
            return open_store(f"{self.storage_url.rstrip('/')}/{SUBMISSIONS_PREFIX}")
        return LocalStore(self.storage_dir)

    @property
    def cache_store(self) -> ObjectStore | None:
        """Where workers publish the metric caches they build for each other (None: cache_dir is the only one)."""
        if self.storage_url:
            return open_store(f"{self.storage_url.rstrip('/')}/{METRIC_CACHE_PREFIX}")
        return None

    @property
    def cache_dir(self) -> Path:
        """Where the metric caches of the splits are built."""
        return self.cache_dir_option or self.data_dir / "cache"


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """Return the process-wide settings read from the environment."""
    return Settings()
