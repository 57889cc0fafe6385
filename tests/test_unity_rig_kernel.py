"""The Unity client's params-mode deformation kernel (OferaRigDeform.compute), compiled and run for real.

Each kernel is compiled with glslang's HLSL front end (`glslangValidator -D -V -S comp -e KERNEL`) and run on a CPU
Vulkan device (lavapipe) through `wgpu`, as tests/test_unity_kernels.py does for the upload kernels (its helpers are
reused). The rig words are the rig body's bins as they arrived (RigGpuWords in the C# core). The kernels' output in
the renderer's splat buffers (position Float32; 10.10.10.2 rotation + Float32 scale) is compared with the golden
frames of PROTOCOL.md 13.7 and, for rigs of small random avatars of both binding types (the server's build_rig),
with the Python reference ofera_protocol.rig.deform_rig on random params, step by step (its vertices, then the
Gaussians on the kernel's own vertices). With mono, the C# core's rig words and its deformation (RigDeformer) are
compared with the same bytes and the same reference. Skipped only without glslangValidator or a Vulkan adapter (CI
installs both and fails instead).
"""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from test_unity_kernels import (
    NAN_BITS,
    SHADERS,
    UNMATCHED,
    _compile,
    _entry,
    build_csharp_tool,
    check_compiles_for_unity,
    device,
    hidden,
    ugs_pack_rotation,
)

RIG = SHADERS / "OferaRigDeform.compute"
KERNELS = ("CSOferaRigPose", "CSOferaRigVertices", "CSOferaRigFaces", "CSOferaRigGaussians")
TEST_DEFINES = ("-DOFERA_STRUCTURED_BUFFERS", "-DOFERA_VK_BINDINGS", "-DOFERA_RIG_DEBUG_ROTATION")
GROUP = 256
UNIFORM = ("vertices", "expr", "pose", "faces", "gaussians", "barycentric", "index", "joints", "joints_expr",
           "template", "expr_basis", "pose_rows", "pose_basis", "weights", "face", "gaussian_face", "local",
           "normal_offset", "local_rotation", "local_scale", "server_count", "splat_count", "mirror_x")
# float32 kernels against the float64 reference, one step at a time. The vertices (steps 1-5) against rig_vertices:
# measured within 6e-8 m on these random rigs at |psi| 2.5. The Gaussians (steps 6-8) against rig_gaussians of the
# kernel's own vertices: measured positions 3e-8 m, quaternion components 9e-7, scales 2.3e-7 relative. Not the two
# at once: a sliver face's frame turns by the vertices' rounding over the face's height (a 6e-8 m vertex error
# moved a Gaussian 7 mm off a 32:1 face by 2.3e-6 m), so no fixed tolerance bounds the whole chain on random faces.
# The renderer keeps 10 bits of each quaternion component (1.4e-3).
VERTEX_ATOL = 2e-7
POS_ATOL = 1e-7
ROT_ATOL = 5e-6
SCALE_RTOL = 2e-6

__all__ = ["device"]  # the wgpu device fixture, shared with test_unity_kernels


@pytest.fixture(scope="module")
def spirv(tmp_path_factory):
    out = tmp_path_factory.mktemp("rigspv")
    return {k: _compile(RIG, k, out, TEST_DEFINES) for k in KERNELS}


# ----------------------------------------------------------------------------- the GPU rig layout

SECTIONS = ("index", "joints", "joints_expr", "template", "expr_basis", "pose_rows", "pose_basis", "weights", "face",
            "gaussian_face", "local", "normal_offset", "local_rotation", "local_scale")


def gpu_words(body: bytes) -> tuple[np.ndarray, dict[str, int]]:
    """The `_OferaRig` words of a rig body (RigGpuWords in the C# core): its bins in wire order, each copied from a
    4-byte boundary (the triangle binding has no normal_offset: an empty section); and the uniform's counts and word
    offsets."""
    m = msgpack.unpackb(body, raw=False)
    m["local"] = m.get("local_position", m.get("bary"))
    words, layout, at = [], {}, 0
    for name in SECTIONS:
        data = m.get(name, b"")
        data += b"\0" * (-len(data) % 4)
        layout[name] = at
        words.append(np.frombuffer(data, "<u4"))
        at += len(data) // 4
    layout |= {"vertices": m["vertices"], "expr": m["expr_dims"], "pose": len(m["pose_rows"]), "faces": m["faces"],
               "gaussians": m["gaussians"], "barycentric": int(m["binding"] == "barycentric")}
    return np.concatenate(words), layout


