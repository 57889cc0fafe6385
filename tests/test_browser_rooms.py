"""The preview page in a room (PROTOCOL.md 12; server/ofera/web/static/rooms.js, member-tile.js): headless Chromium
against a real `ofera serve`, meeting a Python client that publishes (`ofera.client`, in a thread) and another page
that only watches. Every member shows up side by side in its own tile with its fps and latency, the sliders drive
one's own avatar (the Python client receives its frames with the page's member id), and a member who leaves
disappears from every page within 3 s.

Needs /usr/bin/chromium and the `playwright` Python package, as test_browser_preview.py. With
OFERA_DOCS_SCREENSHOTS=1 it writes docs/images/browser_room.png.
"""

from __future__ import annotations

import asyncio
import json
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from browser_support import canvas_pixels, drag_across, foreground, ofera_serve, open_page, page_errors, wait

ROOT = Path(__file__).resolve().parents[1]
VECTORS = ROOT / "protocol" / "vectors"
SCREENSHOT = ROOT / "docs" / "images" / "browser_room.png"  # with OFERA_DOCS_SCREENSHOTS=1
LEAVE_S = 3.0  # the bound for a leaver's `leave` to reach the rest
ROOM_PAGE = "max=20000&enc=f16"  # a reduced avatar: SwiftShader draws several of them on a busy machine
JAW = 17  # arkit52 jawOpen


@pytest.fixture(scope="module")
def server(browser) -> Iterator[str]:
    """`ofera serve --port 0` (the default avatar; rooms in-process) in a subprocess; its base URL."""
    with ofera_serve() as (url, _):
        yield url


class RoomPeer:
    """A Python room member (`ofera.client.connect(room=...)`) in a thread of its own: it publishes jawOpen swinging
    at about 30 Hz (if `publish`) and records every member's frames; `bye` ends it."""

    def __init__(self, url: str, room: str, *, publish: bool = True, max_gaussians: int = 5000) -> None:
        self.url, self.room, self.publish, self.max_gaussians = url, room, publish, max_gaussians
        self.lock = threading.Lock()
        self.frames: dict[str, list[int]] = {}  # member -> seqs received
        self.joins: dict[str, object] = {}  # member -> its Join
        self.leaves: list[object] = []
        self.member: str | None = None
        self.bye_at: float | None = None
        self.error: BaseException | None = None
        self.ready, self.stop = threading.Event(), threading.Event()
        self.thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)
        self.thread.start()
        if not self.ready.wait(120) or self.error is not None:
            raise AssertionError(f"the Python room client did not join: {self.error!r}")

    async def _main(self) -> None:
        from ofera.client import connect

        try:
            client = await connect(self.url, room=self.room, publish=self.publish, avatar="default",
                                   max_gaussians=self.max_gaussians)
        except BaseException as e:  # reported by __init__
            self.error = e
            self.ready.set()
            return
        self.member = client.member
        self.ready.set()

        async def publish() -> None:
            w, k = np.zeros(52, np.float32), 0
            while self.publish and not self.stop.is_set():
                w[JAW] = 0.5 + 0.5 * np.sin(k / 5)
                await client.send_bs(w)
                k += 1
                await asyncio.sleep(1 / 30)

        sender = asyncio.create_task(publish())
        try:
            while not self.stop.is_set():
                try:
                    f = await client.recv_frame(timeout=0.1)
                except TimeoutError:
                    f = None
                with self.lock:
                    if f is not None:
                        self.frames.setdefault(f.member, []).append(f.seq)
                    self.joins = {j.member: j for j in client.joins}
                    self.leaves = list(client.leaves)
        except BaseException as e:
            self.error = e
        finally:
            sender.cancel()
            self.bye_at = time.time()  # wall clock: the pages stamp a leave with Date.now()
            await client.close()  # bye

    def wait_for(self, what: str, condition, timeout_s: float = 120) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.error is None:
            with self.lock:
                if condition(self):
                    return
            time.sleep(0.05)
        with self.lock:
            frames = {k: len(v) for k, v in self.frames.items()}
            pytest.fail(f"the Python client waited {timeout_s} s for {what}: joins {list(self.joins)}, leaves "
                        f"{self.leaves}, frames {frames}, error {self.error!r}")

    def bye(self) -> None:
        self.stop.set()
        self.thread.join(timeout=30)
        assert self.error is None, self.error


