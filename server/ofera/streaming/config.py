"""Server settings: `OFERA_*` environment variables, overridden by `ofera serve` flags."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from ofera_protocol.constants import MAX_CLIENT_MESSAGE
from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

ROOM_CONTROL_BYTES = 256 * 1024 * 1024
"""Default `room_control_bytes`: a newcomer to a full room (16 members) of 115,600-Gaussian avatars (the built-in
one: 6.5 MB of avatar messages each, sh degree 0) queues about 104 MB at once; 256 MiB leaves room for larger ones.
The avatar bytes are shared by every viewer of a wire format: the bound counts them per viewer, memory does not."""



class Settings(BaseSettings):
    """Everything the streaming server can be told. Environment: ``OFERA_<NAME>`` (e.g. ``OFERA_PORT``)."""

    model_config = SettingsConfigDict(env_prefix="OFERA_", extra="ignore")

    host: str = Field("127.0.0.1", description="Interface to listen on (0.0.0.0 for every interface).")
    port: int = Field(8000, ge=0, le=65535, description="TCP port (0: any free port).")
    avatars: Path | None = Field(
        None, description="Directory of avatar files; each may have a sibling EPM <stem>.onnx and BDA "
        "<stem>.bda.npz. 'default' (the built-in avatar) is always available unless the directory has its own.")
    avatar_zip: Path | None = Field(
        None, description="A LAM avatar export (.zip) to serve as avatar <zip stem>, imported once and cached (by "
        "content) in the cache directory; it is the default avatar unless default_avatar is given. A .zip in the "
        "avatars directory is served the same way.")
    devices: Path | None = Field(
        None, description="Directory of device BDA profiles <device>.npz; hello.device selects one.")
    default_avatar: str = Field("default", description="Avatar id that hello.avatar 'default' resolves to.")
    token: str | None = Field(None, description="If set, every hello must carry this token.")
    allowed_origins: str | None = Field(
        None, description="Comma-separated browser origins allowed to open a stream (e.g. https://app.example.com; "
        "'*': any). A WebSocket handshake with an Origin header not in the list is refused with HTTP 403; "
        "clients that send no Origin (native apps, Unity, the Python client) are always allowed. Unset: any.")
    ssl_keyfile: Path | None = Field(None, description="TLS private key (PEM): serve wss:// and https://.")
    ssl_certfile: Path | None = Field(None, description="TLS certificate chain (PEM), with ssl_keyfile.")
    max_message_bytes: int = Field(MAX_CLIENT_MESSAGE, ge=256, description="Largest client message accepted.")
    max_sessions: int = Field(64, ge=1, description="Most concurrent WebSocket sessions.")
    bs_rate: float = Field(240.0, gt=0, description="Most bs (and ping) messages per second per session.")
    bs_burst: float | None = Field(None, gt=0, description="Token-bucket depth for bs_rate (default: one "
                                   "second's worth).")
    compute_threads: int = Field(0, ge=0, description="Threads running pipelines (the compute pool, "
                                 "streaming.compute_pool; 0: one per CPU it may use).")
    cpus: str | None = Field(
        None, description="CPUs the server runs on, as Linux lists them (e.g. 0 or 2-3,6): every thread's affinity, "
        "set when `ofera serve` starts (streaming.affinity; not by an in-process ServerThread), and numba's thread "
        "pool sized to them; unset: any. Keep the server off the cores its clients use (a Unity app, a replay): on a "
        "2-core VM one session's e2e p99 was 1.3-3.4 ms lower in one hour, the same in another, with the server on "
        "CPU 0 and its client on CPU 1 (benchmarks/README.md, round nine).")
    confidence_threshold: float = Field(0.5, ge=0.0, le=1.0, description="bs.conf below this holds that face "
                                        "region's last confident expression (PROTOCOL.md 4.2); 0: never hold.")
    avatar_chunk_bytes: int = Field(4 * 1024 * 1024, ge=1024, description="Largest avatar message payload.")
    hello_timeout: float = Field(10.0, gt=0, description="Seconds a new connection may take to send hello.")
    fast: bool = Field(True, description="Fast paths: the avatar's numba deformation (moving Gaussians only) "
                       "and numba frame encoding; false: the numpy references (lbs + Deformer, codec.encode_frame).")
    kernel_threads: Literal["serial", "auto", "parallel"] = Field(
        "auto", description="Fast path: whether a frame's face frames and per-Gaussian kernels run on numba's threads "
        "(both cores for one session). auto: while the session is the only one computing and the machine is not "
        "busy, if its recent threaded frames were faster per unit of work (measured per session: ofera.avatar.fast); "
        "serial: one thread; parallel: always. On the 2-core Intel VM of 6 December 2026 a lone q13 delta session's "
        "compute p50 was 0.5-0.9 ms lower on two threads, a dense f16 session's 0.2-0.4 ms lower with its e2e p50 and "
        "p99 0.2-0.5 ms lower; on the AMD VM of round eight threads were slower for dense frames, which auto's "
        "measurement sees (benchmarks/README.md, rounds eight, ten and eleven). Same bits in every mode.")
    compute_in_loop: Literal["alone", "never"] = Field(
        "alone", description="alone (default): a session that is the only one connected computes its frames on the "
        "event loop's thread (no hand-off to the compute pool and back: queue 0.13 against 0.18-0.22 ms p50); "
        "never: always on the pool. On the 2-core Intel VM of 7 December 2026, with a threaded frame's workers kept "
        "off the caller's CPU (ofera.thread_placement), a lone q13 delta session's e2e was p50 2.07 / p99 3.09 ms "
        "alone against 2.37 / 4.09 (medians of four alternating pairs; better in two more), a dense f16 session's "
        "the same either way (eight pairs). Before that placement, the loop's CPU was where the scheduler packed "
        "the frame's second thread too, and alone was worse on that VM (benchmarks/README.md, rounds nine, eleven "
        "and twenty).")
    warmup: bool = Field(True, description="Load and run the default avatar's pipeline before accepting.")
    key_interval: int = Field(720, ge=0, description="Delta sessions (hello.delta): a key frame every this many "
                              "frames sent (besides join and resync); 0: only on join and resync.")
    delta_position_mm: float = Field(0.045, gt=0, description="Delta sessions: a Gaussian is re-sent once its "
                                     "position is this far (mm, Euclidean) from what the client holds.")
    delta_rotation_deg: float = Field(0.45, gt=0, description="Delta sessions: ... or its rotation this many "
                                      "degrees from the held one.")
    delta_log_scale: float = Field(0.02, gt=0, description="Delta sessions: ... or a scale axis this far in ln.")
    log_level: str = Field("info", description="uvicorn log level.")
    tcp_congestion: str = Field(
        "cubic,reno", description="TCP congestion control of each streaming connection (Linux; tried in order, "
        "comma-separated; the first the kernel accepts; empty: the system's). Not BBR: it paces a frame's burst at "
        "its estimate of this app-limited stream's rate, which held back the tail of ~2 % of 100-300 kB frames by "
        "10 ms on loopback (benchmarks/README.md). Reno is the fallback a process without CAP_NET_ADMIN may set "
        "where cubic is not in net.ipv4.tcp_allowed_congestion_control.")
    event_loop: Literal["asyncio", "uvloop", "auto"] = Field(
        "auto", description="Event loop, chosen at start: auto (uvloop when the optional `uvloop` extra is installed: "
        "pip install 'ofera[uvloop]'; measured ~0.5 ms lower e2e p50 at 2 MB frames, benchmarks/README.md), asyncio, "
        "or uvloop.")
    room_members: int = Field(16, ge=1, description="Rooms: most members per room (PROTOCOL.md 12.6; one more: "
                              "room_full).")
    max_rooms: int = Field(64, ge=1, description="Rooms: most rooms on this server (a new one beyond: "
                           "too_many_rooms).")
    room_send_bytes: int = Field(32 * 1024 * 1024, ge=1, description="Rooms: most bytes of frames in flight per "
                                 "connection (frames of several members sent concurrently up to this; beyond it "
                                 "they wait, newest wins).")
    room_control_bytes: int = Field(ROOM_CONTROL_BYTES, ge=1, description="Rooms: most bytes of join, avatar "
                                    "and leave messages queued per connection (one member's always may); beyond it "
                                    "the connection reads too slowly: its session ends with a fatal server_full "
                                    "(PROTOCOL.md 12.6). Keep it above room_members x the largest avatar's bytes.")
    room_secret: str | None = Field(None, description="Rooms: if set, every room hello must carry room_token = hex "
                                    "HMAC-SHA256(room_secret, room name) (PROTOCOL.md 12.1).")
    redis_url: str | None = Field(
        None, description="redis://HOST:PORT/DB (or rediss://, unix://): rooms span every server attached to this "
        "Redis (streaming.redis_bus); unset: rooms are in-process.")

    @field_validator("token", "room_secret", "avatars", "avatar_zip", "devices", "ssl_keyfile", "ssl_certfile",
                     mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v

    @field_validator("cpus", mode="before")
    @classmethod
    def _cpu_list(cls, v: object) -> object:
        if v is None or (isinstance(v, str) and not v.strip()):
            return None
        from .affinity import parse_cpus

        parse_cpus(str(v))  # ValueError naming the bad part
        return str(v).strip()

    @field_validator("redis_url", mode="before")
    @classmethod
    def _redis_scheme(cls, v: object) -> object:
        if v is None or (isinstance(v, str) and not v.strip()):
            return None
        if isinstance(v, str) and not v.startswith(("redis://", "rediss://", "unix://")):
            raise ValueError(f"not a Redis URL (redis://HOST:PORT/DB, rediss:// or unix://): {v.split('@')[-1]!r}")
        return v

    @field_validator("allowed_origins", mode="before")
    @classmethod
    def _origin_list(cls, v: object) -> object:
        if isinstance(v, (list, tuple, set, frozenset)):
            v = ",".join(str(o) for o in v)
        return None if v is None or (isinstance(v, str) and not v.strip()) else v

    @model_validator(mode="after")
    def _tls_pair(self) -> Settings:
        if (self.ssl_keyfile is None) != (self.ssl_certfile is None):
            raise ValueError("give both ssl_keyfile and ssl_certfile (or neither)")
        return self

    @property
    def origins(self) -> frozenset[str] | None:
        """Allowed browser origins, normalised (lower case, no trailing slash); None: any."""
        if self.allowed_origins is None:
            return None
        found = frozenset(normalize_origin(o) for o in self.allowed_origins.split(",") if o.strip())
        return None if not found or "*" in found else found

    @property
    def cpu_set(self) -> frozenset[int] | None:
        """`cpus` as CPU numbers (None: unset)."""
        from .affinity import parse_cpus

        return None if self.cpus is None else parse_cpus(self.cpus)

    @property
    def tls(self) -> bool:
        return self.ssl_certfile is not None

    @property
    def burst(self) -> float:
        return self.bs_burst if self.bs_burst is not None else max(1.0, self.bs_rate)


def normalize_origin(origin: str) -> str:
    """An Origin header or a configured origin, compared case-insensitively and without a trailing slash."""
    return origin.strip().rstrip("/").lower()
