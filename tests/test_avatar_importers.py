"""Importers on files written in the exact upstream layouts: GaussianAvatars (PLY + flame_param.npz, teeth
added to a FLAME-topology head) and FATE (torch checkpoint)."""

from __future__ import annotations

import pickle
from collections import OrderedDict

import numpy as np
import pytest
import scipy.sparse as sp
from ofera.avatar import AvatarError, import_fate, import_gaussianavatars, load_avatar, save_avatar
from ofera.avatar.frames import face_frames
from ofera.avatar.teeth import add_teeth, lip_rings, teeth_faces
from ofera.head import load_head
from ofera.head.lbs import forward
from ofera.head.rotations import axis_angle_to_matrix
from plyfile import PlyData, PlyElement

MOUTH_Y = -0.035


def flame_like_model(rng, n_expr=100) -> dict:
    """FLAME's key set and shapes (5023 vertices, 9976 faces) on a head-sized ellipsoid with a mouth slit.

    43 rings of 116 vertices plus two poles (4990 vertices, 9976 counter-clockwise faces); the front of the
    ring nearest the mouth height is split (lower-lip twins appended), the rest are unreferenced padding.
    """
    rows, cols = 43, 116
    phi = np.linspace(0, np.pi, rows + 2)[1:-1]
    theta = 2 * np.pi * np.arange(cols) / cols
    ring = np.stack([0.075 * np.sin(phi)[:, None] * np.sin(theta), 0.11 * np.cos(phi)[:, None] + 0 * theta,
                     0.095 * np.sin(phi)[:, None] * np.cos(theta)], -1).reshape(-1, 3)
    top, bottom = rows * cols, rows * cols + 1
    v = np.concatenate([ring, [[0, 0.11, 0], [0, -0.11, 0]]])
    idx = np.arange(rows * cols).reshape(rows, cols)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1], nxt[:-1], idx[1:], nxt[1:]
    faces = np.concatenate([
        np.stack([np.full(cols, top), idx[0], nxt[0]], -1),
        np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3),
        np.stack([idx[-1], np.full(cols, bottom), nxt[-1]], -1),
    ])
    mouth_row = int(np.argmin(np.abs(v[idx[:, 0], 1] - MOUTH_Y)))
    seam = idx[mouth_row][(np.abs(v[idx[mouth_row], 0]) < 0.022) & (v[idx[mouth_row], 2] > 0)]
    twins = np.arange(len(v), len(v) + len(seam))
    below = np.isin(faces, idx[mouth_row + 1]).any(axis=1)
    for s, t in zip(seam, twins):
        faces[below & (faces == s).any(axis=1)] = np.where(faces[below & (faces == s).any(axis=1)] == s, t,
                                                           faces[below & (faces == s).any(axis=1)])
    v = np.concatenate([v, v[seam], np.zeros((5023 - len(v) - len(seam), 3))])
    assert v.shape == (5023, 3) and faces.shape == (9976, 3)
    weights = np.zeros((5023, 5))
    lower_face = (v[:, 1] < MOUTH_Y - 0.001) & (v[:, 2] > 0.03)
    lower_face[twins] = True
    weights[:, 1] = ~lower_face
    weights[:, 2] = lower_face
    jreg = np.zeros((5, 5023))
    for k, sel in enumerate([idx[-1], idx[-8], idx[20, [20, -20]], idx[12, [8]], idx[12, [-8]]]):
        jreg[k, np.ravel(sel)] = 1.0 / np.size(sel)
    return {
        "v_template": v,
        "f": faces.astype(np.uint32),
        "shapedirs": (rng.normal(size=(5023, 3, 300 + n_expr)) * 1e-3).astype(np.float32),
        "posedirs": rng.normal(size=(5023, 3, 36)) * 1e-4,
        "J_regressor": sp.csc_matrix(jreg),
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.int64),
        "weights": weights,
    }


_FLAME: dict = {}


@pytest.fixture(scope="session")
def flame(tmp_path_factory):
    """(path, raw dict) of a FLAME-format pickle with a mouth (written once per run)."""
    if "path" not in _FLAME:
        raw = flame_like_model(np.random.default_rng(0))
        path = tmp_path_factory.mktemp("flame") / "generic_model.pkl"
        path.write_bytes(pickle.dumps(raw, protocol=2))
        _FLAME.update(path=path, raw=raw)
    return _FLAME["path"], _FLAME["raw"]


