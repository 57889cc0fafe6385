"""The protocol's tables have one source (`ofera_protocol.tables`): `vectors/tables.json` and PROTOCOL.md's generated
tables are current, and every Python copy agrees with it (the C# and JavaScript clients check theirs against
tables.json: unity_client_stub/Tests/TestMain.cs, tests/test_browser_preview.py)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

PROTOCOL_DIR = Path(__file__).resolve().parents[1] / "protocol"
sys.path.insert(0, str(PROTOCOL_DIR))

from ofera_protocol import constants as C  # noqa: E402
from ofera_protocol.errors import ERRORS, Fatality, close_code  # noqa: E402
from ofera_protocol.tables import begin_marker, end_marker, markdown_tables, tables, update_markdown  # noqa: E402

TABLES = json.loads((PROTOCOL_DIR / "vectors" / "tables.json").read_text(encoding="utf-8"))


def test_tables_json_is_current() -> None:
    assert TABLES == tables(), "vectors/tables.json is stale: run python protocol/make_vectors.py"


def test_protocol_md_tables_are_current() -> None:
    md = (PROTOCOL_DIR / "PROTOCOL.md").read_text(encoding="utf-8")
    for name in markdown_tables():
        assert begin_marker(name) in md and end_marker(name) in md, name
    assert update_markdown(md) == md, "PROTOCOL.md's generated tables are stale: run python protocol/make_vectors.py"


def test_the_server_uses_the_protocol_layouts() -> None:
    from ofera.mapping.layouts import LAYOUTS

    assert list(LAYOUTS) == list(TABLES["layouts"]) == list(C.LAYOUTS)
    for name, layout in LAYOUTS.items():
        assert list(layout.names) == TABLES["layouts"][name]["names"], name
        assert layout.length == C.LAYOUTS[name] == TABLES["layouts"][name]["length"], name


def test_error_codes_fatality_and_close_codes() -> None:
    assert list(TABLES["errors"]) == list(ERRORS)
    for code, row in TABLES["errors"].items():
        spec = ERRORS[code]
        assert Fatality(row["fatality"]) is spec.fatality
        if row["close_code"] is not None:
            assert close_code(code) == row["close_code"], code
        else:
            assert spec.fatality is Fatality.NEVER, code
    assert close_code("not_a_v1_code") == TABLES["close_codes"]["unknown_fatal"]


def test_field_sizes_and_limits() -> None:
    assert list(TABLES["encodings"]) == list(C.ENCODINGS)
    for e, row in TABLES["encodings"].items():
        assert (row["position"], row["rotation"], row["scale"]) == C.FIELD_BYTES[e]
        assert row["bytes_per_gaussian"] == C.BYTES_PER_GAUSSIAN[e] == sum(C.FIELD_BYTES[e])
    assert TABLES["limits"]["max_client_message"] == C.MAX_CLIENT_MESSAGE
    assert TABLES["limits"]["max_server_message"] == C.MAX_SERVER_MESSAGE
