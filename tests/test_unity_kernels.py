"""The Unity client's HLSL compute kernels, compiled and run for real.

Each kernel in unity_client_stub/Runtime/Unity/Shaders/*.compute is compiled with glslang's HLSL front end
(`glslangValidator -D -V -S comp -e KERNEL`) and run on a CPU Vulkan device (Mesa's lavapipe) through the
`wgpu` package. Frames are made and decoded by the Python reference codec (protocol/ofera_protocol); the
splat buffers the kernels write must equal, byte for byte, what the reference decoders give, scattered
through the server->GPU permutation and packed the way UnityGaussianSplatting stores them (position
Float32, "other" = 10.10.10.2 rotation + 3 float32 scales). With mono installed, the C# core's own
payload, q13 tables and CPU scatter (FramePayload, UgsPacking.WriteFrame) are checked against the same
bytes. Skipped only when glslangValidator or a Vulkan adapter is missing (CI installs glslang-tools and
mesa-vulkan-drivers); the mono part follows tests/test_unity_stub.py (skipped without mono unless CI).
"""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
from pathlib import Path

import msgpack
import numpy as np
import pytest
from ofera_protocol import codec
from ofera_protocol.encodings import FrameFormat, decode_arrays, dequantize_log_scale, dequantize_positions, make_quant
from ofera_protocol.messages import Frame

ROOT = Path(__file__).resolve().parents[1]
SHADERS = ROOT / "unity_client_stub" / "Runtime" / "Unity" / "Shaders"
UPLOAD = SHADERS / "OferaSplatUpload.compute"
KERNELS = ("CSOferaHide", "CSOferaDecodeF32", "CSOferaDecodeF16", "CSOferaDecodeQ13")
TEST_DEFINES = ("-DOFERA_STRUCTURED_BUFFERS", "-DOFERA_VK_BINDINGS")
GROUP = 256
FIELD_BYTES = {"f32": (12, 16, 12), "f16": (6, 8, 6), "q13": (6, 4, 3)}
NAN_BITS = 0x7FC00000
UNMATCHED = 0xFFFFFFFF


# ----------------------------------------------------------------------------- tools


