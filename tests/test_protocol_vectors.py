"""Golden vectors: regenerating gives identical bytes, each .msgpack decodes to what its .json says,
invalid vectors fail with the stated code, and PROTOCOL.md's worked examples are current."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

PROTOCOL_DIR = Path(__file__).resolve().parents[1] / "protocol"
VECTOR_DIR = PROTOCOL_DIR / "vectors"
sys.path.insert(0, str(PROTOCOL_DIR))

from ofera_protocol import (  # noqa: E402
    AvatarChunk,
    Frame,
    FrameFormat,
    ProtocolError,
    Quant,
    decode_client_message,
    decode_server_message,
    encode,
)
from ofera_protocol.messages import DeltaFrame, ParamsFormat  # noqa: E402


def _load_make_vectors() -> Any:
    spec = importlib.util.spec_from_file_location("make_vectors", PROTOCOL_DIR / "make_vectors.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


MV = _load_make_vectors()
BUILT = MV.build_vectors()
NAMES = [name for name, _, _ in BUILT]
VALID = [n for n in NAMES if not n.startswith("invalid_")]
INVALID = [n for n in NAMES if n.startswith("invalid_")]


def _json(name: str) -> dict[str, Any]:
    return json.loads((VECTOR_DIR / f"{name}.json").read_text(encoding="utf-8"))


def _bytes(name: str) -> bytes:
    return (VECTOR_DIR / f"{name}.msgpack").read_bytes()


def _close(a: Any, b: Any, rel: float = 1e-6) -> bool:
    """Structural equality with a relative tolerance on floats (exp/log may differ by an ulp across libms)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k], rel) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_close(x, y, rel) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, (int, float)) and isinstance(b, (int, float)) and math.isclose(a, b, rel_tol=rel,
                                                                                             abs_tol=1e-12)
    return type(a) is type(b) and a == b


def _fmt(d: dict[str, Any]) -> FrameFormat | ParamsFormat:
    if d["encoding"] == "params":  # PROTOCOL.md 13: params frames carry 68 values, no Gaussians
        return ParamsFormat()
    q = d["quant"]
    quant = None if q is None else Quant(*(np.array(q[k], np.float32) for k in ("pos_min", "pos_max", "log_scale")))
    return FrameFormat(d["encoding"], d["count"], d["sparse"], quant, delta=d.get("delta", False))


def test_every_message_type_and_encoding_has_a_vector() -> None:
    types = {_json(n)["type"] for n in VALID}
    assert types >= {"hello", "bs", "ping", "bye", "resync", "welcome", "avatar", "frame", "error", "pong", "join",
                     "leave"}
    frames = {(_json(n)["format"]["encoding"], _json(n)["format"]["sparse"]) for n in VALID if n.startswith("frame")}
    assert frames == {(e, s) for e in ("f32", "f16", "q13") for s in (False, True)}
    codes = {_json(n)["expect_error"]["code"] for n in INVALID}
    assert {"malformed", "unknown_type", "bad_field", "bad_length", "non_finite", "unsupported_protocol",
            "unknown_layout", "unknown_encoding"} <= codes


def test_regenerating_gives_identical_files() -> None:
    on_disk = {p.name for p in VECTOR_DIR.iterdir()}
    assert on_disk == {f"{n}.{ext}" for n in NAMES for ext in ("msgpack", "json")} | {"tables.json",
                                                                                       "rig_tiny_frames.json"}
    for name, data, desc in BUILT:
        assert _bytes(name) == data, f"{name}.msgpack differs: run python protocol/make_vectors.py"
        assert _close(_json(name), json.loads(MV.json_text(desc))), f"{name}.json differs"


def test_generation_is_deterministic() -> None:
    again = MV.build_vectors()
    assert [(n, b) for n, b, _ in again] == [(n, b) for n, b, _ in BUILT]


def test_protocol_md_examples_are_current() -> None:
    text = (PROTOCOL_DIR / "PROTOCOL.md").read_text(encoding="utf-8")
    assert MV.update_protocol_md(text, MV.render_examples(BUILT)) == text
    for name in VALID:
        assert f"`{name}`" in text


@pytest.mark.parametrize("name", VALID)
def test_json_describes_the_bytes(name: str) -> None:
    data, d = _bytes(name), _json(name)
    assert d["size"] == len(data) and bytes.fromhex(d["hex"]) == data
    wire = msgpack.unpackb(data, raw=False)
    assert list(wire) == list(d["fields"])  # same keys, same order

    def check(w: dict, f: dict) -> None:
        for k, v in w.items():
            if isinstance(v, bytes):
                dt = np.dtype(f[k]["dtype"]).newbyteorder("<")
                a = np.frombuffer(v, dt).reshape(f[k]["shape"])
                assert a.tolist() == f[k]["values"], k
            elif isinstance(v, dict):
                check(v, f[k])
            else:
                assert v == f[k] and type(v) is type(f[k]), k

    check(wire, d["fields"])