def _member(page, member: str) -> dict | None:
    room = page.evaluate("__ofera.room")
    return next((m for m in room["members"] if m["member"] == member), None) if room else None


def _tile_pixels(page, member: str) -> np.ndarray:
    """One member's tile canvas (its drawing buffer is preserved), as RGB."""
    import base64
    import io

    from PIL import Image

    url = page.evaluate(f"document.querySelector('.tile[data-member=\"{member}\"] canvas').toDataURL('image/png')")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB")).astype(np.int16)


def _streaming(member: str, frames: int = 3) -> str:
    return (f"__ofera.room && __ofera.room.members.some(m => m.member === '{member}' && m.state === 'streaming' "
            f"&& m.framesReceived >= {frames} && m.drawnSeq >= 0)")


def test_page_meets_a_python_publisher_and_a_watcher(browser, server) -> None:
    """Done-when on one server: the page (publishing, `self`), a Python client (publishing) and a second page
    (watch only) in one room: each sees the others' frames with the right `member`; a leaver's `leave` reaches the
    rest within 3 s; its tile disappears."""
    room = "lab-browser"
    page = open_page(browser, f"{server}/?{ROOM_PAGE}&room={room}&self=1", settle=False)
    watcher = None
    peer = None
    try:
        wait(page, "__ofera.room && __ofera.room.member !== null")
        me = page.evaluate("__ofera.room.member")
        # with `self` the page's own avatar comes back as a member of its own
        wait(page, _streaming(me, 1))
        assert _member(page, me)["self"] is True

        peer = RoomPeer(server, room)
        wait(page, _streaming(peer.member))
        info = _member(page, peer.member)
        assert 0 < info["count"] <= 20000, info  # the page's own max_gaussians applies to every member
        assert info["avatar"] == "default" and not info["self"], info
        wait(page, f"__ofera.room.members.find(m => m.member === '{peer.member}').fps > 5")
        tile = _tile_pixels(page, peer.member)
        assert foreground(tile).mean() > 0.05, "the Python member's tile shows no avatar"
        listed = page.inner_text("#members")
        assert peer.member in listed and f"{me} (you)" in listed, listed
        caption = page.inner_text(f".tile[data-member='{peer.member}'] figcaption")
        assert "fps" in caption and "latency" in caption, caption  # the peer's clock is not the page's
        assert "other clock" in caption, caption

        # the page's sliders drive its own avatar: the Python client receives frames with the page's member id
        peer.wait_for("the page's join", lambda p: me in p.joins and p.joins[me].avatar is not None)
        before = len(peer.frames.get(me, []))
        page.locator("#bs-jawOpen").fill("1")
        peer.wait_for("frames of the page's avatar", lambda p: len(p.frames.get(me, [])) > before)
        mine = _member(page, me)
        assert mine["latencyMs"] is not None and 0 <= mine["latencyMs"] < 5000, mine  # the page's own clock
        if os.environ.get("OFERA_DOCS_SCREENSHOTS"):  # the room view, on request only
            SCREENSHOT.parent.mkdir(exist_ok=True)
            page.screenshot(path=str(SCREENSHOT))

        # a watch-only page: listed by the others as watching, sees both publishers, has no avatar of its own
        watcher = open_page(browser, f"{server}/?{ROOM_PAGE}&room={room}&watch=1", settle=False)
        wait(watcher, "__ofera.room && __ofera.room.member !== null")
        viewer = watcher.evaluate("__ofera.room.member")
        wait(watcher, _streaming(peer.member))
        watcher.locator("#bs-jawOpen").fill("0.5")  # a watcher's sliders send nothing
        wait(watcher, f"__ofera.room.members.some(m => m.member === '{me}' && m.state === 'streaming')")
        page.locator("#bs-jawOpen").fill("0.3")  # the publishing page moves: the watcher draws its frame
        wait(watcher, _streaming(me, 1))
        assert _member(watcher, viewer) is None or _member(watcher, viewer)["state"] == "watching"
        assert watcher.evaluate("__ofera.lastSentSeq") == -1, "a watch-only page sent bs"
        wait(page, f"__ofera.room.members.some(m => m.member === '{viewer}' && m.state === 'watching')")
        peer.wait_for("the watcher's join", lambda p: viewer in p.joins and p.joins[viewer].publish is False)

        # the Python client leaves: its tile goes from both pages within 3 s of its bye
        peer.bye()
        gone = f"!__ofera.room.members.some(m => m.member === '{peer.member}')"
        for p in (page, watcher):
            wait(p, gone, timeout_s=LEAVE_S + 5)
            assert p.locator(f".tile[data-member='{peer.member}']").count() == 0, "the leaver's tile is still there"
            left = p.evaluate("__ofera.room.left")[0]
            assert (left["member"], left["reason"]) == (peer.member, "bye"), left
            after = left["at"] / 1000 - peer.bye_at
            assert after < LEAVE_S, f"the leave arrived {after:.2f} s after the bye"
        peer = None

        # the watcher closes its page: the publisher's page hears it left
        watcher.close()
        watcher = None
        wait(page, f"!__ofera.room.members.some(m => m.member === '{viewer}')", timeout_s=LEAVE_S + 5)
        left = page.evaluate("__ofera.room.left")[0]
        assert (left["member"], left["reason"]) == (viewer, "closed"), left
        assert not page_errors(page), page_errors(page)
    finally:
        if peer is not None:
            peer.bye()
        if watcher is not None:
            watcher.close()
        page.close()


