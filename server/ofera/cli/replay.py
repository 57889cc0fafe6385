"""`ofera replay LOG --url URL` and `ofera ingest livelink|vmc --url URL`: drive a running server from a
recorded face log or from live UDP face tracking, and report what came back."""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import click
import typer
from typer.core import TyperCommand, TyperGroup

from .errors import CliError, user_errors

UrlOpt = Annotated[str, typer.Option("--url", help="Server: ws://HOST:PORT (the /v1/stream path is added).")]
AvatarOpt = Annotated[str, typer.Option("--avatar", help="Avatar id to ask for ('default': the server's).")]
EncodingOpt = Annotated[str, typer.Option("--encoding", help="Frame encoding: f32, f16 or q13.")]
TokenOpt = Annotated[str | None, typer.Option("--token", help="Access token, if the server requires one.")]
JsonOpt = Annotated[Path | None, typer.Option("--json", help="Write the run's summary as JSON here ('-': stdout).")]

ingest_app = typer.Typer(
    help="Live face tracking over UDP into an avatar session (no Unity needed).", no_args_is_help=True)


def _err_console():
    from rich.console import Console

    return Console(stderr=True, soft_wrap=True, highlight=False)


def _write_json(target: Path | None, summary: dict) -> None:
    if target is None:
        return
    text = json.dumps(summary, indent=2)
    if str(target) == "-":
        print(text)
    else:
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text + "\n")


def _run_with_sigint(coro_factory: Callable[[], object], on_sigint: Callable[[], None]):
    """asyncio.run, with the first Ctrl-C calling `on_sigint` (a graceful stop) instead of raising."""

    async def main():
        loop = asyncio.get_running_loop()
        installed = False
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):

            def first_sigint() -> None:
                loop.remove_signal_handler(signal.SIGINT)  # a second Ctrl-C interrupts for real
                on_sigint()

            loop.add_signal_handler(signal.SIGINT, first_sigint)
            installed = True
        try:
            return await coro_factory()
        finally:
            if installed:
                with contextlib.suppress(Exception):
                    loop.remove_signal_handler(signal.SIGINT)

    return asyncio.run(main())


def _check_encoding(encoding: str) -> None:
    from ofera_protocol import ENCODINGS

    if encoding not in ENCODINGS:
        raise CliError(f"--encoding {encoding!r} is not one of {', '.join(ENCODINGS)}")


def _explain_failure(stats, what: str) -> None:
    """Exit non-zero, saying what went wrong, when the server refused or reported errors."""
    if stats.fatal_error is not None:
        message = stats.fatal_error
    elif stats.errors:
        first = stats.error_messages[0] if stats.error_messages else "?"
        message = f"the server reported {stats.errors} error(s) during the {what}; first: {first}"
    else:
        return
    print(f"error: {message}", file=sys.stderr)
    raise typer.Exit(1)


PLAY = "play"
HELP_OPTIONS = ("-h", "--help")


