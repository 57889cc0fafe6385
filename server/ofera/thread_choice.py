"""Whether a frame's kernels run on numba's threads: the rules the automatic choice follows (a session alone in its
process, a machine not busy) and :class:`ThreadChoice`, which measures both modes and keeps the faster. The server's
sessions (``ofera.avatar.fast``) and the client's frame decoder (``ofera.client.fast_decode``) use it: a parallel
region waits for its slowest thread, so on a loaded core it can be ten times slower than one thread."""

from __future__ import annotations

import math
import os
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable


class Activity:
    """Which sessions of this process computed a frame in the last ``window_s`` seconds (thread-safe): the
    load signal of the automatic thread choice (a session is "alone" when it is the only one)."""

    def __init__(self, window_s: float = 0.5) -> None:
        self.window_s = window_s
        self._last: dict[int, float] = {}
        self._lock = threading.Lock()

    def note(self, key: int, now: float | None = None) -> int:
        """Record that session ``key`` computes a frame now; returns how many sessions are active (>= 1)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._last[key] = now
            if len(self._last) > 1:
                for k in [k for k, t in self._last.items() if now - t > self.window_s]:
                    del self._last[k]
            return len(self._last)

    def forget(self, key: int) -> None:
        with self._lock:
            self._last.pop(key, None)


ACTIVITY = Activity()
"""The process-wide activity record every automatic FastSession consults."""


def use_threads(active_sessions: int, threads: int, load: float | Callable[[], float | None] | None = None) -> bool:
    """Whether parallel kernels may run: a second thread, a session alone, and (if known) a 1-minute load
    average below the thread count. ``load`` may be a function (:func:`load_average`: a system call), called only
    where the rest allows threads."""
    if threads <= 1 or active_sessions > 1:
        return False
    if callable(load):
        load = load()
    return load is None or load < threads


LOAD_REFRESH_S = 1.0
"""How long :func:`load_average` keeps a reading (seconds)."""
_load: tuple[float, float | None] = (-math.inf, None)  # (when read, time.monotonic(); the reading)


def load_average(now: float | None = None) -> float | None:
    """The machine's 1-minute load average (None where the OS has none), read at most once per
    :data:`LOAD_REFRESH_S`: Linux updates it every 5 s, and the read, a system call on every automatic frame's path,
    took 13 us p50 on a cold CPU (round thirteen). ``now``: time.monotonic() (tests)."""
    global _load
    now = time.monotonic() if now is None else now
    when, value = _load
    if now - when >= LOAD_REFRESH_S or now < when:
        try:
            value = os.getloadavg()[0]
        except OSError:
            value = None
        _load = (now, value)
    return value


class ThreadChoice:
    """Serial or parallel for the next frame, from the cost per unit of work (ns / ``work``) of the last ``window``
    frames of each: the lower median wins; every ``probe`` frames the other mode runs once, so a change of load is
    noticed. Until both modes have 3 samples they alternate, serial first; a threaded frame that costs more than
    ``give_up`` times the serial median ends that at once, for serial (threads on cores another process holds: two
    servers on one machine, each alone in its process, whose threads can wait on each other's for a scheduler slice;
    a clean-clone CI run saw a room's first frames across two servers dropped for 0.8 s).

    A delta frame's work grows with what moved (a heavy frame costs twice a median one): per unit of work, a probe
    that lands on a heavy frame does not count against its mode. The choice is made when a frame is recorded, with
    pure-Python medians of ``window`` values (numpy's took 0.16 ms a frame on a cold CPU, on the frame's path: round
    eleven; the server records once the frame is delivered, ``FastSession.defer``); probes are rare (each runs a
    frame in the slower mode: at 1 in 60, 1.7 % of frames, more than a p99 allows, and in step with a looped
    180-frame capture)."""

    def __init__(self, window: int = 15, probe: int = 240, give_up: float = 2.0) -> None:
        self.times: dict[bool, deque[float]] = {False: deque(maxlen=window), True: deque(maxlen=window)}
        self.probe = probe
        self.give_up = give_up
        self.frames = 0
        self.best: bool | None = None  # the mode with the lower median, once known

    def choose(self) -> bool:
        self.frames += 1
        if self.best is None:
            return len(self.times[True]) < len(self.times[False])
        return (not self.best) if self.frames % self.probe == 0 else self.best

    def record(self, parallel: bool, ns: int, work: float = 1.0) -> None:
        """A frame's duration ``ns`` in the mode it ran in, for ``work`` units of work (> 0)."""
        cost = ns / work
        self.times[parallel].append(cost)
        serial, par = self.times[False], self.times[True]
        if self.best is None and parallel and serial and cost > self.give_up * statistics.median(serial):
            self.best = False  # (while exploring only: once known, one slow frame does not outvote the medians)
        elif len(serial) >= 3 and len(par) >= 3:
            self.best = statistics.median(par) < statistics.median(serial)
