"""The browser client's copies of the protocol's tables (`web/static/protocol.js`) against
`protocol/vectors/tables.json` (written from the one Python source, `ofera_protocol.tables`), name by name, in
headless Chromium.

The page's layouts are not a copy: `/static/layouts.json` is generated from the same source
(tests/test_browser_router.py checks it against tables.json). Needs Chromium and playwright, like
tests/test_browser_preview.py (skipped otherwise).
"""

from __future__ import annotations

import functools
import http.server
import json
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STATIC = ROOT / "server" / "ofera" / "web" / "static"
TABLES = json.loads((ROOT / "protocol" / "vectors" / "tables.json").read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def page_url() -> Iterator[str]:
    """The page's static files on a plain HTTP server (127.0.0.1, a free port): protocol.js needs no OFERA server."""
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(STATIC))
    handler.log_message = lambda *a: None  # type: ignore[attr-defined]
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


JS_TABLES = """async () => {
  const P = await import("/protocol.js");
  return { protocol: P.PROTOCOL, endpoint: P.ENDPOINT, encodings: P.ENCODINGS, field_bytes: P.FIELD_BYTES,
           close_codes: P.CLOSE_CODES, unknown_fatal: P.CLOSE_UNKNOWN_FATAL };
}"""


def test_protocol_js_tables_are_the_protocols(browser, page_url) -> None:
    page = browser.new_page()
    try:
        page.goto(f"{page_url}/index.html")
        js = page.evaluate(JS_TABLES)
    finally:
        page.close()
    assert (js["protocol"], js["endpoint"]) == (TABLES["protocol"], TABLES["endpoint"])
    assert js["encodings"] == list(TABLES["encodings"])
    assert list(js["field_bytes"]) == list(TABLES["encodings"])
    for name, row in TABLES["encodings"].items():
        assert js["field_bytes"][name] == [row["position"], row["rotation"], row["scale"]], name
        assert sum(js["field_bytes"][name]) == row["bytes_per_gaussian"], name
    assert js["close_codes"], "protocol.js has no CLOSE_CODES"
    for code, close in js["close_codes"].items():  # the errors the browser client raises itself
        assert TABLES["errors"][code]["close_code"] == close, code
    assert js["unknown_fatal"] == TABLES["close_codes"]["unknown_fatal"]
