"""Small LAM-style zips written here (tests/test_lam_*.py): a curved face patch with ARKit morph targets, in the
variants real exports come in (macOS junk, extra JSON, other glTF writers, larger skin files).

The patch: a 13 x 15 grid, 12 x 16 cm, at LAM's world height (y about 1.6 m), face along +z. Morph targets:
``jawOpen`` moves the rows below the mouth down and back, ``eyeBlinkLeft`` / ``eyeBlinkRight`` a disc around
each eye down, ``mouthSmileLeft`` the left mouth corner up; the other 47 ARKit shapes are present with zero
deltas (as in LAM's exports, where every one of the 51 exists). Left is +x (the subject's left).
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np

ARKIT51 = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft", "jawRight", "jawOpen", "mouthClose", "mouthFunnel",
    "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft",
    "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthPressLeft", "mouthPressRight",
    "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight", "browDownLeft",
    "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight", "cheekPuff", "cheekSquintLeft",
    "cheekSquintRight", "noseSneerLeft", "noseSneerRight",
)  # fmt: skip
LIFT = np.array([0.0, 1.6, 0.02])  # where the patch sits in the glTF (LAM exports sit at body height)
EYE_LEFT, EYE_RIGHT = np.array([0.03, 0.03]), np.array([-0.03, 0.03])
LOWER_FACE_Y = -0.03  # jawOpen moves the vertices below this (patch coordinates, before LIFT)


def patch() -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """vertices (V, 3) in patch coordinates, faces (F, 3) counter-clockwise seen from +z, deltas by name."""
    xs, ys = np.linspace(-0.06, 0.06, 13), np.linspace(-0.08, 0.08, 15)
    gx, gy = np.meshgrid(xs, ys)
    v = np.stack([gx.ravel(), gy.ravel(), 0.1 - 3.0 * (gx.ravel() ** 2 + gy.ravel() ** 2)], axis=1)
    faces = []
    nx = xs.size
    for j in range(ys.size - 1):
        for i in range(nx - 1):
            a, b, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i, (j + 1) * nx + i + 1
            faces += [(a, b, d), (a, d, c)]
    deltas = {n: np.zeros_like(v) for n in ARKIT51}
    low = v[:, 1] < LOWER_FACE_Y
    deltas["jawOpen"][low] = np.array([0.0, -0.012, -0.004]) * ((LOWER_FACE_Y - v[low, 1]) / 0.05)[:, None]
    for name, eye in (("eyeBlinkLeft", EYE_LEFT), ("eyeBlinkRight", EYE_RIGHT)):
        near = np.linalg.norm(v[:, :2] - eye, axis=1) < 0.016
        deltas[name][near] = [0.0, -0.004, 0.0005]
    corner = np.linalg.norm(v[:, :2] - [0.02, -0.04], axis=1) < 0.015
    deltas["mouthSmileLeft"][corner] = [0.003, 0.004, -0.001]
    return v, np.asarray(faces, np.int64), deltas


class _Blob:
    def __init__(self) -> None:
        self.data = bytearray()

    def add(self, arr: np.ndarray) -> tuple[int, int]:
        while len(self.data) % 4:
            self.data.append(0)
        off = len(self.data)
        self.data += np.ascontiguousarray(arr).tobytes()
        return off, arr.nbytes


def make_glb(names_in: str | None = "mesh", sparse: bool = True, extra_mesh: bool = False, interleave: bool = False,
             skinned: bool = True, name_style: str = "plain", node_translation: tuple | None = None,
             order_seed: int | None = 5) -> bytes:
    """skin.glb bytes. names_in: 'mesh' (LAM/Blender), 'primitive', or None (no names). name_style: 'plain'
    (jawOpen) or 'maya' (blendShape1.JawOpen). extra_mesh: a second mesh (a box without targets) first in the
    file; interleave: POSITION and NORMAL in one strided bufferView; node_translation: an unskinned mesh node
    moved by this (the import applies it)."""
    import pygltflib as G

    v, faces, deltas = patch()
    v = v + LIFT
    if node_translation is not None:
        v = v - np.asarray(node_translation)
    order = list(ARKIT51)
    if order_seed is not None:  # LAM's files list them in no particular order
        np.random.default_rng(order_seed).shuffle(order)
    blob = _Blob()
    views, accessors = [], []

    def view(arr: np.ndarray, stride: int | None = None) -> int:
        off, n = blob.add(arr)
        views.append(G.BufferView(buffer=0, byteOffset=off, byteLength=n, byteStride=stride))
        return len(views) - 1

    def acc(arr: np.ndarray | None, ctype: int, kind: str, count: int, view_index: int | None = None,
            offset: int = 0, **kw) -> int:
        if arr is not None and view_index is None:
            view_index = view(arr)
        accessors.append(G.Accessor(bufferView=view_index, byteOffset=offset, componentType=ctype, count=count,
                                    type=kind, **kw))
        return len(accessors) - 1

    f32 = v.astype(np.float32)
    nv = v.shape[0]
    attrs = {}
    if interleave:
        normals = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (nv, 1))
        inter = np.concatenate([f32, normals], axis=1)  # 24 bytes a vertex
        vi = view(inter, stride=24)
        attrs["POSITION"] = acc(None, G.FLOAT, "VEC3", nv, vi, 0, min=f32.min(0).tolist(), max=f32.max(0).tolist())
        attrs["NORMAL"] = acc(None, G.FLOAT, "VEC3", nv, vi, 12)
    else:
        attrs["POSITION"] = acc(f32, G.FLOAT, "VEC3", nv, min=f32.min(0).tolist(), max=f32.max(0).tolist())
    if skinned:
        attrs["JOINTS_0"] = acc(np.zeros((nv, 4), np.uint8), G.UNSIGNED_BYTE, "VEC4", nv)
        w = np.zeros((nv, 4), np.float32)
        w[:, 0] = 1.0
        attrs["WEIGHTS_0"] = acc(w, G.FLOAT, "VEC4", nv)
    indices = acc(faces.astype(np.uint16).ravel(), G.UNSIGNED_SHORT, "SCALAR", faces.size)
    targets = []
    for name in order:
        d = deltas[name].astype(np.float32)
        nz = np.flatnonzero(np.any(d != 0, axis=1)).astype(np.uint32)
        if sparse:
            if nz.size:
                iv, vv = view(nz), view(d[nz])
                sp = G.Sparse(count=int(nz.size),
                              indices=G.AccessorSparseIndices(bufferView=iv, componentType=G.UNSIGNED_INT),
                              values=G.AccessorSparseValues(bufferView=vv))
            else:
                sp = None
            accessors.append(G.Accessor(bufferView=None, componentType=G.FLOAT, count=nv, type="VEC3", sparse=sp,
                                        min=d.min(0).tolist(), max=d.max(0).tolist()))
            targets.append({"POSITION": len(accessors) - 1})
        else:
            targets.append({"POSITION": acc(d, G.FLOAT, "VEC3", nv)})
    styled = [("blendShape1." + n[0].upper() + n[1:]) if name_style == "maya" else n for n in order]
    prim = G.Primitive(attributes=G.Attributes(**attrs), indices=indices, targets=targets)
    mesh = G.Mesh(name="head_final", primitives=[prim], weights=[0.0] * len(order))
    if names_in == "mesh":
        mesh.extras = {"targetNames": styled}
    elif names_in == "primitive":
        prim.extras = {"targetNames": styled}
    meshes, nodes = [], []
    if extra_mesh:  # a small box without morph targets (other tools add eyes, teeth, props)
        box = np.array([[x, y, z] for x in (-0.01, 0.01) for y in (1.5, 1.52) for z in (0, 0.02)], np.float32)
        bidx = np.array([0, 1, 2, 1, 3, 2, 4, 6, 5, 5, 6, 7], np.uint16)
        bp = G.Primitive(attributes=G.Attributes(POSITION=acc(box, G.FLOAT, "VEC3", 8, min=box.min(0).tolist(),
                                                                   max=box.max(0).tolist())),
                         indices=acc(bidx, G.UNSIGNED_SHORT, "SCALAR", bidx.size))
        meshes.append(G.Mesh(name="prop", primitives=[bp]))
        nodes.append(G.Node(name="prop", mesh=0))
    meshes.append(mesh)
    head_node = G.Node(name="head_final", mesh=len(meshes) - 1)
    if node_translation is not None:
        head_node.translation = list(map(float, node_translation))
    if skinned:
        ibm = np.eye(4, dtype=np.float32)[None]
        ibm_acc = acc(ibm.transpose(0, 2, 1).reshape(1, 16), G.FLOAT, "MAT4", 1)
        nodes.append(G.Node(name="head_bone"))
        joint = len(nodes) - 1
        head_node.skin = 0
        skins = [G.Skin(joints=[joint], inverseBindMatrices=ibm_acc)]
    else:
        skins = []
    nodes.append(head_node)
    root = G.Node(name="Armature", children=list(range(len(nodes))))
    nodes.append(root)
    doc = G.GLTF2(asset=G.Asset(generator="ofera tests", version="2.0"), scene=0,
                  scenes=[G.Scene(nodes=[len(nodes) - 1])], nodes=nodes, meshes=meshes, skins=skins,
                  accessors=accessors, bufferViews=views, buffers=[G.Buffer(byteLength=len(blob.data))])
    doc.set_binary_blob(bytes(blob.data))
    return b"".join(doc.save_to_bytes())


def gaussians(n: int, seed: int = 3, nan: bool = False) -> dict[str, np.ndarray]:
    """LAM offset.ply columns: offsets (m), plain RGB, opacity logits, log scales, unit (w, x, y, z) quaternions."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    cols = {
        "offset": rng.normal(0, 0.002, (n, 3)),
        "rgb": rng.uniform(0, 1, (n, 3)),
        "opacity": rng.uniform(-4, 6, n),
        "log_scale": np.log(rng.uniform(0.001, 0.004, (n, 3))),
        "rot": q,
    }
    if nan:
        cols["opacity"][3] = np.nan
    return cols