# ----------------------------------------------------------------------------- running the passes


def _layout(device):
    """0: the uniform; 1-3: rig words, params, server->GPU (read-only); 4: scratch; 5-6: splats; 7: debug rotation."""
    import wgpu

    c = wgpu.ShaderStage.COMPUTE
    ro, rw = wgpu.BufferBindingType.read_only_storage, wgpu.BufferBindingType.storage
    entries = [{"binding": 0, "visibility": c, "buffer": {"type": wgpu.BufferBindingType.uniform}}]
    entries += [{"binding": b, "visibility": c, "buffer": {"type": ro}} for b in (1, 2, 3)]
    entries += [{"binding": b, "visibility": c, "buffer": {"type": rw}} for b in (4, 5, 6, 7)]
    return device.create_bind_group_layout(entries=entries)


class Splats:
    """The renderer's raw buffers (uint32 words), hidden (NaN positions) to start with."""

    def __init__(self, m: int) -> None:
        self.m = m
        self.pos, self.other = hidden(m)


def run_rig(device, spirv, words: np.ndarray, layout: dict[str, int], params: np.ndarray, perm: np.ndarray,
            splats: Splats, mirror: bool) -> tuple[np.ndarray, np.ndarray]:
    """One frame: the four passes in order; updates `splats`, returns the debug rotations (M, 4) float32 and the
    kernel's deformed vertices (S, 3) float32 (its scratch)."""
    import wgpu

    values = {**layout, "server_count": perm.size, "splat_count": splats.m, "mirror_x": int(mirror)}
    uniform = np.array([values[k] for k in UNIFORM], np.uint32)
    uniform = np.concatenate([uniform, np.zeros(-uniform.size % 4, np.uint32)])
    s, u, m = layout["vertices"], layout["faces"], layout["gaussians"]
    vertex_word = layout["pose"] + 12 * 5  # scratch: pose coefficients P | A 5 x 3 x 4 | vertices 3S | faces 17U
    scratch = np.zeros(vertex_word + 3 * s + 17 * u, np.float32)

    def storage(a: np.ndarray, write: bool = False):
        data = np.ascontiguousarray(a).view(np.uint32)
        data = data if data.size else np.zeros(1, np.uint32)
        usage = wgpu.BufferUsage.STORAGE | (wgpu.BufferUsage.COPY_SRC if write else 0)
        return device.create_buffer_with_data(data=data.tobytes(), usage=usage)

    bufs = [device.create_buffer_with_data(data=uniform.tobytes(), usage=wgpu.BufferUsage.UNIFORM),
            storage(words), storage(np.asarray(params, np.float32)), storage(perm.astype(np.uint32)),
            storage(scratch, True), storage(splats.pos, True), storage(splats.other, True),
            storage(np.zeros(4 * max(m, 1), np.float32), True)]
    bgl = _layout(device)
    group = device.create_bind_group(layout=bgl, entries=[
        {"binding": b, "resource": {"buffer": buf, "offset": 0, "size": buf.size}} for b, buf in enumerate(bufs)])
    pl = device.create_pipeline_layout(bind_group_layouts=[bgl])
    enc = device.create_command_encoder()
    for kernel, threads in zip(KERNELS, (1, s, u, m), strict=True):
        spv = spirv[kernel]
        pipe = device.create_compute_pipeline(layout=pl, compute={"module": device.create_shader_module(code=spv),
                                                                  "entry_point": _entry(spv)})
        cp = enc.begin_compute_pass()  # one pass per kernel: each reads what the previous one wrote
        cp.set_pipeline(pipe)
        cp.set_bind_group(0, group)
        cp.dispatch_workgroups(max(1, -(-threads // GROUP)) if kernel != "CSOferaRigPose" else 1, 1, 1)
        cp.end()
    device.queue.submit([enc.finish()])
    splats.pos = np.frombuffer(device.queue.read_buffer(bufs[5]), np.uint32)[: 3 * splats.m].copy()
    splats.other = np.frombuffer(device.queue.read_buffer(bufs[6]), np.uint32)[: 4 * splats.m].copy()
    vertices = np.frombuffer(device.queue.read_buffer(bufs[4]), np.float32)[vertex_word:][: 3 * s]
    debug = np.frombuffer(device.queue.read_buffer(bufs[7]), np.float32)[: 4 * m].reshape(m, 4)
    return debug.copy(), vertices.reshape(s, 3).copy()


# ----------------------------------------------------------------------------- tests


def random_params(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    """68 float32 params: expression values ~N(0, scale), jaw and eyes up to ~0.4 rad from identity (6D)."""
    from ofera.mapping.flame_values import neutral_flame_values

    y = neutral_flame_values(1)[0]
    y[:50] = rng.normal(0, scale, 50)
    y[50:] += rng.normal(0, 0.15 * scale, 18).astype(np.float32)
    return y.astype(np.float32)


@pytest.mark.parametrize("kernel", KERNELS)
def test_rig_kernel_compiles_for_unity(kernel, tmp_path):
    """As Unity binds it (byte-address splat buffers), valid SPIR-V; and the test variant."""
    check_compiles_for_unity(RIG, kernel, tmp_path)


VECTORS = SHADERS.parents[3] / "protocol" / "vectors"


def _check(splats: Splats, debug_rot: np.ndarray, ref, index: np.ndarray, perm: np.ndarray, mirror: bool,
           pos_atol: float = POS_ATOL, rot_atol: float = ROT_ATOL, scale_rtol: float = SCALE_RTOL) -> None:
    """The splat buffers at perm[index] hold the reference (position, rotation (x, y, z, w), scale) of rig order,
    mirrored if asked; the packed rotation words are the debug rotations packed; every other splat is still hidden."""
    dst = perm[index]
    keep = dst != UNMATCHED
    dst = dst[keep].astype(np.int64)
    pos, rot, scale = (np.array(a, np.float32)[keep] for a in ref)
    if mirror:
        pos[:, 0] = -pos[:, 0]
        rot[:, 1:3] = -rot[:, 1:3]
    np.testing.assert_allclose(splats.pos.reshape(-1, 3)[dst].view(np.float32), pos, rtol=0, atol=pos_atol)
    got_rot = debug_rot[keep]
    np.testing.assert_allclose(got_rot, rot, rtol=0, atol=rot_atol)
    other = splats.other.reshape(-1, 4)[dst]
    assert np.array_equal(other[:, 0], ugs_pack_rotation(got_rot)), "rotation words are not the packed rotations"
    np.testing.assert_allclose(other[:, 1:].copy().view(np.float32), scale, rtol=scale_rtol, atol=0)
    untouched = np.ones(splats.m, bool)
    untouched[dst] = False
    assert (splats.pos.reshape(-1, 3)[untouched] == NAN_BITS).all(), "a splat of no rig Gaussian was written"


def _check_steps(splats: Splats, debug: np.ndarray, vertices: np.ndarray, rig, params: np.ndarray, perm: np.ndarray,
                 mirror: bool) -> None:
    """The kernel's vertices are rig_vertices'; its splats hold rig_gaussians of those vertices (see _check)."""
    from ofera_protocol.rig import rig_gaussians, rig_vertices

    np.testing.assert_allclose(vertices, rig_vertices(rig, params), rtol=0, atol=VERTEX_ATOL)
    _check(splats, debug, rig_gaussians(rig, vertices), np.asarray(rig.index, np.int64), perm, mirror)


def test_rig_kernels_reproduce_the_golden_frames(device, spirv):
    """rig_tiny_frames.json (PROTOCOL.md 13.7) within its tolerances: the kernels on the golden rig and params."""
    import json

    from ofera_protocol import codec

    chunk = codec.decode_server_message((VECTORS / "rig_tiny.msgpack").read_bytes())
    words, layout = gpu_words(chunk.data)
    v = json.loads((VECTORS / "rig_tiny_frames.json").read_text())
    tol = v["tolerance"]
    index = np.asarray(v["index"], np.int64)
    perm = np.arange(v["count"], dtype=np.uint32)[::-1].copy()  # a permutation that is not the identity
    for frame in v["frames"]:
        splats = Splats(v["count"])
        debug, _ = run_rig(device, spirv, words, layout, np.asarray(frame["params"], np.float32), perm, splats, False)
        ref = (frame["position"], frame["rotation"], frame["scale"])
        _check(splats, debug, ref, index, perm, False, tol["position_m"], tol["rotation"], tol["scale_relative"])


def _avatar(head, kind: str, seed: int):
    from test_fast_deform import random_avatar

    return random_avatar(head, kind, np.random.default_rng(seed), n=3000, sorted_faces=True)


@pytest.mark.parametrize("kind,mirror", [("triangle", False), ("triangle", True), ("barycentric", False),
                                         ("barycentric", True)])
def test_rig_kernels_match_deform_rig(device, spirv, head, kind, mirror):
    """Random avatars' rigs (the server's build_rig, through the wire encoding) and random params: the kernel's
    vertices are ofera_protocol.rig.rig_vertices', and the splat buffers hold rig_gaussians of those vertices (mirrored
    in `unity` sessions), through a permutation with unmatched Gaussians; no other splat is written."""
    from ofera.avatar.fast import gaussian_selection
    from ofera.avatar.rig import build_rig
    from ofera.head.lbs import HeadSubject
    from ofera_protocol.rig import decode_rig, encode_rig

    avatar = _avatar(head, kind, seed=3 + int(mirror))
    rows = np.flatnonzero(gaussian_selection(avatar, "movable"))
    body = encode_rig(build_rig(avatar, HeadSubject.create(head), rows, rows, avatar.count))
    rig = decode_rig(body)
    words, layout = gpu_words(body)
    rng = np.random.default_rng(11)
    n_splats = avatar.count + 50
    perm = rng.permutation(n_splats)[: avatar.count].astype(np.uint32)
    perm[rng.choice(avatar.count, 30, replace=False)] = UNMATCHED  # server Gaussians without a splat
    for scale in (0.0, 1.0, 2.0):
        y = random_params(rng, scale)
        splats = Splats(n_splats)
        debug, vertices = run_rig(device, spirv, words, layout, y, perm, splats, mirror)
        _check_steps(splats, debug, vertices, rig, y, perm, mirror)


# ----------------------------------------------------------------------------- the C# core, same bytes

TOOL = SHADERS.parents[2] / "Tests" / "RigGpuReference.cs"


@pytest.fixture(scope="module")
def csharp_rig_tool(tmp_path_factory):
    return build_csharp_tool(TOOL, tmp_path_factory.mktemp("cs"))


@pytest.mark.parametrize("kind", ["triangle", "barycentric"])
def test_csharp_rig_words_and_deformation_match(device, spirv, csharp_rig_tool, head, tmp_path, kind):
    """The C# core's GPU words equal the Python layout's; its RigDeformer matches deform_rig (PROTOCOL.md 13.7's
    tolerances); the kernels, run on the same rig and params, pass the step-by-step checks above."""
    import subprocess

    from ofera.avatar.fast import gaussian_selection
    from ofera.avatar.rig import build_rig
    from ofera.head.lbs import HeadSubject
    from ofera_protocol.rig import decode_rig, deform_rig, encode_rig

    avatar = _avatar(head, kind, seed=7)
    rows = np.flatnonzero(gaussian_selection(avatar, "movable"))
    body = encode_rig(build_rig(avatar, HeadSubject.create(head), rows, rows, avatar.count))
    rig = decode_rig(body)
    rng = np.random.default_rng(5)
    params = np.stack([random_params(rng, s) for s in (0.0, 1.0, 2.5)])
    (tmp_path / "rig.bin").write_bytes(body)
    params.astype("<f4").tofile(tmp_path / "params.bin")
    proc = subprocess.run(["mono", str(csharp_rig_tool), str(tmp_path), str(len(params))], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    words, layout = gpu_words(body)
    assert np.array_equal(np.fromfile(tmp_path / "words.bin", "<u4"), words), "C# rig words differ from the layout"
    assert list(np.fromfile(tmp_path / "words.hdr", "<i4")) == [layout[k] for k in SECTIONS]
    perm = np.arange(avatar.count, dtype=np.uint32)
    for k, y in enumerate(params):
        ours = tuple(np.fromfile(tmp_path / f"{a}{k}.bin", "<f4").reshape(-1, w)
                     for a, w in (("position", 3), ("rotation", 4), ("scale", 3)))
        pos, rot, scale = deform_rig(rig, y)
        np.testing.assert_allclose(ours[0], pos, rtol=0, atol=1e-6)
        np.testing.assert_allclose(ours[1], rot, rtol=0, atol=1e-5)
        np.testing.assert_allclose(ours[2], scale, rtol=1e-5, atol=0)
        splats = Splats(avatar.count)
        debug, vertices = run_rig(device, spirv, words, layout, y, perm, splats, False)
        _check_steps(splats, debug, vertices, rig, y, perm, False)
