"""The browser preview (`server/ofera/web`) as a user sees it: headless Chromium (Debian's `chromium`,
WebGL2 through SwiftShader) loading `/` from a real `ofera serve` with the default avatar.

Needs /usr/bin/chromium and the `playwright` Python package (never `playwright install`: the system
browser is used); without them the tests skip, unless the environment variable CI is set (then they
fail). With OFERA_DOCS_SCREENSHOTS=1 it writes docs/images/browser_default.png (the README's
docs/browser.png, the LAM statue, comes from test_lam_browser.py the same way).
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from browser_support import (
    STATE,
    canvas_pixels,
    drag_across,
    foreground,
    ofera_serve,
    open_page,
    wait,
    wait_settled,
)

ROOT = Path(__file__).resolve().parents[1]
SCREENSHOT = ROOT / "docs" / "images" / "browser_default.png"  # docs/browser.png (README) is test_lam_browser.py's
VECTORS = ROOT / "protocol" / "vectors"


@pytest.fixture(scope="module")
def server(browser) -> Iterator[str]:
    """`ofera serve --port 0` (the built-in default avatar, ~100k Gaussians) in a subprocess; its base URL."""
    with ofera_serve() as (url, _):
        yield url


def skin(img: np.ndarray) -> np.ndarray:
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 90) & (r >= g) & (g >= b - 10) & (r - b > 25)


# ----- the page --------------------------------------------------------------------------------------------


def test_page_shows_the_avatar_head(browser, server) -> None:
    page = open_page(browser, f"{server}/?auto=0")
    try:
        info = page.evaluate("({count: __ofera.count, full: __ofera.fullCount, status: __ofera.status, "
                             "errors: __ofera.errors})")
        assert info["status"] == "streaming" and info["errors"] == []
        assert info["count"] == info["full"] >= 50_000, info  # the default avatar, at full size
        img = canvas_pixels(page)
        h, w, _ = img.shape
        centre = img[int(h * 0.35):int(h * 0.65), int(w * 0.4):int(w * 0.6)]
        assert foreground(centre).mean() > 0.9, "the middle of the view is not covered by the avatar"
        assert skin(centre).mean() > 0.5, f"too few skin-coloured pixels: {skin(centre).mean():.2f}"
        assert foreground(img[: h // 20]).mean() < 0.05, "the head should fit in the view"
        hud = page.inner_text("#hud")
        assert re.search(r"latency\s+\d", hud) and re.search(r"frame\s+[\d.]+ KiB", hud), hud
        if os.environ.get("OFERA_DOCS_SCREENSHOTS"):  # regenerate the README's picture on request only
            SCREENSHOT.parent.mkdir(exist_ok=True)
            page.screenshot(path=str(SCREENSHOT))
    finally:
        page.close()


def test_jaw_open_slider_changes_the_mouth(browser, server) -> None:
    page = open_page(browser, f"{server}/?auto=0")
    try:
        before = canvas_pixels(page)
        seq = page.evaluate("__ofera.lastFrameSeq")
        page.locator("#bs-jawOpen").fill("1")  # the slider itself: an input event, then a bs
        wait_settled(page, seq)
        weights = page.evaluate("__ofera.weights()")
        assert weights[17] == 1.0 and sum(weights) == 1.0  # arkit52 index 17 is jawOpen
        after = canvas_pixels(page)
        if os.environ.get("OFERA_BROWSER_DEBUG"):  # look at what the test compares
            from PIL import Image

            for name, a in (("before", before), ("after", after)):
                Image.fromarray(a.astype(np.uint8)).save(f"{os.environ['OFERA_BROWSER_DEBUG']}/jaw_{name}.png")
        changed = np.abs(after - before).max(axis=2) > 40
        fg = foreground(before)
        ys, xs = np.nonzero(fg)
        assert changed.sum() > 0.002 * changed.size, f"jawOpen changed only {changed.sum()} pixels"
        # Where the face is: the rows where the head is widest (the neck below is narrower); the mouth is in
        # the lower half of the head, the forehead and hair above the eyes must not move.
        top = ys.min()
        width = fg.sum(axis=1)
        widest = int(np.argmax(width))
        narrow = np.nonzero(width[widest:] < 0.75 * width[widest])[0]  # the chin, where the neck begins
        head_bottom = widest + int(narrow[0]) if len(narrow) else fg.shape[0]
        cy, cx = np.nonzero(changed)
        upper = changed[top: top + (head_bottom - top) // 3].sum()
        lower = changed[top + (head_bottom - top) // 2:].sum()
        assert lower > 4 * max(upper, 1), f"changes are not around the mouth: upper third {upper}, lower half {lower}"
        assert abs(cx.mean() - xs.mean()) < 0.1 * fg.shape[1], "changes are not centred on the face"
    finally:
        page.close()


def test_delta_stream_draws_what_the_q13_stream_draws(browser, server) -> None:
    """?enc=q13&delta=1: a live delta session (key frame, then deltas applied in the worker) draws the same face
    as plain q13 frames, to within the delta tolerance (a few pixels along edges at most)."""
    shots, sizes = [], []
    for query in ("enc=q13&delta=1", "enc=q13"):
        page = open_page(browser, f"{server}/?auto=0&max=20000&{query}")
        try:
            for value in ("1", "0.3"):  # two expressions: the second frame is a delta against the first
                seq = page.evaluate("__ofera.lastFrameSeq")
                page.evaluate(f"__ofera.setWeight('jawOpen', {value})")
                wait_settled(page, seq)
            assert page.evaluate("__ofera.errors") == [], page.evaluate(STATE)
            shots.append(canvas_pixels(page))
            sizes.append(float(re.search(r"frame\s+([\d.]+) KiB", page.inner_text("#hud")).group(1)))
        finally:
            page.close()
    delta, plain = shots
    assert sizes[0] < sizes[1] / 3, f"the delta session's last frame ({sizes[0]} KiB) is not a small delta frame"
    differ = np.abs(delta - plain).max(axis=2) > 24
    assert foreground(plain).mean() > 0.1 and differ.mean() < 0.01, f"{differ.mean():.4f} of the pixels differ"


def test_reduced_stream_forced_and_automatic(browser, server) -> None:
    page = open_page(browser, f"{server}/?max=20000")
    try:
        info = page.evaluate("({count: __ofera.count, max: __ofera.maxGaussians, full: __ofera.fullCount})")
        # The server serves a few fixed reduction sizes (count x 2^(-k/4)): at most 16 % fewer than asked.
        assert info["max"] == 20000 and 0.84 * 20000 <= info["count"] <= 20000 < info["full"], info
        check_camera_and_presets(page)
    finally:
        page.close()
    # A frame rate nobody reaches: the page must reconnect asking for fewer Gaussians on its own.
    page = open_page(browser, f"{server}/?minfps=1000")
    try:
        wait(page, "__ofera.reductions >= 1 && __ofera.settled")
        info = page.evaluate("({count: __ofera.count, max: __ofera.maxGaussians, full: __ofera.fullCount, "
                             "errors: __ofera.errors})")
        assert info["max"] is not None and info["count"] <= info["max"] < info["full"], info
        assert any("reconnecting for at most" in e for e in info["errors"]), info["errors"]
    finally:
        page.close()


def check_camera_and_presets(page) -> None:
    """Orbit camera: drag rotates, the wheel zooms, a double click goes back; a preset button sends its shape."""
    home = canvas_pixels(page)
    x, y = drag_across(page, "#canvas")
    wait(page, "__ofera.settled")
    turned = canvas_pixels(page)
    assert (np.abs(turned - home).max(axis=2) > 40).mean() > 0.05, "dragging did not turn the view"
    page.mouse.wheel(0, 600)
    wait(page, "__ofera.settled")
    assert foreground(canvas_pixels(page)).mean() < 0.8 * foreground(turned).mean(), "the wheel did not zoom out"
    page.mouse.dblclick(x, y)
    wait(page, "__ofera.settled")
    assert np.abs(canvas_pixels(page) - home).mean() < 2, "a double click did not reset the view"

    seq = page.evaluate("__ofera.lastFrameSeq")
    page.get_by_role("button", name="blink").click()
    wait_settled(page, seq)
    w = page.evaluate("__ofera.weights()")
    assert w[0] == w[7] == 1.0 and sum(w) == 2.0  # eyeBlinkLeft, eyeBlinkRight
    assert page.input_value("#bs-eyeBlinkLeft") == "1"


def _livelink_csv(frames: int = 30) -> str:
    from ofera.mapping.layouts import LIVELINK61_NAMES

    lines = ["Timecode,BlendshapeCount," + ",".join(LIVELINK61_NAMES)]
    jaw = LIVELINK61_NAMES.index("JawOpen")
    for i in range(frames):
        w = np.zeros(len(LIVELINK61_NAMES))
        w[jaw] = i / (frames - 1)
        lines.append(f"17:03:10:{i % 60:02d}.{i * 37 % 1000:03d},61," + ",".join(f"{x:.4f}" for x in w))
    return "\n".join(lines) + "\n"


def test_dropped_recordings_play(browser, server) -> None:
    page = open_page(browser, f"{server}/?max=20000")
    try:
        page.uncheck("#loop")
        seq = page.evaluate("__ofera.lastSentSeq")
        page.set_input_files("#file", files=[{"name": "take.csv", "mimeType": "text/csv",
                                              "buffer": _livelink_csv().encode()}])
        page.wait_for_function("document.getElementById('playinfo').textContent.includes('livelink61')")
        wait(page, "!__ofera.playing && __ofera.settled")
        assert page.evaluate("__ofera.lastSentSeq") > seq + 1, "playback sent no bs"
        assert page.evaluate("__ofera.weights()[17]") == pytest.approx(1.0)  # the last row: JawOpen 1
        assert page.input_value("#bs-jawOpen") == "1"  # the sliders follow the playback

        # A face-log CSV in Meta's layout goes through the server's own ovr63 -> arkit52 map.
        from ofera.mapping.layouts import OVR63_NAMES

        rows = ["# ofera facelog 1", "# layout: ovr63", "time," + ",".join(OVR63_NAMES)]
        for i, t in enumerate((0.0, 0.05, 0.1)):
            w = np.zeros(63)
            w[OVR63_NAMES.index("EYES_CLOSED_L")] = w[OVR63_NAMES.index("EYES_CLOSED_R")] = i / 2
            rows.append(f"{t:.6f}," + ",".join(f"{x:g}" for x in w))
        out = page.evaluate("t => __ofera.playText(t, 'quest.csv')", "\n".join(rows))
        assert out == {"rows": 3, "layout": "ovr63", "duration": pytest.approx(0.1)}
        wait(page, "!__ofera.playing && __ofera.settled")
        w = page.evaluate("__ofera.weights()")
        assert w[0] == pytest.approx(1.0) and w[7] == pytest.approx(1.0)  # eyeBlinkLeft, eyeBlinkRight

        bad = page.evaluate("t => __ofera.playText(t, 'bad.csv')", "time,notAShape\n0,1\n")
        assert "not a known blendshape layout" in bad["error"]
    finally:
        page.close()


def test_javascript_codec_matches_the_golden_vectors(browser, server) -> None:
    """protocol.js/msgpack.js against protocol/vectors: client messages byte for byte, server messages
    decoded to the same values, invalid ones refused with the expected code."""
    vectors = []
    for meta in sorted(p for p in VECTORS.glob("*.json")  # tables: test_browser_tables; rig_tiny_frames (no
                       if p.stem not in ("tables", "rig_tiny_frames")):  # message): test_params_browser.py
        v = json.loads(meta.read_text())
        v["bytes"] = list(meta.with_suffix(".msgpack").read_bytes())
        vectors.append(v)
    page = open_page(browser, f"{server}/static/layouts.json", viewport=None, settle=False)
    try:
        results = page.evaluate(JS_VECTOR_CHECK, vectors)
    finally:
        page.close()
    checked = {r["name"]: r for r in results}
    assert {"hello_full", "bs", "ping", "bye", "welcome_q13", "avatar_chunk1", "frame_f16_sparse",
            "frame_q13", "invalid_frame_nan", "invalid_deep_nesting", "hello_delta", "resync", "welcome_delta",
            "frame_q13_key", "frame_q13_delta", "frame_q13_delta_drop", "frame_f16_delta_drop",
            "invalid_delta_padding"} <= checked.keys()
    bad = [r for r in results if not r["ok"]]
    assert not bad, bad


JS_VECTOR_CHECK = """async (vectors) => {
  const P = await import("/static/protocol.js");
  const hex = (b) => Array.from(b, (x) => x.toString(16).padStart(2, "0")).join("");
  const out = [];
  const byName = Object.fromEntries(vectors.map((v) => [v.name, v]));
  const quantOf = (fmt) => fmt.quant && { pos_min: Float32Array.from(fmt.quant.pos_min),
    pos_max: Float32Array.from(fmt.quant.pos_max), log_scale: Float32Array.from(fmt.quant.log_scale) };
  const deltaState = (fmt) => { // a delta session's client state, avatar complete (section 7.1)
    const st = new P.AvatarState({ avatar: { count: fmt.count, sh_degree: 0 }, encoding: fmt.encoding, sparse: false,
      delta: true, quant: quantOf(fmt) });
    st.complete = true;
    return st;
  };
  for (const v of vectors) {
    const bytes = new Uint8Array(v.bytes);
    const F = v.fields;
    try {
      if (v.name.startsWith("invalid_")) {
        if (v.name.startsWith("invalid_hello_") || v.context?.layout) continue; // the server's own checks
        let code = null;
        try {
          const m = P.decodeServerMessage(bytes);
          const fmt = v.context?.format;
          if (m.type === "frame" && fmt?.delta) {
            const st = deltaState(fmt);
            st.hasKey = true;
            st.applyFrame(m);
          } else if (m.type === "frame" && fmt) {
            const st = new P.AvatarState({ avatar: { count: fmt.count, sh_degree: 0 }, encoding: fmt.encoding,
              sparse: !!fmt.sparse, quant: null });
            st.complete = true;
            st.applyFrame(m);
          }
        } catch (e) { code = e.code; }
        out.push({ name: v.name, ok: code === v.expect_error.code, got: code, want: v.expect_error.code });
        continue;
      }
      if (v.direction === "client_to_server") {
        let b;
        if (F.type === "hello") b = P.helloMessage({ layout: F.layout, avatar: F.avatar, encoding: F.encoding,
          coords: F.coords, sparse: F.sparse, delta: F.delta, device: F.device, token: F.token,
          maxGaussians: F.max_gaussians, room: F.room, publish: F.publish, self: F.self, roomToken: F.room_token });
        else if (F.type === "bs") b = P.bsMessage(F.seq, F.t, F.w.values, F.conf?.values);
        else if (F.type === "ping") b = P.pingMessage(F.t);
        else if (F.type === "resync") b = P.resyncMessage();
        else b = P.byeMessage();
        out.push({ name: v.name, ok: hex(b) === hex(bytes), got: hex(b) });
        continue;
      }
      const m = P.decodeServerMessage(bytes);
      let ok = m.type === F.type;
      if (m.type === "frame" && v.format.delta) { // apply the key / delta sequence, compare every Gaussian
        const st = deltaState(v.format);
        for (const name of [...(v.after ?? []), v.name]) {
          st.applyFrame(P.decodeServerMessage(new Uint8Array(byName[name].bytes)));
        }
        for (const k of ["position", "rotation", "scale"]) {
          const ref = v.decoded[k].flat();
          for (let i = 0; i < ref.length; i++) ok = ok && Math.abs(ref[i] - st[k][i]) <= 1e-6 * Math.abs(ref[i]) + 1e-7;
        }
        ok = ok && m.seq === F.seq && m.key === F.key && m.n === F.n;
      } else if (m.type === "frame" && v.format.encoding === "params") { // PROTOCOL.md 13: 68 values, seq/t if stamped
        ok = ok && m.params.length === F.params.values.length && F.params.values.every((x, i) => m.params[i] === x)
          && m.seq === (F.seq ?? null) && m.t === (F.t ?? null);
      } else if (m.type === "frame") {
        const fmt = v.format;
        const quant = fmt.quant && { pos_min: Float32Array.from(fmt.quant.pos_min),
          pos_max: Float32Array.from(fmt.quant.pos_max), log_scale: Float32Array.from(fmt.quant.log_scale) };
        const d = P.decodeFrameArrays(fmt.encoding, m.n, m, quant);
        for (const k of ["position", "rotation", "scale"]) {
          const ref = v.decoded[k].flat();
          for (let i = 0; i < ref.length; i++) ok = ok && Math.abs(ref[i] - d[k][i]) <= 1e-7;
        }
        ok = ok && m.seq === F.seq && m.t === F.t && m.n === F.n;
      } else if (m.type === "avatar") {
        ok = ok && m.n === F.n && m.offset === F.offset && Math.abs(m.opacity[0] - F.opacity.values[0]) < 1e-7;
      } else if (m.type === "welcome") {
        ok = ok && m.session === F.session && m.avatar?.count === F.avatar?.count && m.encoding === F.encoding
          && m.delta === (F.delta ?? false);
      } else if (m.type === "error") {
        ok = ok && m.code === F.code && m.fatal === F.fatal;
      } else if (m.type === "pong") {
        ok = ok && m.t === F.t;
      }
      out.push({ name: v.name, ok });
    } catch (e) {
      out.push({ name: v.name, ok: false, error: String(e) });
    }
  }
  return out;
}"""