def write_gaussianavatars(folder, rng, n=4000, faces=10144):
    """point_cloud.ply and flame_param.npz exactly as GaussianAvatars saves them."""
    folder.mkdir(parents=True, exist_ok=True)
    binding = np.concatenate([np.arange(9976, 10144), [faces - 1], rng.integers(0, faces, n - 169)])
    attrs = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "binding_0"])
    data = np.empty(n, dtype=[(a, "f4") for a in attrs])
    values = rng.normal(size=(n, len(attrs))).astype(np.float32)
    values[:, 3:6] = 0
    values[:, -1] = binding
    for i, a in enumerate(attrs):
        data[a] = values[:, i]
    PlyData([PlyElement.describe(data, "vertex")]).write(str(folder / "point_cloud.ply"))
    t = 5
    params = {
        "shape": rng.normal(size=300).astype(np.float32), "expr": rng.normal(size=(t, 100)).astype(np.float32),
        "rotation": np.zeros((t, 3), np.float32), "neck_pose": np.zeros((t, 3), np.float32),
        "jaw_pose": np.zeros((t, 3), np.float32), "eyes_pose": np.zeros((t, 6), np.float32),
        "translation": np.zeros((t, 3), np.float32),
        "static_offset": (rng.normal(size=(1, 5143, 3)) * 1e-4).astype(np.float32),
        "dynamic_offset": np.zeros((t, 5143, 3), np.float32),
    }
    np.savez(str(folder / "flame_param.npz"), **params)
    return data, params


def test_teeth_extension_of_a_flame_head(flame):
    path, raw = flame
    head = load_head(path)
    upper, lower = lip_rings(head)
    ux = upper(head.v_template)[:, 0]
    assert ux[0] > 0 > ux[-1] and np.all(np.diff(ux) < 0)  # +x corner first, no repeats
    teeth = add_teeth(head)
    assert (teeth.num_vertices, teeth.num_faces) == (5143, 10144)
    assert np.array_equal(teeth.faces[9976:] - 5023, teeth_faces())
    tv = teeth.v_template[5023:]
    lips = np.concatenate([upper(head.v_template), lower(head.v_template)])
    assert tv[:, 2].max() < lips[:, 2].min()  # behind the lips
    assert np.all(np.abs(tv[:, 1] - MOUTH_Y) < 0.03) and np.ptp(tv[:, 0]) > 0.03
    upper_ids = teeth.vertex_labels["teeth_upper"]
    assert np.all(teeth.weights[upper_ids, 1] == 1)
    assert np.all(teeth.weights[teeth.vertex_labels["teeth_lower"], 2] == 1)
    normals = np.cross(*(np.diff(tv[teeth_faces()], axis=1).transpose(1, 0, 2)))
    assert np.all(normals[:28, 2] > 1e-6)  # the front of the upper teeth faces forwards, nothing degenerate
    assert np.all(np.linalg.norm(normals, axis=1) > 1e-6)
    opened = forward(teeth, jaw=axis_angle_to_matrix(np.array([0.3, 0, 0])))[0]
    moved = np.linalg.norm(opened - teeth.v_template, axis=1)
    assert moved[5023:][teeth.vertex_labels["teeth_lower"][5023:]].min() > 1e-3
    assert moved[5023:][upper_ids[5023:]].max() < 1e-9


def test_teeth_on_the_procedural_head_sit_behind_its_lips(head):
    teeth = add_teeth(head)
    tv = teeth.v_template[head.num_vertices:]
    assert np.abs(tv[:, 0]).max() < 0.03 and tv[:, 2].max() < head.landmarks["mouth_centre"][2] - 0.003


