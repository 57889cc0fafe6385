"""Importing LAM avatar exports (`ofera.avatar.lam`): the real statue in ../shared/data (skipped when absent) and
small zips written here in the variants found in the wild; the vertex binding, its file format, the fast
morph/offset kernels against their numpy reference, and the CLI."""

from __future__ import annotations

import zipfile
from pathlib import Path

import lam_fixtures as L
import numpy as np
import pytest
from ofera.avatar import AvatarError, load_avatar, save_avatar
from ofera.avatar.fast_vertex import FastVertexAvatar, morph_blend_reference, reference_vertex_frame
from ofera.avatar.io import load_avatar_npz
from ofera.avatar.lam import import_lam, import_lam_cached, lam_cache_path, load_lam, read_bs_track
from ofera.avatar.ply import sigmoid
from ofera.avatar.sh import C0
from ofera.mapping.layouts import ARKIT51_NAMES, ARKIT52_NAMES

STATUE = Path(__file__).resolve().parents[2] / "shared" / "data" / "lam_statue.zip"
needs_statue = pytest.mark.skipif(not STATUE.is_file(), reason=f"{STATUE} is absent (real LAM data lives outside "
                                  "the repository: ../shared/data/lam_statue.zip)")
J = {n: i for i, n in enumerate(ARKIT51_NAMES)}


def weights(**named: float) -> np.ndarray:
    w = np.zeros(51, np.float32)
    for k, v in named.items():
        w[J[k]] = v
    return w


@pytest.fixture(scope="module")
def statue():
    if not STATUE.is_file():
        pytest.skip(f"{STATUE} is absent")
    return load_lam(STATUE)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return import_lam(L.make_zip(tmp_path_factory.mktemp("lam") / "small.zip"))


# ----- the real export ---------------------------------------------------------------------------------------


@needs_statue
def test_statue_imports_as_an_arkit_vertex_bound_avatar(statue) -> None:
    a = statue.avatar
    assert (a.count, a.sh_degree, a.binding_type, a.expression) == (20018, 0, "vertex", "arkit51")
    assert a.head.num_vertices == 20018 and a.head.num_faces == 39904 and a.head.expr_dims == 51
    assert a.head.shape_dims == 0 and not np.any(a.head.posedirs) and np.all(a.head.weights[:, 0] == 1)
    assert any("51 ARKit morph targets" in n for n in statue.notes)
    np.testing.assert_array_equal(a.binding.vertex, np.arange(20018))
    # centred like the default avatar (mesh bounding box at the origin), metres, face along +z
    v = a.head.v_template
    np.testing.assert_allclose((v.min(0) + v.max(0)) / 2, 0, atol=1e-9)
    assert 0.15 < np.ptp(v[:, 0]) < 0.3 and 0.25 < np.ptp(v[:, 1]) < 0.4  # a head with its neck, in metres
    nose = v[v[:, 2].argmax()]
    assert abs(nose[0]) < 0.01 and nose[2] > 0.09, nose
    # the raw PLY, converted: position = vertex + offset, RGB -> SH DC, logit -> opacity, log -> scale
    from plyfile import PlyData

    with zipfile.ZipFile(STATUE) as zf:
        raw = PlyData.read(zf.open("arkitWithBSData/offset.ply"))["vertex"].data
    off = np.stack([raw[c] for c in "xyz"], 1)
    neutral = a.neutral()
    np.testing.assert_allclose(neutral.position - v, off, atol=1e-6)
    np.testing.assert_allclose(a.sh[:, 0] * C0 + 0.5, np.stack([raw[f"f_dc_{i}"] for i in range(3)], 1), atol=1e-5)
    np.testing.assert_allclose(a.opacity, sigmoid(raw["opacity"].astype(np.float64)), atol=1e-6)
    np.testing.assert_allclose(neutral.scale, np.exp(np.stack([raw[f"scale_{i}"] for i in range(3)], 1)), rtol=1e-5)
    q = np.stack([raw[f"rot_{i}"] for i in range(4)], 1)  # (w, x, y, z) -> wire (x, y, z, w)
    np.testing.assert_allclose(neutral.rotation, q[:, [1, 2, 3, 0]], atol=1e-6)


