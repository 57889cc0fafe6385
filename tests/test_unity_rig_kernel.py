"""The Unity client's params-mode deformation kernel (OferaRigDeform.compute), compiled and run for real.

Each kernel is compiled with glslang's HLSL front end (`glslangValidator -D -V -S comp -e KERNEL`) and run on a
CPU Vulkan device (lavapipe) through `wgpu`, as tests/test_unity_kernels.py does for the upload kernels (its
helpers are reused). A rig is built for small random avatars of both binding types; the kernels' output in the
renderer's splat buffers (position Float32; 10.10.10.2 rotation + Float32 scale) is compared with the Python
reference deformation for random params. Skipped only without glslangValidator or a Vulkan adapter (CI installs
both and fails instead).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_unity_kernels import NAN_BITS, SHADERS, UNMATCHED, _compile, _entry, device, hidden, ugs_pack_rotation

RIG = SHADERS / "OferaRigDeform.compute"
KERNELS = ("CSOferaRigPose", "CSOferaRigVertices", "CSOferaRigFaces", "CSOferaRigGaussians")
TEST_DEFINES = ("-DOFERA_STRUCTURED_BUFFERS", "-DOFERA_VK_BINDINGS", "-DOFERA_RIG_DEBUG_ROTATION")
GROUP = 256
UNIFORM = ("vertices", "joints", "expr", "pose", "faces", "moving", "barycentric", "template", "basis", "weights",
           "joint", "joint_expr", "parents", "pose_rows", "face_vertices", "gauss_face", "ids", "local", "rotation",
           "scale", "shift", "canonical", "server_count", "splat_count", "mirror_x")
POS_ATOL = 2e-6  # metres: float32 skinning of a ~0.2 m head (the C# and server references run in float64)
ROT_ATOL = 1e-4  # quaternion components: float32 frames of mm-sized faces (the renderer keeps 10 bits, 1.4e-3)
SCALE_RTOL = 2e-5

__all__ = ["device"]  # the wgpu device fixture, shared with test_unity_kernels


@pytest.fixture(scope="module")
def spirv(tmp_path_factory):
    out = tmp_path_factory.mktemp("rigspv")
    return {k: _compile(RIG, k, out, TEST_DEFINES) for k in KERNELS}


# ----------------------------------------------------------------------------- the GPU rig layout


def gpu_words(rig: dict[str, np.ndarray]) -> tuple[np.ndarray, dict[str, int]]:
    """The `_OferaRig` words (see OferaRigDeform.compute) of a rig given as arrays, and the uniform's counts and
    word offsets. Float arrays become float32 bits, integer arrays uint32 (-1 -> 0xffffffff)."""
    order = ("template", "basis", "weights", "joint", "joint_expr", "parents", "pose_rows", "face_vertices",
             "gauss_face", "ids", "local", "rotation", "scale", "shift", "canonical")
    words, offsets, at = [], {}, 0
    for name in order:
        a = np.asarray(rig.get(name, np.zeros(0, np.float32)))
        w = a.astype(np.float32).view(np.uint32) if a.dtype.kind == "f" else a.astype(np.int64).astype(np.uint32)
        offsets[name] = at
        words.append(w.reshape(-1))
        at += w.size
    basis = np.asarray(rig["basis"])
    counts = {"vertices": rig["template"].size // 3, "joints": rig["parents"].size, "expr": basis.shape[0]
              - rig["pose_rows"].size, "pose": rig["pose_rows"].size, "faces": rig["face_vertices"].size // 3,
              "moving": rig["ids"].size, "barycentric": int("shift" in rig)}
    return np.concatenate(words), {**counts, **offsets}


def rig_from_fast(fast) -> dict[str, np.ndarray]:
    """The rig arrays of a server FastAvatar (its subset LBS and per-Gaussian columns)."""
    lbs, a = fast.lbs, fast.arrays
    m = a.ids.size
    gface = np.empty(m, np.int64)
    for face, m0, n in zip(a.run_face, a.run_m, a.run_len, strict=True):
        gface[m0:m0 + n] = face
    rig = {"template": lbs.v_id, "basis": lbs.basis_t, "weights": lbs.weights, "joint": lbs.j_id,
           "joint_expr": lbs.j_expr, "parents": lbs.parents, "pose_rows": lbs.pose_rows,
           "face_vertices": a.face_vids, "gauss_face": gface, "ids": a.ids, "rotation": a.lrot.T,
           "scale": a.lscale.T}
    if a.bary is not None:
        rig |= {"local": a.bary.T, "shift": a.shift, "canonical": a.inv_canonical}
    else:
        rig["local"] = a.lpos.T
    return rig


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
            splats: Splats, mirror: bool) -> np.ndarray:
    """One frame: the four passes in order; updates `splats`, returns the debug rotations (M, 4) float32."""
    import wgpu

    values = {**layout, "server_count": perm.size, "splat_count": splats.m, "mirror_x": int(mirror)}
    uniform = np.array([values[k] for k in UNIFORM], np.uint32)
    uniform = np.concatenate([uniform, np.zeros(-uniform.size % 4, np.uint32)])
    s, k, rows, u, m = (layout["vertices"], layout["joints"], layout["expr"] + layout["pose"], layout["faces"],
                        layout["moving"])
    scratch = np.zeros(rows + 12 * k + 3 * s + 20 * u, np.float32)

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
    return np.frombuffer(device.queue.read_buffer(bufs[7]), np.float32)[: 4 * m].reshape(m, 4).copy()


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
    import shutil
    import subprocess

    spv = _compile(RIG, kernel, tmp_path, defines=())
    assert _entry(spv) == kernel
    assert _entry(_compile(RIG, kernel, tmp_path)) == kernel
    val = shutil.which("spirv-val")
    if val:
        out = tmp_path / "k.spv"
        out.write_bytes(spv)
        proc = subprocess.run([val, "--target-env", "vulkan1.1", str(out)], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stdout + proc.stderr


def _avatar(head, kind: str, seed: int):
    from test_fast_deform import random_avatar

    return random_avatar(head, kind, np.random.default_rng(seed), n=3000, sorted_faces=True)


def _check(splats: Splats, debug_rot: np.ndarray, ref, ids: np.ndarray, perm: np.ndarray, mirror: bool) -> None:
    dst = perm[ids]
    keep = dst != UNMATCHED
    dst, rows = dst[keep].astype(np.int64), ids[keep]
    pos = np.array(ref.position[rows], np.float32)
    rot = np.array(ref.rotation[rows], np.float32)
    if mirror:
        pos[:, 0] = -pos[:, 0]
        rot[:, 1:3] = -rot[:, 1:3]
    got_pos = splats.pos.reshape(-1, 3)[dst].view(np.float32)
    np.testing.assert_allclose(got_pos, pos, rtol=0, atol=POS_ATOL)
    got_rot = debug_rot[keep]
    np.testing.assert_allclose(got_rot, rot, rtol=0, atol=ROT_ATOL)
    other = splats.other.reshape(-1, 4)[dst]
    assert np.array_equal(other[:, 0], ugs_pack_rotation(got_rot)), "rotation words are not the packed rotations"
    np.testing.assert_allclose(other[:, 1:].view(np.float32), ref.scale[rows], rtol=SCALE_RTOL, atol=0)


@pytest.mark.parametrize("kind,mirror", [("triangle", False), ("triangle", True), ("barycentric", False)])
def test_rig_kernels_match_the_server_deformation(device, spirv, head, kind, mirror):
    from ofera.avatar.fast import FastAvatar
    from ofera.mapping.flame_values import split_flame_values

    avatar = _avatar(head, kind, seed=3 + int(mirror))
    fast = FastAvatar(avatar)
    words, layout = gpu_words(rig_from_fast(fast))
    rng = np.random.default_rng(11)
    n_splats = avatar.count + 50
    perm = rng.permutation(n_splats)[: avatar.count].astype(np.uint32)
    perm[rng.choice(avatar.count, 30, replace=False)] = UNMATCHED  # server Gaussians without a splat
    splats = Splats(n_splats)
    session = fast.session()
    for scale in (0.0, 1.0, 2.0):
        y = random_params(rng, scale)
        debug = run_rig(device, spirv, words, layout, y, perm, splats, mirror)
        ref = session.run(*split_flame_values(y))
        _check(splats, debug, ref, fast.arrays.ids, perm, mirror)
    # splats of no moving Gaussian (and unmatched ones) were not touched: still hidden
    touched = np.zeros(n_splats, bool)
    dst = perm[fast.arrays.ids]
    touched[dst[dst != UNMATCHED]] = True
    assert (splats.pos.reshape(-1, 3)[~touched] == NAN_BITS).all()
