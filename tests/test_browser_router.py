"""The preview's routes (`ofera.web.router`), without a browser: the page, its static files, the layout
table the page builds its sliders and CSV conversion from."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from ofera import web
from ofera.mapping.layouts import ARKIT52_NAMES, ARKIT_REGIONS, LAYOUTS, conversion_matrix


@pytest.fixture(scope="module")
def client() -> TestClient:
    app = FastAPI()
    app.include_router(web.router)
    return TestClient(app)


def test_page_and_its_modules_are_served(client: TestClient) -> None:
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert 'src="static/app.js"' in page.text and 'type="module"' in page.text
    assert client.head("/").status_code == 200
    for name in ("app.js", "protocol.js", "msgpack.js", "renderer.js", "splat-worker.js", "facelog.js", "style.css"):
        r = client.get(f"/static/{name}")
        assert r.status_code == 200, name
        kind = "text/css" if name.endswith(".css") else "text/javascript"
        assert r.headers["content-type"].startswith(kind), name  # ES modules need a JavaScript type


def test_modules_load_nothing_from_elsewhere(client: TestClient) -> None:
    """No CDN, no build: every import is a relative path to a file the router serves."""
    for path in sorted(web.STATIC.iterdir()):
        text = path.read_text()
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}/", text), path.name  # no absolute URL
        for spec in re.findall(r"""^\s*import\s[^'"]*['"]([^'"]+)['"]""", text, flags=re.M):
            assert spec.startswith("./"), (path.name, spec)
            assert client.get(f"/static/{spec[2:]}").status_code == 200, (path.name, spec)


def test_only_files_of_the_page_are_served(client: TestClient) -> None:
    for bad in ("/static/nope.js", "/static/../__init__.py", "/static/%2e%2e/__init__.py", "/static/",
                "/static/index.py"):
        assert client.get(bad).status_code == 404, bad


def test_layout_table_is_the_servers(client: TestClient) -> None:
    table = client.get("/static/layouts.json").json()
    assert table["arkit52"] == list(ARKIT52_NAMES)
    assert table["regions"] == {k: list(v) for k, v in ARKIT_REGIONS.items()}
    assert sorted(sum(table["regions"].values(), [])) == sorted(ARKIT52_NAMES)  # every slider in one group
    assert set(table["layouts"]) == set(LAYOUTS)
    for name, info in table["layouts"].items():
        dense = np.zeros((52, len(info["names"])), np.float32)
        for d, s, v in info["to_arkit52"]:
            dense[d, s] = v
        np.testing.assert_allclose(dense, conversion_matrix(name, "arkit52"), atol=1e-6, err_msg=name)


def test_layout_table_has_the_protocols_layouts(client: TestClient) -> None:
    """The page's layouts (generated from ofera.mapping.layouts) against protocol/vectors/tables.json, name by name."""
    tables = json.loads((Path(__file__).resolve().parents[1] / "protocol" / "vectors" / "tables.json").read_text())
    table = client.get("/static/layouts.json").json()
    assert list(table["layouts"]) == list(tables["layouts"])
    for name, row in tables["layouts"].items():
        assert table["layouts"][name]["names"] == row["names"] and len(row["names"]) == row["length"], name
    assert table["arkit52"] == tables["layouts"]["arkit52"]["names"]
