"""Expression streaming (PROTOCOL.md 13): the rig a params-session client deforms the avatar with.

- `Rig`: the arrays of one avatar's rig (the vertices its movable Gaussians are bound to, their blend bases,
  skinning weights, joints, and the binding of each movable Gaussian);
- `encode_rig` / `decode_rig`: the rig body (one msgpack map) <-> `Rig`, strictly validated;
- `split_rig` / `RigAssembler`: the body cut into `rig` messages and put back together;
- `deform_rig`: the plain numpy REFERENCE of the client-side deformation (float64 inside, float32 out), params
  (68,) -> positions, rotations, scales of the rig's Gaussians in FLAME space, in two steps: `rig_vertices`, then
  `rig_gaussians`. Other clients (browser, C#, HLSL) port it; the golden vectors `rig_tiny*` hold its inputs and
  outputs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from . import _fields as F
from .codec import pack_map, unpack_message
from .constants import MAX_SERVER_MESSAGE, UINT32_MAX
from .errors import BAD_FIELD, ProtocolError
from .messages import RigChunk, _ArrayEq

RIG_BINDINGS = ("triangle", "barycentric")
"""How a rig's Gaussians sit on its faces: GaussianAvatars' triangle-local frame, or FATE's barycentric point."""
JOINTS = 5
"""FLAME's joints, in order: root, neck, jaw, left eye, right eye (parents -1, 0, 1, 1, 1)."""
MAX_RIG_BYTES = MAX_SERVER_MESSAGE
"""Largest rig body a client accepts (64 MiB); the built-in avatar's is 5.5 MB."""
DEFAULT_RIG_CHUNK_BYTES = 4 * 1024 * 1024
"""Default upper bound on the body bytes one `rig` message carries (like an avatar chunk's arrays)."""
EPS2 = 1e-20
"""Clamp on squared lengths before a normalisation (degenerate faces), as the server's face frames."""


@dataclass(eq=False)
class Rig(_ArrayEq):
    """One avatar's rig, in FLAME space (metres). S vertices, U faces, M Gaussians, E expression components,
    P pose-corrective rows.

    count: Gaussians of the session's avatar (N); index (M,) uint32 strictly ascending session ids it deforms.
    joints (5, 3) float32 and joints_expr (5, 3, E) float32: the joints are joints + joints_expr . expr.
    template (S, 3) float32 (the subject's identity baked in); expr_basis (S, E, 3) float32; pose_rows (P,)
    uint8, entries of FLAME's 36-long pose feature (R_k - I, k = 1..4, row-major), ascending; pose_basis (S, P, 3)
    float16; weights (S, 5) float32 skinning weights. face (U, 3) uint32 rig vertex ids; gaussian_face (M,) uint32.
    triangle: local_position (M, 3) float32 in face units. barycentric: bary (M, 3) float32, normal_offset (M,)
    float32 (metres per unit of the unnormalised normal). local_rotation (M, 4) float16 (x, y, z, w), unit;
    local_scale (M, 3) float16 (the scale is local_scale * s_f).
    """

    binding: str
    count: int
    index: np.ndarray
    joints: np.ndarray
    joints_expr: np.ndarray
    template: np.ndarray
    expr_basis: np.ndarray
    pose_rows: np.ndarray
    pose_basis: np.ndarray
    weights: np.ndarray
    face: np.ndarray
    gaussian_face: np.ndarray
    local_rotation: np.ndarray
    local_scale: np.ndarray
    local_position: np.ndarray | None = None
    bary: np.ndarray | None = None
    normal_offset: np.ndarray | None = None

    @property
    def vertices(self) -> int:
        return int(self.template.shape[0])

    @property
    def faces(self) -> int:
        return int(self.face.shape[0])

    @property
    def gaussians(self) -> int:
        return int(self.index.shape[0])

    @property
    def expr_dims(self) -> int:
        return int(self.expr_basis.shape[1])


