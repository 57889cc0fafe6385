"""Client WebSocket transports side by side: a 1-byte request -> an N-byte binary message, over loopback.

    python benchmarks/transport.py [--sizes 300,65536,1000000,2000000,4000000] [--requests 500] [--json out.json]

A bare server in a subprocess (this file, ``--serve``: blocking sockets, one thread per connection, every frame
built once at start) answers each masked 1-byte binary request with the prebuilt binary message of the size the
request's byte names. Three clients in this process, each on its own connection to that server:

- ``socket``: a plain blocking socket, the handshake by hand, a prebuilt masked request, ``recv_into`` a buffer
  allocated once until the whole frame is in (no parsing, no event loop): the floor under any client;
- ``fast``: ``ofera.client.transport.open_websocket`` (what ``ofera.client.connect`` uses), on the asyncio loop;
- ``websockets``: the websockets library's asyncio client (``connect(..., transport="websockets")``).

Per size, after --warmup requests per client (the first answer of each checked byte for byte), the clients
alternate request by request (the order rotated each time) so that load from other processes hits them alike,
--requests each. A round trip is request written -> message returned to the caller, on perf_counter; CPU is this
process's CPU time (user + system, all threads: time.process_time) over each request, so the kernel's copies are
in it. Prints a table; writes --json and a PNG next to it.
JSON: {"sizes", "requests", "results": {size: {client: {p50, p99, min, mean, n, cpu_ms}}}, "ratios": {size:
{"websockets_over_fast": {p50, p99, min, cpu_ms}, "fast_over_socket": {...}}}, "cpu", "machine", "definitions"}.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402
from ofera.client.transport import OP_BINARY, accept_key, frame_bytes  # noqa: E402

CLIENTS = ("socket", "fast", "websockets")
DEFAULT_SIZES = "300,65536,1000000,2000000,4000000"
COLORS = {"socket": "tab:grey", "fast": "tab:blue", "websockets": "tab:red"}


def payload(size: int) -> bytes:
    """The message of `size` bytes (the same bytes in the server and in the clients' checks)."""
    return np.random.default_rng(size).bytes(size)


def head_length(n: int) -> int:
    """Bytes of the header of a server frame of `n` payload bytes (7-, 16- or 64-bit length)."""
    return 2 if n < 126 else 4 if n < 65536 else 10


def server_frame(data: bytes) -> bytes:
    """One final, unmasked binary frame (a server's)."""
    n = len(data)
    head = b"\x82" + (bytes([n]) if n < 126 else b"\x7e" + struct.pack("!H", n) if n < 65536 else
                      b"\x7f" + struct.pack("!Q", n))
    return head + data


def masked_request(index: int) -> bytes:
    """The client's masked 1-byte binary frame asking for message `index`."""
    return frame_bytes(OP_BINARY, bytes([index]))


def accept(key: bytes) -> bytes:
    return accept_key(key.decode()).encode()


# ----------------------------------------------------------------------------- the bare server (--serve)


def _read_exactly(sock: socket.socket, n: int) -> bytes:
    out = bytearray()
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        if not chunk:
            raise ConnectionError("client gone")
        out += chunk
    return bytes(out)


def _connection(sock: socket.socket, frames: list[bytes]) -> None:
    with sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = sock.recv(4096)
            if not chunk:
                return
            head += chunk
        key = next(line.split(b":", 1)[1].strip() for line in head.split(b"\r\n")
                   if line.lower().startswith(b"sec-websocket-key:"))
        sock.sendall(b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                     b"Sec-WebSocket-Accept: " + accept(key) + b"\r\n\r\n")
        try:
            while True:
                b0, b1 = _read_exactly(sock, 2)
                n = b1 & 0x7F
                if n == 126:
                    n = struct.unpack("!H", _read_exactly(sock, 2))[0]
                elif n == 127:
                    n = struct.unpack("!Q", _read_exactly(sock, 8))[0]
                mask = _read_exactly(sock, 4)
                data = bytes(b ^ mask[i % 4] for i, b in enumerate(_read_exactly(sock, n)))
                opcode = b0 & 0x0F
                if opcode == 0x8:  # close: echo it, then close TCP (the server's side)
                    sock.sendall(bytes([0x88, len(data)]) + data)
                    return
                if opcode == 0x2 and len(data) == 1 and data[0] < len(frames):
                    sock.sendall(frames[data[0]])
        except (ConnectionError, OSError):
            return


def serve(sizes: list[int]) -> None:
    """Listen on a free loopback port, print it, answer every connection in its own thread (until killed)."""
    frames = [server_frame(payload(n)) for n in sizes]
    listener = socket.create_server(("127.0.0.1", 0))
    print(listener.getsockname()[1], flush=True)
    while True:
        sock, _ = listener.accept()
        threading.Thread(target=_connection, args=(sock, frames), daemon=True).start()


class ServerProc:
    """The bare server in a subprocess."""

    def __init__(self, sizes: list[int]) -> None:
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--serve", "--sizes",
                                      ",".join(map(str, sizes))], stdout=subprocess.PIPE)
        line = self.proc.stdout.readline()  # type: ignore[union-attr]
        if not line.strip().isdigit():
            self.stop()
            raise RuntimeError(f"the benchmark's server did not start (exit code {self.proc.returncode})")
        self.port = int(line)

    def stop(self) -> None:
        C.terminate(self.proc)


