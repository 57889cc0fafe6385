"""Import a LAM avatar export (a zip of ``skin.glb`` + ``offset.ply``) as an ARKit-driven, vertex-bound avatar.

LAM ("Large Avatar Model", Tongyi Lab / Alibaba) exports what OpenAvatarChat and LAM's web renderer drive:

- ``skin.glb`` (or a ``skin.gltf`` JSON with data-URI or in-zip buffers): glTF 2.0, one skinned mesh (an
  upsampled FLAME-topology head), 51 morph targets named with ARKit names in ``mesh.extras.targetNames``
  (the order in the file is arbitrary: matched by name);
- ``offset.ply``: one Gaussian per mesh vertex (row i belongs to vertex i): ``x y z`` = offset from the
  vertex, ``f_dc_*`` = plain RGB in 0..1 (not SH), ``opacity`` = logit, ``scale_*`` = log scale, ``rot_*`` =
  unit quaternion (w, x, y, z);
- anything else (``bsData.json``, ``animation.glb``, ``vertex_order.json``, ``__MACOSX/``, ``.DS_Store``,
  extra JSON) is not needed and skipped.

How LAM moves a Gaussian (checked on LAM's public code): the centre is the morphed vertex plus the fixed
offset, ``v_i + sum_j w_j delta_ij + offset_i``; rotation and scale are NOT re-oriented by the surface. LAM's
training renderer (aigc3d/LAM ``GS3DRenderer.animate_gs_model``) builds each frame's Gaussians with the
canonical ``rotation`` and ``scaling`` and only animates ``xyz``; its web renderer
(``gaussian-splat-renderer-for-lam``, as in its MIT derivative myned-ai/gsplat-flame-avatar-renderer) adds
the morphed mesh vertex to the PLY centre (``SplatBuffer.fillSplatCenterArray``) and blends the per-vertex
morph deltas in the vertex shader, while the covariances come from a texture built once from the PLY's
scale and rotation. The import keeps exactly that (:class:`.binding.VertexBinding`).

The result: a head whose 51 expression directions are the morph targets in the project's ``arkit51`` order
(a missing target is a zero column), no identity basis, no pose correctives, every vertex skinned to the root
(the head pose stays the client's), bound Gaussians with SH degree 0 (``(rgb - 0.5) / C0``), linear opacity,
and ``expression = "arkit51"``: the server drives it with the BDA-aligned ARKit weights (no EPM).

Frame: glTF is already right-handed, y up, metres, front along +z (the project's FLAME axes). The rest pose
the skin defines (joint world matrices x inverse bind matrices) is applied when it is not the identity (it is
for LAM exports): to the vertices and morph targets, and its rotation R and uniform scale s to the Gaussians
(glTF from other tools may rotate or scale the root): offset -> s R offset, rotation -> quat(R) (x) rotation,
log scale -> log scale + log s. The head is then translated so that the mesh's bounding-box centre is the
origin, as the default avatar's is.
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
import posixpath
import sys
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from ofera_protocol.layouts import ARKIT51_NAMES, ARKIT52_NAMES

from ..assets import cache_dir
from ..head.model import FLAME_PARENTS, HeadModel
from ..head.rotations import matrix_to_quaternion, quaternion_multiply
from .binding import VertexBinding, normalize_quaternions
from .errors import AvatarError
from .io import load_avatar_npz, save_avatar
from .model import GaussianAvatar
from .ply import sigmoid
from .sh import rgb_to_dc

IMPORTER_VERSION = 1
SKIN_NAME, OFFSET_NAME, TRACK_NAME = "skin.glb", "offset.ply", "bsdata.json"
MAX_MEMBER_BYTES = 1 << 30  # an entry larger than this (uncompressed) is refused: zip bombs
MAX_TOTAL_BYTES = 2 << 30
TARGET_ORDERS = ("arkit", "sorted")
"""Fallbacks when a glTF has no morph target names: ``arkit`` = Apple's order (51 or 52 targets), ``sorted``
= the 51 ARKit names alphabetically (MediaPipe's order without ``_neutral``), then ``tongueOut`` if 52."""
_NECK_MARGIN_M = 0.01
_MOVED_M = 1e-4  # a morph target moving a vertex by more than 0.1 mm per unit weight


def _norm(name: str) -> str:
    """Morph target / blendshape name -> comparison key: the part after the last '.' or ':' (``blendShape1.jawOpen``),
    lower case, without '_', '-' and spaces."""
    tail = name.replace(":", ".").rsplit(".", 1)[-1]
    return "".join(c for c in tail.lower() if c not in "_- ")


_ARKIT_KEY = {_norm(n): n for n in ARKIT52_NAMES}


# ----- the zip -------------------------------------------------------------------------------------------------


def _is_junk(name: str) -> bool:
    parts = name.split("/")
    base = parts[-1]
    return "__MACOSX" in parts or base.startswith("._") or base in (".DS_Store", "Thumbs.db", "desktop.ini")


@dataclass(frozen=True)
class LamFiles:
    """The members of a LAM zip that the import reads (bytes), and what it skipped."""

    skin: bytes
    offset: bytes
    skin_name: str
    offset_name: str
    members: tuple[str, ...] = field(repr=False)
    track: bytes | None = None  # bsData.json next to skin.glb, if any
    skipped: tuple[str, ...] = ()
    source: str = ""

    def resolver(self) -> Callable[[str], bytes]:
        """Reads a glTF's external buffer ``uri`` (relative to skin.glb) from the zip."""
        return lambda uri: _zip_uri(Path(self.source), self.skin_name, uri, set(self.members))


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, source: str) -> bytes:
    if info.file_size > MAX_MEMBER_BYTES:
        raise AvatarError(f"{source}: {info.filename} is {info.file_size / 1e9:.1f} GB uncompressed, more than the "
                          f"{MAX_MEMBER_BYTES / 1e9:.1f} GB limit")
    try:
        with zf.open(info) as fh:
            data = fh.read(MAX_MEMBER_BYTES + 1)
    except (zipfile.BadZipFile, OSError, RuntimeError, NotImplementedError, EOFError) as exc:
        raise AvatarError(f"{source}: cannot read {info.filename} ({type(exc).__name__}: {exc})") from None
    if len(data) > MAX_MEMBER_BYTES:
        raise AvatarError(f"{source}: {info.filename} inflates beyond the {MAX_MEMBER_BYTES / 1e9:.1f} GB limit")
    return data


