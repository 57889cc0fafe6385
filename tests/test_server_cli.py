"""`ofera serve` as a user runs it: a subprocess that prints where to connect and stops on Ctrl-C."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import httpx
import pytest
from ofera.cli.main import app
from test_server_support import SMALL, avatars_dir
from typer.testing import CliRunner


def test_serve_help_lists_the_options() -> None:
    out = CliRunner().invoke(app, ["serve", "--help"], env={"COLUMNS": "200"})
    assert out.exit_code == 0
    for opt in ("--host", "--port", "--avatars", "--token", "--devices", "--max-sessions", "--bs-rate", "--redis",
                "--room-members", "--max-rooms", "--kernel-threads", "--cpus", "--compute-in-loop"):
        assert opt in out.output
    text = " ".join(out.output.split())  # the environment hints are shown (not eaten as rich markup)
    assert "[env OFERA_PORT; default 8000]" in text and "OFERA_REDIS_URL" in text


def test_serve_refuses_a_missing_avatars_dir() -> None:
    out = CliRunner().invoke(app, ["serve", "--avatars", "/no/such/dir", "--port", "0"])
    assert out.exit_code == 2
    assert "error:" in out.output and "/no/such/dir" in out.output and "Traceback" not in out.output


def test_serve_refuses_an_unknown_kernel_thread_mode() -> None:
    out = CliRunner().invoke(app, ["serve", "--kernel-threads", "many", "--port", "0"])
    assert out.exit_code == 2
    assert "kernel_threads" in out.output and "Traceback" not in out.output


@pytest.mark.parametrize("cpus,problem", [("1-0", "runs backwards"), ("x", "not a CPU list"),
                                          ("100000", "none of CPUs [100000] can be used")])
def test_serve_refuses_bad_cpus(cpus: str, problem: str) -> None:
    out = CliRunner().invoke(app, ["serve", "--cpus", cpus, "--port", "0"])
    assert out.exit_code == 2
    assert problem in out.output and "Traceback" not in out.output


def test_serve_starts_prints_urls_and_stops_on_ctrl_c() -> None:
    """... on the CPU --cpus names: every thread of the process, as /healthz and /proc say."""
    env = dict(os.environ, OFERA_LOG_LEVEL="warning", PYTHONUNBUFFERED="1", OPENBLAS_NUM_THREADS="1")
    cpu = min(os.sched_getaffinity(0))
    cmd = [sys.executable, "-c", "from ofera.cli.main import main; main()", "serve", "--port", "0",
           "--avatars", str(avatars_dir()), "--default-avatar", SMALL, "--cpus", str(cpu)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        lines: list[str] = []
        deadline = time.monotonic() + 300  # the warm-up compiles every kernel when the numba cache is empty
        url = None
        while "/metrics" not in "".join(lines) and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            m = re.search(r"health\s+(http://\S+/healthz)", line)
            url = m.group(1) if m else url
        assert url, "".join(lines) + proc.stderr.read() if proc.poll() is not None else "".join(lines)
        text = "".join(lines)
        assert re.search(r"stream\s+ws://127\.0\.0\.1:\d+/v1/stream", text)
        assert "/metrics" in text and f"on CPUs {cpu}" in text
        health = httpx.get(url, timeout=10).json()
        assert health["status"] == "ok" and health["cpus"] == [cpu]
        tasks = os.listdir(f"/proc/{proc.pid}/task")
        assert len(tasks) >= 2 and {cpus_allowed(proc.pid, t) for t in tasks} == {str(cpu)}  # main, the pool, ...
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
        assert "stopped" in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def cpus_allowed(pid: int, task: str) -> str:
    """A thread's CPU list as the kernel reports it ("0", "0-1")."""
    with open(f"/proc/{pid}/task/{task}/status") as f:
        return next(line.split()[1] for line in f if line.startswith("Cpus_allowed_list"))
