"""Helpers of the browser tests (test_browser_preview.py, test_browser_quest.py, test_lam_browser.py): a real
`ofera serve` in a subprocess, a page opened on it (page errors collected, the page settled), waits that say
what the page was doing, and the canvas's pixels. The browser itself is conftest.py's `browser` fixture (skips
without Chromium or playwright, fails in CI)."""

from __future__ import annotations

import base64
import contextlib
import io
import os
import re
import signal
import subprocess
import sys
import time
import weakref
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BACKGROUND = np.array([32, 35, 42])  # the page's clear colour (renderer.js: 0.125, 0.137, 0.165)
SERVER_START_S = 300  # the default avatar's warm-up, on a busy machine
PAGE_S = 240  # a full-size avatar through SwiftShader, on a busy machine
VIEWPORT = {"width": 1100, "height": 720}
_PAGE_ERRORS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


@contextlib.contextmanager
def ofera_serve(*args: str, env: dict | None = None) -> Iterator[tuple[str, list[str]]]:
    """`ofera serve --port 0 ARGS` in a subprocess: (its base URL, its start-up lines); stopped with Ctrl-C."""
    env = dict(os.environ, OFERA_LOG_LEVEL="warning", PYTHONUNBUFFERED="1", **(env or {}))
    cmd = [sys.executable, "-c", "from ofera.cli.main import main; main()", "serve", "--port", "0", *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        lines: list[str] = []
        url = None
        deadline = time.monotonic() + SERVER_START_S
        while url is None and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            m = re.search(r"health\s+(http://\S+)/healthz", line)
            if m:
                url = m.group(1)
        assert url, "ofera serve did not start:\n" + "".join(lines)
        yield url, lines
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def open_page(browser, url: str, *, viewport: dict | None = VIEWPORT, settle: bool = True):
    """A new page at `url` that records its JavaScript errors (:func:`page_errors`). `settle`: wait until the
    preview (`/`) has connected and drawn (`__ofera.settled`) and fail on any page error so far; False for
    plain resources such as `/static/layouts.json`. The caller closes the page."""
    page = browser.new_page(viewport=viewport) if viewport is not None else browser.new_page()
    problems: list[str] = []
    _PAGE_ERRORS[page] = problems
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    try:
        page.goto(url)
        if settle:
            wait(page, "window.__ofera && window.__ofera.settled")
            assert not problems, problems
    except BaseException:
        page.close()
        raise
    return page


def page_errors(page) -> list[str]:
    """The JavaScript errors a page from :func:`open_page` has raised so far (a live list)."""
    return _PAGE_ERRORS[page]


STATE = """JSON.stringify(window.__ofera && {status: __ofera.status, count: __ofera.count, sent: __ofera.lastSentSeq,
  received: __ofera.lastFrameSeq, drawn: __ofera.drawnSeq, fps: __ofera.fps, reductions: __ofera.reductions,
  errors: __ofera.errors, hud: document.getElementById("hud").textContent,
  status_line: document.getElementById("status").textContent})"""


def wait(page, condition: str, timeout_s: float = PAGE_S) -> None:
    """Wait for a JavaScript condition; on timeout, say what the page was doing."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        page.wait_for_function(condition, timeout=timeout_s * 1000)
    except PlaywrightTimeout:
        pytest.fail(f"timed out after {timeout_s} s waiting for {condition!r}; page: {page.evaluate(STATE)}")


def wait_settled(page, after_seq: int) -> None:
    wait(page, f"__ofera.settled && __ofera.drawnSeq > {after_seq}")


def drag_across(page, selector: str) -> tuple[float, float]:
    """The orbit gesture: press at the centre of `selector`'s box, drag 150 px right and 20 px down, release; the
    centre, for a double click that brings the view back."""
    box = page.locator(selector).bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 150, y + 20, steps=5)
    page.mouse.up()
    return x, y


def canvas_pixels(page) -> np.ndarray:
    """The canvas's own pixels (its drawing buffer is preserved), without the text drawn over it."""
    from PIL import Image

    url = page.evaluate("document.getElementById('canvas').toDataURL('image/png')")
    png = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)


def foreground(img: np.ndarray) -> np.ndarray:
    return np.abs(img - BACKGROUND).max(axis=2) > 24