def _pick(found: list[str], what: str, source: str, near: str | None = None) -> str:
    if near is not None:
        same = [n for n in found if posixpath.dirname(n) == posixpath.dirname(near)]
        if len(same) == 1:
            return same[0]
    if len(found) == 1:
        return found[0]
    if not found:
        raise AvatarError(f"{source}: no {what} in the zip (a LAM export holds skin.glb and offset.ply, usually in "
                          "one folder such as arkitWithBSData/)")
    raise AvatarError(f"{source}: {len(found)} files named {what} ({', '.join(found[:6])}): give a zip with one "
                      "LAM avatar")


def read_lam_zip(path: str | Path) -> LamFiles:
    """Find and read ``skin.glb`` and ``offset.ply`` anywhere in a LAM zip (names case-insensitive; macOS junk
    skipped; when several folders hold them, the pair sharing a folder wins)."""
    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise AvatarError(f"{path}: no such file")
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise AvatarError(f"{path}: not a readable zip ({type(exc).__name__}: {exc})") from None
    with zf:
        infos = [i for i in zf.infolist() if not i.is_dir()]
        total = sum(i.file_size for i in infos)
        if total > MAX_TOTAL_BYTES:
            raise AvatarError(f"{path}: {total / 1e9:.1f} GB uncompressed, more than the "
                              f"{MAX_TOTAL_BYTES / 1e9:.1f} GB limit")
        members = {i.filename: i for i in infos if not _is_junk(i.filename)}
        skipped = tuple(sorted(i.filename for i in infos if _is_junk(i.filename)))

        def named(base: str) -> list[str]:
            return sorted(n for n in members if posixpath.basename(n).lower() == base)

        skins, offsets = named(SKIN_NAME) or named("skin.gltf"), named(OFFSET_NAME)  # .gltf: JSON, data URIs
        if len(skins) > 1 and offsets:  # prefer the skin that has an offset.ply beside it
            paired = [s for s in skins if any(posixpath.dirname(o) == posixpath.dirname(s) for o in offsets)]
            skins = paired or skins
        skin_name = _pick(skins, SKIN_NAME, source)
        offset_name = _pick(offsets, OFFSET_NAME, source, near=skin_name)
        tracks = [n for n in named(TRACK_NAME) if posixpath.dirname(n) == posixpath.dirname(skin_name)]
        return LamFiles(
            skin=_read_member(zf, members[skin_name], source),
            offset=_read_member(zf, members[offset_name], source),
            skin_name=skin_name, offset_name=offset_name, members=tuple(members),
            track=_read_member(zf, members[tracks[0]], source) if tracks else None,
            skipped=skipped, source=source,
        )


def _zip_uri(path: Path, base: str, uri: str, members: set[str]) -> bytes:
    from urllib.parse import unquote

    name = posixpath.normpath(posixpath.join(posixpath.dirname(base), unquote(uri)))
    if name not in members:
        raise AvatarError(f"{path}: {base} refers to buffer {uri!r}, which is not in the zip")
    try:
        with zipfile.ZipFile(path) as zf:
            return _read_member(zf, zf.getinfo(name), str(path))
    except (zipfile.BadZipFile, OSError, KeyError) as exc:
        raise AvatarError(f"{path}: cannot read {name} ({type(exc).__name__}: {exc})") from None


# ----- glTF ----------------------------------------------------------------------------------------------------

