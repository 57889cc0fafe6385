"""Expression streaming's rig (PROTOCOL.md 13): golden vectors, the rig body and chunks round trip and refuse bad
input, a float32 port of 13.4 matches the reference, and the rig of the built-in avatar reproduces the server's own
float32 frames (random expressions, and every frame of the real capture in ../shared/data when present)."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import SHARED_DATA
from ofera_protocol import ProtocolError
from ofera_protocol.codec import decode_server_message
from ofera_protocol.messages import ParamsFormat, ParamsFrame, RigChunk
from ofera_protocol.rig import RigAssembler, decode_rig, deform_rig, encode_rig, rig_vertices, split_rig

ROOT = Path(__file__).resolve().parents[1]
VECTORS = ROOT / "protocol" / "vectors"
CAPTURE = SHARED_DATA / "livelink_dao.gesichter"
sys.path.insert(0, str(ROOT / "protocol"))
from params_vectors import tiny_params, tiny_rig  # noqa: E402

pytestmark = pytest.mark.timeout(600)


def rotation_error(a: np.ndarray, b: np.ndarray) -> float:
    """Largest component difference of two quaternion arrays, up to sign."""
    return float(np.minimum(np.abs(a - b).max(axis=1), np.abs(a + b).max(axis=1)).max())


# ----------------------------------------------------------------------------- a float32 port of PROTOCOL.md 13.4


def port_f32(rig, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PROTOCOL.md 13.4 step by step in float32 (what a shader or C# does), written from the text, not the code."""
    f = np.float32
    p = params.astype(f)
    e = rig.expr_dims
    psi = p[:e]

    def m6(d):
        a1, a2 = d[:3], d[3:]
        b1 = a1 / max(np.sqrt(f(a1 @ a1)), f(1e-12))
        c = a2 - f(b1 @ a2) * b1
        b2 = c / max(np.sqrt(f(c @ c)), f(1e-12))
        return np.stack([b1, b2, np.cross(b1, b2)]).astype(f)

    rot = [np.eye(3, dtype=f), np.eye(3, dtype=f), m6(p[50:56]), m6(p[56:62]), m6(p[62:68])]
    joints = rig.joints.astype(f) + (rig.joints_expr.astype(f) @ psi)
    a = np.stack([np.concatenate([r, (j - r @ j)[:, None]], axis=1) for r, j in zip(rot, joints)]).astype(f)
    coef = np.array([rot[1 + r // 9][(r % 9) // 3, r % 3] - (1 if (r % 9) // 3 == r % 3 else 0)
                     for r in rig.pose_rows.astype(int)], f)
    v_po = (rig.template.astype(f) + np.einsum("sec,e->sc", rig.expr_basis.astype(f), psi)
            + np.einsum("spc,p->sc", rig.pose_basis.astype(f), coef)).astype(f)
    t = np.einsum("sk,kij->sij", rig.weights.astype(f), a).astype(f)
    v = (np.einsum("sij,sj->si", t[:, :, :3], v_po) + t[:, :, 3]).astype(f)
    pos, rots, scales = [], [], []
    for m in range(rig.gaussians):
        v0, v1, v2 = v[rig.face[rig.gaussian_face[m]].astype(int)]
        e1, e2 = v1 - v0, v2 - v0
        a0 = e1 / np.sqrt(max(f(e1 @ e1), f(1e-20)))
        n = np.cross(a0, e2)
        a1 = n / np.sqrt(max(f(n @ n), f(1e-20)))
        a2 = np.cross(a0, a1)
        r = np.stack([a0, a1, a2], axis=1)
        s_f = (np.sqrt(max(f(e1 @ e1), f(1e-20))) + abs(f(a2 @ e2))) / 2
        if rig.binding == "triangle":
            pos.append(r @ (rig.local_position[m].astype(f) * s_f) + (v0 + v1 + v2) / 3)
        else:
            b = rig.bary[m].astype(f)
            pos.append(b[0] * v0 + b[1] * v1 + b[2] * v2 + np.cross(e1, e2) * rig.normal_offset[m])
        t4 = [1 + r[0, 0] + r[1, 1] + r[2, 2], 1 + r[0, 0] - r[1, 1] - r[2, 2], 1 - r[0, 0] + r[1, 1] - r[2, 2],
              1 - r[0, 0] - r[1, 1] + r[2, 2]]
        rows = [[t4[0], r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]],
                [r[2, 1] - r[1, 2], t4[1], r[1, 0] + r[0, 1], r[0, 2] + r[2, 0]],
                [r[0, 2] - r[2, 0], r[1, 0] + r[0, 1], t4[2], r[2, 1] + r[1, 2]],
                [r[1, 0] - r[0, 1], r[0, 2] + r[2, 0], r[2, 1] + r[1, 2], t4[3]]]
        qf = np.array(rows[int(np.argmax(t4))], f)
        qf /= np.sqrt(qf @ qf)
        qf = -qf if qf[0] < 0 else qf
        lx, ly, lz, lw = rig.local_rotation[m].astype(f) / np.linalg.norm(rig.local_rotation[m].astype(f))
        w, x, y, z = qf
        q = np.array([w * lw - x * lx - y * ly - z * lz, w * lx + x * lw + y * lz - z * ly,
                      w * ly - x * lz + y * lw + z * lx, w * lz + x * ly - y * lx + z * lw], f)
        q /= np.sqrt(q @ q)
        rots.append([q[1], q[2], q[3], q[0]])
        scales.append(rig.local_scale[m].astype(f) * s_f)
    return np.array(pos, f), np.array(rots, f), np.array(scales, f)