def test_import_gaussianavatars(flame, tmp_path):
    path, raw = flame
    head = load_head(path)
    rng = np.random.default_rng(4)
    data, params = write_gaussianavatars(tmp_path / "ga", rng)
    avatar = import_gaussianavatars([tmp_path / "ga"], head)
    same = import_gaussianavatars([tmp_path / "ga" / "flame_param.npz", tmp_path / "ga" / "point_cloud.ply"], head)
    assert np.array_equal(same.binding.position, avatar.binding.position)
    assert avatar.count == len(data) and avatar.binding_type == "triangle" and avatar.sh_degree == 3
    assert (avatar.head.num_vertices, avatar.head.num_faces) == (5143, 10144)
    assert np.array_equal(avatar.binding.face, data["binding_0"].astype(int))
    assert np.allclose(avatar.opacity, 1 / (1 + np.exp(-data["opacity"].astype(np.float64))), atol=1e-6)
    rest = np.stack([data[f"f_rest_{i}"] for i in range(45)], 1).reshape(-1, 3, 15)
    assert np.allclose(avatar.sh[:, 1:], rest.transpose(0, 2, 1)) and np.allclose(avatar.sh[:, 0, 2], data["f_dc_2"])
    # identity: template + shapedirs . shape + static_offset (the teeth follow the mean lip shape)
    expected = raw["v_template"] + raw["shapedirs"][:, :, :300].astype(np.float64) @ params["shape"].astype(np.float64)
    expected += params["static_offset"][0, :5023]
    assert np.allclose(avatar.head.v_template[:5023], expected, atol=1e-6)
    # neutral deformation = upstream's formula on the personalised mesh, LOCAL attributes from the PLY
    state = avatar.neutral()
    rot_f, s_f, c_f = face_frames(avatar.head.v_template, avatar.head.faces[avatar.binding.face])
    local = np.stack([data["x"], data["y"], data["z"]], 1).astype(np.float64)
    assert np.allclose(state.position, np.einsum("nij,nj->ni", rot_f, local) * s_f[:, None] + c_f, atol=1e-6)
    log_s = np.stack([data[f"scale_{i}"] for i in range(3)], 1).astype(np.float64)
    assert np.allclose(state.scale, np.exp(log_s) * s_f[:, None], rtol=1e-5)
    # lower teeth Gaussians follow the jaw, upper ones do not
    jaw = forward(avatar.head, jaw=axis_angle_to_matrix(np.array([0.3, 0, 0])))[0]
    opened = avatar.deformer().deform(jaw)
    delta = np.linalg.norm(opened.position - state.position, axis=1)
    face = avatar.binding.face
    assert delta[(face >= 9976) & (face < 9976 + 84)].max() < 1e-6 and delta[face >= 9976 + 84].min() > 1e-3
    assert avatar.movable[face >= 9976 + 84].all()
    # round trip through the project's format keeps the personalised head
    back = load_avatar(save_avatar(avatar, tmp_path / "ga.npz"))
    assert np.allclose(back.neutral().position, state.position, atol=1e-6)


def test_gaussianavatars_refusals(head, flame, tmp_path):
    rng = np.random.default_rng(5)
    write_gaussianavatars(tmp_path / "big", rng, n=500, faces=20000)
    with pytest.raises(AvatarError, match="face 19999 but head 'procedural-head' has 16699 faces"):
        import_gaussianavatars([tmp_path / "big"], head)
    with pytest.raises(AvatarError, match="flame_param.npz"):
        import_gaussianavatars([tmp_path / "big" / "point_cloud.ply"], head)
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "point_cloud.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    np.savez(tmp_path / "plain" / "flame_param.npz", shape=np.zeros(300))
    with pytest.raises(AvatarError, match="point_cloud.ply"):
        import_gaussianavatars([tmp_path / "plain"], head)


