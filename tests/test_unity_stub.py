"""The Unity client stub's own test run (unity_client_stub/Tests/run.sh) under mono.

run.sh compiles the Unity-independent C# core with mono's `mcs` (C# 7.2, the source Unity compiles),
decodes every golden vector, and runs a live session against an `ofera serve` it starts itself. It ends
with the line "N passed, N failed". Without mono the test is skipped, unless the environment variable CI
is set: then a missing mono is a failure (CI must install mono-mcs and mono-runtime).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUN_SH = ROOT / "unity_client_stub" / "Tests" / "run.sh"
CLOSING = re.compile(r"^(\d+) passed, (\d+) failed$")


def test_unity_stub_run_sh() -> None:
    missing = [tool for tool in ("mcs", "mono") if shutil.which(tool) is None]
    if missing:
        reason = (f"{' and '.join(missing)} not found: install mono to test the Unity client stub "
                  "(Debian/Ubuntu: apt-get install -y mono-mcs mono-runtime)")
        if os.environ.get("CI"):
            pytest.fail(f"CI is set but {reason}")
        pytest.skip(reason)
    assert RUN_SH.is_file(), f"{RUN_SH} is missing"
    env = dict(os.environ, PYTHON=sys.executable)
    proc = subprocess.run(["bash", str(RUN_SH)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    output = proc.stdout + proc.stderr
    lines = [line.strip() for line in proc.stdout.splitlines() if line.strip()]
    closing = lines[-1] if lines else ""
    match = CLOSING.match(closing)
    tail = "\n".join(output.splitlines()[-40:])
    assert match is not None, f"run.sh did not end with 'N passed, N failed' (exit {proc.returncode}):\n{tail}"
    passed, failed = int(match.group(1)), int(match.group(2))
    assert failed == 0, f"run.sh: {closing}\n{tail}"
    assert passed > 0, f"run.sh ran no checks:\n{tail}"
    assert proc.returncode == 0, f"run.sh exited {proc.returncode} although it printed '{closing}':\n{tail}"


def test_unity_scripts_run_in_the_order_their_comments_state() -> None:
    """OVRFaceExpressions (0) -> OvrFaceSource (100) -> the readers OferaAvatarClient and FaceLogRecorder (200):
    a reader before the source would see the previous frame's weights. FaceLogRecorder.cs is not type-checked
    by run.sh (it needs more of UnityEngine than the stand-in has), so its attribute is checked here."""
    unity = ROOT / "unity_client_stub" / "Runtime" / "Unity"
    order = {}
    for name, path in (("OvrFaceSource", unity / "MetaQuest" / "OvrFaceSource.cs"),
                       ("OferaAvatarClient", unity / "OferaAvatarClient.cs"),
                       ("FaceLogRecorder", unity / "FaceLogRecorder.cs")):
        m = re.search(r"\[DefaultExecutionOrder\((-?\d+)\)\]\s*(?://[^\n]*)?\n\s*public sealed class " + name,
                      path.read_text())
        assert m, f"{path.name}: no [DefaultExecutionOrder(N)] on {name}"
        order[name] = int(m.group(1))
    assert order == {"OvrFaceSource": 100, "OferaAvatarClient": 200, "FaceLogRecorder": 200}, order
    comment = (unity / "MetaQuest" / "OvrFaceSource.cs").read_text()
    assert "FaceLogRecorder's reads (200)" in comment