_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_NORMALIZE = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}


@dataclass(frozen=True)
class SkinMesh:
    """What the import takes from ``skin.glb``: rest-pose vertices (V, 3) metres, triangles (F, 3), morph target
    deltas by ARKit name (V, 3) each, and notes (names not understood, rest pose applied, ...)."""

    vertices: np.ndarray
    faces: np.ndarray
    targets: dict[str, np.ndarray]
    notes: tuple[str, ...] = ()
    rest_linear: np.ndarray = field(default_factory=lambda: np.eye(3))
    """The linear part (rotation R times uniform scale s, (3, 3)) of the rest transform applied to the vertices and
    morph targets: the Gaussians' offsets, rotations and scales get the same (:func:`build_lam_avatar`)."""


class _Gltf:
    """Accessor decoding over pygltflib's parsed JSON (dense, strided, normalised and sparse accessors)."""

    def __init__(self, data: bytes, where: str, resolve: Callable[[str], bytes] | None) -> None:
        try:
            import pygltflib
        except ImportError:  # pragma: no cover - a dependency of the package
            raise AvatarError("reading LAM avatars needs pygltflib (pip install pygltflib)") from None
        self.where = where
        try:
            if data[:4] == b"glTF":
                self.doc = pygltflib.GLTF2.load_from_bytes(data)
            else:
                self.doc = pygltflib.GLTF2.from_json(data.decode("utf-8"))
        except Exception as exc:  # pygltflib raises many types on malformed input
            raise AvatarError(f"{where}: not a readable glTF 2.0 file ({type(exc).__name__}: {exc})") from None
        version = str(getattr(self.doc.asset, "version", "") or "")
        if not version.startswith("2"):
            raise AvatarError(f"{where}: glTF version {version!r}, expected 2.0")
        self._resolve = resolve
        self._buffers: dict[int, bytes] = {}

    def buffer(self, index: int) -> bytes:
        if index not in self._buffers:
            try:
                buf = self.doc.buffers[index]
            except IndexError:
                raise AvatarError(f"{self.where}: buffer {index} does not exist") from None
            uri = buf.uri
            if uri is None:
                blob = self.doc.binary_blob() if index == 0 else None
                if blob is None:
                    raise AvatarError(f"{self.where}: buffer {index} has no data (no GLB chunk and no uri)")
                data = bytes(blob)
            elif uri.startswith("data:"):
                try:
                    data = base64.b64decode(uri.split(",", 1)[1], validate=False)
                except (IndexError, ValueError) as exc:
                    raise AvatarError(f"{self.where}: buffer {index} has a bad data URI ({exc})") from None
            elif self._resolve is not None:
                data = self._resolve(uri)
            else:
                raise AvatarError(f"{self.where}: buffer {index} is an external file {uri!r} (not supported here)")
            if len(data) < (buf.byteLength or 0):
                raise AvatarError(f"{self.where}: buffer {index} has {len(data)} bytes, byteLength says "
                                  f"{buf.byteLength}")
            self._buffers[index] = data
        return self._buffers[index]

    def _view(self, view_index: int, offset: int, count: int, width: int, dtype: np.dtype) -> np.ndarray:
        try:
            view = self.doc.bufferViews[view_index]
        except (IndexError, TypeError):
            raise AvatarError(f"{self.where}: bufferView {view_index} does not exist") from None
        data = self.buffer(view.buffer)
        item = dtype.itemsize
        elem = width * item
        stride = view.byteStride or elem
        start = (view.byteOffset or 0) + offset
        end_view = (view.byteOffset or 0) + view.byteLength
        if stride < elem or (count and start + stride * (count - 1) + elem > min(end_view, len(data))):
            raise AvatarError(f"{self.where}: bufferView {view_index} is too short for its accessor")
        if count == 0:
            return np.zeros((0, width), dtype)
        arr = np.ndarray((count, width), dtype.newbyteorder("<"), buffer=data, offset=start, strides=(stride, item))
        return np.array(arr, dtype)

    def accessor(self, index: int) -> np.ndarray:
        """(count, width) float64 (normalised integers scaled per the spec) or int64 for integer data."""
        try:
            acc = self.doc.accessors[index]
        except (IndexError, TypeError):
            raise AvatarError(f"{self.where}: accessor {index} does not exist") from None
        if acc.componentType not in _COMPONENTS or acc.type not in _WIDTH:
            raise AvatarError(f"{self.where}: accessor {index} has component {acc.componentType} / type {acc.type}")
        dtype = np.dtype(_COMPONENTS[acc.componentType])
        width = _WIDTH[acc.type]
        count = int(acc.count)
        if acc.bufferView is None:
            out = np.zeros((count, width), dtype)
        else:
            out = self._view(acc.bufferView, acc.byteOffset or 0, count, width, dtype)
        sparse = acc.sparse
        if sparse is not None and sparse.count:
            idx_dtype = np.dtype(_COMPONENTS.get(sparse.indices.componentType, np.uint32))
            idx = self._view(sparse.indices.bufferView, sparse.indices.byteOffset or 0, sparse.count, 1,
                             idx_dtype)[:, 0].astype(np.int64)
            if idx.size and (idx.min() < 0 or idx.max() >= count):
                raise AvatarError(f"{self.where}: accessor {index} has sparse indices outside 0..{count - 1}")
            out = np.array(out)
            out[idx] = self._view(sparse.values.bufferView, sparse.values.byteOffset or 0, sparse.count, width,
                                  dtype)
        if dtype.kind == "f":
            res = out.astype(np.float64)
        elif acc.normalized:
            res = np.maximum(out.astype(np.float64) / _NORMALIZE[acc.componentType], -1.0)
        else:
            return out.astype(np.int64)
        if not np.all(np.isfinite(res)):
            raise AvatarError(f"{self.where}: accessor {index} holds NaN or infinite values")
        return res

    # ----- scene graph -----

    def node_matrices(self) -> list[np.ndarray]:
        """World matrix (4, 4) of every node (TRS or matrix, parents first)."""
        nodes = self.doc.nodes
        parent: dict[int, int] = {}
        for i, n in enumerate(nodes):
            for c in n.children or []:
                parent[c] = i
        local = [_local_matrix(n) for n in nodes]
        world: list[np.ndarray | None] = [None] * len(nodes)

        def get(i: int, depth: int = 0) -> np.ndarray:
            if depth > len(nodes):
                raise AvatarError(f"{self.where}: the node hierarchy has a cycle")
            if world[i] is None:
                world[i] = local[i] if i not in parent else get(parent[i], depth + 1) @ local[i]
            return world[i]

        return [get(i) for i in range(len(nodes))]