# ----------------------------------------------------------------------------- the clients


class SocketClient:
    """The floor: a blocking socket reading each whole frame into one buffer with recv_into."""

    def __init__(self, port: int, sizes: list[int]) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        key = base64.b64encode(os.urandom(16))
        self.sock.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                          b"Sec-WebSocket-Key: " + key + b"\r\nSec-WebSocket-Version: 13\r\n\r\n")
        head = b""
        while not head.endswith(b"\r\n\r\n"):  # the server sends nothing more until asked
            chunk = self.sock.recv(1)
            if not chunk:
                raise ConnectionError("the server closed the connection during the handshake")
            head += chunk
        if not head.startswith(b"HTTP/1.1 101") or accept(key) not in head:
            raise ConnectionError(f"no upgrade: {head[:80]!r}")
        self.heads = [head_length(n) for n in sizes]
        self.lengths = [head_length(n) + n for n in sizes]
        self.requests = [masked_request(i) for i in range(len(sizes))]
        self.buf = bytearray(max(self.lengths))
        self.view = memoryview(self.buf)

    async def roundtrip(self, index: int) -> memoryview:
        """Message `index`: its frame read whole into the client's one buffer; the payload's view."""
        self.sock.sendall(self.requests[index])
        total, got = self.lengths[index], 0
        view = self.view
        while got < total:
            n = self.sock.recv_into(view[got:total])
            if not n:
                raise ConnectionError("the server closed the connection")
            got += n
        return view[self.heads[index]:total]

    async def close(self) -> None:
        self.sock.close()


class FastClient:
    def __init__(self, ws: Any) -> None:
        self.ws = ws

    @classmethod
    async def open(cls, port: int, max_size: int) -> FastClient:
        from ofera.client.transport import open_websocket

        return cls(await open_websocket(f"ws://127.0.0.1:{port}/", max_size=max_size))

    async def roundtrip(self, index: int) -> Any:
        await self.ws.send(bytes([index]))
        return await self.ws.recv()

    async def close(self) -> None:
        await self.ws.close()


class WebsocketsClient(FastClient):
    @classmethod
    async def open(cls, port: int, max_size: int) -> WebsocketsClient:
        from websockets.asyncio.client import connect

        return cls(await connect(f"ws://127.0.0.1:{port}/", compression=None, max_size=max_size, ping_interval=None,
                                 max_queue=2))


