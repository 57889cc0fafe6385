"""`ofera serve`: run the streaming server (built-in default avatar when given no argument)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .errors import CliError, user_errors


@user_errors()
def serve(
    host: Annotated[str | None, typer.Option(help="Interface [env OFERA_HOST; default 127.0.0.1].")] = None,
    port: Annotated[int | None, typer.Option(help="TCP port, 0 = any free [env OFERA_PORT; default 8000].")] = None,
    avatars: Annotated[Path | None, typer.Option(help="Directory of avatars (each may have a sibling <id>.onnx EPM "
                                                  "and <id>.bda.npz BDA) [env OFERA_AVATARS].")] = None,
    avatar_zip: Annotated[Path | None, typer.Option(help="A LAM avatar export .zip to serve (imported once, "
                                                     "cached by content); the default avatar unless "
                                                     "--default-avatar is given [env OFERA_AVATAR_ZIP].")] = None,
    devices: Annotated[Path | None, typer.Option(help="Directory of device BDA profiles <device>.npz "
                                                  "[env OFERA_DEVICES].")] = None,
    default_avatar: Annotated[str | None, typer.Option(help="Avatar id that 'default' means "
                                                        "[env OFERA_DEFAULT_AVATAR].")] = None,
    token: Annotated[str | None, typer.Option(help="Require this token in hello [env OFERA_TOKEN].")] = None,
    allowed_origins: Annotated[str | None, typer.Option(help="Comma-separated browser origins allowed to connect; "
                                                         "others get HTTP 403, clients without Origin are "
                                                         "allowed [env OFERA_ALLOWED_ORIGINS].")] = None,
    ssl_keyfile: Annotated[Path | None, typer.Option(help="TLS private key (PEM), with --ssl-certfile: serve "
                                                       "wss:// [env OFERA_SSL_KEYFILE].")] = None,
    ssl_certfile: Annotated[Path | None, typer.Option(help="TLS certificate chain (PEM) [env "
                                                        "OFERA_SSL_CERTFILE].")] = None,
    max_sessions: Annotated[int | None, typer.Option(help="Most concurrent sessions [env OFERA_MAX_SESSIONS].")] = None,
    max_message_bytes: Annotated[int | None, typer.Option(help="Largest client message "
                                                           "[env OFERA_MAX_MESSAGE_BYTES].")] = None,
    bs_rate: Annotated[float | None, typer.Option(help="Most bs per second per session [env OFERA_BS_RATE].")] = None,
    compute_threads: Annotated[int | None, typer.Option(help="Pipeline threads, 0 = one per core "
                                                         "[env OFERA_COMPUTE_THREADS].")] = None,
    confidence_threshold: Annotated[float | None, typer.Option(help="A face region whose bs confidence is below "
                                                                "this keeps its last confident expression (default "
                                                                "0.5; 0: never) [env OFERA_CONFIDENCE_THRESHOLD]."
                                                                )] = None,
    key_interval: Annotated[int | None, typer.Option(help="Delta sessions: a key frame every N frames sent, 0 = "
                                                      "only on join and resync (default 720) [env "
                                                      "OFERA_KEY_INTERVAL].")] = None,
    delta_position_mm: Annotated[float | None, typer.Option(help="Delta sessions: position tolerance, mm (default "
                                                             "0.045) [env OFERA_DELTA_POSITION_MM].")] = None,
    delta_rotation_deg: Annotated[float | None, typer.Option(help="Delta sessions: rotation tolerance, degrees "
                                                              "(default 0.45) [env OFERA_DELTA_ROTATION_DEG].")] = None,
    delta_log_scale: Annotated[float | None, typer.Option(help="Delta sessions: scale tolerance, |ln ratio| (default "
                                                           "0.02) [env OFERA_DELTA_LOG_SCALE].")] = None,
    kernel_threads: Annotated[str | None, typer.Option(help="Fast path threads: auto (a lone session's frames on "
                                                        "both cores where it measures that faster), serial, or "
                                                        "parallel (every frame on both cores) (default auto) [env "
                                                        "OFERA_KERNEL_THREADS].")] = None,
    compute_in_loop: Annotated[str | None, typer.Option(help="alone (default): a lone session computes on the "
                                                         "event loop's thread, no hand-off to the pool; never: always "
                                                         "on the pool [env OFERA_COMPUTE_IN_LOOP].")] = None,
    cpus: Annotated[str | None, typer.Option(help="CPUs to run on, e.g. 0 or 2-3 (Linux affinity of every thread; "
                                              "keep the server off its clients' cores) [env OFERA_CPUS]; default: "
                                              "any.")] = None,
    log_level: Annotated[str | None, typer.Option(help="uvicorn log level [env OFERA_LOG_LEVEL].")] = None,
    redis: Annotated[str | None, typer.Option("--redis", help="redis://HOST:PORT/DB: rooms span every server "
                                              "attached to this Redis [env OFERA_REDIS_URL].")] = None,
    room_members: Annotated[int | None, typer.Option(help="Rooms: most members per room (default 16) [env "
                                                      "OFERA_ROOM_MEMBERS].")] = None,
    max_rooms: Annotated[int | None, typer.Option(help="Rooms: most rooms on this server (default 64) [env "
                                                   "OFERA_MAX_ROOMS].")] = None,
    room_secret: Annotated[str | None, typer.Option(help="Rooms: every room hello must carry room_token = hex "
                                                     "HMAC-SHA256(secret, room) [env OFERA_ROOM_SECRET].")] = None,
) -> None:
    """Stream Gaussian avatars over WebSocket: warms up the default avatar, prints where to connect."""
    from pydantic import ValidationError

    from ..streaming.config import Settings
    from ..streaming.registry import AvatarRegistry
    from ..streaming.server import serve as run

    given = {k: v for k, v in dict(host=host, port=port, avatars=avatars, avatar_zip=avatar_zip, devices=devices,
                                   default_avatar=default_avatar, token=token, allowed_origins=allowed_origins,
                                   ssl_keyfile=ssl_keyfile, ssl_certfile=ssl_certfile, max_sessions=max_sessions,
                                   max_message_bytes=max_message_bytes, bs_rate=bs_rate,
                                   compute_threads=compute_threads, confidence_threshold=confidence_threshold,
                                   key_interval=key_interval, delta_position_mm=delta_position_mm,
                                   delta_rotation_deg=delta_rotation_deg, delta_log_scale=delta_log_scale,
                                   kernel_threads=kernel_threads, compute_in_loop=compute_in_loop, cpus=cpus,
                                   log_level=log_level, redis_url=redis,
                                   room_members=room_members, max_rooms=max_rooms,
                                   room_secret=room_secret).items() if v is not None}
    try:
        settings = Settings(**given)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise CliError(f"bad settings: {problems}") from None
    if settings.redis_url:  # refuse to start (one line naming the URL) before warming up
        import asyncio

        from ..streaming.redis_bus import check_redis

        asyncio.run(check_redis(settings.redis_url))
    default = AvatarRegistry.default_id_for(settings)
    print(f"OFERA server: warming up avatar {default!r} on {settings.host}:{settings.port} ...",
          flush=True)
    run(settings)
