"""Print an `info` summary: one JSON object (`--json`) or aligned `key: value` lines."""

from __future__ import annotations

import json


def print_summary(summary: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(summary))
        return
    for k, v in summary.items():
        print(f"{k:>12}: {v}")
