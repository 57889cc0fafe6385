"""The project's avatar .npz, the default avatar and its cache, and the standard 3DGS PLY export."""

from __future__ import annotations

import numpy as np
import pytest
from ofera.avatar import AvatarError, export_state_ply, load_avatar, save_avatar
from ofera.avatar.io import FORMAT_VERSION, avatar_arrays
from ofera.avatar.sh import C0
from plyfile import PlyData
from test_avatar_core import random_barycentric_avatar, random_triangle_avatar

_GENERATED: dict = {}


@pytest.fixture(scope="session")
def default_avatar(tmp_path_factory):
    """The default avatar generated once per run into a fresh cache folder (shared by the avatar tests)."""
    import os

    from ofera.avatar import cache

    if "avatar" not in _GENERATED:
        before = os.environ.get("OFERA_CACHE")
        os.environ["OFERA_CACHE"] = str(tmp_path_factory.mktemp("ofera-cache"))
        cache._cached.cache_clear()
        _GENERATED["avatar"] = load_avatar("default")
        _GENERATED["env"] = before
    yield _GENERATED["avatar"]
    if "env" in _GENERATED:  # restore the caller's cache setting at the end of the run
        before = _GENERATED.pop("env")
        os.environ.pop("OFERA_CACHE", None) if before is None else os.environ.__setitem__("OFERA_CACHE", before)


def test_default_avatar_contract(default_avatar):
    a = default_avatar
    assert a.count >= 100_000 and a.sh_degree == 3 and a.binding_type == "triangle"
    assert a.opacity.dtype == np.float32 and a.opacity.shape == (a.count,)
    assert a.sh.dtype == np.float32 and a.sh.shape == (a.count, 16, 3)
    assert a.movable.shape == (a.count,) and 0.2 < a.movable.mean() < 0.9
    state = a.neutral()
    extent = state.position.max(axis=0) - state.position.min(axis=0)
    assert np.all((extent > 0.12) & (extent < 0.4)), extent  # head-sized, metres
    assert np.abs(a.sh[:, 1:]).max() < 0.5  # view dependence is small


def test_default_avatar_colours_follow_the_labels(default_avatar):
    a = default_avatar
    head = a.head
    rgb = a.sh[:, 0] * C0 + 0.5
    faces_of = {k: m[head.faces].all(axis=1) for k, m in head.vertex_labels.items()}

    on_surface = np.abs(a.binding.position[:, 1]) < 0.05  # teeth and hair sit off their faces

    def mean_rgb(label):
        return rgb[faces_of[label][a.binding.face] & on_surface].mean(axis=0)

    skin, sclera_ish = mean_rgb("skin"), mean_rgb("eyeball_left")
    assert skin[0] > skin[2] + 0.1  # warm skin
    assert mean_rgb("pupil_left").max() < 0.35 < sclera_ish.min()  # dark pupil, bright eyeball
    assert mean_rgb("mouth_cavity").max() < 0.3
    teeth = faces_of["mouth_cavity"][a.binding.face] & ~on_surface
    assert teeth.sum() > 1000 and rgb[teeth].mean() > 0.6
    assert mean_rgb("scalp").max() < 0.35  # dark hair
    lips = rgb[faces_of["lips"][a.binding.face]].mean(axis=0)
    assert lips[0] - lips[1] > skin[0] - skin[1]  # redder than skin


def test_default_avatar_is_cached_and_regenerated_when_corrupt(default_avatar):
    from ofera.avatar import cache

    path = cache.default_avatar_path()
    assert path.is_file() and path.name.startswith("avatar-default-")
    path.write_bytes(b"not a zip")
    cache._cached.cache_clear()
    again = load_avatar("default")
    assert again.count == default_avatar.count
    assert np.array_equal(again.binding.face, default_avatar.binding.face)  # deterministic
    assert load_avatar("default").count == again.count and path.stat().st_size > 1_000_000


