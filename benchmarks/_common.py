"""Helpers shared by benchmarks/{latency,capacity,bandwidth,scaling}.py.

- Avatars of a given size: the procedural default avatar generator at ``count`` Gaussians, cached as
  ``bench-<N>-<key>.npz`` in the OFERA cache (``$OFERA_CACHE`` or ~/.cache/ofera/bench).
- The EPM: the shipped default when present; otherwise a stand-in with the paper's shape (51 -> 128,
  4 residual blocks, -> 68) and fixed random weights, built with ``onnx`` (same run-time cost; its
  outputs are plausible FLAME values but not a trained mapping: results say so in a ``notes`` entry).
- A server in a subprocess (its own interpreter and GIL, like a deployment) on a free port, the fast
  path or the numpy reference (``--impl``), reachable when ``/healthz`` answers (after warm-up).
- The blendshape input: the real capture ``livelink_dao.gesichter`` in the shared data folder
  (``$OFERA_SHARED_DATA``, default ``../shared/data`` next to the repository; ``$OFERA_CAPTURE`` names the
  file itself) when present, else a synthetic smooth log (noted).
- Accounting of dropped ``bs`` (``drop_latencies``), server RSS (``rss_mb``), percentiles, tables, JSON and
  the PNG next to it.

Run as a script, this module is the server process: ``python benchmarks/_common.py serve '<json>'``.
"""

from __future__ import annotations

import atexit
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SHARED_DATA = Path(os.environ.get("OFERA_SHARED_DATA") or ROOT.parent / "shared" / "data")
"""The shared data folder (not in the repository): ``$OFERA_SHARED_DATA``, else ``../shared/data`` from the root."""
CAPTURE = Path(os.environ.get("OFERA_CAPTURE") or SHARED_DATA / "livelink_dao.gesichter")
AVATAR_ID = "bench"
IMPLS = ("fast", "reference")
PARAMS_SESSION_JS = """\
  const P = await import("/static/protocol.js");
  const R = await import("/static/rig.js");
  const ws = new WebSocket(`ws://${location.host}/v1/stream`);
  ws.binaryType = "arraybuffer";
  const queue = []; let waiter = null;
  ws.onmessage = (ev) => { if (waiter) { const w = waiter; waiter = null; w(ev.data); } else queue.push(ev.data); };
  const next = () => queue.length ? Promise.resolve(queue.shift()) : new Promise((r) => { waiter = r; });
  await new Promise((r) => { ws.onopen = r; });
  ws.send(P.helloMessage({ layout, encoding: "params" }));
  const welcome = P.decodeServerMessage(new Uint8Array(await next()));
  const asm = new R.RigAssembler(welcome.rigBytes ?? null);
  for (;;) {
    const m = P.decodeServerMessage(new Uint8Array(await next()));
    if (m.type === "rig" && asm.add(m)) break;
  }
"""
"""JavaScript, the start of an async function of ``layout`` run in a page of the server: a params session
(``ws``, ``next()`` its next message, ``welcome``) whose rig ``asm`` has come in whole (``P``: protocol.js, ``R``:
rig.js). Shared by benchmarks/params.py and tests/test_params_browser.py."""


# ----------------------------------------------------------------------------- inputs


def cache_dir() -> Path:
    from ofera.assets import cache_dir as ofera_cache

    return ofera_cache("bench")


def bench_avatar(count: int | None) -> Path:
    """Path of a procedural avatar .npz of about ``count`` Gaussians (None: the default avatar)."""
    from ofera.avatar.cache import default_avatar_key

    path = cache_dir() / f"bench-{count or 'default'}-{default_avatar_key()}.npz"
    if not path.is_file():
        from ofera.avatar import save_avatar
        from ofera.avatar.procedural import make_default_avatar

        avatar = make_default_avatar(count=count)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
        save_avatar(avatar, tmp)
        os.replace(tmp, path)
    return path