@needs_statue
def test_statue_morph_targets_move_the_right_parts(statue) -> None:
    a = statue.avatar
    h = a.head
    eye_left = np.linalg.norm(h.exprdirs[:, :, J["eyeBlinkLeft"]], axis=1) > 1e-4
    eye_right = np.linalg.norm(h.exprdirs[:, :, J["eyeBlinkRight"]], axis=1) > 1e-4
    jaw = np.linalg.norm(h.exprdirs[:, :, J["jawOpen"]], axis=1) > 1e-4
    assert h.v_template[eye_left, 0].mean() > 0.02 and h.v_template[eye_right, 0].mean() < -0.02  # left = +x
    assert h.v_template[jaw, 1].mean() < h.v_template[eye_left, 1].mean() - 0.05
    d = reference_vertex_frame(a, weights(jawOpen=1)).position - a.neutral().position
    assert d[:, 1].min() < -0.02  # the chin drops by centimetres
    # rotation and scale do not follow the surface (LAM's renderer and training keep them)
    ref = reference_vertex_frame(a, weights(jawOpen=1, mouthSmileLeft=1))
    np.testing.assert_array_equal(ref.rotation, a.neutral().rotation)
    np.testing.assert_array_equal(ref.scale, a.neutral().scale)


@needs_statue
def test_statue_round_trips_through_the_npz(statue, tmp_path) -> None:
    a = statue.avatar
    save_avatar(a, tmp_path / "statue.npz")
    b = load_avatar(tmp_path / "statue.npz")
    assert (b.binding_type, b.expression, b.count) == ("vertex", "arkit51", 20018)
    w = weights(jawOpen=0.7, eyeBlinkLeft=1)
    assert reference_vertex_frame(b, w).position.tobytes() == reference_vertex_frame(a, w).position.tobytes()


@needs_statue
def test_statue_sample_track_reads() -> None:
    with zipfile.ZipFile(STATUE) as zf:
        track = read_bs_track(zf.read("arkitWithBSData/bsData.json"))
    assert track.weights.shape == (184, 52) and track.fps == 30.0
    np.testing.assert_allclose(np.diff(track.times), 1 / 30, atol=1e-3)
    assert 0.3 < track.weights[0, ARKIT52_NAMES.index("jawOpen")] < 0.4  # the first frame's jawOpen 0.3636


@needs_statue
def test_statue_fast_path_matches_the_reference(statue) -> None:
    a = statue.avatar
    fast = FastVertexAvatar(a)
    s = fast.session()
    rng = np.random.default_rng(1)
    for _ in range(3):
        w = (rng.uniform(0, 1, 51) * (rng.uniform(size=51) < 0.4)).astype(np.float32)
        got, ref = s.run(w), reference_vertex_frame(a, w)
        np.testing.assert_allclose(got.position, ref.position, atol=1e-7)
        assert got.rotation.tobytes() == ref.rotation.tobytes() and got.scale.tobytes() == ref.scale.tobytes()


# ----- variants of the zip -------------------------------------------------------------------------------------


def test_small_zip_imports_centred_with_its_offsets(tmp_path) -> None:
    z = L.make_zip(tmp_path / "anna.zip")
    a = import_lam(z)
    v, _, _ = L.patch()
    assert a.name == "anna" and a.count == v.shape[0] and a.expression == "arkit51"
    centre = (v.min(0) + v.max(0)) / 2
    np.testing.assert_allclose(a.head.v_template, v - centre, atol=1e-6)
    cols = L.gaussians(v.shape[0])
    np.testing.assert_allclose(a.neutral().position, v - centre + cols["offset"], atol=1e-6)
    np.testing.assert_allclose(a.sh[:, 0] * C0 + 0.5, cols["rgb"], atol=1e-6)


@pytest.mark.parametrize("variant", ["junk_and_json", "no_folder", "stored", "interleaved_extra_mesh", "dense",
                                     "primitive_names", "maya_names", "unskinned_moved"])
def test_zip_variants_import_the_same_avatar(tmp_path, small, variant) -> None:
    kw: dict = {}
    glb: dict = {}
    if variant == "junk_and_json":
        kw = dict(junk=True, extra_json=True)
    elif variant == "no_folder":
        kw = dict(folder="")
    elif variant == "stored":
        kw = dict(compress=False, folder="export/lam/")
    elif variant == "interleaved_extra_mesh":
        glb = dict(interleave=True, extra_mesh=True)
    elif variant == "dense":
        glb = dict(sparse=False)
    elif variant == "primitive_names":
        glb = dict(names_in="primitive")
    elif variant == "maya_names":
        glb = dict(name_style="maya")
    elif variant == "unskinned_moved":
        glb = dict(skinned=False, node_translation=(0.0, 1.0, 0.0))
    z = L.make_zip(tmp_path / "v.zip", skin=L.make_glb(**glb) if glb else None, **kw)
    a = import_lam(z)
    np.testing.assert_allclose(a.head.v_template, small.head.v_template, atol=1e-6)
    np.testing.assert_allclose(a.head.exprdirs, small.head.exprdirs, atol=1e-7)
    np.testing.assert_allclose(a.neutral().position, small.neutral().position, atol=1e-6)


