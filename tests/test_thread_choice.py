"""The automatic thread choice (ofera.thread_choice): its rules, the cached load average, and ThreadChoice's
measured pick."""

from __future__ import annotations

import numpy as np
import pytest
from ofera import thread_choice
from ofera.thread_choice import Activity, ThreadChoice, use_threads


def test_load_average_is_read_at_most_once_a_refresh(monkeypatch: pytest.MonkeyPatch) -> None:
    """The 1-minute load average (a system call on every automatic frame's path) is re-read only after
    LOAD_REFRESH_S, or when the clock went back; where the OS has none: None."""
    reads = []
    monkeypatch.setattr(thread_choice, "_load", (-np.inf, None))
    monkeypatch.setattr(thread_choice.os, "getloadavg", lambda: reads.append(1) or (0.25 * len(reads), 0.0, 0.0))
    assert thread_choice.load_average(now=100.0) == 0.25 and len(reads) == 1
    assert thread_choice.load_average(now=100.0 + thread_choice.LOAD_REFRESH_S / 2) == 0.25 and len(reads) == 1
    assert thread_choice.load_average(now=100.0 + thread_choice.LOAD_REFRESH_S) == 0.5 and len(reads) == 2
    assert thread_choice.load_average(now=50.0) == 0.75 and len(reads) == 3  # a clock that went back: read again

    def no_load() -> tuple[float, float, float]:
        raise OSError("no load average here")

    monkeypatch.setattr(thread_choice.os, "getloadavg", no_load)
    assert thread_choice.load_average(now=200.0) is None


def test_thread_choice_rules() -> None:
    assert use_threads(1, 2) and use_threads(1, 2, load=0.5)
    assert not use_threads(2, 2)  # another session computes: one thread each
    assert not use_threads(1, 1)  # no second thread
    assert not use_threads(1, 2, load=2.3)  # other processes hold the cores
    calls = []
    assert not use_threads(2, 2, load=lambda: calls.append(1) or 0.1) and not calls  # read only where threads may run
    assert use_threads(1, 2, load=lambda: calls.append(1) or 0.1) and calls == [1]
    activity = Activity(window_s=0.5)
    assert activity.note(1, now=10.0) == 1
    assert activity.note(2, now=10.1) == 2
    assert activity.note(2, now=10.7) == 1  # session 1 has not computed for 0.6 s: alone again
    activity.forget(2)
    assert activity.note(3, now=10.8) == 1


def test_thread_choice_follows_the_measured_times() -> None:
    choice = ThreadChoice(window=5, probe=10)
    explored = []
    for _ in range(6):  # exploration: the modes alternate, serial first, until both have 3 samples
        par = choice.choose()
        explored.append(par)
        choice.record(par, 100 if par else 300)
    assert explored == [False, True] * 3
    picks = [choice.choose() for _ in range(20)]
    assert picks.count(True) == 18 and picks.count(False) == 2  # parallel is faster; serial is probed (10th, 20th)
    for _ in range(5):
        choice.record(True, 5000)  # the other core became busy: parallel frames are slow now
    assert [choice.choose() for _ in range(8)] == [False] * 3 + [True] + [False] * 4  # frame 30: a probe


def test_thread_choice_gives_up_threads_that_wait_on_another_process() -> None:
    """While exploring, one threaded frame costing more than twice the serial median settles it: serial, threads only
    at probes (two servers on one machine's cores); once the modes are known, one slow threaded frame does not."""
    choice = ThreadChoice(window=5, probe=10)
    assert not choice.choose()
    choice.record(False, 300)
    assert choice.choose()
    choice.record(True, 5000)  # its partner thread waited for a core another process held
    assert [choice.choose() for _ in range(7)] == [False] * 7 and choice.choose()  # the 10th frame: a probe
    known = ThreadChoice(window=5, probe=1000)
    for _ in range(3):
        known.record(False, 300)
        known.record(True, 100)
    known.record(True, 5000)  # an outlier after the modes are known: the medians still say threads
    assert known.choose()


def test_thread_choice_compares_the_cost_per_unit_of_work() -> None:
    """A delta frame's time follows what moved: a serial probe on a heavy frame is not counted against serial, nor a
    run of heavy parallel frames against parallel (the durations are normalised by each frame's work)."""
    choice = ThreadChoice(window=5, probe=1000)
    for _ in range(3):
        choice.record(False, 300, work=1.0)
        choice.record(True, 200, work=1.0)
    assert choice.choose()  # parallel: 200 ns per unit against 300
    for _ in range(5):
        choice.record(True, 500, work=3.0)  # heavy frames: 167 ns per unit, still the faster mode
    assert choice.choose()
    for _ in range(3):
        choice.record(False, 450, work=3.0)  # serial on heavy frames too: 150 per unit, now the faster
    assert not choice.choose()