class ReplayGroup(TyperGroup):
    """`ofera replay LOG ...` replays a log (the hidden `play` command); `ofera replay inspect LOG` and any
    other subcommand are dispatched by name. A first argument that is neither a subcommand nor a help option
    is the log. `ofera replay --help` shows the replay's usage, arguments and options, then the subcommands."""

    def parse_args(self, ctx, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in HELP_OPTIONS:
            args = [PLAY, *args]
        return super().parse_args(ctx, args)

    def format_help(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        self.commands[PLAY].format_help(ctx, formatter)  # usage `ofera replay [OPTIONS] LOG` (PlayCommand)
        rows = [(name, cmd.get_short_help_str(limit=70)) for name, cmd in self.commands.items() if not cmd.hidden]
        with formatter.section("Commands"):  # plain click help, like every command's (cli.main: no rich markup)
            formatter.write_dl(rows)


class PlayCommand(TyperCommand):
    """The hidden `play` command: its usage line is `ofera replay [OPTIONS] LOG`, how it is invoked."""

    def get_usage(self, ctx: click.Context) -> str:
        formatter = ctx.make_formatter()
        self.format_usage(ctx, formatter)
        return formatter.getvalue().rstrip("\n")

    def format_usage(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        path = ctx.command_path
        if ctx.info_name == PLAY and ctx.parent is not None:
            path = ctx.parent.command_path
        formatter.write_usage(path, " ".join(self.collect_usage_pieces(ctx)))


replay_app = typer.Typer(cls=ReplayGroup, context_settings={"help_option_names": list(HELP_OPTIONS)},
                         no_args_is_help=True,
                         help="Replay a recorded face log through a running server "
                         "(`ofera replay LOG --url URL`), or describe it (`ofera replay inspect LOG`).")


def replay(
    log: Annotated[Path | None, typer.Argument(help="Face log: face-log/MediaPipe/ARKit CSV, Quest Pro Unity log, "
                                              "Live Link Face CSV or .gesichter capture (optional with --watch).",
                                              show_default=False)] = None,
    url: UrlOpt = "ws://127.0.0.1:8000",
    speed: Annotated[float, typer.Option("--speed", help="Playback speed (2: twice as fast).")] = 1.0,
    loop: Annotated[bool, typer.Option("--loop", help="Repeat the log until Ctrl-C.")] = False,
    passes: Annotated[int | None, typer.Option("--passes", help="With --loop: stop after N passes.")] = None,
    layout: Annotated[str, typer.Option("--layout", help="'auto' (detect from the column names) or a layout "
                                        "the log must hold: arkit52, arkit51, mediapipe52, ovr63, ovr70, "
                                        "livelink61.")] = "auto",
    fps: Annotated[float | None, typer.Option("--fps", help="Frame rate of a Live Link timecode (default 60), "
                                              "of a CSV frame column, or the row rate of a log without "
                                              "time (Quest snapshot or headerless logs).")] = None,
    record: Annotated[Path | None, typer.Option("--record", help="Save the received frames to this .npz "
                                                "(seq, t_us, recv_us, latency, timing, answered weights).")] = None,
    record_positions: Annotated[bool, typer.Option("--record-positions", help="With --record: also save every "
                                                   "frame's Gaussian positions (F x N x 3).")] = False,
    json_out: JsonOpt = None,
    avatar: AvatarOpt = "default",
    encoding: EncodingOpt = "f32",
    delta: Annotated[bool, typer.Option("--delta", help="Ask for temporal deltas (key and delta frames; --encoding "
                                        "f16 or q13). With --record-positions the client's reconstruction is "
                                        "recorded.")] = False,
    token: TokenOpt = None,
    max_lag: Annotated[float, typer.Option("--max-lag", help="Skip frames found more than this many seconds "
                                           "overdue (a stalled sender catches up).")] = 1.0,
    drain: Annotated[float, typer.Option("--drain", help="Seconds to wait for the last frames after "
                                         "sending.")] = 2.0,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    room: Annotated[str | None, typer.Option("--room", help="Join this room (PROTOCOL.md 12): the log drives this "
                                             "client's avatar there, and every other member's frames are counted "
                                             "per member.")] = None,
    watch: Annotated[bool, typer.Option("--watch", help="With --room: watch only (send nothing), for --seconds, or "
                                        "for the LOG's duration, or until Ctrl-C.")] = False,
    self_view: Annotated[bool, typer.Option("--self", help="With --room: also receive one's own avatar (latency of "
                                            "one's own frames, as without a room).")] = False,
    room_token: Annotated[str | None, typer.Option("--room-token", help="With --room: the room's token, if the "
                                                   "server has a room secret.")] = None,
    seconds: Annotated[float | None, typer.Option("--seconds", help="With --watch: how long to watch.")] = None,
    full_decode: Annotated[bool, typer.Option("--full-decode", help="Decode and check every frame's arrays. "
                                              "Default: read only each frame's seq, t and timing (a light load "
                                              "generator), unless --record-positions or --delta need the "
                                              "arrays.")] = False,
) -> None:
    """Send a recorded face log to a server at its recorded pace and measure the frames that come back.

    Quest Pro logs send one `bs` per tracker sample (repeated rows dropped), with their lower/upper face
    confidences when the log has them. `ofera replay inspect LOG` shows what a log holds, without a server.

    With --room, several replays into one room are several people meeting (each sees the others); --watch joins
    as a watch-only member.

    Exits 1 when the server refuses the session or reports errors, 2 on a bad argument or log.
    """
    if watch or room is not None:
        _room_checks(log, room, watch, delta, seconds)
    if watch:
        _watch(log, url, room, encoding, token, room_token, json_out, seconds, quiet, full_decode)
        return
    _replay(log, url, speed, loop, passes, layout, fps, record, record_positions, json_out, avatar, encoding,
            token, max_lag, drain, quiet, delta, room, self_view, room_token, full_decode)


@user_errors()
def _room_checks(log, room, watch, delta, seconds) -> None:
    if room is None:
        raise CliError("--watch needs --room NAME (the room to watch)")
    if delta:
        raise CliError("--delta is not offered in rooms (PROTOCOL.md 12.1)")
    if not watch and log is None:
        raise CliError("give the face LOG to replay into the room (or --watch to watch it)")
    if seconds is not None and seconds <= 0:
        raise CliError(f"--seconds must be positive, got {seconds}")


@user_errors()
def _watch(log_path, url, room, encoding, token, room_token, json_out, seconds, quiet, full_decode=False) -> None:
    from ofera.replay import LinkOptions, stream_url, watch_through

    _check_encoding(encoding)
    target = stream_url(url)
    if seconds is None and log_path is not None:
        from ofera.sources import read_facelog_report

        log, _ = read_facelog_report(log_path, "auto", None)
        seconds = float(log.duration)
    options = LinkOptions(layout="arkit52", encoding=encoding, token=token, room=room, publish=False,
                          room_token=room_token, header_only=not full_decode)
    console = _err_console()
    console.print(f"watching room {room!r} at {target}" + (f" for {seconds:g} s" if seconds else " until Ctrl-C"))
    stop = asyncio.Event()

    def on_tick(stats) -> None:
        if not quiet:
            counts = ", ".join(f"{m} {len(v)}" for m, v in sorted(stats.members.items())) or "no frames yet"
            console.print(f"\r{counts}", end="")

    stats = _run_with_sigint(lambda: watch_through(target, options, seconds, stop, on_tick, tick_s=0.5), stop.set)
    if not quiet:
        console.print()
    summary = stats.summary(url=target, room=room, watch=True, seconds=seconds)
    _write_json(json_out, summary)
    for member, info in summary.get("members", {}).items():
        lat = info["latency_ms"]
        console.print(f"member {member}: {info['received']} frames, latency p50 {lat['p50']} ms, p99 {lat['p99']} ms")
    console.print(f"joined {len(stats.joined)}, left {len(stats.left)}, errors {stats.errors}")
    _explain_failure(stats, "watch")


@user_errors()
def _replay(log_path, url, speed, loop, passes, layout, fps, record, record_positions, json_out, avatar,
            encoding, token, max_lag, drain, quiet, delta=False, room=None, self_view=False, room_token=None,
            full_decode=False) -> None:
    from ofera.replay import FrameRecorder, LinkOptions, Replayer, replay_through, stream_url
    from ofera.sources import read_facelog_report

    if log_path is None:
        raise CliError("give the face LOG to replay (ofera replay LOG --url URL)")
    if passes is not None and passes < 1:
        raise CliError(f"--passes must be at least 1, got {passes}")
    _check_encoding(encoding)
    if delta and encoding not in ("f16", "q13"):
        raise CliError(f"--delta needs --encoding f16 or q13 (got {encoding})")
    if record_positions and record is None:
        raise CliError("--record-positions needs --record OUT.npz (the file the positions go to)")
    target = stream_url(url)
    log, report = read_facelog_report(log_path, layout, fps)
    replayer = Replayer(log, speed=speed, loop=loop, max_lag=max_lag,
                        max_passes=passes if loop else 1)
    recorder = FrameRecorder(log.layout.name, log.weights, replayer.times, record_positions) if record else None
    options = LinkOptions(layout=log.layout.name, avatar=avatar, encoding=encoding, token=token, delta=delta,
                          track=record_positions, room=room, self_view=self_view, room_token=room_token,
                          header_only=not (full_decode or record_positions or delta))
    console = _err_console()
    console.print(f"replaying {log_path} ({len(log)} frames, {log.duration:.2f} s, layout {log.layout.name}) "
                  f"to {target} at x{speed:g}{' in a loop' if loop else ''}")
    if report.format.startswith("quest"):
        console.print(f"{report.format}: {report.rows} rows -> {report.samples} samples ({report.duplicates} "
                      f"repeats, {report.invalid + report.malformed} invalid dropped), time: {report.time_source}"
                      + (", with lower/upper confidence" if log.confidence is not None else ""))
    for note in report.problems:
        console.print(f"note: {note}")
    progress, on_tick = _progress(console, replayer, quiet)
    with progress or contextlib.nullcontext():
        stats = _run_with_sigint(
            lambda: replay_through(replayer, target, options, recorder, drain_s=drain, on_tick=on_tick),
            replayer.stop)
    summary = stats.summary(
        log=str(log_path), layout=log.layout.name, url=target, speed=speed, loop=loop, passes=stats.passes, room=room,
        frames_in_log=len(log), log_duration_s=round(replayer.log_duration, 4),
        log_format=report.format, rows_in_log=report.rows, time_source=report.time_source,
        confidence_sent=log.confidence is not None,
    )
    _write_json(json_out, summary)
    if recorder is not None:
        saved = recorder.save(record)
        console.print(f"recorded {len(recorder)} frames to {saved}")
    lat = summary["latency_ms"]
    console.print(
        f"sent {stats.sent}, received {stats.received}, skipped {stats.skipped}, errors {stats.errors}; "
        f"sending took {stats.duration:.3f} s (expected {stats.expected_duration or 0:.3f} s), "
        f"wall {stats.wall:.3f} s; latency p50 {lat['p50']} ms, p99 {lat['p99']} ms")
    for member, info in summary.get("members", {}).items():
        mlat = info["latency_ms"]
        console.print(f"member {member}: {info['received']} frames, latency p50 {mlat['p50']} ms, "
                      f"p99 {mlat['p99']} ms")
    _explain_failure(stats, "replay")


replay_app.command(PLAY, hidden=True, cls=PlayCommand)(replay)


@replay_app.command("inspect")
@user_errors()
def inspect_log(
    log: Annotated[Path, typer.Argument(help="Face log to describe (any format `ofera replay` reads).",
                                       show_default=False)],
    layout: Annotated[str, typer.Option("--layout", help="As for `ofera replay`: 'auto', or the layout the "
                                        "log must hold (a headerless Quest log: ovr63 or ovr70).")] = "auto",
    fps: Annotated[float | None, typer.Option("--fps", help="As for `ofera replay`: the row rate of a log "
                                              "without time.")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the report as JSON instead of text.")] = False,
) -> None:
    """Describe a face log as `ofera replay` would read it: detected format and layout, rows, samples kept,
    duplicates and invalid rows dropped, time source, rate, duration, columns ignored. Needs no server."""
    from ofera.sources import read_facelog_report

    _, report = read_facelog_report(log, layout, fps)
    if json_out:
        print(json.dumps(report.to_dict(), indent=2))
    else:
        print(report.text())


def _progress(console, replayer, quiet: bool):
    if quiet or not console.is_terminal:
        return None, None
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    progress = Progress(TextColumn("replay"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        TextColumn("{task.fields[info]}"), console=console, transient=False)
    task = progress.add_task("replay", total=replayer.total_frames, info="")

    def on_tick(r) -> None:
        s = r.stats
        recent = s.latencies[-100:]
        p50 = f"{sorted(recent)[len(recent) // 2] * 1e3:.1f} ms" if recent else "-"
        progress.update(task, completed=r.position,
                        info=f"received {s.received}  errors {s.errors}  latency {p50}")

    return progress, on_tick


def _ingest(kind: str, listen: str, url: str, avatar: str, encoding: str, token: str | None,
            seconds: float | None, status_every: float, json_out: Path | None, quiet: bool) -> None:
    from ofera.ingest import LiveLinkDecoder, VmcDecoder, parse_listen, run_ingest
    from ofera.ingest.run import IngestResult
    from ofera.replay import LinkOptions, stream_url

    if seconds is not None and seconds <= 0:
        raise CliError(f"--seconds must be positive, got {seconds}")
    if status_every <= 0:
        raise CliError(f"--status-every must be positive, got {status_every}")
    _check_encoding(encoding)
    default_port = 11111 if kind == "livelink" else 39539
    host, port = parse_listen(listen, default_port)
    decoder = LiveLinkDecoder() if kind == "livelink" else VmcDecoder()
    layout = decoder.layout.name
    target = stream_url(url)
    console = _err_console()
    stop = asyncio.Event()
    result = IngestResult()

    def on_listening(addr) -> None:
        console.print(f"{decoder.name} on udp {addr[0]}:{addr[1]} -> {target} (layout {layout}); "
                      + (f"for {seconds:g} s" if seconds else "Ctrl-C to stop"))

    def on_status(r) -> None:
        if not quiet:
            console.print(r.status_line(), highlight=False)

    try:
        _run_with_sigint(
            lambda: run_ingest(decoder, layout, host, port, target,
                               LinkOptions(layout=layout, avatar=avatar, encoding=encoding, token=token),
                               seconds=seconds, status_every=status_every, on_status=on_status,
                               on_listening=on_listening, stop=stop, result=result),
            stop.set)
    except OSError as e:
        raise CliError(f"cannot listen on udp {host}:{port}: {e.strerror or e} (port in use? try --listen "
                       f"{host}:0 or another port)") from None
    summary = result.summary(kind=kind, layout=layout, url=target)
    _write_json(json_out, summary)
    console.print(result.status_line(window=10**9), highlight=False)
    if result.packets.last_problem and result.packets.bad:
        console.print(f"last bad packet: {result.packets.last_problem}", highlight=False)
    _explain_failure(result.stats, "ingest")


ListenHelp = "UDP address to listen on, HOST:PORT (port 0: any free port)."
SecondsOpt = Annotated[float | None, typer.Option("--seconds", help="Stop after this many seconds "
                                                  "(default: until Ctrl-C).")]
StatusOpt = Annotated[float, typer.Option("--status-every", help="Seconds between status lines.")]
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="No periodic status lines.")]


@ingest_app.command("livelink")
@user_errors()
def ingest_livelink(
    url: UrlOpt = "ws://127.0.0.1:8000",
    listen: Annotated[str, typer.Option("--listen", help=ListenHelp)] = "0.0.0.0:11111",
    avatar: AvatarOpt = "default",
    encoding: EncodingOpt = "f32",
    token: TokenOpt = None,
    seconds: SecondsOpt = None,
    status_every: StatusOpt = 1.0,
    json_out: JsonOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Receive Epic Live Link Face packets (iPhone, UDP 11111) and drive an avatar with layout livelink61.

    Point the Live Link Face app's target at this machine. The newest packet wins; malformed packets are
    counted and skipped. Exits 1 when the server refuses the session or reports errors.
    """
    _ingest("livelink", listen, url, avatar, encoding, token, seconds, status_every, json_out, quiet)


@ingest_app.command("vmc")
@user_errors()
def ingest_vmc(
    url: UrlOpt = "ws://127.0.0.1:8000",
    listen: Annotated[str, typer.Option("--listen", help=ListenHelp)] = "0.0.0.0:39539",
    avatar: AvatarOpt = "default",
    encoding: EncodingOpt = "f32",
    token: TokenOpt = None,
    seconds: SecondsOpt = None,
    status_every: StatusOpt = 1.0,
    json_out: JsonOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Receive VMC protocol blendshapes (OSC over UDP 39539: VSeeFace, VMagicMirror perfect sync, ...) and
    drive an avatar with layout arkit52: `/VMC/Ext/Blend/Val` sets a shape, `/VMC/Ext/Blend/Apply` sends
    the frame. Malformed datagrams are counted and skipped."""
    _ingest("vmc", listen, url, avatar, encoding, token, seconds, status_every, json_out, quiet)