def make_ply(cols: dict[str, np.ndarray]) -> bytes:
    from plyfile import PlyData, PlyElement

    n = cols["offset"].shape[0]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    arr = np.zeros(n, dtype=[(k, "<f4") for k in names])
    for i, c in enumerate("xyz"):
        arr[c] = cols["offset"][:, i]
        arr[f"scale_{i}"] = cols["log_scale"][:, i]
        arr[f"f_dc_{i}"] = cols["rgb"][:, i]
    arr["opacity"] = cols["opacity"]
    for i in range(4):
        arr[f"rot_{i}"] = cols["rot"][:, i]
    buf = io.BytesIO()
    PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(buf)
    return buf.getvalue()


def bs_track(frames: int = 6, fps: float = 30.0) -> bytes:
    """A bsData.json: the 52 ARKit names alphabetically (tongueOut last), jawOpen rising to 1."""
    names = [*sorted(ARKIT51), "tongueOut"]
    rows = []
    for i in range(frames):
        w = [0.0] * 52
        w[names.index("jawOpen")] = i / (frames - 1)
        rows.append({"weights": w, "time": i / fps, "rotation": []})
    return json.dumps({"names": names, "metadata": {"fps": fps, "frame_count": frames,
                                                      "blendshape_names": names}, "frames": rows}).encode()