def _missing(reason: str) -> None:
    """Skip without the tools, but fail in CI (which installs them: .ci/run): the kernels must run there."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason} (CI is set: .ci/run installs it)")
    pytest.skip(reason)


def _glslang() -> str:
    tool = shutil.which("glslangValidator")
    if tool is None:
        _missing("glslangValidator not found: install glslang-tools (Debian/Ubuntu: apt-get install -y glslang-tools)")
    return tool


def _compile(path: Path, kernel: str, out_dir: Path, defines: tuple[str, ...] = TEST_DEFINES) -> bytes:
    out = out_dir / f"{path.stem}.{kernel}{'.test' if defines else ''}.spv"
    cmd = [_glslang(), "-D", "-V", "-S", "comp", "-e", kernel, *defines, str(path), "-o", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"{' '.join(cmd)} failed:\n{proc.stdout}{proc.stderr}"
    return out.read_bytes()


@pytest.fixture(scope="module")
def device():
    try:
        import wgpu
    except ImportError:  # pragma: no cover - a dev extra
        pytest.fail("the wgpu package is missing: pip install -e '.[dev]'")
    os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp")
    try:
        adapters = wgpu.gpu.enumerate_adapters_sync()
    except Exception as e:  # noqa: BLE001 - any failure means "no adapter"
        _missing(f"no Vulkan adapter ({type(e).__name__}: {e}): install mesa-vulkan-drivers (lavapipe)")
    vulkan = [a for a in adapters if a.info.get("backend_type") == "Vulkan"]
    if not vulkan:
        found = ", ".join(f"{a.info.get('backend_type')} {a.info.get('device')}" for a in adapters) or "none"
        _missing(f"no Vulkan adapter (found: {found}): install mesa-vulkan-drivers (lavapipe)")
    # prefer the CPU device (lavapipe) so results do not depend on whichever GPU a machine has
    adapter = next((a for a in vulkan if a.info.get("adapter_type") == "CPU"), vulkan[0])
    return adapter.request_device_sync()


@pytest.fixture(scope="module")
def spirv(tmp_path_factory):
    out = tmp_path_factory.mktemp("spv")
    return {k: _compile(UPLOAD, k, out) for k in KERNELS}


class Splats:
    """GPU-side state of one renderer: its raw position and "other" buffers, as uint32 words."""

    def __init__(self, m: int) -> None:
        self.m = m
        self.pos = np.full(3 * m, 0x12345678, dtype=np.uint32)  # asset data before the hide pass
        self.other = np.full(4 * m, 0x9ABCDEF0, dtype=np.uint32)


def _run(device, spv: bytes, splats: Splats, threads: int, params: dict[str, int], payload: np.ndarray,
         perm: np.ndarray, pos_table: np.ndarray, scale_table: np.ndarray) -> None:
    import wgpu

    names = ("n", "has_index", "index_word", "pos_word", "rot_word", "scale_word", "server_count", "splat_count",
             "mirror_x")
    uniform = np.array([params.get(k, 0) for k in names] + [0, 0, 0], dtype=np.uint32)  # padded to 48 B

    def storage(a: np.ndarray, write: bool = False):
        a = np.ascontiguousarray(a, dtype=np.uint32)
        if a.size == 0:
            a = np.zeros(1, dtype=np.uint32)
        usage = wgpu.BufferUsage.STORAGE | (wgpu.BufferUsage.COPY_SRC if write else 0)
        return device.create_buffer_with_data(data=a.tobytes(), usage=usage)

    ubuf = device.create_buffer_with_data(data=uniform.tobytes(), usage=wgpu.BufferUsage.UNIFORM)
    bufs = [storage(payload), storage(perm), storage(pos_table), storage(scale_table),
            storage(splats.pos, True), storage(splats.other, True)]
    shader = device.create_shader_module(code=spv)
    layout = _layout(device)
    pipeline = device.create_compute_pipeline(layout=device.create_pipeline_layout(bind_group_layouts=[layout]),
                                              compute={"module": shader, "entry_point": _entry(spv)})
    entries = [{"binding": b, "resource": {"buffer": buf, "offset": 0, "size": buf.size}}
               for b, buf in enumerate([ubuf, *bufs])]
    group = device.create_bind_group(layout=layout, entries=entries)
    enc = device.create_command_encoder()
    cp = enc.begin_compute_pass()
    cp.set_pipeline(pipeline)
    cp.set_bind_group(0, group)
    cp.dispatch_workgroups(max(1, (threads + GROUP - 1) // GROUP), 1, 1)
    cp.end()
    device.queue.submit([enc.finish()])
    splats.pos = np.frombuffer(device.queue.read_buffer(bufs[4]), dtype=np.uint32)[: 3 * splats.m].copy()
    splats.other = np.frombuffer(device.queue.read_buffer(bufs[5]), dtype=np.uint32)[: 4 * splats.m].copy()


def _entry(spv: bytes) -> str:
    """Name of the (single) OpEntryPoint in a SPIR-V module."""
    words = np.frombuffer(spv, dtype="<u4")
    i = 5
    while i < len(words):
        op, count = int(words[i]) & 0xFFFF, int(words[i]) >> 16
        if op == 15:  # OpEntryPoint: model, id, name...
            raw = words[i + 3: i + count].tobytes()
            return raw.split(b"\0", 1)[0].decode()
        i += count
    raise AssertionError("no entry point in SPIR-V")


def _layout(device):
    """Binding 0: the parameters (uniform); 1-4: read-only inputs; 5-6: the splat buffers (read-write)."""
    import wgpu

    c = wgpu.ShaderStage.COMPUTE
    entries = [{"binding": 0, "visibility": c, "buffer": {"type": wgpu.BufferBindingType.uniform}}]
    entries += [{"binding": b, "visibility": c, "buffer": {"type": wgpu.BufferBindingType.read_only_storage}}
                for b in (1, 2, 3, 4)]
    entries += [{"binding": b, "visibility": c, "buffer": {"type": wgpu.BufferBindingType.storage}} for b in (5, 6)]
    return device.create_bind_group_layout(entries=entries)


# ----------------------------------------------------------------------------- reference (numpy)


def ugs_pack_rotation(q: np.ndarray) -> np.ndarray:
    """(N, 4) float32 (x, y, z, w) -> UnityGaussianSplatting's 10.10.10.2 words, in the float32 operation
    order of UgsPacking.PackRotation (C#) and PackUgsRotation (HLSL)."""
    q = np.array(q, dtype=np.float32, copy=True)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    n2 = ((x * x + y * y) + z * z) + w * w
    length = np.sqrt(n2)
    ok = (length > 0) & (length <= np.float32(3.402823466e38))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.float32(1.0) / length
    q = np.where(ok[:, None], q * inv[:, None], np.array([0, 0, 0, 1], dtype=np.float32))
    a = np.abs(q)
    index = np.zeros(len(q), dtype=np.uint32)
    best = a[:, 0].copy()
    for c in (1, 2, 3):
        bigger = a[:, c] > best
        index[bigger] = c
        best[bigger] = a[bigger, c]
    keep = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[index]
    three = np.take_along_axis(q, keep, axis=1)
    d = q[np.arange(len(q)), index]
    s = np.where(d >= 0, np.float32(1), np.float32(-1)).astype(np.float32)
    v = ((three * s[:, None]) * np.float32(1.41421356)) * np.float32(0.5) + np.float32(0.5)
    u = (np.clip(v, 0, 1) * np.float32(1023.5)).astype(np.uint32)
    return u[:, 0] | (u[:, 1] << 10) | (u[:, 2] << 20) | (index << 30)


def hidden(m: int) -> tuple[np.ndarray, np.ndarray]:
    pos = np.full(3 * m, NAN_BITS, dtype=np.uint32)
    other = np.zeros(4 * m, dtype=np.uint32)
    other[0::4] = ugs_pack_rotation(np.array([[0, 0, 0, 1]], dtype=np.float32))[0]
    return pos, other


def scatter(pos: np.ndarray, other: np.ndarray, frame: Frame, perm: np.ndarray, mirror: bool) -> None:
    """What the kernel must do, from the Python codec's decoded frame."""
    n = frame.n
    g = np.arange(n) if frame.index is None else frame.index.astype(np.int64)
    dst = perm[g]
    keep = dst != UNMATCHED
    dst = dst[keep].astype(np.int64)
    p = np.array(frame.position, dtype=np.float32)[keep]
    r = np.array(frame.rotation, dtype=np.float32)[keep]
    if mirror:
        p = p * np.array([-1, 1, 1], dtype=np.float32)
        r = r * np.array([1, -1, -1, 1], dtype=np.float32)
    s = np.array(frame.scale, dtype=np.float32)[keep]
    p3 = pos.reshape(-1, 3)
    o4 = other.reshape(-1, 4)
    p3[dst] = p.view(np.uint32)
    o4[dst, 0] = ugs_pack_rotation(r)
    o4[dst, 1:] = s.view(np.uint32)


def payload_of(message: bytes, encoding: str) -> tuple[np.ndarray, dict[str, int]]:
    """The wire payload as the client uploads it: index, position, rotation, scale bins, each section
    starting on a 4-byte boundary (the layout FramePayload documents)."""
    m = msgpack.unpackb(message, raw=False)
    n = m["n"]
    sections = ([m["index"]] if "index" in m else []) + [m["position"], m["rotation"], m["scale"]]
    words, offsets, at = [], [], 0
    for sec in sections:
        padded = sec + b"\0" * (-len(sec) % 4)
        offsets.append(at)
        words.append(np.frombuffer(padded, dtype="<u4"))
        at += len(padded) // 4
    has_index = "index" in m
    pw, rw, sw = offsets[-3:]
    params = {"n": n, "has_index": int(has_index), "index_word": 0, "pos_word": pw, "rot_word": rw,
              "scale_word": sw}
    assert [len(x) for x in sections[-3:]] == [n * b for b in FIELD_BYTES[encoding]]
    return np.concatenate(words) if words else np.zeros(0, np.uint32), params


def q13_tables(quant) -> tuple[np.ndarray, np.ndarray]:
    levels = np.arange(65536, dtype=np.uint16)
    pos = dequantize_positions(np.stack([levels] * 3, axis=1), quant)  # (65536, 3)
    pos_table = np.ascontiguousarray(pos.T).reshape(-1).view(np.uint32)  # x table, y table, z table
    scale_table = dequantize_log_scale(np.arange(256, dtype=np.uint8).reshape(-1, 1), quant).reshape(-1)
    return pos_table, scale_table.view(np.uint32)


# ----------------------------------------------------------------------------- data


def make_avatar(n: int, rng: np.random.Generator):
    position = (rng.normal(0, 0.06, (n, 3)) + [0, 0.02, 0.03]).astype(np.float32)
    rotation = rng.normal(0, 1, (n, 4)).astype(np.float32)
    rotation /= np.linalg.norm(rotation, axis=1, keepdims=True)
    # awkward cases: ties between components, negative dropped component, axis-aligned, identity
    special = np.array([[0, 0, 0, 1], [0, 0, 0, -1], [0.5, 0.5, 0.5, 0.5], [-0.5, 0.5, -0.5, 0.5],
                        [0.70710677, 0.70710677, 0, 0], [0, -0.70710677, 0, 0.70710677], [1, 0, 0, 0],
                        [0, 0, -1, 0]], dtype=np.float32)
    rotation[: len(special)] = special
    scale = np.exp(rng.uniform(np.log(2e-6), np.log(0.03), (n, 3))).astype(np.float32)  # f16 subnormals too
    return position, rotation, scale


def moved(position, rotation, scale, rng, k: float):
    p = position + rng.normal(0, 0.002 * k, position.shape).astype(np.float32)
    r = rotation + rng.normal(0, 0.05 * k, rotation.shape).astype(np.float32)
    r[:4] = rotation[:4]
    s = scale * np.exp(rng.normal(0, 0.1 * k, scale.shape)).astype(np.float32)
    return p.astype(np.float32), r.astype(np.float32), s.astype(np.float32)


N_SERVER, N_SPLATS = 1500, 1600  # 100 GPU splats no server Gaussian maps to


def make_perm(rng: np.random.Generator) -> np.ndarray:
    perm = rng.permutation(N_SPLATS)[:N_SERVER].astype(np.uint32)
    perm[rng.choice(N_SERVER, 40, replace=False)] = UNMATCHED  # server Gaussians without a splat
    return perm


CASES = [(enc, sparse, mirror) for enc in ("f32", "f16", "q13") for sparse in (False, True) for mirror in (False, True)]


def check_compiles_for_unity(path: Path, kernel: str, tmp_path: Path) -> None:
    """`kernel` of `path` compiles as Unity binds it (byte-address buffers: valid SPIR-V, checked by spirv-val when
    installed) and in the test variant (TEST_DEFINES), each with `kernel` as its entry point."""
    spv = _compile(path, kernel, tmp_path, defines=())
    assert _entry(spv) == kernel
    assert _entry(_compile(path, kernel, tmp_path)) == kernel
    val = shutil.which("spirv-val")
    if val:
        out = tmp_path / "k.spv"
        out.write_bytes(spv)
        proc = subprocess.run([val, "--target-env", "vulkan1.1", str(out)], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.parametrize("kernel", KERNELS)
def test_kernel_compiles_for_unity_and_tests(kernel, tmp_path):
    """Both variants compile: byte-address buffers (what Unity binds) and structured (what the tests run)."""
    check_compiles_for_unity(UPLOAD, kernel, tmp_path)


def test_hide_writes_nan_positions_and_zero_scales(device, spirv):
    splats = Splats(N_SPLATS)
    _run(device, spirv["CSOferaHide"], splats, N_SPLATS, {"splat_count": N_SPLATS}, np.zeros(1, np.uint32),
         np.zeros(1, np.uint32), np.zeros(1, np.uint32), np.zeros(1, np.uint32))
    pos, other = hidden(N_SPLATS)
    assert np.array_equal(splats.pos, pos)
    assert np.array_equal(splats.other, other)


def _session(encoding: str, sparse: bool, rng):
    position, rotation, scale = make_avatar(N_SERVER, rng)
    quant = make_quant(position, scale) if encoding == "q13" else None
    fmt = FrameFormat(encoding=encoding, count=N_SERVER, sparse=sparse, quant=quant)
    return fmt, (position, rotation, scale)


def _frames(fmt: FrameFormat, neutral, rng) -> list[bytes]:
    """A dense frame, then (sparse sessions) two sparse ones with different index sets."""
    out = []
    p, r, s = moved(*neutral, rng, 1.0)
    out.append(codec.encode_frame(Frame(seq=0, t=1, position=p, rotation=r, scale=s, timing={"total": 9}), fmt))
    if fmt.sparse:
        for seq, frac in ((1, 0.3), (2, 0.05)):
            idx = np.sort(rng.choice(N_SERVER, int(N_SERVER * frac), replace=False)).astype(np.uint32)
            p, r, s = moved(*neutral, rng, 2.0)
            out.append(codec.encode_frame(Frame(seq=seq, t=seq, position=p[idx], rotation=r[idx], scale=s[idx],
                                                index=idx, timing={}), fmt))
        out.append(codec.encode_frame(Frame(seq=3, t=3, position=p[:0], rotation=r[:0], scale=s[:0],
                                            index=np.zeros(0, np.uint32), timing={}), fmt))  # empty sparse
    return out


@pytest.mark.parametrize("encoding,sparse,mirror", CASES)
def test_decode_kernel_matches_python_reference(device, spirv, encoding, sparse, mirror):
    rng = np.random.default_rng(CASES.index((encoding, sparse, mirror)))  # deterministic per case
    fmt, neutral = _session(encoding, sparse, rng)
    perm = make_perm(rng)
    tables = q13_tables(fmt.quant) if encoding == "q13" else (np.zeros(1, np.uint32), np.zeros(1, np.uint32))
    splats = Splats(N_SPLATS)
    common = {"server_count": N_SERVER, "splat_count": N_SPLATS, "mirror_x": int(mirror)}
    _run(device, spirv["CSOferaHide"], splats, N_SPLATS, common, np.zeros(1, np.uint32), perm, *tables)
    exp_pos, exp_other = hidden(N_SPLATS)
    kernel = {"f32": "CSOferaDecodeF32", "f16": "CSOferaDecodeF16", "q13": "CSOferaDecodeQ13"}[encoding]
    frames = _frames(fmt, neutral, rng)
    for message in frames:
        frame = codec.decode_server_message(message, fmt)
        payload, params = payload_of(message, encoding)
        _run(device, spirv[kernel], splats, frame.n, {**common, **params}, payload, perm, *tables)
        scatter(exp_pos, exp_other, frame, perm, mirror)
        bad = np.flatnonzero(splats.pos != exp_pos)
        assert bad.size == 0, f"seq {frame.seq}: {bad.size} position words differ, first at word {bad[:5]}"
        bad = np.flatnonzero(splats.other != exp_other)
        assert bad.size == 0, (f"seq {frame.seq}: {bad.size} other words differ, first at {bad[:5]}: "
                               f"{splats.other[bad[:5]]} != {exp_other[bad[:5]]}")
    # unmatched GPU splats stay hidden; every matched one was written
    matched = np.zeros(N_SPLATS, dtype=bool)
    matched[perm[perm != UNMATCHED]] = True
    assert (splats.pos.reshape(-1, 3)[~matched] == NAN_BITS).all()
    assert (splats.pos.reshape(-1, 3)[matched] != NAN_BITS).all()


def test_q13_tables_match_the_codec():
    """The q13 tables the kernel reads give exactly the codec's decoded values (checked on every level)."""
    rng = np.random.default_rng(5)
    position, _, scale = make_avatar(100, rng)
    quant = make_quant(position, scale)
    pos_table, scale_table = q13_tables(quant)
    q = rng.integers(0, 65536, (5000, 3)).astype(np.uint16)
    ref = dequantize_positions(q, quant).view(np.uint32)
    looked = np.stack([pos_table[a * 65536 + q[:, a].astype(np.int64)] for a in range(3)], axis=1)
    assert np.array_equal(looked, ref)
    qs = np.arange(256, dtype=np.uint8).reshape(-1, 1).repeat(3, 1)
    p, r, s = decode_arrays("q13", 256, np.zeros((256, 3), "<u2").tobytes(), np.zeros(256, "<u4").tobytes(),
                            qs.tobytes(), quant)
    assert np.array_equal(s[:, 0].view(np.uint32), scale_table)


# ----------------------------------------------------------------------------- the C# core, same bytes

TOOL = ROOT / "unity_client_stub" / "Tests" / "GpuReference.cs"


def build_csharp_tool(tool: Path, out_dir: Path) -> Path:
    """`tool` (a .cs in unity_client_stub/Tests) compiled with the C# core (Runtime/Core) by mcs: `<stem>.exe` in
    `out_dir`. Skips without mcs and mono (fails in CI)."""
    missing = [t for t in ("mcs", "mono") if shutil.which(t) is None]
    if missing:
        reason = f"{' and '.join(missing)} not found (apt-get install -y mono-mcs mono-runtime)"
        if os.environ.get("CI"):
            pytest.fail(f"CI is set but {reason}")
        pytest.skip(reason)
    out = out_dir / f"{tool.stem}.exe"
    core = sorted((tool.parents[1] / "Runtime" / "Core").glob("*.cs"))
    cmd = ["mcs", "-langversion:7.2", "-nologo", "-warn:4", "-r:System.dll", f"-out:{out}", str(tool), *map(str, core)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out


@pytest.fixture(scope="module")
def csharp_tool(tmp_path_factory):
    return build_csharp_tool(TOOL, tmp_path_factory.mktemp("cs"))


def _run_tool(tool: Path, work: Path, welcome: bytes, frames: list[bytes], perm: np.ndarray, m: int, mirror: bool):
    """GpuReference.exe: decodes with the C# core and writes, per frame, the payload it would upload,
    its section offsets, the q13 tables and the CPU scatter (hide first) as raw little-endian files."""
    (work / "welcome.msgpack").write_bytes(welcome)
    for i, f in enumerate(frames):
        (work / f"frame{i}.msgpack").write_bytes(f)
    perm.astype("<u4").tofile(work / "perm.bin")
    cmd = ["mono", str(tool), str(work), str(len(frames)), str(m), "1" if mirror else "0"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


@pytest.mark.parametrize("encoding,sparse,mirror", [("f32", True, False), ("f16", True, True), ("q13", True, False),
                                                    ("q13", False, True)])
def test_csharp_core_payload_tables_and_cpu_scatter_match_the_kernel(device, spirv, csharp_tool, tmp_path,
                                                                     encoding, sparse, mirror):
    from ofera_protocol.messages import AvatarInfo, Welcome

    rng = np.random.default_rng(17)
    fmt, neutral = _session(encoding, sparse, rng)
    perm = make_perm(rng)
    welcome = codec.encode_welcome(Welcome(session="s", avatar=AvatarInfo(id="a", count=N_SERVER, sh_degree=0),
                                           layout="ovr63", encoding=encoding, coords="unity", sparse=sparse,
                                           quant=fmt.quant))
    frames = _frames(fmt, neutral, rng)
    _run_tool(csharp_tool, tmp_path, welcome, frames, perm, N_SPLATS, mirror)
    tables = (np.zeros(1, np.uint32), np.zeros(1, np.uint32))
    if encoding == "q13":
        tables = q13_tables(fmt.quant)
        assert np.array_equal(np.fromfile(tmp_path / "pos_table.bin", "<u4"), tables[0]), "C# q13 position table"
        assert np.array_equal(np.fromfile(tmp_path / "scale_table.bin", "<u4"), tables[1]), "C# q13 scale table"
    splats = Splats(N_SPLATS)
    common = {"server_count": N_SERVER, "splat_count": N_SPLATS, "mirror_x": int(mirror)}
    _run(device, spirv["CSOferaHide"], splats, N_SPLATS, common, np.zeros(1, np.uint32), perm, *tables)
    kernel = {"f32": "CSOferaDecodeF32", "f16": "CSOferaDecodeF16", "q13": "CSOferaDecodeQ13"}[encoding]
    for i, message in enumerate(frames):
        payload = np.fromfile(tmp_path / f"payload{i}.bin", "<u4")
        header = struct.unpack("<7i", (tmp_path / f"payload{i}.hdr").read_bytes())
        n, has_index, iw, pw, rw, sw, words = header
        py_payload, py_params = payload_of(message, encoding)
        assert words == len(payload) == len(py_payload)
        assert np.array_equal(payload, py_payload), f"frame {i}: C# payload differs from the wire bytes"
        assert (n, has_index, pw, rw, sw) == (py_params["n"], py_params["has_index"], py_params["pos_word"],
                                              py_params["rot_word"], py_params["scale_word"])
        params = {"n": n, "has_index": has_index, "index_word": iw, "pos_word": pw, "rot_word": rw, "scale_word": sw}
        _run(device, spirv[kernel], splats, n, {**common, **params}, payload, perm, *tables)
        cpu_pos = np.fromfile(tmp_path / f"cpu_pos{i}.bin", "<u4")
        cpu_other = np.fromfile(tmp_path / f"cpu_other{i}.bin", "<u4")
        assert np.array_equal(splats.pos, cpu_pos), f"frame {i}: GPU positions differ from UgsPacking.WriteFrame"
        bad = np.flatnonzero(splats.other != cpu_other)
        assert bad.size == 0, f"frame {i}: {bad.size} rotation/scale words differ from UgsPacking.WriteFrame"