def test_room_field_joins_and_leaves(browser, server) -> None:
    """The Room field: a bad name is refused on the page; Join turns a v1 page into a room member; Leave goes back
    to the one-avatar v1 view."""
    page = open_page(browser, f"{server}/?max=20000")  # a v1 page, settled
    try:
        assert page.evaluate("__ofera.room") is None
        assert page.is_visible("#canvas") and not page.is_visible("#tiles")
        page.fill("#room", "no spaces")
        page.click("#join")
        assert any("room name 'no spaces'" in e for e in page.evaluate("__ofera.errors"))
        assert page.evaluate("__ofera.room") is None
        page.fill("#room", "lab-field")
        page.check("#self")
        page.click("#join")
        wait(page, "__ofera.room && __ofera.room.room === 'lab-field'")
        me = page.evaluate("__ofera.room.member")
        wait(page, _streaming(me, 1))
        assert page.is_visible(f".tile[data-member='{me}']") and not page.is_visible("#canvas")
        home = _tile_pixels(page, me)
        assert foreground(home).mean() > 0.05, "one's own tile shows no avatar"
        # the tiles' orbit camera: a drag turns the view, a double click brings it back
        x, y = drag_across(page, f".tile[data-member='{me}'] canvas")
        wait(page, "__ofera.room.settled")
        assert (np.abs(_tile_pixels(page, me) - home).max(axis=2) > 40).mean() > 0.05, "dragging did not turn the tile"
        page.mouse.dblclick(x, y)
        wait(page, "__ofera.room.settled")
        assert np.abs(_tile_pixels(page, me) - home).mean() < 2, "a double click did not reset the tile's view"
        page.click("#leave")
        wait(page, "__ofera.room === null && __ofera.settled")
        assert page.is_visible("#canvas") and page.locator(".tile").count() == 0
        assert foreground(canvas_pixels(page)).mean() > 0.05  # the v1 view is back
    finally:
        page.close()