def _schema(binding: str, s: int, u: int, m: int, e: int, p: int) -> dict[str, tuple[str, tuple[int, ...]]]:
    """Wire dtype and shape of every array of a rig body, in wire order."""
    out: dict[str, tuple[str, tuple[int, ...]]] = {
        "index": ("<u4", (m,)), "joints": ("<f4", (JOINTS, 3)), "joints_expr": ("<f4", (JOINTS, 3, e)),
        "template": ("<f4", (s, 3)), "expr_basis": ("<f4", (s, e, 3)), "pose_rows": ("u1", (p,)),
        "pose_basis": ("<f2", (s, p, 3)), "weights": ("<f4", (s, JOINTS)), "face": ("<u4", (u, 3)),
        "gaussian_face": ("<u4", (m,)),
    }
    if binding == "triangle":
        out["local_position"] = ("<f4", (m, 3))
    else:
        out["bary"] = ("<f4", (m, 3))
        out["normal_offset"] = ("<f4", (m,))
    out["local_rotation"] = ("<f2", (m, 4))
    out["local_scale"] = ("<f2", (m, 3))
    return out


def encode_rig(rig: Rig) -> bytes:
    """The rig body: one msgpack map (scalars, then the arrays of `_schema` as little-endian bins)."""
    if rig.binding not in RIG_BINDINGS:
        raise ValueError(f"unknown rig binding {rig.binding!r}; expected one of {RIG_BINDINGS}")
    schema = _schema(rig.binding, rig.vertices, rig.faces, rig.gaussians, rig.expr_dims, int(rig.pose_rows.size))
    d: dict[str, Any] = {"binding": rig.binding, "count": rig.count, "vertices": rig.vertices, "faces": rig.faces,
                         "gaussians": rig.gaussians, "expr_dims": rig.expr_dims}
    for key, (dtype, shape) in schema.items():
        a = np.ascontiguousarray(getattr(rig, key), dtype=dtype)
        if a.shape != shape:
            raise ValueError(f"rig {key} has shape {a.shape}, expected {shape}")
        d[key] = a
    return pack_map(d)


def decode_rig(body: bytes) -> Rig:
    """A rig body -> Rig (arrays are read-only views). ProtocolError on any malformed, missing, mis-sized or
    out-of-range field (indices beyond their arrays, an unsorted `index`, non-finite floats)."""
    w = "rig"
    m = unpack_message(body, MAX_RIG_BYTES)
    binding = F.get_choice(m, "binding", w, RIG_BINDINGS, BAD_FIELD)
    count = F.get_int(m, "count", w, lo=0, hi=UINT32_MAX)
    s, u = F.get_int(m, "vertices", w, lo=0, hi=UINT32_MAX), F.get_int(m, "faces", w, lo=0, hi=UINT32_MAX)
    g = F.get_int(m, "gaussians", w, lo=0, hi=count)
    e = F.get_int(m, "expr_dims", w, lo=0, hi=256)
    p = len(F.get_bin(m, "pose_rows", w))
    schema = _schema(binding, s, u, g, e, p)
    arrays = {key: F.get_array(m, key, w, dtype, shape) for key, (dtype, shape) in schema.items()}
    index, rows = arrays["index"], arrays["pose_rows"]
    problems = []
    if g and int(index[-1]) >= count:
        problems.append(f"'index' holds {int(index[-1])}, the avatar has {count} Gaussians")
    if g > 1 and not (index[1:] > index[:-1]).all():
        problems.append("'index' is not strictly ascending")
    if p and (int(rows.max()) >= 9 * (JOINTS - 1) or (p > 1 and not (rows[1:] > rows[:-1]).all())):
        problems.append(f"'pose_rows' must be strictly ascending entries below {9 * (JOINTS - 1)}")
    if u and int(arrays["face"].max()) >= s:
        problems.append(f"'face' indexes vertex {int(arrays['face'].max())} of {s}")
    if g and int(arrays["gaussian_face"].max()) >= u:
        problems.append(f"'gaussian_face' indexes face {int(arrays['gaussian_face'].max())} of {u}")
    if problems:
        raise ProtocolError(BAD_FIELD, "rig: " + "; ".join(problems))
    return Rig(binding=binding, count=count, **arrays)


