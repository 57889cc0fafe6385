"""The browser preview with a LAM avatar: `ofera serve --avatar-zip ../shared/data/lam_statue.zip` in headless
Chromium (helpers of test_browser_preview.py). The statue (20k Gaussians, SH degree 0) is shown, the jawOpen
slider moves its mouth, and LAM's own bsData.json track plays. Writes the README's screenshot, docs/browser.png.

Skipped without the real zip (../shared/data), /usr/bin/chromium or the playwright package.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
from collections.abc import Iterator

import numpy as np
import pytest
from test_browser_preview import (
    ROOT,
    canvas_pixels,
    foreground,
    ofera_serve,
    open_page,
    wait,
    wait_settled,
)

STATUE = ROOT.parent / "shared" / "data" / "lam_statue.zip"
SCREENSHOT = ROOT / "docs" / "browser.png"
pytestmark = pytest.mark.skipif(not STATUE.is_file(), reason=f"{STATUE} is absent (real LAM data: ../shared/data)")


@pytest.fixture(scope="module")
def lam_server(browser) -> Iterator[str]:
    """`ofera serve --port 0 --avatar-zip STATUE` (a private cache: the zip is imported at start-up)."""
    cache = tempfile.mkdtemp(prefix="ofera-lam-cache-")
    with ofera_serve("--avatar-zip", str(STATUE), env={"OFERA_CACHE": cache}) as (url, lines):
        assert any("lam_statue" in line for line in lines), lines
        yield url


def test_statue_is_shown_and_its_jaw_opens(browser, lam_server) -> None:
    page = open_page(browser, f"{lam_server}/?auto=0")
    try:
        info = page.evaluate("({count: __ofera.count, expression: __ofera.expression, errors: __ofera.errors})")
        assert info == {"count": 20018, "expression": "arkit51", "errors": []}, info
        before = canvas_pixels(page)
        h, w, _ = before.shape
        assert foreground(before[int(h * 0.3):int(h * 0.7), int(w * 0.4):int(w * 0.6)]).mean() > 0.9
        assert "arkit51" in page.inner_text("#hud")
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
            page.screenshot(path=str(ROOT / "docs" / "images" / "browser_lam_jaw.png"))
    finally:
        page.close()


def test_lam_bsdata_track_plays(browser, lam_server) -> None:
    with zipfile.ZipFile(STATUE) as zf:
        text = zf.read("arkitWithBSData/bsData.json").decode()
    page = open_page(browser, f"{lam_server}/?auto=0")
    try:
        page.uncheck("#loop")
        seq = page.evaluate("__ofera.lastSentSeq")
        out = page.evaluate("t => __ofera.playText(t, 'bsData.json')", text)
        assert out["rows"] == 184 and out["layout"] == "arkit52" and out["duration"] == pytest.approx(183 / 30, 0.01)
        wait(page, "!__ofera.playing && __ofera.settled")
        assert page.evaluate("__ofera.lastSentSeq") > seq + 10, "playback sent too few bs"
        assert "bsData.json" in page.inner_text("#playinfo")
        assert page.evaluate("__ofera.errors") == []
        bad = page.evaluate("t => __ofera.playText(t, 'x.json')", '{"names": ["smile"], "frames": [[1]]}')
        assert "not an ARKit blendshape name" in bad["error"]
    finally:
        page.close()