# ----------------------------------------------------------------------------- vectors


def test_rig_tiny_vector_decodes_to_the_tiny_rig():
    chunk = decode_server_message((VECTORS / "rig_tiny.msgpack").read_bytes())
    assert isinstance(chunk, RigChunk) and chunk.chunks == 1 and chunk.size == chunk.data.size
    rig = decode_rig(chunk.data.tobytes())
    assert rig == tiny_rig()
    desc = json.loads((VECTORS / "rig_tiny.json").read_text())
    assert desc["body"]["gaussians"] == 4 and desc["body"]["pose_basis"]["dtype"] == "float16"
    np.testing.assert_array_equal(np.array(desc["body"]["pose_basis"]["values"], np.float16), rig.pose_basis)


def test_rig_tiny_frames_match_the_reference_and_a_float32_port():
    rig = tiny_rig()
    frames = json.loads((VECTORS / "rig_tiny_frames.json").read_text())
    assert frames["index"] == [0, 2, 3, 5] and len(frames["frames"]) == 3
    for fr, (_, y) in zip(frames["frames"], tiny_params()):
        np.testing.assert_array_equal(np.array(fr["params"], np.float32), y)
        p, q, s = deform_rig(rig, y)
        np.testing.assert_array_equal(p, np.array(fr["position"], np.float32))
        np.testing.assert_array_equal(q, np.array(fr["rotation"], np.float32))
        np.testing.assert_array_equal(s, np.array(fr["scale"], np.float32))
        np.testing.assert_allclose(rig_vertices(rig, y), fr["vertices"], atol=1e-7)
        p32, q32, s32 = port_f32(rig, y)
        assert np.abs(p32 - p).max() < 1e-6
        assert rotation_error(q32, q) < 1e-5
        assert (np.abs(s32 - s) / s).max() < 1e-5
        msg = decode_server_message(bytes.fromhex(fr["hex"]), ParamsFormat())
        assert isinstance(msg, ParamsFrame)
        np.testing.assert_array_equal(msg.params, y)