def split_rig(body: bytes, max_chunk_bytes: int = DEFAULT_RIG_CHUNK_BYTES, member: str | None = None
              ) -> list[RigChunk]:
    """Cut a rig body into consecutive `rig` chunks of at most `max_chunk_bytes` (at least one chunk; views)."""
    step = max(1, int(max_chunk_bytes))
    starts = list(range(0, len(body), step)) or [0]
    data = np.frombuffer(body, np.uint8)
    return [RigChunk(chunk=c, chunks=len(starts), size=len(body), offset=o, data=data[o:o + step], member=member)
            for c, o in enumerate(starts)]


class RigAssembler:
    """Collects the `rig` chunks of one avatar, which must arrive in order without gaps."""

    def __init__(self) -> None:
        self._parts: list[np.ndarray] = []
        self._next = 0
        self._size: int | None = None
        self._chunks: int | None = None

    @property
    def complete(self) -> bool:
        return self._chunks is not None and len(self._parts) == self._chunks

    def add(self, chunk: RigChunk) -> bool:
        """Add the next chunk; True once the body is complete. ProtocolError `bad_field` if it does not continue
        the sequence (chunk number, chunks, size, offset) or the body would exceed MAX_RIG_BYTES."""
        problems = []
        if self.complete:
            problems.append("a rig chunk after the rig was complete")
        if chunk.chunk != len(self._parts):
            problems.append(f"chunk {chunk.chunk} arrived, expected {len(self._parts)}")
        if self._chunks is not None and (chunk.chunks != self._chunks or chunk.size != self._size):
            problems.append(f"chunks {chunk.chunks} / size {chunk.size} differ from the first chunk's")
        if chunk.offset != self._next:
            problems.append(f"offset {chunk.offset} != {self._next}")
        end = chunk.offset + int(chunk.data.size)
        if end > chunk.size or (chunk.chunk == chunk.chunks - 1 and end != chunk.size):
            problems.append(f"chunk ends at byte {end} of a {chunk.size}-byte rig")
        if chunk.size > MAX_RIG_BYTES:
            problems.append(f"a rig of {chunk.size} bytes exceeds the limit of {MAX_RIG_BYTES}")
        if problems:
            raise ProtocolError(BAD_FIELD, "bad rig chunk: " + "; ".join(problems))
        self._chunks, self._size = chunk.chunks, chunk.size
        self._parts.append(chunk.data)
        self._next = end
        return self.complete

    def result(self) -> bytes:
        """The whole rig body. Only once `complete`."""
        if not self.complete:
            raise RuntimeError("rig is not complete")
        return b"".join(p.tobytes() for p in self._parts)


# ============================================================================= the reference deformation


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(np.maximum(np.sum(v * v, axis=-1, keepdims=True), EPS2))


