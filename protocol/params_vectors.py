"""Golden vectors of expression streaming (PROTOCOL.md 13), written by make_vectors.py.

- `hello_params`, `welcome_params`: the handshake of a params session;
- `rig_tiny`: one `rig` message carrying a whole tiny rig (5 vertices, 3 faces, 4 Gaussians, E = 3, P = 2); its
  JSON adds `body`, the rig body's fields (bins as typed arrays);
- `params_frame_stamped` (seq, t, timing) and `params_frame` (unstamped, 294 B): params frames;
- `rig_tiny_frames.json`: params and the deformation `deform_rig` gives for them (vertices after step 5, the
  Gaussians' position, rotation, scale), for the clients' tests;
- invalid: `invalid_params_length`, `invalid_params_seq_without_t`.

Every input is a fixed decimal, so the bytes are the same on every machine.
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
from ofera_protocol import AvatarInfo, Hello, Welcome, encode
from ofera_protocol.messages import ParamsFrame
from ofera_protocol.rig import Rig, decode_rig, deform_rig, encode_rig, rig_vertices, split_rig

C2S, S2C = "client_to_server", "server_to_client"
TINY_COUNT = 6
"""Gaussians of the tiny rig's avatar; the rig deforms 4 of them (ids 0, 2, 3, 5)."""
PARAMS_FORMAT = {"encoding": "params", "count": TINY_COUNT, "sparse": False, "quant": None}
"""The `format` (as other frame vectors give it) of a params session's frames: decode with ParamsFormat()."""


def _rot6d(axis: tuple[float, float, float], angle: float) -> list[float]:
    """6D (the first two rows) of the rotation by `angle` radians about the unit `axis` (Rodrigues, float64)."""
    k = np.asarray(axis, np.float64)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    r = np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx
    return r[:2].reshape(6).tolist()


def tiny_rig() -> Rig:
    """A triangle-bound rig small enough to check by hand."""
    a = np.arange
    template = np.array([[0.0, 0.0, 0.1], [0.02, 0.0, 0.1], [0.01, 0.02, 0.105], [-0.01, 0.015, 0.1],
                         [0.03, 0.02, 0.095]], np.float32)
    weights = np.array([[0.1, 0.2, 0.7, 0.0, 0.0], [0.0, 0.5, 0.5, 0.0, 0.0], [0.0, 0.6, 0.0, 0.4, 0.0],
                        [0.0, 0.3, 0.2, 0.0, 0.5], [0.25, 0.25, 0.0, 0.25, 0.25]], np.float32)
    rot = np.array([[0.0, 0.0, 0.0, 1.0], [0.1, 0.2, 0.3, 0.9], [0.2, -0.9, 0.1, 0.3], [-0.5, 0.5, -0.5, 0.5]])
    return Rig(
        binding="triangle", count=TINY_COUNT, index=np.array([0, 2, 3, 5], np.uint32),
        joints=np.array([[0.0, 0.0, 0.0], [0.0, 0.02, -0.01], [0.0, -0.02, 0.02], [0.03, 0.035, 0.06],
                         [-0.03, 0.035, 0.06]], np.float32),
        joints_expr=((a(45, dtype=np.float64).reshape(5, 3, 3) - 22) / 10000).astype(np.float32),
        template=template,
        expr_basis=((a(45, dtype=np.float64).reshape(5, 3, 3) - 20) / 8192).astype(np.float32),
        pose_rows=np.array([13, 20], np.uint8),
        pose_basis=((a(30, dtype=np.float64).reshape(5, 2, 3) - 14) / 4096).astype(np.float16),
        weights=weights, face=np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]], np.uint32),
        gaussian_face=np.array([0, 1, 2, 1], np.uint32),
        local_position=np.array([[0.0, 0.0, 0.0], [0.25, 0.1, -0.3], [-0.5, 0.05, 0.4], [1.5, -0.2, 0.75]],
                                np.float32),
        local_rotation=(rot / np.sqrt((rot ** 2).sum(1, keepdims=True))).astype(np.float16),
        local_scale=np.array([[0.5, 0.25, 0.125], [1.0, 0.75, 0.1], [0.3, 0.3, 0.05], [2.0, 0.5, 0.2]],
                             np.float16))


def tiny_params() -> list[tuple[str, np.ndarray]]:
    """(note, params (68,) float32) of the tiny rig's frames."""
    neutral = np.zeros(68, np.float64)
    neutral[50:] = [1, 0, 0, 0, 1, 0] * 3
    open_jaw = neutral.copy()
    open_jaw[:3] = [1.5, -0.75, 0.5]
    open_jaw[50:56] = _rot6d((1.0, 0.0, 0.0), 0.3)
    open_jaw[56:62] = _rot6d((0.0, 1.0, 0.0), 0.25)
    open_jaw[62:68] = _rot6d((0.6, 0.8, 0.0), -0.2)
    raw = neutral.copy()  # a network's raw 6D: not orthonormal (step 2 re-orthonormalises it)
    raw[:3] = [-2.0, 0.5, 3.0]
    raw[3:50] = 0.25  # components beyond the rig's E = 3: unused
    raw[50:56] = [2.0, 0.1, 0.0, 0.3, 1.5, 0.4]
    raw[56:62] = [0.9, 0.0, -0.2, 0.0, 1.1, 0.0]
    return [("neutral: the rig's rest pose", neutral.astype(np.float32)),
            ("expression (1.5, -0.75, 0.5), jaw 0.3 rad about x, left eye 0.25 about y, right eye -0.2 about "
             "(0.6, 0.8, 0)", open_jaw.astype(np.float32)),
            ("un-normalised 6D jaw and left eye, expression components beyond E set (unused)",
             raw.astype(np.float32))]