def test_params_frame_vectors():
    stamped = decode_server_message((VECTORS / "params_frame_stamped.msgpack").read_bytes(), ParamsFormat())
    plain = decode_server_message((VECTORS / "params_frame.msgpack").read_bytes(), ParamsFormat())
    assert stamped.seq == 42 and stamped.t is not None and stamped.timing["total"] == 597
    assert plain.seq is None and plain.t is None and plain.timing is None
    np.testing.assert_array_equal(stamped.params, plain.params)
    assert (VECTORS / "params_frame.msgpack").stat().st_size == 294
    for name in ("invalid_params_length", "invalid_params_seq_without_t"):
        d = json.loads((VECTORS / f"{name}.json").read_text())
        with pytest.raises(ProtocolError) as e:
            decode_server_message(bytes.fromhex(d["hex"]), ParamsFormat())
        assert e.value.code == d["expect_error"]["code"]


# ----------------------------------------------------------------------------- body and chunks


def test_rig_round_trip_in_small_chunks():
    body = encode_rig(tiny_rig())
    chunks = split_rig(body, 100, member="m-1")
    assert len(chunks) == -(-len(body) // 100) and all(c.member == "m-1" for c in chunks)
    asm = RigAssembler()
    from ofera_protocol import encode

    done = [asm.add(decode_server_message(encode(c))) for c in chunks]
    assert done == [False] * (len(chunks) - 1) + [True]
    assert decode_rig(asm.result()) == tiny_rig()


def test_rig_chunks_out_of_order_are_refused():
    chunks = split_rig(encode_rig(tiny_rig()), 300)
    asm = RigAssembler()
    with pytest.raises(ProtocolError, match="chunk 1 arrived, expected 0"):
        asm.add(chunks[1])
    asm = RigAssembler()
    asm.add(chunks[0])
    bad = dataclasses.replace(chunks[1], offset=chunks[1].offset + 1)
    with pytest.raises(ProtocolError, match="offset"):
        asm.add(bad)


@pytest.mark.parametrize("change, code, text", [
    (dict(index=np.array([0, 3, 2, 5], np.uint32)), "bad_field", "strictly ascending"),
    (dict(index=np.array([0, 2, 3, 6], np.uint32)), "bad_field", "avatar has 6"),
    (dict(gaussian_face=np.array([0, 1, 3, 1], np.uint32)), "bad_field", "gaussian_face"),
    (dict(face=np.array([[0, 1, 2], [0, 2, 3], [1, 5, 2]], np.uint32)), "bad_field", "'face'"),
    (dict(pose_rows=np.array([20, 13], np.uint8)), "bad_field", "pose_rows"),
    (dict(pose_rows=np.array([13, 36], np.uint8)), "bad_field", "pose_rows"),
])
def test_bad_rig_bodies_are_refused(change, code, text):
    body = encode_rig(dataclasses.replace(tiny_rig(), **change))
    with pytest.raises(ProtocolError, match=text) as e:
        decode_rig(body)
    assert e.value.code == code


def test_rig_body_field_errors():
    import msgpack
    from ofera_protocol.codec import pack_map

    m = msgpack.unpackb(encode_rig(tiny_rig()))
    for key, value, code in (("binding", "vertex", "bad_field"), ("template", b"\x00" * 12, "bad_length"),
                             ("weights", np.full((5, 5), np.nan, np.float32).tobytes(), "non_finite")):
        with pytest.raises(ProtocolError) as e:
            decode_rig(pack_map({**m, key: value}))
        assert e.value.code == code, key


# ----------------------------------------------------------------------------- the built-in avatar vs the server


@pytest.fixture(scope="module")
def default_assets():
    from ofera.avatar import load_avatar
    from ofera.mapping.runtime import Mapper
    from ofera.streaming.pipeline import AvatarAssets

    return AvatarAssets.create("default", load_avatar("default"), Mapper.default())


def _rig(assets, size=None):
    from ofera.streaming.params import rig_body

    return decode_rig(rig_body(assets, size))


def _flame_values(rng: np.random.Generator) -> np.ndarray:
    from ofera.head.rotations import axis_angle_to_matrix

    y = np.zeros(68, np.float32)
    y[:50] = rng.normal(0, 1, 50)
    for o, aa in ((50, [0.3, 0.02, 0.01]), (56, [0.1, 0.3, 0]), (62, [0.1, -0.3, 0])):
        y[o:o + 6] = axis_angle_to_matrix(np.array(aa))[:2].reshape(6)
    return y


def test_default_rig_size_and_content(default_assets):
    rig = _rig(default_assets)
    movable = np.flatnonzero(default_assets.movable())
    np.testing.assert_array_equal(rig.index, movable)
    assert rig.binding == "triangle" and rig.expr_dims == 50 and rig.count == default_assets.count
    assert set(rig.pose_rows.tolist()) <= set(range(9, 36))  # no neck rows
    assert len(encode_rig(rig)) < 6_000_000  # 5.5 MB: PROTOCOL.md 13.3


def test_default_rig_matches_the_server_frames(default_assets):
    """The rig of the built-in avatar against the server's own fast path (what f32 frames carry): random FLAME values
    with jaw and eyes turned, within the bound PROTOCOL.md 13.3 states."""
    rig = _rig(default_assets)
    pipeline = default_assets.pipeline("arkit52")
    rng = np.random.default_rng(18)
    for _ in range(3):
        y = _flame_values(rng)
        state, _ = pipeline.deform_values(y)
        p, q, s = deform_rig(rig, y)
        idx = rig.index.astype(np.int64)
        assert np.abs(p - state.position[idx]).max() < 5e-6
        assert rotation_error(q, state.rotation[idx]) < 5e-3
        assert (np.abs(s - state.scale[idx]) / state.scale[idx]).max() < 5e-3


def test_reduced_rig_uses_session_numbering(default_assets):
    from ofera.streaming.wire import reduced_size

    size = reduced_size(20_000, default_assets.count)
    rig = _rig(default_assets, size)
    rows, ids = default_assets.selection(True, size)
    assert rig.count == size and rig.gaussians == ids.size
    np.testing.assert_array_equal(rig.index, ids)
    y = _flame_values(np.random.default_rng(1))
    state, _ = default_assets.pipeline("arkit52").deform_values(y)
    p, _, _ = deform_rig(rig, y)
    assert np.abs(p - state.position[rows]).max() < 1e-5


@pytest.mark.skipif(not CAPTURE.is_file(), reason=f"{CAPTURE} is absent (real capture: ../shared/data)")
def test_real_capture_offline(default_assets):
    """Every frame of the real Live Link capture: the server's pipeline (BDA, EPM, fast deformation) vs the client
    deforming the same frame's values from the rig."""
    from ofera.client.params import RigDeformer
    from ofera.sources import read_gesichter

    log = read_gesichter(CAPTURE)
    rig = _rig(default_assets)
    client = RigDeformer(rig)
    idx = rig.index.astype(np.int64)
    pipeline = default_assets.pipeline("livelink61")
    worst = 0.0
    for w in log.weights:
        state, _ = pipeline.run(w)
        cp, _, _ = client.deform(pipeline.values)
        worst = max(worst, float(np.abs(cp - state.position[idx]).max()))
    assert len(log.weights) == 180 and worst < 1e-5, worst


# ----------------------------------------------------------------------------- the state machines


def _handshake(tiny_rig_body: bytes, chunk_bytes: int = 300):
    """Both ends of a params session, in memory: (client connection, server connection, rig messages)."""
    from ofera_protocol import Avatar, AvatarInfo, ClientConnection, ServerConnection, encode

    client, server = ClientConnection(), ServerConnection()
    server.receive(client.hello("arkit52", encoding="params", sparse=True))
    client.receive(server.accept("s-1", AvatarInfo("default", 6, 0), rig_bytes=len(tiny_rig_body)))
    n = 6
    avatar = Avatar(np.ones(n, np.float32), np.zeros((n, 1, 3), np.float32), np.zeros((n, 3), np.float32),
                    np.tile(np.float32([0, 0, 0, 1]), (n, 1)), np.full((n, 3), 0.01, np.float32))
    for data in server.avatar(avatar):
        client.receive(data)
    return client, server, [encode(c) for c in split_rig(tiny_rig_body, chunk_bytes)]


def test_client_connection_receives_the_rig_then_params_frames():
    from ofera_protocol import ClientState, encode

    body = encode_rig(tiny_rig())
    client, _, rig_messages = _handshake(body)
    assert client.welcome.encoding == "params" and client.welcome.sparse is False and client.welcome.rig_bytes
    assert client.state is ClientState.RECEIVING_RIG and len(rig_messages) > 1
    for data in rig_messages:
        client.receive(data)
    assert client.state is ClientState.STREAMING and client.rig == tiny_rig()
    msg = client.receive(encode(ParamsFrame(params=tiny_params()[1][1])))
    assert isinstance(msg, ParamsFrame) and msg.seq is None
    with pytest.raises(ProtocolError) as e:  # a bad frame while streaming costs that frame only
        client.receive(encode(ParamsFrame(params=np.full(68, np.inf, np.float32))))
    assert e.value.code == "non_finite" and not e.value.fatal


def test_client_connection_refuses_frames_before_the_rig():
    from ofera_protocol import ClientState, encode

    client, _, rig_messages = _handshake(encode_rig(tiny_rig()))
    client.receive(rig_messages[0])
    with pytest.raises(ProtocolError) as e:
        client.receive(encode(ParamsFrame(params=tiny_params()[0][1])))
    assert e.value.code == "not_ready" and e.value.fatal and client.state is ClientState.CLOSED


def test_client_connection_refuses_a_rig_of_another_size():
    from ofera_protocol import encode

    body = encode_rig(tiny_rig())
    client, _, _ = _handshake(body)
    (other,) = split_rig(body + b"\x00")
    with pytest.raises(ProtocolError, match="welcome announced") as e:
        client.receive(encode(other))
    assert e.value.fatal


def barycentric_rig_and_frames(n: int = 1500, frames: int = 3):
    """A FATE-style (barycentric) avatar on the default head: its rig body, FLAME values, and the server's frames."""
    from ofera.head import default_head
    from ofera.mapping.runtime import Mapper
    from ofera.streaming.params import rig_body
    from ofera.streaming.pipeline import AvatarAssets
    from test_fast_deform import random_avatar

    rng = np.random.default_rng(13)
    assets = AvatarAssets.create("bary", random_avatar(default_head(), "barycentric", rng, n=n), Mapper.default())
    pipeline = assets.pipeline("arkit52")
    ys = [_flame_values(rng) for _ in range(frames)]
    return rig_body(assets, None), ys, [pipeline.deform_values(y)[0] for y in ys]


def test_barycentric_rig_matches_the_server_frames():
    body, ys, states = barycentric_rig_and_frames()
    rig = decode_rig(body)
    assert rig.binding == "barycentric" and rig.local_position is None and rig.gaussians > 0
    idx = rig.index.astype(np.int64)
    for y, state in zip(ys, states):
        p, q, s = deform_rig(rig, y)
        assert np.abs(p - state.position[idx]).max() < 5e-6
        assert rotation_error(q, state.rotation[idx]) < 5e-3
        assert (np.abs(s - state.scale[idx]) / state.scale[idx]).max() < 5e-3
        p32, q32, s32 = port_f32(dataclasses.replace(rig, index=rig.index[:50], gaussian_face=rig.gaussian_face[:50],
                                                     bary=rig.bary[:50], normal_offset=rig.normal_offset[:50],
                                                     local_rotation=rig.local_rotation[:50],
                                                     local_scale=rig.local_scale[:50]), y)
        assert np.abs(p32 - p[:50]).max() < 1e-6 and rotation_error(q32, q[:50]) < 1e-5
