"""Expression streaming in the browser (PROTOCOL.md 13): in headless Chromium, the page's splat worker deforms the
avatar from params frames (rig.js) and matches, Gaussian for Gaussian, what an f32 session of the same `ofera serve`
receives for the same bs (every frame of the real capture in ../shared/data when present, else synthetic ones);
and the preview itself streams in params mode (`?enc=params`) and shows the jaw opening.

Needs /usr/bin/chromium and the `playwright` package (conftest.py's `browser` fixture skips without them)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from browser_support import canvas_pixels, foreground, ofera_serve, open_page, wait_settled
from conftest import SHARED_DATA

CAPTURE = SHARED_DATA / "livelink_dao.gesichter"
pytestmark = pytest.mark.timeout(900)

COMPARE = (Path(__file__).resolve().parent / "params_compare.js").read_text()



@pytest.fixture(scope="module")
def server(browser) -> Iterator[str]:
    """`ofera serve --port 0` (the built-in default avatar, 115,600 Gaussians) in a subprocess; its base URL."""
    with ofera_serve() as (url, _):
        yield url


def frames() -> tuple[np.ndarray, str]:
    """The real capture (livelink61) when present, else a synthetic arkit52 sweep of jaw, smile and blinks."""
    if CAPTURE.is_file():
        from ofera.sources import read_gesichter

        return read_gesichter(CAPTURE).weights, "livelink61"
    w = np.zeros((24, 52), np.float32)
    t = np.linspace(0, 1, 24)
    w[:, 17], w[:, 43], w[:, 0] = t, 1 - t, (t > 0.5)  # jawOpen, mouthSmileLeft, eyeBlinkLeft
    return w, "arkit52"


def test_worker_matches_the_server_f32_frames(browser, server) -> None:
    weights, layout = frames()
    page = open_page(browser, f"{server}/?auto=0")
    try:
        r = page.evaluate(COMPARE, [weights.tolist(), layout, "flame"])
    finally:
        page.close()
    assert r["frames"] == len(weights) and r["count"] >= 50_000
    assert r["maxPos"] < 5e-5, r  # the 0.05 mm (measured: ~1.4 um, the rig's float16 parts)
    assert r["maxRot"] < 5e-3 and r["maxScale"] < 5e-3, r
    sizes = np.array(r["sizes"])
    assert (sizes[1:] <= 400).all() and np.median(sizes) == 294, sizes


def test_worker_in_unity_coordinates(browser, server) -> None:
    weights, layout = frames()
    page = open_page(browser, f"{server}/?auto=0")
    try:
        r = page.evaluate(COMPARE, [weights[::30].tolist(), layout, "unity"])
    finally:
        page.close()
    assert r["maxPos"] < 5e-5 and r["maxRot"] < 5e-3, r


def test_preview_streams_in_params_mode(browser, server) -> None:
    page = open_page(browser, f"{server}/?auto=0&enc=params")
    try:
        info = page.evaluate("({encoding: __ofera.encoding, status: __ofera.status, errors: __ofera.errors})")
        assert info == {"encoding": "params", "status": "streaming", "errors": []}, info
        before = canvas_pixels(page)
        seq = page.evaluate("__ofera.lastFrameSeq")
        page.locator("#bs-jawOpen").fill("1")
        wait_settled(page, seq)
        after = canvas_pixels(page)
        assert page.evaluate("__ofera.errors") == []
        h, w, _ = after.shape
        changed = np.abs(after - before).max(axis=2) > 24
        assert foreground(after[int(h * 0.35):int(h * 0.65), int(w * 0.4):int(w * 0.6)]).mean() > 0.9
        lower, upper = changed[int(h * 0.55):, :].mean(), changed[: int(h * 0.3), :].mean()
        assert lower > upper, f"the jaw should move the lower face ({lower:.3f} vs {upper:.3f} of the pixels)"
    finally:
        page.close()


RIG_JS = """async ([body, params, count]) => {
  const R = await import("/static/rig.js");
  const d = new R.RigDeformer(R.decodeRig(new Uint8Array(body)));
  const out = [];
  for (const y of params) {
    const P = new Float32Array(3 * count), Q = new Float32Array(4 * count), S = new Float32Array(3 * count);
    d.apply(Float32Array.from(y), P, Q, S, "flame");
    out.push({ position: Array.from(P), rotation: Array.from(Q), scale: Array.from(S) });
  }
  return out;
}"""


def test_rig_js_matches_the_reference_on_a_barycentric_rig(browser, server) -> None:
    """rig.js's barycentric path (FATE-style avatars; the built-in avatar is triangle-bound) against deform_rig."""
    from ofera_protocol.rig import decode_rig, deform_rig
    from test_params_rig import barycentric_rig_and_frames

    body, ys, _ = barycentric_rig_and_frames(n=600, frames=2)
    rig = decode_rig(body)
    page = open_page(browser, f"{server}/static/layouts.json", viewport=None, settle=False)
    try:
        got = page.evaluate(RIG_JS, [list(body), [y.tolist() for y in ys], rig.count])
    finally:
        page.close()
    idx = rig.index.astype(np.int64)
    for y, g in zip(ys, got):
        p, q, s = deform_rig(rig, y)
        np.testing.assert_allclose(np.array(g["position"]).reshape(-1, 3)[idx], p, atol=1e-7)
        np.testing.assert_allclose(np.array(g["rotation"]).reshape(-1, 4)[idx], q, atol=1e-6)
        np.testing.assert_allclose(np.array(g["scale"]).reshape(-1, 3)[idx], s, rtol=1e-6)