def _with_root_transform(glb: bytes, rotation_xyzw: list[float], scale: float, skinned: bool) -> bytes:
    """The same glb with its head placed by a rotated, scaled node: the skin's joint (skinned) or the mesh node."""
    import pygltflib

    doc = pygltflib.GLTF2.load_from_bytes(glb)
    name = "head_bone" if skinned else "head_final"
    node = next(n for n in doc.nodes if n.name == name)
    node.rotation, node.scale = rotation_xyzw, [scale] * 3
    return b"".join(doc.save_to_bytes())


@pytest.mark.parametrize("skinned", [True, False])
def test_rotated_scaled_rest_pose_moves_the_gaussians_with_the_mesh(tmp_path, skinned) -> None:
    from ofera.head.rotations import quaternion_to_matrix

    glb = L.make_glb(skinned=skinned)
    plain = import_lam(L.make_zip(tmp_path / "plain.zip", skin=glb))
    half = np.sqrt(0.5)  # 90 degrees about +y, glTF order (x, y, z, w); and 1 cm units
    moved = load_lam(L.make_zip(tmp_path / "moved.zip", skin=_with_root_transform(glb, [0.0, half, 0.0, half],
                                                                                    0.01, skinned)))
    assert any("rest pose applied to the mesh and the Gaussians (rotation 90 deg, uniform scale 0.01" in n
               for n in moved.notes), moved.notes
    lin = 0.01 * np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    rot = lin / 0.01
    a, b = plain.neutral(), moved.avatar.neutral()
    pa, pb = a.position - a.position.mean(0), b.position - b.position.mean(0)
    np.testing.assert_allclose(pb, pa @ lin.T, atol=1e-8)  # world-space centres, centred
    np.testing.assert_allclose(b.scale, 0.01 * a.scale, rtol=1e-5)
    ra = quaternion_to_matrix(a.rotation[:, [3, 0, 1, 2]])  # wire (x, y, z, w) -> (w, x, y, z)
    rb = quaternion_to_matrix(b.rotation[:, [3, 0, 1, 2]])
    np.testing.assert_allclose(rb, rot @ ra, atol=1e-5)
    cov = lambda r, sc: r @ (sc[:, :, None] ** 2 * np.swapaxes(r, 1, 2))  # noqa: E731
    np.testing.assert_allclose(cov(rb, b.scale), lin @ cov(ra, a.scale) @ lin.T, atol=1e-14)


def test_gltf_json_with_embedded_buffers_imports(tmp_path, small) -> None:
    import pygltflib

    doc = pygltflib.GLTF2.load_from_bytes(L.make_glb())
    doc.convert_buffers(pygltflib.BufferFormat.DATAURI)  # a .gltf JSON text with base64 data URIs
    z = tmp_path / "json.zip"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("lam/skin.gltf", doc.to_json())
        zf.writestr("lam/offset.ply", L.make_ply(L.gaussians(L.patch()[0].shape[0])))
    a = import_lam(z)
    np.testing.assert_allclose(a.head.exprdirs, small.head.exprdirs, atol=1e-7)
    # ... or with its buffer in a separate file next to it
    doc = pygltflib.GLTF2.load_from_bytes(L.make_glb())
    blob = doc.binary_blob()
    doc.buffers[0].uri = "skin%20data.bin"
    doc.set_binary_blob(None)
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("lam/skin.gltf", doc.to_json())
        zf.writestr("lam/skin data.bin", blob)
        zf.writestr("lam/offset.ply", L.make_ply(L.gaussians(L.patch()[0].shape[0])))
    np.testing.assert_allclose(import_lam(z).head.exprdirs, small.head.exprdirs, atol=1e-7)


def test_missing_target_names_is_a_clear_error_with_a_fallback(tmp_path, small) -> None:
    z = L.make_zip(tmp_path / "unnamed.zip", skin=L.make_glb(names_in=None, order_seed=None))
    with pytest.raises(AvatarError, match=r"no names.*--target-order"):
        import_lam(z)
    a = import_lam(z, target_order="arkit")  # the targets are in Apple's order
    np.testing.assert_allclose(a.head.exprdirs, small.head.exprdirs, atol=1e-7)


