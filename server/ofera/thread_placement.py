"""Where a threaded frame's threads run: numba's worker threads on CPUs other than the calling thread's.

A threaded kernel (``parallel=True``) wakes numba's OpenMP workers when it starts; the OS places each woken worker.
On the 2-vCPU VM of December 2026 (a kernel that packs tasks onto few vCPUs) it put the worker on the caller's own
CPU in most frames while the other CPU idled: the worker then ran the frame while the caller waited, runnable, beside
it, and a parallel region's head waited for a vertex block the preempted thread had claimed (threaded delta frames'
head p90 1.59 ms against 0.23 serial; ``perf sched``, benchmarks/README.md, round twenty). The caller's own thread
moves (the server's loop wakes it where it runs), so no fixed split holds: :meth:`Placement.before_parallel`, called
by a frame before its parallel region, pins the calling thread's workers to the other CPUs this process may use, and
again only when the caller is found on another CPU (a ``sched_getcpu``, 0.1 us; a pin, 1.5 us).

Linux only (thread affinity, glibc's ``gettid``); elsewhere :meth:`Placement.before_parallel` does nothing.
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
import threading

import numba
import numpy as np

from .jit import NB, os_thread_id

log = logging.getLogger(__name__)


def _libc_getcpu():
    """glibc's ``sched_getcpu`` (the calling thread's CPU now), or None where there is none."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None).sched_getcpu
    except (OSError, AttributeError):
        return None
    fn.restype, fn.argtypes = ctypes.c_int, []
    return fn


class Placement:
    """Pins, per calling thread, numba's workers of that thread (each caller has its own OpenMP team) to the CPUs this
    process may use (its main thread's affinity) other than the caller's current one, worker i to the i-th of them
    (round robin). Thread-safe: every caller has its own record (a thread-local)."""

    def __init__(self) -> None:
        self._getcpu = _libc_getcpu()
        self._local = threading.local()  # .team: the caller's workers' thread ids; .cpu: the CPU they were placed for
        self.pins = 0  # how many times workers were (re)pinned (tests)
        self.failed: str | None = None  # why a pin failed, if one did (that caller's frames then go unplaced)

    def before_parallel(self) -> None:
        """Called by a frame right before its parallel region: the caller's workers away from its CPU."""
        if self._getcpu is None:
            return
        cpu = self._getcpu()
        local = self._local
        if getattr(local, "cpu", None) == cpu:
            return
        local.cpu = cpu  # (also when nothing is pinned below: tried once per move)
        team = self.team()
        others = [c for c in sorted(os.sched_getaffinity(os.getpid())) if c != cpu]
        if not others or not team:
            return
        try:
            for i, tid in enumerate(team):
                os.sched_setaffinity(tid, {others[i % len(others)]})
        except ProcessLookupError:  # a worker ended (numba's pool was replaced): find the team on the next frame
            local.team = local.cpu = None
            return
        except OSError as exc:  # (a CPU the cpuset no longer allows, say): this caller stays as it is
            self.failed = f"pinning numba's workers failed: {exc}; their frames run where the OS puts them"
            log.warning(self.failed)
            local.team = ()
            return
        self.pins += 1

    def team(self) -> tuple[int, ...]:
        """The calling thread's numba workers' Linux thread ids (found on first use)."""
        team = getattr(self._local, "team", None)
        if team is None:
            team = self._local.team = workers()
        return team


def workers() -> tuple[int, ...]:
    """The Linux thread ids of the numba threads a parallel region started by the calling thread runs on, but the
    caller's own: one parallel loop with an iteration per thread, each writing its thread's id."""
    ids = np.zeros(numba.get_num_threads(), np.int32)
    team_ids(ids)
    me = threading.get_native_id()
    return tuple(sorted({int(t) for t in ids} - {me}))


@numba.njit(parallel=True, **NB)
def team_ids(ids):
    """ids (T,) int32 <- the thread id of the thread that ran iteration t (one iteration per thread of numba's T)."""
    for t in numba.prange(ids.shape[0]):
        ids[t] = os_thread_id()


PLACEMENT = Placement()
"""The process-wide placement every threaded FastSession frame goes through."""
