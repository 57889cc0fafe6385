"""Where a threaded frame's threads run (ofera.thread_placement): numba's workers away from the caller's CPU."""

from __future__ import annotations

import os
import sys
import threading

import numba
import pytest
from ofera.jit import NB, os_thread_id
from ofera.thread_placement import Placement, workers

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux") or len(os.sched_getaffinity(0)) < 2
                                or numba.get_num_threads() < 2, reason="needs Linux and two CPUs for numba")


@numba.njit(**NB)
def _my_thread_id():
    return os_thread_id()


def _in_thread(fn):
    """fn() on a new thread (its own numba team, its own affinity); returns its result or raises its error."""
    out: dict = {}

    def run() -> None:
        try:
            out["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 (re-raised on the test's thread)
            out["error"] = exc

    t = threading.Thread(target=run)
    t.start()
    t.join()
    if "error" in out:
        raise out["error"]
    return out["value"]


def test_os_thread_id_is_the_callers_linux_thread_id():
    assert _my_thread_id() == threading.get_native_id()
    mine, native = _in_thread(lambda: (_my_thread_id(), threading.get_native_id()))
    assert mine == native


def test_workers_are_this_threads_own_team_of_live_threads_of_this_process():
    def team():
        return threading.get_native_id(), workers(), workers()

    me, first, again = _in_thread(team)
    assert first == again  # the same team every time
    assert len(first) == numba.get_num_threads() - 1 and me not in first
    main = workers()
    assert not set(main) & set(first)  # each caller has its own
    tasks = {int(t) for t in os.listdir("/proc/self/task")}
    assert set(main) <= tasks


def test_workers_are_pinned_away_from_the_callers_cpu_and_again_only_when_it_moves():
    allowed = sorted(os.sched_getaffinity(0))
    a, b = allowed[0], allowed[1]
    placement = Placement()

    def run():
        seen = []
        for cpu in (a, a, b, b, a):
            os.sched_setaffinity(0, {cpu})  # the caller on that CPU (this thread only)
            placement.before_parallel()
            seen.append((cpu, placement.pins, [os.sched_getaffinity(t) for t in placement.team()]))
        return seen

    seen = _in_thread(run)
    assert [pins for _, pins, _ in seen] == [1, 1, 2, 2, 3]
    for cpu, _, masks in seen:
        assert masks and all(len(m) == 1 and cpu not in m for m in masks)
    assert placement.failed is None


def test_a_worker_that_ended_is_found_again():
    placement = Placement()

    def run():
        placement.before_parallel()
        team = placement.team()
        placement._local.team, placement._local.cpu = (2**22 + 7,), None  # beyond any pid_max: no such thread
        placement.before_parallel()  # ESRCH: forgotten, found again on the next frame
        assert placement._local.team is None
        placement.before_parallel()
        assert placement.team() == team
        return True

    assert _in_thread(run)


def test_a_refused_pin_is_reported_once_and_not_tried_again(monkeypatch, caplog):
    import ofera.thread_placement as tp

    placement = Placement()
    team = _in_thread(placement.team)
    real = os.sched_setaffinity
    tried = []

    def refusing(pid, cpus):
        if pid in team:
            tried.append(pid)
            raise OSError(22, "Invalid argument")
        return real(pid, cpus)

    monkeypatch.setattr(tp.os, "sched_setaffinity", refusing)
    allowed = sorted(os.sched_getaffinity(0))

    def run():
        placement._local.team = team  # (this thread's record: the team found above, as if its own)
        for cpu in (allowed[0], allowed[1], allowed[0]):
            real(0, {cpu})
            placement.before_parallel()

    with caplog.at_level("WARNING", logger="ofera.thread_placement"):
        _in_thread(run)
    assert len(tried) == 1 and placement.pins == 0
    assert "Invalid argument" in placement.failed and len(caplog.records) == 1


def test_a_threaded_session_frame_places_its_workers():
    from ofera.avatar import load_avatar
    from ofera.avatar.fast import FastAvatar
    from ofera.head.lbs import HeadSubject
    from ofera.mapping.flame_values import neutral_flame_values

    calls = []

    class Recorder:
        def before_parallel(self) -> None:
            calls.append(threading.get_native_id())

    avatar = load_avatar("default")
    fast = FastAvatar(avatar, HeadSubject.create(avatar.head))
    for parallel, expected in ((True, [threading.get_native_id()]), (False, [])):
        calls.clear()
        session = fast.session(pool_size=1, parallel=parallel)
        session.placement = Recorder()
        session.flame_head(neutral_flame_values())
        assert calls == expected