def make_zip(path: Path, *, folder: str = "arkitWithBSData/", junk: bool = False, extra_json: bool = False,
             skin: bytes | None = None, ply: bytes | None = None, track: bool = True, compress: bool = True,
             extra_files: dict[str, bytes] | None = None) -> Path:
    """A LAM-layout zip at ``path``; ``skin`` / ``ply`` default to :func:`make_glb` / :func:`make_ply`."""
    v, _, _ = patch()
    skin = make_glb() if skin is None else skin
    ply = make_ply(gaussians(v.shape[0])) if ply is None else ply
    mode = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", mode) as zf:
        if folder:
            zf.writestr(folder, b"")
        if junk:
            zf.writestr(".DS_Store", b"\x00\x00\x00\x01Bud1")
            zf.writestr(f"__MACOSX/{folder}._skin.glb", b"\x00\x05\x16\x07junk")
            zf.writestr(f"__MACOSX/{folder}._offset.ply", b"\x00\x05\x16\x07junk")
            zf.writestr(f"{folder}.DS_Store", b"\x00\x00\x00\x01Bud1")
            zf.writestr(f"{folder}._skin.glb", b"AppleDouble")
        zf.writestr(f"{folder}skin.glb", skin)
        zf.writestr(f"{folder}offset.ply", ply)
        if track:
            zf.writestr(f"{folder}bsData.json", bs_track())
        if extra_json:
            zf.writestr(f"{folder}vertex_order.json", json.dumps(list(range(v.shape[0]))))
            zf.writestr(f"{folder}config.json", json.dumps({"exporter": "LAM", "version": 2}))
            zf.writestr("meta/skin.json", json.dumps({"note": "not the mesh"}))
        for name, data in (extra_files or {}).items():
            zf.writestr(name, data)
    return path