def test_page_meets_a_python_publisher_on_another_server(browser) -> None:
    """Two `ofera serve` processes joined by a real Redis (`--redis`, PROTOCOL.md 12.5): the page on one, the Python
    client on the other; each sees the other's avatar move (mapped expressions cross, each server deforms), and the
    Python client's leave reaches the page within 3 s."""
    from redis_support import running_redis

    room = "lab-redis"
    with running_redis() as redis, ofera_serve("--redis", redis.url) as (a, _), \
            ofera_serve("--redis", redis.url) as (b, _):
        page = open_page(browser, f"{a}/?{ROOM_PAGE}&room={room}", settle=False)
        peer = None
        try:
            wait(page, "__ofera.room && __ofera.room.member !== null")
            me = page.evaluate("__ofera.room.member")
            peer = RoomPeer(b, room)
            wait(page, _streaming(peer.member))
            assert foreground(_tile_pixels(page, peer.member)).mean() > 0.05, "the remote member's tile shows no avatar"
            peer.wait_for("the page's join, across servers", lambda p: me in p.joins)
            before = len(peer.frames.get(me, []))
            page.locator("#bs-jawOpen").fill("1")
            peer.wait_for("frames of the page's avatar, across servers", lambda p: len(p.frames.get(me, [])) > before)
            peer.bye()
            wait(page, f"!__ofera.room.members.some(m => m.member === '{peer.member}')", timeout_s=LEAVE_S + 5)
            left = page.evaluate("__ofera.room.left")[0]
            assert left["member"] == peer.member and left["at"] / 1000 - peer.bye_at < LEAVE_S, left
            peer = None
            assert page.evaluate("__ofera.errors") == [], page.evaluate("__ofera.errors")
        finally:
            if peer is not None:
                peer.bye()
            page.close()


def test_params_room_deforms_in_the_page(browser, server) -> None:
    """A params session in a room (PROTOCOL.md 13.6): one's own avatar (`self`) arrives with its join, avatar and
    rig, each frame's 68 values are deformed in the tile's worker, and jawOpen moves the picture."""
    page = open_page(browser, f"{server}/?enc=params&max=20000&room=lab-params&self=1", settle=False)
    try:
        wait(page, "__ofera.room && __ofera.room.member !== null")
        me = page.evaluate("__ofera.room.member")
        wait(page, _streaming(me, 1) + " && __ofera.room.settled")
        before = _tile_pixels(page, me)
        seq = _member(page, me)["drawnSeq"]
        page.locator("#bs-jawOpen").fill("1")
        wait(page, f"__ofera.room.members.find(m => m.member === '{me}').drawnSeq > {seq} && __ofera.room.settled")
        changed = np.abs(_tile_pixels(page, me) - before).max(axis=2) > 40
        assert foreground(before).mean() > 0.05 and changed.mean() > 0.002, f"jawOpen changed {changed.mean():.4f}"
        assert page.evaluate("__ofera.errors") == [], page.evaluate("__ofera.errors")
    finally:
        page.close()


