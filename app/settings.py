"""Service configuration: the one pydantic-settings class (environment prefix `DETCAL_`)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

TOKEN_FILE = "admin_token"


class Settings(BaseSettings):
    """Everything the service reads from its environment; `DETCAL_<FIELD>` overrides a field."""

    model_config = SettingsConfigDict(env_prefix="DETCAL_", extra="ignore")

    data_dir: Path = Field(Path("./data"), description="Store, uploaded dumps and token file.")
    database_url: str | None = Field(
        None, description="SQLAlchemy URL; default a SQLite file (WAL) in data_dir.")
    admin_token: SecretStr | None = Field(
        None, description="Bearer token for admin endpoints; default read from "
                          "data_dir/admin_token if that file exists, else admin is refused.")
    default_profile: str = Field("lidar", description="Profile name used when none is given.")
    max_request_bytes: int = Field(8 * 2**20, gt=0,
                                   description="Body limit (413) except dump uploads.")
    max_upload_bytes: int = Field(512 * 2**20, gt=0, description="Body limit of multipart dump "
                                  "uploads (POST /v1/fit, /v1/feedback).")
    max_dump_bytes: int = Field(64 * 2**20, gt=0, description="Inflated size of an uploaded "
                                "dump (all NPZ arrays, or each nuScenes JSON file) a fit or "
                                "feedback request may carry; 413 (NPZ, from its headers, before "
                                "inflating) or 422 above.")
    max_fit_detections: int = Field(75_000, gt=0, description="Detections (or ground-truth "
                                    "boxes) of one uploaded fit dump, and of each part of a "
                                    "dataset fit in place (413 / 422 above).")
    max_json_dump_bytes: int = Field(32 * 2**20, gt=0, description="A nuScenes results and "
                                     "ground-truth JSON pair uploaded to POST /v1/fit, both "
                                     "files together (JSON takes ~6x its size to parse); 413 "
                                     "above.")
    max_feedback_detections: int = Field(100_000, gt=0, description="Detections (or ground-"
                                         "truth boxes) of one feedback request (413 above).")
    max_detections: int = Field(20_000, gt=0, description="Detections one calibrate or detect "
                                                          "request may carry (413 above).")
    header_timeout_s: float = Field(10.0, gt=0, description="Seconds a connection has to send "
                                    "its request line and headers (from opening, or from the "
                                    "first byte of a later request); 408 and closed after.")
    body_timeout_s: float = Field(20.0, gt=0, description="Seconds a request body may take, "
                                  "plus one per DETCAL_BODY_MIN_RATE bytes received; closed "
                                  "after.")
    body_min_rate: int = Field(8192, gt=0, description="Bytes per second a request body must "
                               "keep up after its first DETCAL_BODY_TIMEOUT_S seconds.")
    max_header_bytes: int = Field(65536, ge=1024, description="Request line and headers; 431 "
                                  "and closed above.")
    keep_alive_s: float = Field(5.0, gt=0, description="Idle seconds a kept-alive connection "
                                "waits for its next request (uvicorn timeout_keep_alive).")
    limit_concurrency: int = Field(512, ge=1, description="Connections and requests one server "
                                   "process serves at once; 503 beyond (uvicorn "
                                   "limit_concurrency).")
    log_format: str = Field("text", pattern="^(text|json)$", description="Server log lines: "
                            "`text`, or `json` (one JSON object per line).")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    workers: int = Field(1, ge=1)
    fit_workers: int = Field(1, ge=1, description="Fit jobs run at once in one process.")
    calibrate_processes: int = Field(1, ge=0, description="Worker processes per server process "
                                     "for large calibrate bodies (0: all in threads).")
    offload_bytes: int = Field(1 * 2**20, ge=0, description="Calibrate bodies larger than this "
                               "are parsed and calibrated in a worker process.")
    dashboard_sensor: str = Field("lidar", description="Sensor of the dashboard's BEV frame.")
    dashboard_seed: int = Field(0, description="Simulated frame seed drawn on the dashboard.")
    datasets_dir: Path | None = Field(None, description="Folder under which POST /v1/fit may "
                                      "name a Parquet dataset (form field `dataset`); unset: "
                                      "datasets are refused.")
    health_window_frames: int = Field(500, ge=1, description="Feedback frames in the rolling "
                                      "window of GET /v1/profiles/{name}/health.")
    health_chunk_frames: int = Field(25, ge=1, description="Feedback frames per stored health "
                                     "point (the time series' resolution).")
    auto_refit: bool = Field(False, description="Keep feedback frames and, when feedback first "
                             "degrades a champion, fit a `challenger` version on them (never "
                             "activated).")
    feedback_token: SecretStr | None = Field(
        None, description="A second bearer token that may only POST /v1/feedback (for the "
                          "labelling pipeline); the admin token may too.")

    @model_validator(mode="after")
    def _token_from_file(self) -> Settings:
        if self.admin_token is None:
            path = self.data_dir / TOKEN_FILE
            if path.is_file():
                token = path.read_text().strip()
                if token:
                    self.admin_token = SecretStr(token)
        return self

    @property
    def sqlalchemy_url(self) -> str:
        """The database URL, defaulting to `sqlite:///<data_dir>/detcal.db`."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'detcal.db').resolve()}"

    @property
    def dumps_dir(self) -> Path:
        """Where uploaded dumps are kept, content-addressed by sha256."""
        return self.data_dir / "dumps"


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings read from the environment (cached)."""
    return Settings()