def load_bench_avatar(count: int | None):
    from ofera.avatar import load_avatar

    return load_avatar(bench_avatar(count))


def standin_epm(path: Path, seed: int = 0, hidden: int = 128, blocks: int = 4) -> Path:
    """An EPM-shaped ONNX model with fixed random weights (needs the `onnx` package)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(seed)
    inits, nodes = [], []

    def linear(name: str, x: str, n_in: int, n_out: int, scale: np.ndarray | float, bias=None) -> str:
        w = (rng.standard_normal((n_in, n_out)) / np.sqrt(n_in) * scale).astype(np.float32)
        b = np.zeros(n_out, np.float32) if bias is None else np.asarray(bias, np.float32)
        inits.extend([numpy_helper.from_array(w, f"{name}_w"), numpy_helper.from_array(b, f"{name}_b")])
        nodes.append(helper.make_node("Gemm", [x, f"{name}_w", f"{name}_b"], [name]))
        return name

    def relu(x: str) -> str:
        nodes.append(helper.make_node("Relu", [x], [f"{x}_relu"]))
        return f"{x}_relu"

    h = relu(linear("stem", "blendshapes", 51, hidden, 2.0))
    for i in range(blocks):
        a = relu(linear(f"block{i}a", h, hidden, hidden, 1.0))
        c = relu(linear(f"block{i}b", a, hidden, hidden, 0.3))
        nodes.append(helper.make_node("Add", [h, c], [f"res{i}"]))
        h = f"res{i}"
    bias = np.zeros(68)
    bias[50:] = [1, 0, 0, 0, 1, 0] * 3  # identity jaw and eyes
    out_scale = np.concatenate([np.full(50, 0.25), np.full(18, 0.02)])  # expressions ~1, rotations ~0.1 rad
    out = linear("head", h, hidden, 68, out_scale, bias)
    nodes.append(helper.make_node("Identity", [out], ["flame"]))
    graph = helper.make_graph(nodes, "standin_epm",
                              [helper.make_tensor_value_info("blendshapes", TensorProto.FLOAT, ["batch", 51])],
                              [helper.make_tensor_value_info("flame", TensorProto.FLOAT, ["batch", 68])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="ofera-bench")
    model.ir_version = 8  # readable by older ONNX Runtime builds
    onnx.checker.check_model(model)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    onnx.save(model, str(tmp))
    os.replace(tmp, path)
    return path


def epm() -> tuple[Path | None, list[str]]:
    """(EPM ONNX to use, or None for the shipped default; notes)."""
    from ofera.assets import asset_path

    if asset_path("epm_default.onnx").is_file():
        return None, []
    path = cache_dir() / "standin_epm.onnx"
    if not path.is_file():
        try:
            standin_epm(path)
        except ImportError:
            raise SystemExit("the default EPM (server/ofera/assets/epm_default.onnx) is missing and the `onnx` "
                             "package needed for a stand-in is not installed: run `ofera mapping make-default` "
                             "or `pip install onnx`") from None
    return path, ["the shipped default EPM is missing: a stand-in EPM (same architecture, fixed random weights) "
                  "maps the blendshapes; timings are representative, the motion is not a trained mapping"]


def mapper():
    from ofera.mapping.runtime import Mapper

    path, notes = epm()
    return (Mapper.default() if path is None else Mapper.load(path)), notes


def avatars_dir(count: int | None) -> tuple[Path, list[str]]:
    """A temporary avatars directory holding ``bench`` (and its EPM if the default is missing), removed when the
    benchmark exits."""
    d = Path(tempfile.mkdtemp(prefix="ofera-bench-"))
    atexit.register(shutil.rmtree, d, ignore_errors=True)
    src = bench_avatar(count)
    try:
        (d / f"{AVATAR_ID}.npz").symlink_to(src)
    except OSError:
        shutil.copy(src, d / f"{AVATAR_ID}.npz")
    path, notes = epm()
    if path is not None:
        shutil.copy(path, d / f"{AVATAR_ID}.onnx")
    return d, notes


def capture(layout_fallback: str = "arkit52", seconds: float = 10.0,
            fps: float = 60.0) -> tuple[np.ndarray, str, float, list[str]]:
    """Blendshape frames (T, L) float32, their layout, fps, notes: the real capture, else synthetic."""
    if CAPTURE.is_file():
        from ofera.sources import read_facelog

        log = read_facelog(CAPTURE)
        fps = float(1.0 / np.median(np.diff(log.times))) if len(log.times) > 1 else 60.0
        return log.weights.astype(np.float32), log.layout.name, fps, []
    from ofera_protocol import LAYOUTS

    n = LAYOUTS[layout_fallback]
    t = np.arange(int(seconds * fps)) / fps
    rng = np.random.default_rng(0)
    freq = rng.uniform(0.2, 1.5, n)
    phase = rng.uniform(0, 2 * np.pi, n)
    amp = rng.uniform(0.0, 0.8, n) * (rng.random(n) < 0.5)
    w = np.clip(amp * (0.5 + 0.5 * np.sin(2 * np.pi * freq * t[:, None] + phase)), 0, 1).astype(np.float32)
    return w, layout_fallback, fps, [f"capture {CAPTURE} not found: a synthetic smooth {layout_fallback} log "
                                     "stands in (bandwidth depends on the motion: re-run with the capture)"]


# ----------------------------------------------------------------------------- servers


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def terminate(proc: subprocess.Popen, timeout: float = 10.0) -> None:
    """End a benchmark's subprocess: SIGTERM, then SIGKILL if it is still there after `timeout` seconds."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def read_params_frame(client, data, deformer=None):  # noqa: ANN001, ANN201 - ParamsFrame | None
    """A params session's message (PROTOCOL.md 13) -> its ParamsFrame when it is a stamped frame (else None), after
    `deformer` (an ofera.client.params.RigDeformer, or None: not deformed) wrote its Gaussians into the client's."""
    from ofera_protocol.messages import ParamsFrame

    msg = client.conn.receive(data)
    if not isinstance(msg, ParamsFrame) or msg.seq is None:
        return None
    if deformer is not None:
        deformer.apply(msg.params, client.conn.gaussians, client.welcome.coords)
    return msg