@pytest.mark.parametrize("case, match", [
    ("no_skin", r"no skin\.glb"),
    ("two_avatars", r"2 files named skin\.glb.*one LAM avatar"),
    ("count_mismatch", r"no morphing mesh has 10 vertices"),
    ("not_glb", r"not a readable glTF"),
    ("nan_ply", r"NaN"),
    ("not_ply", r"not a readable PLY"),
    ("not_zip", r"not a readable zip"),
])
def test_bad_zips_fail_with_a_clear_error(tmp_path, case, match) -> None:
    p = tmp_path / "bad.zip"
    v, _, _ = L.patch()
    if case == "no_skin":
        with zipfile.ZipFile(p, "w") as zf:
            zf.writestr("x/offset.ply", L.make_ply(L.gaussians(v.shape[0])))
    elif case == "two_avatars":
        ply = L.make_ply(L.gaussians(v.shape[0]))  # two complete avatars (a lone skin.glb would not count)
        L.make_zip(p, extra_files={"b/skin.glb": L.make_glb(), "b/offset.ply": ply})
    elif case == "count_mismatch":
        L.make_zip(p, ply=L.make_ply(L.gaussians(10)))
    elif case == "not_glb":
        L.make_zip(p, skin=b"glTF\x02\x00\x00\x00garbage")
    elif case == "nan_ply":
        L.make_zip(p, ply=L.make_ply(L.gaussians(v.shape[0], nan=True)))
    elif case == "not_ply":
        L.make_zip(p, ply=b"ply\nformat nonsense\n")
    else:
        p.write_bytes(b"PK\x03\x04 this is not a zip")
    with pytest.raises(AvatarError, match=match):
        import_lam(p)


def test_bs_track_variants() -> None:
    t = read_bs_track(L.bs_track(frames=6))
    assert t.weights.shape == (6, 52) and t.weights[-1, ARKIT52_NAMES.index("jawOpen")] == 1.0
    with pytest.raises(AvatarError, match="not an ARKit blendshape"):
        read_bs_track(b'{"names": ["smile"], "frames": [[1.0]]}')
    with pytest.raises(AvatarError, match="frame 0 has 1 weights"):
        read_bs_track(b'{"names": ["jawOpen", "eyeBlinkLeft"], "frames": [[1.0]]}')
    with pytest.raises(AvatarError, match="no frames"):  # as the page's reader (bsdata.js) refuses it
        read_bs_track(b'{"names": ["jawOpen"], "frames": []}')
    with pytest.raises(AvatarError, match="'jawOpen' and 'blendShape1.JawOpen' are both the ARKit shape 'jawOpen'"):
        read_bs_track(b'{"names": ["jawOpen", "blendShape1.JawOpen"], "frames": [[1.0, 0.0]]}')
    for times in ([0.0, 0.1, 0.1], [0.0, 0.2, 0.1]):
        frames = ",".join(f'{{"weights": [0.5], "time": {t}}}' for t in times)
        with pytest.raises(AvatarError, match="frame times must increase, frame 2"):
            read_bs_track(f'{{"names": ["jawOpen"], "frames": [{frames}]}}'.encode())
    np.testing.assert_allclose(read_bs_track(b'{"names": ["jawOpen"], "frames": [[0.5]]}').times, [0.0])


@pytest.mark.parametrize("scale, expect", [(1.0, "plain RGB (colour auto"), (3.0, "SH DC coefficients (colour auto")])
def test_colour_heuristic_is_reported_in_the_notes(tmp_path, scale, expect) -> None:
    cols = L.gaussians(L.patch()[0].shape[0])
    cols["rgb"] = 0.5 + (cols["rgb"] - 0.5) * scale  # 3.0: values outside 0..1, read as 3DGS SH DC
    z = L.make_zip(tmp_path / "c.zip", ply=L.make_ply(cols))
    notes = load_lam(z).notes
    assert any(expect in n for n in notes), notes
    given = load_lam(z, colour="sh").notes
    assert any("SH DC coefficients (colour sh, given)" in n for n in given), given


# ----- the fast path and the binding --------------------------------------------------------------------------


@pytest.mark.parametrize("gaussians", ["exact", "all"])
def test_fast_kernels_match_the_numpy_reference(small, gaussians) -> None:
    fast = FastVertexAvatar(small, gaussians=gaussians)
    s = fast.session()
    rng = np.random.default_rng(4)
    for w in (np.zeros(51, np.float32), weights(jawOpen=1), rng.uniform(0, 1, 51).astype(np.float32)):
        got, ref = s.run(w), reference_vertex_frame(small, w)
        np.testing.assert_allclose(got.position, ref.position, atol=1e-7)
        assert got.rotation.tobytes() == ref.rotation.tobytes() and got.scale.tobytes() == ref.scale.tobytes()
    full = morph_blend_reference(small.head, weights(jawOpen=0.5))
    np.testing.assert_allclose(s.blend(weights(jawOpen=0.5)), full[fast.vertex_ids], atol=1e-12)
    with pytest.raises(ValueError, match="no joint rotations"):
        s.head(weights(), np.stack([np.eye(3)] * 4 + [np.diag([1.0, -1.0, -1.0])]))
    if gaussians == "exact":  # only Gaussians on vertices some target moves are deformed
        moving = np.any(small.head.exprdirs.reshape(small.count, -1) != 0, axis=1)
        assert fast.deformed_count == int(moving.sum()) < small.count