def write_fate_checkpoint(path, raw, rng, n=3000, n_shape=100, n_expr=50, extra=None):
    """A FATE checkpoint: {'model': state_dict, ...} with upstream's names and shapes."""
    import torch

    v, f = 5023, raw["f"].astype(np.int64)
    from ofera.avatar.frames import face_scales

    shaped = raw["v_template"] + raw["shapedirs"][:, :, :n_shape] @ rng.normal(size=n_shape) * 0.5
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    state = OrderedDict(
        _offset=t(rng.normal(size=(n, 1)).astype(np.float32)),
        _features_dc=t(rng.normal(size=(n, 1, 3)).astype(np.float32)),
        _features_rest=t(np.zeros((n, 0, 3), np.float32)),
        _scaling=t(rng.normal(-6, 0.3, size=(n, 3)).astype(np.float32)),
        _rotation=t(rng.normal(size=(n, 4)).astype(np.float32)),
        _opacity=t(rng.normal(size=(n, 1)).astype(np.float32)),
        face_index=t(rng.integers(0, len(f), n)),
        bary_coords=t(rng.dirichlet(np.ones(3), n).astype(np.float32)),
        delta_shapedirs=t((rng.normal(size=(v, 3, n_shape + n_expr)) * 1e-4).astype(np.float32)),
        delta_posedirs=t((rng.normal(size=(36, 3 * v)) * 1e-5).astype(np.float32)),
        delta_vertex=t((rng.normal(size=(v, 3)) * 1e-4).astype(np.float32)),
        face_scaling_canonical=t(face_scales(shaped, f)[:, None].astype(np.float32)),
        faces=t(f),
        **{"flame.v_template": t(shaped.astype(np.float32)), "mean_scaling": t(np.ones(1, np.float32))},
    )
    torch.save({"step": 1000, "model": state} | (extra or {}), str(path))
    return {k: x.numpy() for k, x in state.items()}


def test_import_fate(flame, tmp_path):
    path, raw = flame
    head = load_head(path)
    rng = np.random.default_rng(6)
    s = write_fate_checkpoint(tmp_path / "fate.pth", raw, rng)
    avatar = import_fate(tmp_path / "fate.pth", head)
    assert avatar.count == 3000 and avatar.binding_type == "barycentric" and avatar.sh_degree == 0
    h = avatar.head
    assert h.expr_dims == 50 and h.num_faces == 9976
    assert np.allclose(h.v_template, s["flame.v_template"] + s["delta_vertex"], atol=1e-6)
    assert np.allclose(h.exprdirs, raw["shapedirs"][:, :, 300:350] + s["delta_shapedirs"][:, :, 100:], atol=1e-7)
    assert np.allclose(h.posedirs, head.posedirs + s["delta_posedirs"], atol=1e-9)
    assert np.allclose(avatar.opacity, 1 / (1 + np.exp(-s["_opacity"][:, 0].astype(np.float64))), atol=1e-6)
    # neutral: canonical face scales were taken on the shaped template, the deltas change them slightly
    state = avatar.neutral()
    fi, bary = s["face_index"], s["bary_coords"].astype(np.float64)
    corners = h.v_template[h.faces[fi]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    expected = np.einsum("nk,nkc->nc", bary, corners) + normal * 0.05 * np.tanh(s["_offset"].astype(np.float64))
    assert np.allclose(state.position, expected, atol=1e-7)
    ratio = face_frames(h.v_template, h.faces[fi])[1] / s["face_scaling_canonical"][fi, 0]
    assert np.allclose(state.scale, np.exp(s["_scaling"]) * ratio[:, None], rtol=1e-4)
    back = load_avatar(save_avatar(avatar, tmp_path / "fate.npz"))
    assert np.allclose(back.neutral().scale, state.scale, rtol=1e-5)


def test_fate_refusals(flame, tmp_path):
    import torch

    path, raw = flame
    head = load_head(path)
    rng = np.random.default_rng(8)
    write_fate_checkpoint(tmp_path / "odd.pth", raw, rng, n=10, n_shape=100, n_expr=23)
    with pytest.raises(AvatarError, match="n_expr"):
        import_fate(tmp_path / "odd.pth", head)
    assert import_fate(tmp_path / "odd.pth", head, n_expr=23).head.expr_dims == 23

    class Evil:
        def __reduce__(self):
            return (print, ("this must never run",))

    torch.save({"model": {}, "evil": Evil()}, str(tmp_path / "evil.pth"))
    with pytest.raises(AvatarError, match="not a loadable torch checkpoint"):
        import_fate(tmp_path / "evil.pth", head)
    torch.save({"model": {"_offset": torch.zeros(3, 1)}}, str(tmp_path / "partial.pth"))
    with pytest.raises(AvatarError, match="missing"):
        import_fate(tmp_path / "partial.pth", head)
    with pytest.raises(AvatarError, match="9976 faces, head 'procedural-head' has 16699"):
        write_fate_checkpoint(tmp_path / "ok.pth", raw, rng, n=10)
        from ofera.head import default_head

        import_fate(tmp_path / "ok.pth", default_head())