async def measure(port: int, sizes: list[int], requests: int, warmup: int, server_pid: int) -> dict[str, Any]:
    """Round trips (ms) and CPU (ms) per request of every client at every size; the run's CpuMeter report."""
    max_size = max(sizes) + 16
    clients: dict[str, Any] = {"socket": SocketClient(port, sizes), "fast": await FastClient.open(port, max_size),
                               "websockets": await WebsocketsClient.open(port, max_size)}
    rtt: dict[int, dict[str, list[float]]] = {n: {c: [] for c in CLIENTS} for n in sizes}
    cpu: dict[int, dict[str, list[float]]] = {n: {c: [] for c in CLIENTS} for n in sizes}
    clock, cpu_clock = time.perf_counter_ns, time.process_time_ns
    try:
        with C.CpuMeter(server_pid) as meter:
            for i, n in enumerate(sizes):
                expected = payload(n)
                for name, client in clients.items():
                    message = await client.roundtrip(i)
                    if bytes(message) != expected:
                        raise RuntimeError(f"client {name} received {len(message)} bytes, not the {n} sent")
                    del message
                    for _ in range(warmup - 1):
                        await client.roundtrip(i)
                print(f"[transport] {n} B: {requests} round trips per client ...", flush=True)
                for k in range(requests):
                    for j in range(len(CLIENTS)):
                        name = CLIENTS[(j + k) % len(CLIENTS)]
                        client = clients[name]
                        c0, t0 = cpu_clock(), clock()
                        message = await client.roundtrip(i)
                        t1, c1 = clock(), cpu_clock()
                        if len(message) != n:
                            raise RuntimeError(f"client {name} received {len(message)} bytes, not {n}")
                        del message
                        rtt[n][name].append((t1 - t0) / 1e6)
                        cpu[n][name].append((c1 - c0) / 1e6)
    finally:
        for client in clients.values():
            await client.close()
    results: dict[str, Any] = {}
    for n in sizes:
        results[str(n)] = {}
        for name in CLIENTS:
            p = C.pct(rtt[n][name])
            results[str(n)][name] = {"p50": p["p50"], "p99": p["p99"], "min": round(min(rtt[n][name]), 3),
                                     "mean": p["mean"], "n": len(rtt[n][name]),
                                     "cpu_ms": round(float(np.mean(cpu[n][name])), 3)}
    return {"results": results, "cpu": meter.report(), "_rtt": rtt}