def test_vertex_binding_keeps_rotation_and_scale(small) -> None:
    st = reference_vertex_frame(small, weights(jawOpen=1, eyeBlinkLeft=1))
    n = small.neutral()
    assert st.rotation.tobytes() == n.rotation.tobytes() and st.scale.tobytes() == n.scale.tobytes()
    moved = np.abs(st.position - n.position).max(axis=1) > 0
    assert moved.any() and not moved.all()


# ----- cache and CLI -------------------------------------------------------------------------------------------


def test_cached_import_is_keyed_by_content(tmp_path) -> None:
    z = L.make_zip(tmp_path / "c.zip")
    cache = tmp_path / "cache"
    a = import_lam_cached(z, cache=cache)
    target = lam_cache_path(z, cache)
    assert target.is_file() and target.parent == cache / "lam"
    stamp = target.stat().st_mtime_ns
    b = import_lam_cached(z, cache=cache)  # read from the cache, not re-imported
    assert target.stat().st_mtime_ns == stamp and b.count == a.count and b.expression == "arkit51"
    L.make_zip(z, junk=True)  # new bytes: a new key
    assert lam_cache_path(z, cache) != target
    target.write_bytes(b"corrupt")
    L.make_zip(z)
    assert import_lam_cached(z, cache=cache).count == a.count  # a corrupt cache entry is re-imported


def test_cli_import_info_render_export(tmp_path, monkeypatch) -> None:
    from ofera.cli.main import app
    from typer.testing import CliRunner

    monkeypatch.setenv("OFERA_CACHE", str(tmp_path / "cache"))
    z = L.make_zip(tmp_path / "c.zip", junk=True, extra_json=True)
    r = CliRunner()
    out = tmp_path / "face.npz"
    res = r.invoke(app, ["avatar", "import", "lam", str(z), "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "51 ARKit morph targets" in res.output and "skipped 5" in res.output
    assert "f_dc read as plain RGB (colour auto: every value lies in 0..1" in res.output
    assert load_avatar_npz(out).name == "face"
    res = r.invoke(app, ["avatar", "info", str(out), "--json"])
    assert res.exit_code == 0 and '"expression": "arkit51"' in res.output, res.output
    for src in (str(out), str(z)):  # the npz, and the zip itself (imported through the cache)
        res = r.invoke(app, ["avatar", "render", src, "-o", str(tmp_path / "r.png"), "--size", "48",
                             "--expr", "jawOpen=1"])
        assert res.exit_code == 0 and (tmp_path / "r.png").is_file(), res.output
    res = r.invoke(app, ["avatar", "export", str(out), "-o", str(tmp_path / "e.ply"), "--expr", "eyeBlinkLeft=1"])
    assert res.exit_code == 0, res.output
    res = r.invoke(app, ["avatar", "render", str(out), "-o", str(tmp_path / "r.png"), "--jaw", "10"])
    assert res.exit_code != 0 and "jawOpen" in res.output
    res = r.invoke(app, ["avatar", "import", "lam", str(tmp_path / "missing.zip"), "-o", str(out)])
    assert res.exit_code != 0 and "no such file" in res.output and "Traceback" not in res.output


def test_benchmark_script_runs_on_a_small_zip(tmp_path) -> None:
    import json
    import os
    import subprocess
    import sys

    z = L.make_zip(tmp_path / "b.zip")
    out = tmp_path / "lam.json"
    env = dict(os.environ, OFERA_CACHE=str(tmp_path / "cache"))
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "lam.py"
    res = subprocess.run([sys.executable, str(script), "--zip", str(z), "--variants", "lam", "--frames", "5",
                          "--ref-frames", "2", "--json", str(out)], capture_output=True, text=True, env=env,
                         timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    report = json.loads(out.read_text())
    lam = report["results"]["lam"]
    assert lam["expression"] == "arkit51" and lam["fast"]["epm"]["p50"] < 0.01  # skipped: no EPM (ms)
    assert {"fast", "reference"} <= set(lam) and out.with_suffix(".png").is_file()