def _local_matrix(node) -> np.ndarray:
    if node.matrix is not None and len(node.matrix) == 16:
        return np.asarray(node.matrix, np.float64).reshape(4, 4).T  # glTF matrices are column-major
    x, y, z, w = node.rotation or (0.0, 0.0, 0.0, 1.0)
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = r * np.asarray(node.scale or (1.0, 1.0, 1.0), np.float64)[None]
    m[:3, 3] = node.translation or (0.0, 0.0, 0.0)
    return m


def _target_names(mesh, prim, n_targets: int, target_order: str | None, where: str) -> tuple[list[str], str]:
    """The names of the primitive's morph targets and where they came from."""
    for holder, label in ((mesh, "mesh.extras.targetNames"), (prim, "primitive.extras.targetNames")):
        extras = holder.extras if isinstance(holder.extras, dict) else {}
        names = extras.get("targetNames")
        if isinstance(names, list) and len(names) == n_targets and all(isinstance(n, str) for n in names):
            return names, label
    if target_order is not None:
        if target_order not in TARGET_ORDERS:
            raise AvatarError(f"unknown target order {target_order!r} (expected one of {', '.join(TARGET_ORDERS)})")
        base = list(ARKIT52_NAMES) if target_order == "arkit" else [*sorted(ARKIT51_NAMES), "tongueOut"]
        if n_targets not in (51, 52):
            raise AvatarError(f"{where}: {n_targets} morph targets; the '{target_order}' order needs 51 or 52")
        return base[:n_targets], f"the {target_order} order (given)"
    raise AvatarError(
        f"{where}: mesh {mesh.name or '(unnamed)'!r} has {n_targets} morph targets but no names "
        "(mesh.extras.targetNames or primitive.extras.targetNames, as Blender and three.js write them): which is "
        "jawOpen cannot be told. Re-export with shape key names, or give the order the targets are in "
        f"(--target-order {' or '.join(TARGET_ORDERS)})")


