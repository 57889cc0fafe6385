"""Shared fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_DATA = Path(os.environ.get("OFERA_SHARED_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data")
"""Real captures made by others (not in the repository): ``$OFERA_SHARED_DATA``, else ``../shared/data``."""


@pytest.fixture(scope="session")
def head():
    from ofera.head import default_head

    return default_head()