def ratios(results: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for size, r in results.items():
        out[size] = {f"{b}_over_{a}": {k: C.ratio(r[a][k], r[b][k]) for k in ("p50", "p99", "min", "cpu_ms")}
                     for a, b in (("fast", "websockets"), ("socket", "fast"))}
    return out


def plot(path: Path, sizes: list[int], report: dict[str, Any], rtt: dict[int, dict[str, list[float]]]) -> None:
    plt = C.pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    results = report["results"]
    xs = np.asarray(sizes, np.float64)
    for name in CLIENTS:
        p50 = [results[str(n)][name]["p50"] for n in sizes]
        p99 = [results[str(n)][name]["p99"] for n in sizes]
        axes[0].plot(xs, p50, "o-", color=COLORS[name], label=f"{name} p50")
        axes[0].plot(xs, p99, "x--", color=COLORS[name], lw=0.8, label=f"{name} p99")
        axes[2].plot(xs, [results[str(n)][name]["cpu_ms"] for n in sizes], "o-", color=COLORS[name], label=name)
    for ax, label in ((axes[0], "round trip (ms, log)"), (axes[2], "client CPU per request (ms, log)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("message size (bytes, log)")
        ax.set_ylabel(label)
        ax.legend(fontsize=8)
    big = sizes[-1]
    for name in CLIENTS:
        s = np.sort(np.asarray(rtt[big][name]))
        axes[1].plot(s, np.arange(1, s.size + 1) / s.size, color=COLORS[name],
                     label=f"{name} (p50 {results[str(big)][name]['p50']} ms)")
    axes[1].set_xscale("log")
    axes[1].set_xlabel(f"round trip at {big} B (ms, log)")
    axes[1].set_ylabel("fraction of requests")
    axes[1].legend(fontsize=8)
    load = report["machine"]["loadavg_at_start"]
    C.save_figure(fig, path, "WebSocket client transports over loopback: 1-byte request -> N-byte message"
                  + (f" (load {load[0]:.1f})" if load else ""))


def parse_sizes(text: str) -> list[int]:
    sizes = [int(s) for s in text.split(",") if s.strip()]
    if not sizes or len(sizes) > 255 or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"--sizes: 1 to 255 positive byte counts, got {text!r}")
    return sizes


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=parse_sizes, default=parse_sizes(DEFAULT_SIZES),
                    help=f"message sizes in bytes, comma-separated (default {DEFAULT_SIZES})")
    ap.add_argument("--requests", type=int, default=500, help="measured round trips per client and size")
    ap.add_argument("--warmup", type=int, default=20, help="round trips per client and size first, not counted")
    ap.add_argument("--event-loop", default="asyncio", choices=["asyncio", "uvloop"],
                    help="the event loop of the asyncio clients")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "transport.json")
    ap.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)  # the server process
    args = ap.parse_args(argv)
    if args.serve:
        serve(args.sizes)
        return {}
    if args.requests < 1 or args.warmup < 1:
        ap.error("--requests and --warmup must be at least 1")

    machine = C.machine()
    server = ServerProc(args.sizes)
    try:
        if args.event_loop == "uvloop":
            import uvloop

            run = uvloop.run
        else:
            run = asyncio.run
        measured = run(measure(server.port, args.sizes, args.requests, args.warmup, server.proc.pid))
    finally:
        server.stop()
    rtt = measured.pop("_rtt")
    report = {
        "benchmark": "transport",
        "sizes": args.sizes,
        "requests": args.requests,
        "warmup": args.warmup,
        "event_loop": args.event_loop,
        "clients": list(CLIENTS),
        "results": measured["results"],
        "ratios": ratios(measured["results"]),
        "cpu": measured["cpu"],
        "definitions": {
            "round trip": "ms, perf_counter: the 1-byte request written -> the N-byte message returned to the caller",
            "cpu_ms": "this process's CPU time (user + system, all threads) over one round trip, mean",
            "socket": "blocking socket, recv_into one preallocated buffer until the whole frame is in: the floor",
            "fast": "ofera.client.transport.open_websocket on the asyncio loop (ofera.client.connect's default)",
            "websockets": "the websockets library's asyncio client (compression off, max_queue 2)",
            "ratios": "b_over_a = b / a of each statistic",
            "cpu": "cores used on average over the measured run: the clients (this process) and the server; "
                   "steal_pct: the machine's CPU time its hypervisor gave to other guests (%)",
        },
        "machine": machine,
    }
    path = C.write_json(args.json, report)
    plot(C.png_path(path), args.sizes, report, rtt)
    rows = []
    for n in args.sizes:
        r, q = report["results"][str(n)], report["ratios"][str(n)]
        for name in CLIENTS:
            x = r[name]
            ratio = q["websockets_over_fast"]["p50"] if name == "websockets" else None
            rows.append([n, name, x["n"], x["p50"], x["p99"], x["min"], x["cpu_ms"], ratio])
    print(C.table(rows, ["bytes", "client", "n", "p50 ms", "p99 ms", "min ms", "cpu ms", "websockets/fast p50"]))
    print(f"client cores {report['cpu']['client_cores']}, server cores {report['cpu']['server_cores']}, "
          f"load at start {machine['loadavg_at_start']}")
    print(f"wrote {path} and {C.png_path(path)}")
    return report


if __name__ == "__main__":
    main()