def parse_skin(data: bytes, where: str = SKIN_NAME, resolve: Callable[[str], bytes] | None = None,
               vertex_count: int | None = None, target_order: str | None = None) -> SkinMesh:
    """``skin.glb`` (or ``.gltf`` JSON) bytes -> :class:`SkinMesh`. ``vertex_count``: pick the primitive with that
    many vertices (the Gaussians' count) when the file holds several meshes."""
    g = _Gltf(data, where, resolve)
    doc = g.doc
    found = []
    for mi, mesh in enumerate(doc.meshes or []):
        for pi, prim in enumerate(mesh.primitives or []):
            if prim.attributes.POSITION is None or prim.mode not in (None, 4):
                continue
            n = int(doc.accessors[prim.attributes.POSITION].count)
            found.append((mi, pi, n, len(prim.targets or [])))
    morphs = [f for f in found if f[3] > 0]
    if not morphs:
        listing = ", ".join(f"mesh {m} primitive {p}: {n} vertices" for m, p, n, _ in found) or "no triangle meshes"
        raise AvatarError(f"{where}: no mesh with morph targets ({listing}); a LAM skin.glb has one with 51 ARKit "
                          "morph targets")
    if vertex_count is not None:
        fits = [f for f in morphs if f[2] == vertex_count]
        if not fits:
            listing = ", ".join(f"mesh {m} primitive {p}: {n} vertices" for m, p, n, _ in morphs)
            raise AvatarError(f"{where}: no morphing mesh has {vertex_count} vertices ({listing}); LAM binds Gaussian "
                              "i of offset.ply to vertex i of the head mesh")
        morphs = fits
    mi, pi, nv, _ = max(morphs, key=lambda f: (f[3], f[2]))
    mesh = doc.meshes[mi]
    prim = mesh.primitives[pi]
    vertices = g.accessor(prim.attributes.POSITION)
    if vertices.shape[1] != 3:
        raise AvatarError(f"{where}: POSITION is {vertices.shape[1]}-dimensional")
    if prim.indices is not None:
        idx = g.accessor(prim.indices).reshape(-1)
    else:
        idx = np.arange(nv - nv % 3, dtype=np.int64)
    if idx.size % 3 or (idx.size and (idx.min() < 0 or idx.max() >= nv)):
        raise AvatarError(f"{where}: triangle indices are not triples of vertices 0..{nv - 1}")
    faces = idx.reshape(-1, 3).astype(np.int64)
    names, origin = _target_names(mesh, prim, len(prim.targets), target_order, where)
    notes = [f"morph target names from {origin}"]
    targets: dict[str, np.ndarray] = {}
    unknown = []
    for name, target in zip(names, prim.targets):
        arkit = _ARKIT_KEY.get(_norm(name))
        if arkit is None:
            unknown.append(name)
            continue
        pos = target.get("POSITION") if isinstance(target, dict) else getattr(target, "POSITION", None)
        delta = g.accessor(pos) if pos is not None else np.zeros((nv, 3))
        if delta.shape != (nv, 3):
            raise AvatarError(f"{where}: morph target {name!r} has {delta.shape[0]} deltas for {nv} vertices")
        if arkit in targets:
            raise AvatarError(f"{where}: two morph targets are {arkit!r}")
        targets[arkit] = delta
    if unknown:
        notes.append(f"ignored {len(unknown)} morph targets that are not ARKit shapes: {', '.join(unknown[:8])}")
    if not targets:
        raise AvatarError(f"{where}: none of the {len(names)} morph target names is an ARKit blendshape "
                          f"(e.g. {', '.join(names[:5])})")
    vertices, targets, rest_note, rest_linear = _rest_pose(g, mi, prim, vertices, targets)
    if rest_note:
        notes.append(rest_note)
    return SkinMesh(vertices, faces, targets, tuple(notes), rest_linear)