def wait_healthz(proc: subprocess.Popen, port: int, timeout: float) -> bool:
    """Wait for the server process ``proc`` to answer ``http://127.0.0.1:<port>/healthz`` with 200: True when it
    does, False when ``proc`` exits first or ``timeout`` seconds pass (``proc.poll()`` tells which)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return False
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=2) as r:
                if r.status == 200:
                    return True
        except OSError:
            time.sleep(0.2)
    return False


@dataclass
class ServerProcess:
    """``ofera`` server in a subprocess serving the ``bench`` avatar as the default."""

    avatars: Path
    impl: str = "fast"
    threads: int = 2
    max_sessions: int = 64
    extra: dict[str, Any] = field(default_factory=dict)  # more Settings (e.g. redis_url for benchmarks/rooms.py)
    pythonpath: str | None = None  # run the server from other sources (another checkout's server:protocol dirs)
    port: int = field(default_factory=free_port)
    proc: subprocess.Popen | None = None
    log: Any = None

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/v1/stream"

    def start(self, timeout: float = 300.0) -> ServerProcess:
        settings = {"host": "127.0.0.1", "port": self.port, "avatars": str(self.avatars),
                    "default_avatar": AVATAR_ID, "compute_threads": self.threads, "log_level": "warning",
                    "max_sessions": self.max_sessions, "bs_rate": 1000.0, "fast": self.impl == "fast", **self.extra}
        self.log = tempfile.TemporaryFile()
        env = None if self.pythonpath is None else {**os.environ, "PYTHONPATH": self.pythonpath}
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "serve", json.dumps(settings),
                                      self.impl], stdout=self.log, stderr=subprocess.STDOUT, env=env)
        if wait_healthz(self.proc, self.port, timeout):
            return self
        if self.proc.poll() is not None:
            raise RuntimeError(f"benchmark server exited ({self.proc.returncode}):\n{self.output()}")
        self.stop()
        raise RuntimeError(f"benchmark server did not come up in {timeout:.0f} s:\n{self.output()}")

    def output(self) -> str:
        if self.log is None:
            return ""
        self.log.seek(0)
        return self.log.read().decode(errors="replace")[-4000:]

    def stop(self) -> None:
        if self.proc is not None:
            terminate(self.proc, 15)

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _echo_server(port: int, size: int) -> None:
    """A bare websockets server answering every message with `size` random bytes (transport floor)."""
    import asyncio

    from websockets.asyncio.server import serve

    payload = os.urandom(size)

    async def handler(ws) -> None:  # noqa: ANN001
        async for _ in ws:
            await ws.send(payload)

    async def main() -> None:
        async with serve(handler, "127.0.0.1", port, compression=None, max_size=2**26):
            await asyncio.Future()

    asyncio.run(main())


def transport_floor(size: int, rate: float = 72.0, seconds: float = 3.0, client: str = "fast") -> dict:
    """Round trips (ms) of a tiny request answered by a `size`-byte message between two Python processes
    over loopback WebSocket, no compute: a websockets-library server, and the client on `client` ("fast":
    ofera.client.transport, what the benchmarks' clients use; "websockets": the library): the floor under any
    frame of that size on this machine."""
    import asyncio

    from ofera.client.transport import open_websocket
    from websockets.asyncio.client import connect

    port = free_port()
    proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "echo", str(port), str(size)])

    async def run() -> list[float]:
        for _ in range(100):
            try:
                if client == "fast":
                    ws = await open_websocket(f"ws://127.0.0.1:{port}/", max_size=2**26)
                else:
                    ws = await connect(f"ws://127.0.0.1:{port}", compression=None, max_size=2**26,
                                       ping_interval=None)
                break
            except OSError:
                await asyncio.sleep(0.1)
        else:
            raise RuntimeError("echo server did not start")
        lat = []
        try:
            for _ in range(int(rate * seconds)):
                t = time.perf_counter()
                await ws.send(b"x")
                await ws.recv()
                lat.append((time.perf_counter() - t) * 1e3)
                await asyncio.sleep(max(0.0, 1 / rate - (time.perf_counter() - t)))
        finally:
            await ws.close()
        return lat[int(rate * 0.3):]

    try:
        lat = asyncio.run(run())
    finally:
        proc.terminate()
        proc.wait()
    p = pct(lat)
    return {"bytes": size, "client": client, "p50": p["p50"], "p99": p["p99"], "min": round(float(np.min(lat)), 3)}


@contextmanager
def params_stamped_every_frame() -> Iterator[None]:
    """OFERA_PARAMS_STAMP_INTERVAL=0 while servers started inside are made (they inherit it: every params frame then
    carries seq and t, so that each can be timed); the previous value afterwards."""
    old = os.environ.get("OFERA_PARAMS_STAMP_INTERVAL")
    os.environ["OFERA_PARAMS_STAMP_INTERVAL"] = "0"
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("OFERA_PARAMS_STAMP_INTERVAL", None)
        else:
            os.environ["OFERA_PARAMS_STAMP_INTERVAL"] = old


def server_health(port: int) -> dict:
    """What a running server reports on /healthz ({} if it cannot be read)."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=5) as r:
            return json.loads(r.read())
    except (OSError, ValueError):
        return {}


def server_event_loop(port: int) -> str | None:
    """The event loop a running server reports on /healthz (what `--event-loop auto` resolved to)."""
    return server_health(port).get("event_loop")


def pin_split(pin: bool) -> dict | None:
    """``--pin``: the server on every CPU this process may use but the last (its ``cpus`` setting, as a user would
    run ``ofera serve --cpus``), this process (the client, and any client it starts) on the last one. Returns what
    the report records ({"server": "0", "client": [1]}), or None (unpinned). SystemExit on a single CPU."""
    if not pin:
        return None
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        raise SystemExit("--pin needs two CPUs: the server's and the client's")
    server = ",".join(map(str, cpus[:-1]))
    os.sched_setaffinity(0, {cpus[-1]})
    return {"server": server, "client": [cpus[-1]]}


def server_extra(pinned: dict | None, **extra: Any) -> dict:
    """A ServerProcess's extra settings, with the server's CPUs of :func:`pin_split`."""
    return {**extra, **({"cpus": pinned["server"]} if pinned else {})}


def _serve(settings_json: str, impl: str) -> None:
    from ofera.streaming import Settings
    from ofera.streaming.server import serve

    interval = os.environ.get("OFERA_BENCH_SWITCH_INTERVAL")  # experiment: the GIL hand-off interval (s)
    if interval:
        sys.setswitchinterval(float(interval))
    serve(Settings(**json.loads(settings_json)))


# ----------------------------------------------------------------------------- statistics and output


def pct(samples, qs=(50, 90, 99, 99.9)) -> dict[str, float | None]:
    a = np.asarray(samples, np.float64)
    keys = {50: "p50", 90: "p90", 99: "p99", 99.9: "p999"}
    if a.size == 0:
        return {**{keys[q]: None for q in qs}, "max": None, "mean": None}
    out = {keys[q]: round(float(np.percentile(a, q)), 3) for q in qs}
    out["max"] = round(float(a.max()), 3)
    out["mean"] = round(float(a.mean()), 3)
    return out


SPIN_US = 3000.0
"""The last this-many microseconds before a scheduled send are waited out with zero-length sleeps (the loop
keeps reading): asyncio's timers wake up late (epoll's timeout is in whole ms, rounded up, and on the AMD EPYC VM a
sleeping vCPU wakes later still), which would otherwise be counted as latency. Sending 300 times at 72 Hz there
(December 2026), the send came 173 / 513 / 575 us (p50 / p90 / p99) after its time with a 1.5 ms spin, 4 / 6 / 34 us
with 3 ms. The spin costs the client 3 ms of CPU a period (in the reports' client_cores), while a lone session's
server is idle (its frame left about 10 ms earlier)."""


async def sleep_until(due_us: float, spin_us: float = SPIN_US) -> None:
    """Wait until ``due_us`` (ofera.client.now_us clock) within a few microseconds: sleep, then spin the loop."""
    import asyncio

    from ofera.client import now_us

    delay = (due_us - now_us() - spin_us) / 1e6
    if delay > 0:
        await asyncio.sleep(delay)
    while now_us() < due_us:
        await asyncio.sleep(0)


async def paced_session(client, weights: np.ndarray, start_us: float, period_us: float, total: int,
                        on_message, tail_s: float) -> float:
    """Send ``total`` bs without coordinated omission (bs k is due at ``start_us + k * period_us`` and carries
    that time in ``t``) while every received message goes to ``on_message(data, received_us) -> bool`` (True:
    the last one came). Waits ``tail_s`` seconds for the receiver after the last send; returns the end time (us).
    ``weights`` (T, L) are used in a loop."""
    import asyncio

    from ofera.client import now_us

    async def sender() -> None:
        for k in range(total):
            due = start_us + k * period_us
            await sleep_until(due)
            await client.send_bs(weights[k % len(weights)], seq=k, t=int(due))

    async def receiver() -> None:
        while True:
            data = await client.ws.recv()
            if on_message(data, now_us()):
                return

    send_task = asyncio.create_task(sender())
    recv_task = asyncio.create_task(receiver())
    await send_task
    try:
        await asyncio.wait_for(recv_task, timeout=tail_s)
    except asyncio.TimeoutError:
        recv_task.cancel()
    return now_us()


def largest_ok(results: dict) -> int:
    """The largest K of ``results`` (K -> a run with ``passes``) such that every K' <= K passed (a later pass after
    a failure is noise); 0 when the smallest fails."""
    best = 0
    for k in sorted(results):
        if not results[k]["passes"]:
            break
        best = k
    return best


def drop_latencies(scheduled_us: dict[int, float], arrivals: list[tuple[int, float]],
                   end_us: float) -> dict[int, float]:
    """seq -> latency (ms) of each bs that were sent but never answered (newest-wins dropped them).

    A dropped bs counts as answered by the first later frame: latency = arrival of the first frame with a
    greater seq - the bs's scheduled time; with no later frame, the end of listening (``end_us``) stands in.
    ``scheduled_us``: seq -> scheduled send time of every counted bs; ``arrivals``: (seq, arrival time) of the
    frames received, same clock (microseconds)."""
    answered = {seq for seq, _ in arrivals}
    order = sorted(arrivals)
    seqs = np.array([s for s, _ in order], np.int64)
    later_arrival = np.minimum.accumulate(np.array([t for _, t in order], np.float64)[::-1])[::-1]  # earliest at >= i
    out = {}
    for seq, due in sorted(scheduled_us.items()):
        if seq in answered:
            continue
        i = int(np.searchsorted(seqs, seq, side="right"))
        arrived = later_arrival[i] if i < seqs.size else end_us
        out[seq] = (float(arrived) - due) / 1000.0
    return out


def cpu_seconds(pid: int | None = None) -> float:
    """User + system CPU seconds used so far by process ``pid`` (default: this one, all threads), from /proc."""
    with open(f"/proc/{pid or os.getpid()}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def machine_ticks() -> tuple[int, int] | None:
    """(steal, total) clock ticks of every CPU so far, from /proc/stat's first line; None where there is none."""
    try:
        with open("/proc/stat") as f:
            fields = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    return (fields[7], sum(fields)) if len(fields) > 7 else None


class CpuMeter:
    """CPU used by the benchmark's own process (the clients) and by the server process over a window:
    ``with CpuMeter(server_pid) as m: ...`` then ``m.report()`` -> cores used on average (CPU s / wall s), and
    ``steal_pct``: the share of the machine's CPU time its hypervisor gave to other guests in that window (the
    December 2026 VM's slow minutes: 0-3 % steal in a quiet one, 15-26 % in runs whose e2e p50 doubled)."""

    def __init__(self, server_pid: int | None = None) -> None:
        self.server_pid = server_pid
        self.start = self.end = None

    def _now(self) -> tuple[float, float, float | None, tuple[int, int] | None]:
        server = cpu_seconds(self.server_pid) if self.server_pid else None
        return time.monotonic(), cpu_seconds(), server, machine_ticks()

    def __enter__(self) -> CpuMeter:
        self.start = self._now()
        return self

    def __exit__(self, *exc: object) -> None:
        self.end = self._now()

    def report(self) -> dict[str, float | None]:
        (w0, c0, s0, m0), (w1, c1, s1, m1) = self.start, self.end
        wall = max(w1 - w0, 1e-9)
        steal = None if m0 is None or m1 is None else round(100 * (m1[0] - m0[0]) / max(m1[1] - m0[1], 1), 1)
        return {"wall_s": round(wall, 3), "client_cores": round((c1 - c0) / wall, 3),
                "server_cores": None if s0 is None or s1 is None else round((s1 - s0) / wall, 3),
                "cpus": os.cpu_count(), "steal_pct": steal}


def metrics_text(http_url: str) -> str:
    """The server's /metrics page ('' if it does not answer)."""
    try:
        return urllib.request.urlopen(f"{http_url}/metrics", timeout=5).read().decode()
    except OSError:
        return ""


def stage_histograms(text: str) -> dict[str, dict[str, Any]]:
    """``ofera_stage_seconds`` of a /metrics page: stage -> {"le": [upper bounds], "cum": [counts], "sum", "count"}."""
    import re

    out: dict[str, dict[str, Any]] = {}
    for m in re.finditer(r'ofera_stage_seconds_bucket\{le="([^"]+)",stage="([^"]+)"\}\s+([0-9.eE+-]+)', text):
        h = out.setdefault(m.group(2), {"le": [], "cum": [], "sum": 0.0, "count": 0.0})
        h["le"].append(float(m.group(1)))
        h["cum"].append(float(m.group(3)))
    for kind in ("sum", "count"):
        for m in re.finditer(rf'ofera_stage_seconds_{kind}\{{stage="([^"]+)"\}}\s+([0-9.eE+-]+)', text):
            if m.group(1) in out:
                out[m.group(1)][kind] = float(m.group(2))
    return out


def histogram_window(before: dict, after: dict, stage: str) -> dict[str, float | None]:
    """Mean and p50/p99 (ms, linear within a bucket) of one stage between two ``stage_histograms`` snapshots."""
    a = after.get(stage)
    if a is None:
        return {"mean": None, "p50": None, "p99": None, "count": 0}
    b = before.get(stage) or {"cum": [0.0] * len(a["cum"]), "sum": 0.0, "count": 0.0}
    cum = np.asarray(a["cum"]) - np.asarray(b["cum"])
    n = float(a["count"] - b["count"])
    if n <= 0:
        return {"mean": None, "p50": None, "p99": None, "count": 0}
    le = np.asarray(a["le"])

    def q(f: float) -> float:
        i = int(np.searchsorted(cum, f * n))
        if i >= le.size or not np.isfinite(le[i]):
            return float(le[-2]) * 1e3  # beyond the last finite bucket: its bound (a lower bound)
        lo, c_lo = (0.0, 0.0) if i == 0 else (le[i - 1], cum[i - 1])
        width = cum[i] - c_lo
        return float(lo + (le[i] - lo) * ((f * n - c_lo) / width if width > 0 else 1.0)) * 1e3

    return {"mean": round((a["sum"] - b["sum"]) / n * 1e3, 4), "p50": round(q(0.5), 4), "p99": round(q(0.99), 4),
            "count": int(n)}


def rss_mb(pid: int | None = None) -> float:
    """Resident set size of process ``pid`` (default: this one), MB, from Linux /proc; NaN for a process that
    has exited but not been reaped (no VmRSS line), so that any comparison with it fails."""
    with open(f"/proc/{pid or os.getpid()}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def ratio(a: float | None, b: float | None) -> float | None:
    return None if not a or not b else round(b / a, 2)


def machine() -> dict[str, Any]:
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    return {"python": platform.python_version(), "numpy": np.__version__, "cpus": os.cpu_count(),
            "processor": platform.processor() or platform.machine(), "loadavg_at_start": load}


def table(rows: list[list[Any]], headers: list[str]) -> str:
    cells = [[str(h) for h in headers]] + [["-" if v is None else (f"{v:g}" if isinstance(v, float) else str(v))
                                             for v in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def write_json(path: Path, report: dict[str, Any]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n")
    return path


def png_path(json_path: Path) -> Path:
    return Path(json_path).with_suffix(".png")


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path, title: str) -> None:
    """Title the figure, lay it out, write it to ``path`` (PNG, 110 dpi) and close it."""
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    pyplot().close(fig)


if __name__ == "__main__" and len(sys.argv) >= 3 and sys.argv[1] == "serve":
    _serve(sys.argv[2], sys.argv[3] if len(sys.argv) > 3 else "fast")
elif __name__ == "__main__" and len(sys.argv) >= 4 and sys.argv[1] == "echo":
    _echo_server(int(sys.argv[2]), int(sys.argv[3]))
