"""The browser preview with a LAM avatar: `ofera serve --avatar-zip ZIP` in headless Chromium (helpers in
browser_support.py). The avatar is shown, the jawOpen slider moves its lower face, and a bsData.json track plays.

Runs on a small LAM zip written here (tests/lam_fixtures.py) everywhere, CI included (conftest.py's `browser`
fixture skips locally without Chromium or playwright, fails in CI), and again on the real statue
(../shared/data/lam_statue.zip, 20k Gaussians) when it is present; with OFERA_DOCS_SCREENSHOTS=1 the statue run
writes the README's screenshot, docs/browser.png.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import lam_fixtures as L
import numpy as np
import pytest
from browser_support import ROOT, canvas_pixels, foreground, ofera_serve, open_page, wait, wait_settled

STATUE = ROOT.parent / "shared" / "data" / "lam_statue.zip"
SCREENSHOT = ROOT / "docs" / "browser.png"
SMALL_TRACK_ROWS = 45


@dataclass(frozen=True)
class LamAvatar:
    kind: str  # "small" (written here) or "statue" (the real export)
    url: str
    count: int
    track: str  # a bsData.json text
    rows: int


def _small_zip(folder: Path) -> Path:
    """The fixture patch with Gaussians large and opaque enough to cover it on screen, and a longer track."""
    n = L.patch()[0].shape[0]
    cols = L.gaussians(n)
    cols["log_scale"][:] = np.log(0.007)
    cols["opacity"][:] = 6.0
    return L.make_zip(folder / "patch.zip", ply=L.make_ply(cols), track=False,
                      extra_files={"arkitWithBSData/bsData.json": L.bs_track(frames=SMALL_TRACK_ROWS)})


@pytest.fixture(scope="module", params=["small", "statue"])
def lam(request, browser) -> Iterator[LamAvatar]:
    """`ofera serve --port 0 --avatar-zip ZIP` (a private cache: the zip is imported at start-up)."""
    root = Path(tempfile.mkdtemp(prefix="ofera-lam-browser-"))
    if request.param == "statue":
        if not STATUE.is_file():
            pytest.skip(f"{STATUE} is absent (real LAM data: ../shared/data); the small zip ran")
        z, count, stem = STATUE, 20018, "lam_statue"
    else:
        z, count, stem = _small_zip(root), L.patch()[0].shape[0], "patch"
    with zipfile.ZipFile(z) as zf:
        track = zf.read("arkitWithBSData/bsData.json").decode()
    rows = len(json.loads(track)["frames"])
    with ofera_serve("--avatar-zip", str(z), env={"OFERA_CACHE": str(root / "cache")}) as (url, lines):
        assert any(stem in line for line in lines), lines
        yield LamAvatar(request.param, url, count, track, rows)


def test_lam_avatar_is_shown_and_its_jaw_opens(browser, lam) -> None:
    page = open_page(browser, f"{lam.url}/?auto=0")
    try:
        info = page.evaluate("({count: __ofera.count, expression: __ofera.expression, errors: __ofera.errors})")
        assert info == {"count": lam.count, "expression": "arkit51", "errors": []}, info
        before = canvas_pixels(page)
        h, w, _ = before.shape
        assert foreground(before[int(h * 0.3):int(h * 0.7), int(w * 0.4):int(w * 0.6)]).mean() > 0.9
        assert "arkit51" in page.inner_text("#hud")
        if lam.kind == "statue":
            if os.environ.get("OFERA_DOCS_SCREENSHOTS"):  # regenerate the README's picture on request only
                SCREENSHOT.parent.mkdir(exist_ok=True)
                page.screenshot(path=str(SCREENSHOT))
        seq = page.evaluate("__ofera.lastFrameSeq")
        page.locator("#bs-jawOpen").fill("1")
        wait_settled(page, seq)
        after = canvas_pixels(page)
        changed = np.abs(after - before).max(axis=2) > 40
        ys = np.flatnonzero(changed.any(axis=1))
        assert changed.sum() > 200, "jawOpen changed (almost) nothing on screen"
        fg_rows = np.flatnonzero(foreground(before).any(axis=1))
        middle = (fg_rows.min() + fg_rows.max()) / 2
        assert np.median(ys) > middle - 0.05 * h, "jawOpen should change the lower half of the head"
        if os.environ.get("OFERA_BROWSER_DEBUG"):
            page.screenshot(path=str(ROOT / "docs" / "images" / f"browser_lam_jaw_{lam.kind}.png"))
    finally:
        page.close()


def test_lam_bsdata_track_plays(browser, lam) -> None:
    page = open_page(browser, f"{lam.url}/?auto=0")
    try:
        page.uncheck("#loop")
        seq = page.evaluate("__ofera.lastSentSeq")
        out = page.evaluate("t => __ofera.playText(t, 'bsData.json')", lam.track)
        assert out["rows"] == lam.rows and out["layout"] == "arkit52", out
        assert out["duration"] == pytest.approx((lam.rows - 1) / 30, 0.01)
        wait(page, "!__ofera.playing && __ofera.settled")
        assert page.evaluate("__ofera.lastSentSeq") > seq + 10, "playback sent too few bs"
        assert "bsData.json" in page.inner_text("#playinfo")
        assert page.evaluate("__ofera.errors") == []
        bad = page.evaluate("t => __ofera.playText(t, 'x.json')", '{"names": ["smile"], "frames": [[1]]}')
        assert "not an ARKit blendshape name" in bad["error"]
        for text, error in (('{"names": ["jawOpen"], "frames": []}', "no frames"),
                            ('{"names": ["jawOpen", "JawOpen"], "frames": [[1, 0]]}', "both the ARKit shape"),
                            ('{"names": ["jawOpen"], "frames": [{"weights": [1], "time": 0.1}, '
                             '{"weights": [0], "time": 0.1}]}', "frame times must increase")):
            bad = page.evaluate("t => __ofera.playText(t, 'x.json')", text)
            assert error in bad.get("error", ""), (text, bad)  # refused like ofera.avatar.lam.read_bs_track
    finally:
        page.close()