_BODY_DTYPES = {"<f4": "float32", "<f2": "float16", "<u4": "uint32", "u1": "uint8"}


def describe_body(body: bytes) -> dict[str, Any]:
    """The rig body's map in wire order, bins as {"dtype", "shape", "values"}."""
    from ofera_protocol.rig import _schema

    rig = decode_rig(body)
    schema = _schema(rig.binding, rig.vertices, rig.faces, rig.gaussians, rig.expr_dims, int(rig.pose_rows.size))
    out: dict[str, Any] = {}
    for k, v in msgpack.unpackb(body, raw=False).items():
        if k in schema:
            dtype, shape = schema[k]
            a = np.frombuffer(v, dtype=np.dtype(dtype)).reshape(shape)
            out[k] = {"dtype": _BODY_DTYPES[dtype], "shape": list(shape), "values": a.tolist()}
        else:
            out[k] = v
    return out


def _entry(name: str, direction: str, data: bytes, note: str, **extra: Any) -> tuple[str, bytes, dict[str, Any]]:
    m = msgpack.unpackb(data, raw=False)
    dtypes = {"params": "<f4", "data": "u1"}
    fields = {k: ({"dtype": "float32" if k == "params" else "uint8", "shape": [len(v) // (4 if k == "params" else 1)],
                   "values": np.frombuffer(v, dtypes[k]).tolist()} if k in dtypes else v) for k, v in m.items()}
    return name, data, {"name": name, "direction": direction, "type": m["type"], "note": note, "size": len(data),
                        "hex": data.hex(), "fields": fields, **extra}


def _invalid(name: str, data: bytes, code: str, note: str) -> tuple[str, bytes, dict[str, Any]]:
    return name, data, {"name": name, "direction": S2C, "note": note, "size": len(data), "hex": data.hex(),
                        "context": {"format": PARAMS_FORMAT}, "expect_error": {"code": code}}


def params_vectors(seq: int, t: int, timing: dict[str, int]) -> list[tuple[str, bytes, dict[str, Any]]]:
    """The vectors of PROTOCOL.md 13 (see the module docstring), with the frames' seq, t and timing."""
    from ofera_protocol.codec import pack_map

    body = encode_rig(tiny_rig())
    (chunk,) = split_rig(body)
    params = tiny_params()
    y = params[1][1]
    welcome = Welcome(session="s-0006", avatar=AvatarInfo("default", TINY_COUNT, 0), layout="arkit52",
                      encoding="params", server="ofera/0.1.0", rig_bytes=len(body))
    short = pack_map({"type": "frame", "params": np.ascontiguousarray(y[:67], "<f4")})
    return [
        _entry("hello_params", C2S, encode(Hello(layout="arkit52", encoding="params")),
               "hello asking for expression streaming (params)"),
        _entry("welcome_params", S2C, encode(welcome),
               f"welcome of a params session: the rig body that follows has {len(body)} bytes"),
        _entry("rig_tiny", S2C, encode(chunk), "a whole tiny rig in one rig message (triangle binding, 5 vertices, "
               "3 faces, 4 of 6 Gaussians, 3 expression components, pose rows 13 and 20)",
               body=describe_body(body)),
        _entry("params_frame_stamped", S2C, encode(ParamsFrame(params=y, seq=seq, t=t, timing=timing)),
               "a stamped params frame (seq, t, timing): the tiny rig's second frame of rig_tiny_frames.json",
               format=PARAMS_FORMAT),
        _entry("params_frame", S2C, encode(ParamsFrame(params=y)),
               "the same values unstamped: 294 bytes, what most params frames are", format=PARAMS_FORMAT),
        _invalid("invalid_params_length", short, "bad_length", "params frame with 67 values"),
        _invalid("invalid_params_seq_without_t", pack_map({"type": "frame", "seq": seq, "params": y}), "bad_field",
                 "params frame with seq but no t"),
    ]


def rig_frames(seq: int, t: int, timing: dict[str, int]) -> dict[str, Any]:
    """`rig_tiny_frames.json`: the tiny rig's frames and what deform_rig makes of them."""
    rig = tiny_rig()
    frames = []
    for i, (note, y) in enumerate(tiny_params()):
        position, rotation, scale = deform_rig(rig, y)
        msg = ParamsFrame(params=y, seq=seq + i, t=t + 13_889 * i, timing=timing) if i == 0 else ParamsFrame(params=y)
        frames.append({"note": note, "params": y.tolist(), "hex": encode(msg).hex(),
                       "vertices": rig_vertices(rig, y).astype(np.float32).tolist(), "position": position.tolist(),
                       "rotation": rotation.tolist(), "scale": scale.tolist()})
    return {"name": "rig_tiny_frames", "rig": "rig_tiny", "coords": "flame", "count": rig.count,
            "index": rig.index.tolist(),
            "tolerance": {"position_m": 1e-6, "rotation": 1e-5, "scale_relative": 1e-5, "vertices_m": 1e-6},
            "note": "PROTOCOL.md 13.4 applied to rig_tiny: params, the rig's vertices after step 5, and the "
                    "position, rotation (x, y, z, w), scale of Gaussians index[0..3], FLAME space, float32",
            "frames": frames}