def rot6d_to_matrix(d6: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3): rows b1 = normalize(a1), b2 = normalize(a2 - (b1.a2) b1), b3 = b1 x b2
    (pytorch3d's convention: the 6 numbers are the first two ROWS; norms clamped at 1e-12)."""
    d6 = np.asarray(d6, np.float64)
    a1, a2 = d6[..., 0:3], d6[..., 3:6]
    b1 = a1 / np.maximum(np.linalg.norm(a1, axis=-1, keepdims=True), 1e-12)
    c = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = c / np.maximum(np.linalg.norm(c, axis=-1, keepdims=True), 1e-12)
    return np.stack([b1, b2, np.cross(b1, b2)], axis=-2)


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 4) unit quaternions (w, x, y, z) with w >= 0: the branch of the largest of
    4w^2, 4x^2, 4y^2, 4z^2 (the first on ties), normalised, negated if w < 0."""
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    sq = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1)
    d21, d02, d10 = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    s21, s02, s10 = r[..., 2, 1] + r[..., 1, 2], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 0] + r[..., 0, 1]
    cand = np.stack([np.stack([sq[..., 0], d21, d02, d10], axis=-1), np.stack([d21, sq[..., 1], s10, s02], axis=-1),
                     np.stack([d02, s10, sq[..., 2], s21], axis=-1), np.stack([d10, s02, s21, sq[..., 3]], axis=-1)],
                    axis=-2)
    q = np.take_along_axis(cand, np.argmax(sq, axis=-1)[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a (x) b of (..., 4) quaternions (w, x, y, z)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def joint_rotations(params: np.ndarray) -> np.ndarray:
    """params (68,) -> (5, 3, 3): root and neck the identity, then jaw, left eye, right eye from their 6D."""
    params = np.asarray(params, np.float64)
    e = params.shape[0] - 18
    return np.concatenate([np.broadcast_to(np.eye(3), (2, 3, 3)), rot6d_to_matrix(params[e:].reshape(3, 6))])


def rig_vertices(rig: Rig, params: np.ndarray) -> np.ndarray:
    """Steps 1-5 of PROTOCOL.md 13.4: params (68,) float32 -> the rig's deformed vertices (S, 3) float64."""
    params = np.asarray(params, np.float64).reshape(-1)
    expr = params[: rig.expr_dims]
    rot = joint_rotations(params)
    joints = rig.joints.astype(np.float64) + rig.joints_expr.astype(np.float64) @ expr  # (5, 3)
    a = np.zeros((JOINTS, 3, 4))  # A_k = [R_k | J_k - R_k J_k]; root and neck [I | 0]
    a[:, :, :3] = rot
    a[:, :, 3] = joints - np.einsum("kij,kj->ki", rot, joints)
    rows = rig.pose_rows.astype(np.int64)
    coef = (rot[1 + rows // 9, (rows % 9) // 3, rows % 3] - ((rows % 9) // 3 == rows % 3))  # (P,)
    v_po = (rig.template.astype(np.float64) + np.einsum("sec,e->sc", rig.expr_basis.astype(np.float64), expr)
            + np.einsum("spc,p->sc", rig.pose_basis.astype(np.float64), coef))
    t = np.einsum("sk,kij->sij", rig.weights.astype(np.float64), a)  # (S, 3, 4)
    return np.einsum("sij,sj->si", t[:, :, :3], v_po) + t[:, :, 3]


def deform_rig(rig: Rig, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PROTOCOL.md 13.4: params (68,) -> position (M, 3) m, rotation (M, 4) (x, y, z, w), scale (M, 3) m of the
    rig's Gaussians (session ids `rig.index`), float32, FLAME space."""
    return rig_gaussians(rig, rig_vertices(rig, params))


def rig_gaussians(rig: Rig, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 6-7 of PROTOCOL.md 13.4: deformed vertices (S, 3) m -> the Gaussians' position (M, 3) m, rotation
    (M, 4) (x, y, z, w) and scale (M, 3) m, float32. Lets a test feed a client's own vertices: a sliver face's frame
    turns by a client's vertex rounding divided by its height, which no tolerance on the whole chain can bound."""
    v = np.asarray(vertices, np.float64)
    corners = v[rig.face.astype(np.int64)[rig.gaussian_face.astype(np.int64)]]  # (M, 3 corners, 3)
    v0, v1, v2 = corners[:, 0], corners[:, 1], corners[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    a0 = _normalize(e1)
    a1 = _normalize(np.cross(a0, e2))
    a2 = np.cross(a0, a1)
    rot_f = np.stack([a0, a1, a2], axis=-1)  # columns
    s_f = (np.sqrt(np.maximum(np.sum(e1 * e1, axis=-1), EPS2)) + np.abs(np.sum(a2 * e2, axis=-1))) / 2
    if rig.binding == "triangle":
        local = rig.local_position.astype(np.float64) * s_f[:, None]
        position = np.einsum("nij,nj->ni", rot_f, local) + (v0 + v1 + v2) / 3.0
    else:
        bary = rig.bary.astype(np.float64)
        position = (bary[:, :1] * v0 + bary[:, 1:2] * v1 + bary[:, 2:] * v2
                    + np.cross(e1, e2) * rig.normal_offset.astype(np.float64)[:, None])
    lq = rig.local_rotation.astype(np.float64)
    lq = lq / np.maximum(np.linalg.norm(lq, axis=-1, keepdims=True), 1e-12)
    q = quaternion_multiply(matrix_to_quaternion(rot_f), lq[:, [3, 0, 1, 2]])
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    scale = rig.local_scale.astype(np.float64) * s_f[:, None]
    return (position.astype(np.float32), q[:, [1, 2, 3, 0]].astype(np.float32), scale.astype(np.float32))
