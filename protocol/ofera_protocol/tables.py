"""The protocol's tables, from their one Python source, as data (`vectors/tables.json`) and as PROTOCOL.md text.

Layouts (names and lengths: `layouts`), frame field sizes (`constants.FIELD_BYTES`), limits (`constants`), error
codes with their fatality and close codes, and the other close codes (`errors`). `python protocol/make_vectors.py`
writes `tables.json` and the generated tables of PROTOCOL.md (between ``<!-- BEGIN GENERATED TABLE name ... -->``
and ``<!-- END GENERATED TABLE name -->``); `--check` fails when either is stale. The C# client's tests
(unity_client_stub/Tests) and the browser client's (tests/test_browser_preview.py) check their own copies of these
tables against `tables.json`, name by name.
"""

from __future__ import annotations

import re
from typing import Any

from . import constants as C
from .errors import CLOSE_GOING_AWAY, CLOSE_NORMAL, CLOSE_UNKNOWN_FATAL, ERRORS
from .layouts import LAYOUT_NAMES, LAYOUT_ORDER

FIELDS = ("position", "rotation", "scale")

LIMITS: dict[str, int] = {
    "max_client_message": C.MAX_CLIENT_MESSAGE,
    "max_server_message": C.MAX_SERVER_MESSAGE,
    "max_depth": C.MAX_DEPTH,
    "max_container_len": C.MAX_CONTAINER_LEN,
    "max_str_len": C.MAX_STR_LEN,
    "max_id_len": C.MAX_ID_LEN,
    "max_timing_stages": C.MAX_TIMING_STAGES,
    "max_sh_degree": C.MAX_SH_DEGREE,
}
"""Limits of section 1 and 2 (bytes, entries, characters), by name."""

FIELD_TYPES: dict[str, tuple[str, str, str]] = {
    "f32": ("3 x float32", "4 x float32 (x, y, z, w)", "3 x float32"),
    "f16": ("3 x float16", "4 x float16 (x, y, z, w)", "3 x float16"),
    "q13": ("3 x uint16", "1 x uint32 (10.10.10.2)", "3 x uint8"),
}
"""What `position`, `rotation` and `scale` hold per Gaussian in each encoding (PROTOCOL.md section 6)."""

_MESSAGE_LIMIT_RULES = (
    ("client -> server", C.MAX_CLIENT_MESSAGE, "a client MUST NOT send more; a server MUST accept up to this (a `bs` "
     "is 230 to 310 B)"),
    ("server -> client", C.MAX_SERVER_MESSAGE, "a server MUST NOT send more; a client MUST accept up to this"),
)


def tables() -> dict[str, Any]:
    """Everything `vectors/tables.json` holds (JSON-ready, in documentation order)."""
    return {
        "protocol": C.PROTOCOL_VERSION,
        "endpoint": C.ENDPOINT,
        "layouts": {name: {"length": len(names), "names": list(names)} for name, names in LAYOUT_NAMES.items()},
        "encodings": {e: {**dict(zip(FIELDS, C.FIELD_BYTES[e], strict=True)),
                          "bytes_per_gaussian": C.BYTES_PER_GAUSSIAN[e]} for e in C.ENCODINGS},
        "coords": list(C.COORDS),
        "errors": {code: {"fatality": s.fatality.value, "close_code": s.close_code} for code, s in ERRORS.items()},
        "close_codes": {"normal": CLOSE_NORMAL, "going_away": CLOSE_GOING_AWAY, "unknown_fatal": CLOSE_UNKNOWN_FATAL},
        "limits": dict(LIMITS),
    }


def _size(n: int) -> str:
    unit = "MiB" if n >= 1 << 20 else "KiB"
    return f"{n:,} ({n >> (20 if unit == 'MiB' else 10)} {unit})"


def markdown_tables() -> dict[str, str]:
    """The generated tables of PROTOCOL.md by name (markdown, without the BEGIN/END lines)."""
    limits = ["| direction | limit | rule |", "|---|---|---|"]
    limits += [f"| {d} | {_size(n)} | {rule} |" for d, n, rule in _MESSAGE_LIMIT_RULES]
    layouts = ["| layout | L | order |", "|---|---|---|"]
    layouts += [f"| `{name}` | {len(names)} | {LAYOUT_ORDER[name]} |" for name, names in LAYOUT_NAMES.items()]
    errors = ["| code | fatal | close code | meaning |", "|---|---|---|---|"]
    errors += [f"| `{code}` | {s.fatality.value} | {'-' if s.close_code is None else s.close_code} | {s.description} |"
               for code, s in ERRORS.items()]
    encodings = ["| encoding | `position` | `rotation` | `scale` | bytes | 100k Gaussians at 72 Hz |",
                 "|---|---|---|---|---|---|"]
    for e in C.ENCODINGS:
        sizes, total = C.FIELD_BYTES[e], C.BYTES_PER_GAUSSIAN[e]
        rate = round(total * 100_000 * 72 * 8 / 1e9, 2)
        encodings.append(f"| `{e}` | {' | '.join(FIELD_TYPES[e])} | {' + '.join(map(str, sizes))} = **{total}** | "
                         f"{rate:g} Gbit/s |")
    return {"limits": "\n".join(limits), "layouts": "\n".join(layouts), "encodings": "\n".join(encodings),
            "errors": "\n".join(errors)}


def begin_marker(name: str) -> str:
    return f"<!-- BEGIN GENERATED TABLE {name} (python protocol/make_vectors.py) -->"


def end_marker(name: str) -> str:
    return f"<!-- END GENERATED TABLE {name} -->"


def update_markdown(text: str) -> str:
    """`text` (PROTOCOL.md) with every generated table replaced by the current one, at the BEGIN line's indent."""
    for name, table in markdown_tables().items():
        found = re.search(rf"^([ \t]*){re.escape(begin_marker(name))}\n.*?^[ \t]*{re.escape(end_marker(name))}$",
                          text, re.S | re.M)
        if found is None:
            raise ValueError(f"PROTOCOL.md has no generated table {name!r} ({begin_marker(name)} ... "
                             f"{end_marker(name)})")
        pad = found.group(1)
        body = "\n".join(pad + line for line in [begin_marker(name), *table.splitlines(), end_marker(name)])
        text = text[:found.start()] + body + text[found.end():]
    return text