@pytest.mark.parametrize("name", VALID)
def test_decoding_matches_json(name: str) -> None:
    data, d = _bytes(name), _json(name)
    if d["direction"] == "client_to_server":
        msg = decode_client_message(data)
    else:
        msg = decode_server_message(data, _fmt(d["format"]) if "format" in d else None)
    assert msg.TYPE == d["type"]
    if isinstance(msg, DeltaFrame):  # its values need the frames before it: test_delta_sequences_decode
        changed = np.unpackbits(np.array(d["fields"]["changed"]["values"], np.uint8), bitorder="little")
        assert msg.index.tolist() == np.flatnonzero(changed).tolist() and msg.n == d["fields"]["n"]
        assert msg.key is False and msg.seq == d["fields"]["seq"]
    elif isinstance(msg, Frame):
        for k in ("position", "rotation", "scale"):
            np.testing.assert_allclose(getattr(msg, k), np.array(d["decoded"][k], np.float32), rtol=1e-6, atol=0)
        n = d["fields"]["n"]
        assert msg.n == n and msg.seq == d["fields"]["seq"] and msg.timing == d["fields"]["timing"]
        assert (msg.index is None) == ("index" not in d["fields"])
        if msg.index is not None:
            assert msg.index.tolist() == d["fields"]["index"]["values"]
    elif isinstance(msg, AvatarChunk):
        for k in ("opacity", "sh", "position", "rotation", "scale"):
            assert getattr(msg, k).tolist() == d["fields"][k]["values"]
    else:
        for k, v in d["fields"].items():
            if k == "type":
                continue
            got = getattr(msg, k)
            if isinstance(v, dict) and "dtype" in v:
                assert got.tolist() == v["values"]
            elif k == "avatar" and isinstance(v, dict):
                assert vars(got) == v
            elif k == "quant":
                assert all(getattr(got, q).tolist() == v[q]["values"] for q in v)
            else:
                assert got == v, k


def test_delta_sequences_decode() -> None:
    """Key, delta, and delta-after-a-drop vectors applied in order give the `decoded` state of every Gaussian."""
    from ofera_protocol.delta import DeltaDecoder

    seqs = [n for n in VALID if _json(n).get("after")]
    assert {n for n in seqs} == {f"frame_{e}_delta{x}" for e in ("q13", "f16") for x in ("", "_drop")}
    for name in seqs:
        d = _json(name)
        fmt = _fmt(d["format"])
        dec = DeltaDecoder(fmt)
        state = None
        for step in [*d["after"], name]:
            msg = decode_server_message(_bytes(step), fmt)
            if isinstance(msg, DeltaFrame):
                got = dec.apply(msg)
                for a, k in zip(state, ("position", "rotation", "scale"), strict=True):
                    a[got.index] = getattr(got, k)
            else:
                assert msg.key is True
                dec.key(msg)
                state = [np.array(getattr(msg, k)) for k in ("position", "rotation", "scale")]
        for a, k in zip(state, ("position", "rotation", "scale"), strict=True):
            np.testing.assert_allclose(a, np.array(d["decoded"][k], np.float32), rtol=1e-6, atol=0)


@pytest.mark.parametrize("name", [n for n in VALID if n != "hello_minimal"])
def test_reencoding_the_decoded_message_gives_the_same_bytes(name: str) -> None:
    data, d = _bytes(name), _json(name)
    if d["direction"] == "client_to_server":
        assert encode(decode_client_message(data)) == data
    else:
        fmt = _fmt(d["format"]) if "format" in d else None
        assert encode(decode_server_message(data, fmt), fmt) == data


@pytest.mark.parametrize("name", INVALID)
def test_invalid_vectors_fail_with_their_code(name: str) -> None:
    data, d = _bytes(name), _json(name)
    ctx = d["context"] or {}
    with pytest.raises(ProtocolError) as ei:
        if d["direction"] == "client_to_server":
            decode_client_message(data, ctx.get("layout"))
        else:
            decode_server_message(data, _fmt(ctx["format"]) if "format" in ctx else None)
    assert ei.value.code == d["expect_error"]["code"]


def test_check_mode_reports_up_to_date(capsys: pytest.CaptureFixture[str]) -> None:
    assert MV.main(["--check"]) == 0