def _rest_pose(g: _Gltf, mesh_index: int, prim, vertices: np.ndarray, targets: dict[str, np.ndarray]
               ) -> tuple[np.ndarray, dict[str, np.ndarray], str, np.ndarray]:
    """Apply the transform that places the mesh at rest (skin: joints x inverse binds; else the node's), when it
    is one rigid similarity for the whole mesh and not already the identity. Also returns its linear part
    (rotation times uniform scale, (3, 3)), which the Gaussians bound to the mesh must follow."""
    doc = g.doc
    nodes = [i for i, n in enumerate(doc.nodes or []) if n.mesh == mesh_index]
    if not nodes:
        return vertices, targets, "", np.eye(3)
    world = g.node_matrices()
    node = doc.nodes[nodes[0]]
    if node.skin is not None:
        skin = doc.skins[node.skin]
        joints = list(skin.joints or [])
        if skin.inverseBindMatrices is not None:
            ibm = g.accessor(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
        else:
            ibm = np.broadcast_to(np.eye(4), (len(joints), 4, 4))
        if ibm.shape[0] != len(joints):
            raise AvatarError(f"{g.where}: skin has {len(joints)} joints but {ibm.shape[0]} inverse bind matrices")
        mats = np.stack([world[j] @ ibm[k] for k, j in enumerate(joints)]) if joints else np.eye(4)[None]
        used = []
        if prim.attributes.JOINTS_0 is not None and prim.attributes.WEIGHTS_0 is not None:
            jid = g.accessor(prim.attributes.JOINTS_0)
            w = g.accessor(prim.attributes.WEIGHTS_0)
            if jid.size and (jid.min() < 0 or jid.max() >= len(joints)):
                raise AvatarError(f"{g.where}: JOINTS_0 refers to joints outside the skin's {len(joints)}")
            used = np.unique(jid[w > 0])
        cand = mats[used] if len(used) else mats[:1]
    else:
        cand = world[nodes[0]][None]
    m = cand[0]
    scale = max(1.0, float(np.abs(m[:3, :3]).max()))
    if np.abs(cand - m).max() > 1e-4 * scale:
        raise AvatarError(f"{g.where}: the skin's rest pose is not one rigid transform for the head (its joints are "
                          "not in their bind pose); export the head in its bind pose")
    if np.abs(m - np.eye(4)).max() < 1e-5:
        return vertices, targets, "rest pose: identity (joints in their bind pose)", np.eye(3)
    lin = m[:3, :3]
    s = np.cbrt(np.linalg.det(lin))
    if s <= 0 or np.abs(lin.T @ lin / s**2 - np.eye(3)).max() > 1e-4:
        raise AvatarError(f"{g.where}: the mesh's rest transform is not a rotation and uniform scale")
    verts = vertices @ lin.T + m[:3, 3]
    angle = float(np.degrees(np.arccos(np.clip((np.trace(lin / s) - 1) / 2, -1.0, 1.0))))
    return verts, {k: d @ lin.T for k, d in targets.items()}, (
        f"rest pose applied to the mesh and the Gaussians (rotation {angle:.4g} deg, uniform scale {s:.4g}, "
        f"translation {np.round(m[:3, 3], 4).tolist()})"), lin


# ----- offset.ply ----------------------------------------------------------------------------------------------


def parse_offsets(data: bytes, where: str = OFFSET_NAME, colour: str = "auto") -> dict[str, np.ndarray | str]:
    """``offset.ply`` bytes -> ``offset`` (N, 3) m, ``rotation`` (N, 4) (w, x, y, z) unit, ``log_scale`` (N, 3),
    ``opacity`` (N,) linear, ``sh`` (N, 1, 3) and ``colour`` (how f_dc was read: ``rgb`` or ``sh``).

    ``colour``: ``rgb`` (LAM: f_dc is plain RGB in 0..1), ``sh`` (a 3DGS DC coefficient) or ``auto``
    (``rgb`` when every f_dc value lies in 0..1); ``colour_note`` says which was used and why (a heuristic:
    the import's notes print it)."""
    from plyfile import PlyData

    try:
        vertex = PlyData.read(io.BytesIO(data))["vertex"].data
    except Exception as exc:  # plyfile raises many types on malformed input
        raise AvatarError(f"{where}: not a readable PLY ({type(exc).__name__}: {exc})") from None
    names = set(vertex.dtype.names or ())
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [k for k in need if k not in names]
    if missing:
        raise AvatarError(f"{where}: not a LAM offset PLY, missing properties {missing}")

    def cols(*keys: str) -> np.ndarray:
        out = np.stack([np.asarray(vertex[k], np.float64) for k in keys], axis=1)
        if not np.all(np.isfinite(out)):
            raise AvatarError(f"{where}: {'/'.join(keys)} hold NaN or infinite values")
        return out

    dc = cols("f_dc_0", "f_dc_1", "f_dc_2")
    if colour not in ("auto", "rgb", "sh"):
        raise AvatarError(f"unknown colour mode {colour!r} (expected auto, rgb or sh)")
    if colour == "auto":
        in_range = dc.size == 0 or (dc.min() >= -1e-6 and dc.max() <= 1 + 1e-6)
        colour = "rgb" if in_range else "sh"
        lo, hi = (float(dc.min()), float(dc.max())) if dc.size else (0.0, 0.0)
        how = (f"f_dc read as plain RGB (colour auto: every value lies in 0..1, here {lo:.3g}..{hi:.3g}, as in LAM "
               "exports; if it holds 3DGS SH DC coefficients, import with --colour sh)" if in_range else
               f"f_dc read as SH DC coefficients (colour auto: values {lo:.3g}..{hi:.3g} lie outside 0..1, so not "
               "LAM's plain RGB; if it is RGB, import with --colour rgb)")
    else:
        how = f"f_dc read as {'plain RGB' if colour == 'rgb' else 'SH DC coefficients'} (colour {colour}, given)"
    sh = rgb_to_dc(np.clip(dc, 0.0, 1.0)) if colour == "rgb" else dc
    return {
        "offset": cols("x", "y", "z"),
        "rotation": normalize_quaternions(cols("rot_0", "rot_1", "rot_2", "rot_3")),
        "log_scale": cols("scale_0", "scale_1", "scale_2"),
        "opacity": sigmoid(cols("opacity")[:, 0]),
        "sh": sh[:, None, :].astype(np.float32),
        "colour": colour,
        "colour_note": how,
    }


# ----- the avatar ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LamImport:
    """An imported avatar and what the import noticed (printed by the CLI)."""

    avatar: GaussianAvatar
    notes: tuple[str, ...]


def build_lam_head(skin: SkinMesh, name: str = "lam-head") -> tuple[HeadModel, np.ndarray]:
    """The ARKit morph-target head (centred) and the translation applied (3,) metres (new = old + shift)."""
    v = skin.vertices
    shift = -(v.min(axis=0) + v.max(axis=0)) / 2
    nv = v.shape[0]
    exprdirs = np.zeros((nv, 3, len(ARKIT51_NAMES)))
    for j, n in enumerate(ARKIT51_NAMES):
        if n in skin.targets:
            exprdirs[:, :, j] = skin.targets[n]
    weights = np.zeros((nv, 5))
    weights[:, 0] = 1.0  # everything on the root: the client owns head pose; jaw and eyes are morph targets
    # float32-rounded, as the .npz stores them: an imported avatar deforms exactly like its saved file
    template = (v + shift).astype(np.float32).astype(np.float64)
    exprdirs = exprdirs.astype(np.float32).astype(np.float64)
    moved = np.abs(exprdirs).max(axis=(1, 2)) > _MOVED_M
    labels = {}
    if moved.any():  # below the lowest vertex an expression visibly moves (the chin): neck and shoulders
        labels["neck"] = template[:, 1] < template[moved, 1].min() - _NECK_MARGIN_M
    head = HeadModel(
        v_template=template, shapedirs=np.zeros((nv, 3, 0)), exprdirs=exprdirs, posedirs=np.zeros((36, 3 * nv)),
        j_regressor=np.full((5, nv), 1.0 / max(nv, 1)), parents=FLAME_PARENTS.copy(), weights=weights,
        faces=skin.faces, name=name, vertex_labels=labels,
    )
    return head, shift


def _rest_gaussians(lin: np.ndarray, gaussians: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The PLY's offsets, rotations (w, x, y, z) and log scales under the rest transform's linear part ``lin`` =
    s R: offset' = lin offset, rotation' = quat(R) (x) rotation (Hamilton, w first, as the binding stores them),
    log_scale' = log_scale + log s."""
    offset, rotation, log_scale = gaussians["offset"], gaussians["rotation"], gaussians["log_scale"]
    if np.abs(lin - np.eye(3)).max() < 1e-12:
        return offset, rotation, log_scale
    s = float(np.cbrt(np.linalg.det(lin)))
    q = matrix_to_quaternion(lin / s)
    return (offset @ lin.T, normalize_quaternions(quaternion_multiply(q[None], rotation)),
            log_scale + np.log(s))


def build_lam_avatar(skin: SkinMesh, gaussians: dict, name: str = "lam") -> GaussianAvatar:
    """Head + Gaussian i bound to vertex i with its offset; see the module docstring."""
    n = gaussians["offset"].shape[0]
    if n != skin.vertices.shape[0]:
        raise AvatarError(f"offset.ply has {n} Gaussians but the head mesh has {skin.vertices.shape[0]} vertices: "
                          "LAM binds Gaussian i to vertex i")
    head, _ = build_lam_head(skin, f"lam-{name}")
    offset, rotation, log_scale = _rest_gaussians(skin.rest_linear, gaussians)
    binding = VertexBinding(vertex=np.arange(n, dtype=np.int64), offset=offset.astype(np.float32),
                            rotation=rotation.astype(np.float32), log_scale=log_scale.astype(np.float32))
    return GaussianAvatar(head=head, binding=binding, opacity=gaussians["opacity"].astype(np.float32),
                          sh=gaussians["sh"], name=name, expression="arkit51")


def load_lam(path: str | Path, name: str | None = None, target_order: str | None = None,
             colour: str = "auto") -> LamImport:
    """Import a LAM zip; ``name`` defaults to the zip's stem. Every failure is an :class:`AvatarError`."""
    path = Path(path)
    files = read_lam_zip(path)
    gaussians = parse_offsets(files.offset, f"{path}:{files.offset_name}", colour)
    n = gaussians["offset"].shape[0]
    skin = parse_skin(files.skin, f"{path}:{files.skin_name}", files.resolver(), vertex_count=n,
                      target_order=target_order)
    avatar = build_lam_avatar(skin, gaussians, name or path.stem.split(".", 1)[0])
    missing = [k for k in ARKIT51_NAMES if k not in skin.targets]
    notes = [f"{files.skin_name}: {skin.vertices.shape[0]} vertices, {skin.faces.shape[0]} triangles, "
             f"{len(skin.targets)} ARKit morph targets", *skin.notes,
             f"{files.offset_name}: {n} Gaussians, {gaussians['colour_note']}"]
    if missing:
        notes.append(f"no morph target for {', '.join(missing)} (those weights do nothing)")
    if files.skipped:
        notes.append(f"skipped {len(files.skipped)} macOS/Windows junk entries")
    return LamImport(avatar, tuple(notes))


def import_lam(path: str | Path, name: str | None = None, target_order: str | None = None) -> GaussianAvatar:
    """A LAM zip -> :class:`GaussianAvatar` (vertex binding, ``expression == "arkit51"``)."""
    return load_lam(path, name, target_order).avatar


# ----- the import cache (`ofera serve` with a zip) --------------------------------------------------------------


def zip_digest(path: str | Path) -> str:
    """16 hex digits of SHA-256 over the zip's bytes and the importer version."""
    h = hashlib.sha256(f"lam-importer-{IMPORTER_VERSION}/".encode())
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:16]


def lam_cache_path(path: str | Path, cache: Path | None = None) -> Path:
    """Where the imported ``.npz`` of a zip is cached: ``<cache dir>/lam/<stem>-<digest>.npz``."""
    path = Path(path)
    return (cache or cache_dir(create=False)) / "lam" / f"{path.stem.split('.', 1)[0]}-{zip_digest(path)}.npz"


def import_lam_cached(path: str | Path, name: str | None = None, cache: Path | None = None) -> GaussianAvatar:
    """Import a LAM zip once: later calls (any process) load the cached ``.npz`` keyed by the zip's content. A
    cache that cannot be written is not an error (the import is then redone next time)."""
    path = Path(path)
    if not path.is_file():
        raise AvatarError(f"{path}: no such file")
    target = lam_cache_path(path, cache)
    if target.is_file():
        try:
            avatar = load_avatar_npz(target)
            return avatar if name is None or avatar.name == name else _renamed(avatar, name)
        except AvatarError as exc:
            print(f"warning: re-importing {path} ({exc})", file=sys.stderr)
    avatar = import_lam(path, name)
    try:
        save_avatar(avatar, target)
    except OSError as exc:
        print(f"warning: cannot cache the import of {path} at {target}: {exc}", file=sys.stderr)
    return avatar


def _renamed(avatar: GaussianAvatar, name: str) -> GaussianAvatar:
    from dataclasses import replace

    return replace(avatar, name=name)


# ----- bsData.json (LAM's sample expression track) --------------------------------------------------------------


@dataclass(frozen=True)
class BsTrack:
    """A recorded ARKit track: times (T,) seconds from 0, weights (T, 52) in Apple's ARKit (``arkit52``) order."""

    times: np.ndarray
    weights: np.ndarray
    fps: float


def read_bs_track(data: bytes | str | Path) -> BsTrack:
    """LAM/OpenAvatarChat ``bsData.json``: ``{"names": [52 names], "metadata": {"fps": 30, ...}, "frames":
    [{"weights": [52 values], "time": s, ...}, ...]}`` (frames may also be bare lists; times default to i/fps).
    Names are matched to ARKit by name; shapes it lacks stay 0. Refused (:class:`AvatarError`): no frames, two
    names for one ARKit shape, frame times that do not increase."""
    if isinstance(data, Path) or (isinstance(data, str) and not data.lstrip().startswith("{")):
        data = Path(data).read_bytes()
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise AvatarError(f"bsData: not JSON ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
        raise AvatarError("bsData: expected an object with 'frames' (a list) and 'names'")
    meta = doc.get("metadata") if isinstance(doc.get("metadata"), dict) else {}
    names = doc.get("names") or meta.get("blendshape_names")
    if not isinstance(names, list) or not names:
        raise AvatarError("bsData: no blendshape 'names'")
    cols: list[int] = []
    for n in names:
        key = _ARKIT_KEY.get(_norm(str(n)))
        if key is None:
            raise AvatarError(f"bsData: {n!r} is not an ARKit blendshape name")
        col = ARKIT52_NAMES.index(key)
        if col in cols:
            first = names[cols.index(col)]
            raise AvatarError(f"bsData: names {first!r} and {n!r} are both the ARKit shape {key!r}")
        cols.append(col)
    try:
        fps = float(meta.get("fps") or doc.get("fps") or 30.0)
    except (TypeError, ValueError):
        raise AvatarError(f"bsData: fps {meta.get('fps') or doc.get('fps')!r} is not a number") from None
    if not (fps > 0 and np.isfinite(fps)):
        raise AvatarError(f"bsData: fps {fps} is not positive")
    frames = doc["frames"]
    if not frames:
        raise AvatarError("bsData: the track has no frames")
    weights = np.zeros((len(frames), 52), np.float32)
    times = np.arange(len(frames), dtype=np.float64) / fps
    for i, f in enumerate(frames):
        w = f.get("weights") if isinstance(f, dict) else f
        if not isinstance(w, list) or len(w) != len(names):
            raise AvatarError(f"bsData: frame {i} has {len(w) if isinstance(w, list) else 'no'} weights, "
                              f"expected {len(names)}")
        try:
            weights[i, cols] = np.asarray(w, np.float32)
        except (TypeError, ValueError):
            raise AvatarError(f"bsData: frame {i} holds non-numbers") from None
        if isinstance(f, dict) and isinstance(f.get("time"), (int, float)):
            times[i] = float(f["time"])
    if not np.all(np.isfinite(weights)) or not np.all(np.isfinite(times)):
        raise AvatarError("bsData: NaN or infinite values")
    back = np.flatnonzero(np.diff(times) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise AvatarError(f"bsData: frame times must increase, frame {i} is at {times[i]:.6g} s after "
                          f"{times[i - 1]:.6g} s")
    return BsTrack(times - times[0], np.clip(weights, 0.0, 1.0), fps)
