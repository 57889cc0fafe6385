"""`compute_in_loop` (`Source.in_loop`): a session alone on its server computes its frames on the event loop's thread,
with no hand-off to the compute pool and back; once a second session connects, frames go to the pool again. The
frames are the same either way (same code, same thread-safety: one frame at a time per source)."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest
from ofera.client import connect
from ofera.streaming import roles
from ofera.streaming.server import ServerThread
from test_server_eager_encode import frames_of, roles_session, stream
from test_server_support import SMALL, run, settings

WAIT = 30.0  # seconds a step may take before the test calls it hung (never a performance claim)


@pytest.mark.parametrize("in_loop", [True, False])
def test_a_source_computes_on_the_loop_only_while_told(in_loop: bool) -> None:
    source, viewer, writer, compute, encode, sent = roles_session()
    source.in_loop = lambda: in_loop
    with compute, encode:
        run(stream(source, viewer, 3, sent))
    assert len(sent) == 3 and [seq for seq, _ in writer.calls] == [0, 1, 2]
    assert compute.submitted == (0 if in_loop else 3)
    names = {name for _, name in writer.calls}  # eager encoding, in whichever thread computed
    assert names == ({threading.main_thread().name} if in_loop else {"compute_0"})


@pytest.fixture(scope="module")
def alone_server() -> Any:
    server = ServerThread(settings(compute_in_loop="alone")).start()
    yield server
    server.stop()


def test_a_session_alone_computes_on_the_loop_and_shares_the_pool_when_not(alone_server: Any,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    threads: list[str] = []
    compute = roles.Source._compute

    def recording(self: roles.Source, pending: Any) -> Any:
        threads.append(threading.current_thread().name)
        return compute(self, pending)

    monkeypatch.setattr(roles.Source, "_compute", recording)

    async def main() -> None:
        a = await connect(alone_server.url, avatar=SMALL, encoding="f16")
        alone = await frames_of(a, 3)
        b = await connect(alone_server.url, avatar=SMALL, encoding="q13")
        shared = await frames_of(a, 3) + await frames_of(b, 2)
        for c in (a, b):
            await c.close()
        assert [f.seq for f in alone] == [0, 1, 2] and len(shared) == 5
        assert all(np.isfinite(f.position).all() for f in alone + shared)

    run(main())
    loop_thread = alone_server.thread.name
    assert threads[:3] == [loop_thread] * 3  # alone: on the server's event loop thread
    assert all(name.startswith("ofera-compute") for name in threads[3:]) and len(threads) == 8


def test_the_setting_is_refused_when_unknown() -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="compute_in_loop"):
        settings(compute_in_loop="sometimes")