def test_room_vectors_in_javascript(browser, server) -> None:
    """protocol.js against the rooms' golden vectors (PROTOCOL.md 12): hellos byte for byte; welcome, join, leave,
    member avatar chunks and frames decoded with their room fields."""
    vectors = {}
    for name in ("hello_room", "hello_room_watch", "welcome_room", "welcome_room_watch", "join", "join_f16",
                 "join_watch", "avatar_member", "frame_q13_member", "frame_f16_sparse_member", "leave"):
        v = json.loads((VECTORS / f"{name}.json").read_text())
        v["bytes"] = list((VECTORS / f"{name}.msgpack").read_bytes())
        vectors[name] = v
    page = open_page(browser, f"{server}/static/layouts.json", viewport=None, settle=False)
    try:
        out = page.evaluate(JS_ROOM_VECTORS, vectors)
    finally:
        page.close()
    want = {k: v["fields"] for k, v in vectors.items()}
    for name in ("hello_room", "hello_room_watch"):
        assert out[name] == out[name + "_expected"], name
    w = out["welcome_room"]
    assert (w["room"], w["member"], w["count"], w["quant"]) == ("lab-1", want["welcome_room"]["member"], 4, False)
    watch = want["welcome_room_watch"]
    assert out["welcome_room_watch"] == {"room": "lab-1", "member": watch["member"], "avatar": None}
    assert out["join"] == {"member": want["join"]["member"], "publish": True, "count": 4,
                           "pos_min": pytest.approx(want["join"]["quant"]["pos_min"]["values"])}
    assert out["join_f16"] == {"member": want["join_f16"]["member"], "publish": True, "count": 4, "quant": False}
    assert out["join_watch"] == {"member": want["join_watch"]["member"], "publish": False, "avatar": None}
    assert out["avatar_member"] == {"member": want["avatar_member"]["member"], "n": 4}
    # a member's frames decode with the viewer's encoding and the member's join (count, quant)
    dec = vectors["frame_q13_member"]["decoded"]
    assert out["frame_q13_member"]["member"] == want["frame_q13_member"]["member"]
    assert out["frame_q13_member"]["seq"] == 42
    np.testing.assert_allclose(out["frame_q13_member"]["position"], np.asarray(dec["position"]).ravel(), atol=1e-7)
    assert out["frame_f16_sparse_member"] == {"member": want["frame_f16_sparse_member"]["member"], "n": 2}
    assert out["leave"] == {"member": want["leave"]["member"], "reason": "bye"}
    bad = out["bad"]
    assert bad == {"join_watch_with_avatar": "bad_field", "welcome_room_without_member": "bad_field"}, bad


JS_ROOM_VECTORS = """async (V) => {
  const P = await import("/static/protocol.js");
  const M = await import("/static/msgpack.js");
  const hex = (b) => Array.from(b, (x) => x.toString(16).padStart(2, "0")).join("");
  const dec = (name) => P.decodeServerMessage(new Uint8Array(V[name].bytes));
  const out = {};
  for (const name of ["hello_room", "hello_room_watch"]) {
    const F = V[name].fields;
    out[name] = hex(P.helloMessage({ layout: F.layout, avatar: F.avatar, encoding: F.encoding, coords: F.coords,
      sparse: F.sparse, room: F.room, publish: F.publish, self: F.self, roomToken: F.room_token }));
    out[name + "_expected"] = hex(new Uint8Array(V[name].bytes));
  }
  let w = dec("welcome_room");
  out.welcome_room = { room: w.room, member: w.member, count: w.avatar.count, quant: w.quant !== undefined };
  w = dec("welcome_room_watch");
  out.welcome_room_watch = { room: w.room, member: w.member, avatar: w.avatar };
  let j = dec("join");
  const quant = j.quant;
  out.join = { member: j.member, publish: j.publish, count: j.avatar.count, pos_min: Array.from(j.quant.pos_min) };
  j = dec("join_f16");
  out.join_f16 = { member: j.member, publish: j.publish, count: j.avatar.count, quant: j.quant !== undefined };
  j = dec("join_watch");
  out.join_watch = { member: j.member, publish: j.publish, avatar: j.avatar };
  const a = dec("avatar_member");
  out.avatar_member = { member: a.member, n: a.n };
  const f = dec("frame_q13_member");
  const d = P.decodeFrameArrays("q13", f.n, f, quant);
  out.frame_q13_member = { member: f.member, seq: f.seq, position: Array.from(d.position) };
  const s = dec("frame_f16_sparse_member");
  out.frame_f16_sparse_member = { member: s.member, n: s.n };
  const l = dec("leave");
  out.leave = { member: l.member, reason: l.reason };
  const code = (msg) => { try { P.decodeServerMessage(M.encode(msg)); return null; } catch (e) { return e.code; } };
  out.bad = {
    join_watch_with_avatar: code({ type: "join", member: "m-1", publish: false,
      avatar: { id: "a", count: 1, sh_degree: 0 } }),
    welcome_room_without_member: code({ type: "welcome", protocol: 1, session: "s", layout: "arkit52", encoding: "f32",
      coords: "flame", sparse: false, room: "lab" }),
  };
  return out;
}"""