@pytest.mark.parametrize("kind", ["triangle", "barycentric"])
def test_own_format_round_trip(head, tmp_path, kind):
    rng = np.random.default_rng(11)
    avatar = (random_triangle_avatar if kind == "triangle" else random_barycentric_avatar)(head, rng, 500)
    path = save_avatar(avatar, tmp_path / "a.npz")
    with np.load(path, allow_pickle=False) as z:  # no object arrays anywhere
        assert str(z["format"]) == "ofera-avatar" and int(z["format_version"]) == FORMAT_VERSION
        assert str(z["binding"]) == kind and "head/v_template" in z.files and "head/label/lips" in z.files
    back = load_avatar(path)
    assert back.binding_type == kind and back.count == avatar.count and back.name == avatar.name
    for key, value in avatar_arrays(avatar).items():
        assert np.array_equal(avatar_arrays(back)[key], value), key
    verts = head.v_template + 0.001
    s1, s2 = avatar.deformer().deform(verts), back.deformer().deform(verts)
    assert np.allclose(s1.position, s2.position, atol=1e-6) and np.allclose(s1.rotation, s2.rotation, atol=1e-6)
    assert np.array_equal(avatar.movable, back.movable)
    assert set(back.head.vertex_labels) == set(head.vertex_labels) and set(back.head.landmarks) == set(head.landmarks)


def test_bad_avatar_files_give_one_clear_error(head, tmp_path):
    with pytest.raises(AvatarError, match="no such file"):
        load_avatar(tmp_path / "missing.npz")
    (tmp_path / "x.ply").write_text("ply")
    with pytest.raises(AvatarError, match="ofera avatar import"):
        load_avatar(tmp_path / "x.ply")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(AvatarError, match="not an OFERA avatar"):
        load_avatar(tmp_path / "other.npz")
    arrays = avatar_arrays(random_triangle_avatar(head, np.random.default_rng(0), 20))
    np.savez(tmp_path / "newer.npz", **(arrays | {"format_version": np.array(FORMAT_VERSION + 1)}))
    with pytest.raises(AvatarError, match="newer"):
        load_avatar(tmp_path / "newer.npz")
    np.savez(tmp_path / "objects.npz", **(arrays | {"name": np.array([{"evil": 1}], dtype=object)}))
    with pytest.raises(AvatarError, match="objects.npz"):
        load_avatar(tmp_path / "objects.npz")


def test_ply_export_is_standard_3dgs(head, tmp_path):
    rng = np.random.default_rng(2)
    avatar = random_triangle_avatar(head, rng, 300)
    avatar = type(avatar)(avatar.head, avatar.binding, avatar.opacity, avatar.sh[:, :4].copy())  # degree 1
    state = avatar.neutral()
    path = export_state_ply(tmp_path / "x.ply", state, avatar.opacity, avatar.sh)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    v = PlyData.read(str(path))["vertex"].data
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *(f"f_rest_{i}" for i in range(45)),
             "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert list(v.dtype.names) == names and all(v.dtype[n] == np.dtype("<f4") for n in names)
    assert len(v) == avatar.count
    col = {n: np.asarray(v[n], np.float64) for n in names}
    assert np.allclose(np.stack([col["x"], col["y"], col["z"]], 1), state.position)
    assert np.allclose(1 / (1 + np.exp(-col["opacity"])), avatar.opacity, atol=1e-5)
    assert np.allclose(np.exp(np.stack([col[f"scale_{i}"] for i in range(3)], 1)), state.scale, rtol=1e-5)
    wxyz = np.stack([col[f"rot_{i}"] for i in range(4)], 1)
    assert np.allclose(wxyz, state.rotation_wxyz(), atol=1e-7)
    rest = np.stack([col[f"f_rest_{i}"] for i in range(45)], 1).reshape(-1, 3, 15)  # channel-major
    assert np.allclose(rest[:, :, :3], avatar.sh[:, 1:4].transpose(0, 2, 1)) and not rest[:, :, 3:].any()
    assert np.allclose(np.stack([col[f"f_dc_{i}"] for i in range(3)], 1), avatar.sh[:, 0])
