"""Service settings, read from the environment (``ARTIFACTS_DIR=... MAX_BATCH=...``)."""

from __future__ import annotations

from pydantic import Field

from services.common.settings import ApiSettings, Port, RegistrySettings


class Settings(ApiSettings, RegistrySettings):
    """Every knob of the emulator service (beside host, port, log level, API keys and CORS origins);
    environment variables have the upper-case names."""

    max_body_bytes: int = Field(
        8 * 1024 * 1024,
        ge=1024,
        description="the largest body of POST /step and POST /models/{model}/poses (413 beyond, before it "
        "is read); every other endpoint takes at most SMALL_BODY_BYTES",
    )
    small_body_bytes: int = Field(
        65_536, ge=1024, description="the largest body of the endpoints that take small ones (sessions)"
    )
    max_batch: int = Field(4096, ge=1, description="most rows in one ORT call, and items in one POST /step")
    max_json_body_bytes: int = Field(
        4 * 1024 * 1024,
        ge=1024,
        description="the largest JSON body of POST /step, refused before it is parsed (the binary form may "
        "use up to MAX_BODY_BYTES)",
    )
    max_wait_ms: float = Field(
        1.0,
        ge=0.0,
        le=50.0,
        description="longest batching window: requests are gathered while they keep arriving, up to this long",
    )
    session_ttl_s: float = Field(600.0, gt=0.0, description="idle sessions expire after this")
    max_sessions: int = Field(100_000, ge=1, description="sessions alive in this replica (429 beyond)")
    max_steps_per_request: int = Field(1000, ge=1)
    max_frames_per_request: int = Field(10_000, ge=1, description="steps × frames_per_step cap")
    replica_id: str = Field("r0", pattern=r"^[A-Za-z0-9_]+$", description="prefix of every session id")
    ort_threads: int = Field(1, ge=1, description="ORT intra-op threads per emulator")
    registry_poll_s: float = Field(2.0, ge=0.0, description="how often pointer files are re-read")
    sweep_interval_s: float = Field(5.0, gt=0.0, description="how often expired sessions are removed")
    max_sessions_per_key: int = Field(1000, ge=1, description="sessions one API key may hold (429 beyond)")
    redis_url: str = Field("", description="e.g. redis://redis:6379/0; empty: no persistence")
    redis_prefix: str = Field("neuroanimator:emulator", min_length=1, description="prefix of Redis keys")
    checkpoint_interval_s: float = Field(1.0, gt=0.0, description="sessions are written to Redis this often")
    ws_realtime_scale: float = Field(
        1.0,
        gt=0.0,
        le=100.0,
        description="real-time websocket period = the model's Δt × this (tests shorten it)",
    )
    ws_queue_size: int = Field(
        1, ge=1, le=2, description="state frames queued per real-time client (latest wins)"
    )
    ws_send_timeout_s: float = Field(
        5.0, gt=0.0, description="a websocket send that takes longer closes the connection (client gone)"
    )
    gc_thresholds: tuple[int, int, int] = Field(
        (20_000, 20, 20), description="gc.set_threshold after start-up (Python's default: 700, 10, 10)"
    )
    port: Port = 8000
