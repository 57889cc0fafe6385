"""Shared fixtures."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

SHARED_DATA = Path(os.environ.get("OFERA_SHARED_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data")
"""Real captures made by others (not in the repository): ``$OFERA_SHARED_DATA``, else ``../shared/data``."""


def skip_or_fail(missing: str, what: str) -> None:
    """Skip the test for a missing tool (`missing`: which, and how to install it); fail instead when CI is set (CI
    installs the tools: .ci/run), saying that `what` cannot run in CI."""
    if os.environ.get("CI"):
        pytest.fail(f"{what} cannot run in CI: {missing}")
    pytest.skip(missing)


@pytest.fixture(scope="session")
def head():
    from ofera.head import default_head

    return default_head()


CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--no-sandbox", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
]


def _browser_missing() -> str | None:
    if not Path(CHROMIUM).exists():
        return f"{CHROMIUM} is missing (apt-get install chromium)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the playwright Python package is missing (pip install playwright; do not run `playwright install`)"
    return None


@pytest.fixture(scope="module")
def browser() -> Iterator:
    """Headless Chromium (the system's, through playwright) for the browser tests; skips (fails in CI) without it."""
    missing = _browser_missing()
    if missing:
        skip_or_fail(missing, "browser test")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()

