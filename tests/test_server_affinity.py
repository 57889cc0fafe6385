"""The server's CPUs (`cpus` setting, streaming.affinity): CPU lists as Linux writes them, and the pinning of every
thread of a process, numba's pool sized to it (in a subprocess: pinning the test process would slow the suite)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from ofera.streaming import Settings
from ofera.streaming.affinity import parse_cpus
from pydantic import ValidationError


@pytest.mark.parametrize("text,cpus", [("0", {0}), (" 3 ", {3}), ("2-3,6", {2, 3, 6}), ("0-2,1", {0, 1, 2}),
                                       ("5 - 5", {5})])
def test_cpu_lists_parse_as_linux_writes_them(text: str, cpus: set[int]) -> None:
    assert parse_cpus(text) == cpus


@pytest.mark.parametrize("text,problem", [("a", "not a CPU list"), ("1,,2", "at ''"), ("-1", "at '-1'"),
                                          ("3-1", "runs backwards"), ("0-", "not a CPU list")])
def test_bad_cpu_lists_name_the_bad_part(text: str, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        parse_cpus(text)


def test_the_setting_is_checked_and_read() -> None:
    assert Settings(cpus="0-1,3").cpu_set == {0, 1, 3}
    assert Settings(cpus="").cpu_set is None and Settings().cpu_set is None
    with pytest.raises(ValidationError, match="runs backwards"):
        Settings(cpus="2-1")


TOTAL = """
@numba.njit(parallel=True)
def total(a):
    s = 0.0
    for i in numba.prange(a.size):
        s += a[i]
    return s
"""  # a parallel sum: the probes' numba pool starts on its first call

PROBE = """
import json, os, threading, time
import numba  # imported before the pinning, its pool not started
from ofera.streaming.affinity import pin_process
stop = threading.Event()
early = threading.Thread(target=stop.wait)  # a thread started before the pinning
early.start()
cpu = min(os.sched_getaffinity(0))
pinned = pin_process(frozenset({cpu, 100000}))  # CPUs this process may not use are left out
late = threading.Thread(target=stop.wait)  # ... and one started after it
late.start()
import numpy as np
from numba.np.ufunc import parallel
""" + TOTAL + """
a = np.ones(1 << 20)
sums = [total(a) for _ in range(50)]  # the pool starts here, sized as the pinning said
tasks = {}
for t in os.listdir("/proc/self/task"):
    tasks[t] = sorted(os.sched_getaffinity(int(t)))
stop.set()
print(json.dumps({"cpu": cpu, "pinned": sorted(pinned), "tasks": tasks, "numba": numba.config.NUMBA_NUM_THREADS,
                  "pool": parallel.NUM_THREADS, "threads": numba.get_num_threads(), "sums": sorted(set(sums))}))
"""


def test_every_thread_is_pinned_and_numba_sized_to_it() -> None:
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["pinned"] == [r["cpu"]] and r["numba"] == r["pool"] == r["threads"] == 1
    assert r["sums"] == [1 << 20]  # (with the pool started for more threads than the config said: heap corruption)
    assert len(r["tasks"]) >= 3 and all(cpus == [r["cpu"]] for cpus in r["tasks"].values())


def test_cpus_no_process_may_use_are_refused() -> None:
    from ofera.streaming.affinity import pin_process

    before = os.sched_getaffinity(0)
    with pytest.raises(ValueError, match=r"none of CPUs \[100000\] can be used"):
        pin_process(frozenset({100000}))
    assert os.sched_getaffinity(0) == before


SPIN_PROBE = """
import json, os, sys, time
import numba, numpy as np
from ofera.streaming.affinity import bound_spinning
set_now = bound_spinning() if sys.argv[1] == "bound" else None
from ofera.thread_placement import workers
""" + TOTAL + """
a = np.ones(1 << 16)
total(a)
team = workers()
def ran(tid):  # ns this thread has run (schedstat)
    return int(open(f"/proc/self/task/{tid}/schedstat").read().split()[0])
spins = []
for _ in range(9):
    time.sleep(0.03)
    before = ran(team[0]); total(a); time.sleep(0.03)
    spins.append((ran(team[0]) - before) / 1e6)
print(json.dumps({"set": set_now, "env": os.environ.get("GOMP_SPINCOUNT"), "again": bound_spinning(),
                  "ms": sorted(spins)[4]}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or len(os.sched_getaffinity(0)) < 2, reason="two CPUs")
def test_idle_workers_spin_briefly_unless_the_user_says_otherwise() -> None:
    def probe(mode: str, **env: str) -> dict:
        environ = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
        out = subprocess.run([sys.executable, "-c", SPIN_PROBE, mode], capture_output=True, text=True, timeout=120,
                             check=True, env={**environ, **env})
        return json.loads(out.stdout)

    bound = probe("bound")
    assert bound["set"] is True and bound["env"] == "10000" and bound["again"] is False  # (the pool has started)
    assert bound["ms"] < 2.0  # a worker's time per region: its share of the sum, then ~0.3 ms of spinning
    user = probe("bound", OMP_WAIT_POLICY="active")
    assert user["set"] is False and user["env"] is None  # the user's policy stands
