"""numba kernels of the fast deformation path (:mod:`.fast`); each mirrors the numpy reference
(:mod:`.frames`, :mod:`.deform`) formula for formula, in float64, writing float32 results in place.

Two passes per frame, one call each:

1. :func:`face_frames_kernel`: per used face, from its 3 vertices, the frame of :mod:`.frames`: the
   rotation R_f (columns a0, a1, a2), its unit quaternion (w >= 0, the branch :func:`matrix_to_quaternion`
   picks), the scale s_f, the centroid c_f and the unnormalised normal n_f (FATE) -> ``face`` (U, 17).
2. :func:`triangle_kernel` / :func:`barycentric_kernel`: per deformed Gaussian, the position, the
   rotation ``quat(R_f) (x) q_local`` written (x, y, z, w), and the scale, into its row of the full
   float32 output arrays. Gaussians are visited in runs of consecutive rows on one face (avatars keep
   a face's Gaussians together), so the face's values are loaded once per run.

Deviations from the reference, all at float64 rounding level (~1e-16): multiplications by reciprocals
instead of divisions, fused multiply-adds, a2 = a0 x a1 without renormalising (a0, a1 orthonormal), and
no renormalisation of ``quat(R_f) (x) q_local`` (a product of unit quaternions).

Compiled with ``cache=True`` (on disk next to this file) and ``nogil=True``, so sessions computing in
a thread pool run in parallel.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..jit import NB as _NB

_NBC = {**_NB, "fastmath": {"contract"}}  # fused multiply-add allowed (no reassociation)
_EPS2 = 1e-20  # frames._EPS2: clamp on squared lengths

# Columns of the per-face scratch (U, FACE_COLS) float64.
R0 = 0  # R_f row-major, 9 values (R[i, j] at R0 + 3 i + j)
Q0 = 9  # quaternion (w, x, y, z)
S_F = 13  # scale s_f
C0 = 14  # centroid (3)
FACE_COLS = 17
N0 = 17  # unnormalised normal (3), barycentric only
FACE_COLS_BARY = 20


@nb.njit(**_NBC)
def face_frames_kernel(verts, face_vids, face, with_normal):
    """verts (S, 3) f64; face_vids (U, 3) int rows of verts -> face (U, FACE_COLS[_BARY]) f64."""
    for u in range(face_vids.shape[0]):
        _face_frame(u, verts, face_vids, face, with_normal)


@nb.njit(parallel=True, **_NBC)
def face_frames_kernel_parallel(verts, face_vids, face, with_normal):
    """:func:`face_frames_kernel` over numba's threads (prange)."""
    for u in nb.prange(face_vids.shape[0]):
        _face_frame(u, verts, face_vids, face, with_normal)


@nb.njit(inline="always", **_NBC)
def _face_frame(u, verts, face_vids, face, with_normal):
    i0 = np.uint64(face_vids[u, 0])  # unsigned indices (see _triangle_run)
    i1 = np.uint64(face_vids[u, 1])
    i2 = np.uint64(face_vids[u, 2])
    v0x = verts[i0, 0]
    v0y = verts[i0, 1]
    v0z = verts[i0, 2]
    e1x = verts[i1, 0] - v0x
    e1y = verts[i1, 1] - v0y
    e1z = verts[i1, 2] - v0z
    e2x = verts[i2, 0] - v0x
    e2y = verts[i2, 1] - v0y
    e2z = verts[i2, 2] - v0z
    # a0 = normalize(e1)
    ll = math.sqrt(max(e1x * e1x + e1y * e1y + e1z * e1z, _EPS2))
    inv = 1.0 / ll
    a0x = e1x * inv
    a0y = e1y * inv
    a0z = e1z * inv
    # a1 = normalize(cross(a0, e2))
    cx = a0y * e2z - a0z * e2y
    cy = a0z * e2x - a0x * e2z
    cz = a0x * e2y - a0y * e2x
    inv = 1.0 / math.sqrt(max(cx * cx + cy * cy + cz * cz, _EPS2))
    a1x = cx * inv
    a1y = cy * inv
    a1z = cz * inv
    # a2 = -normalize(cross(a1, a0)) = a0 x a1: a0 and a1 are orthonormal, so the cross product is
    # unit to rounding (the reference's renormalisation changes it by ~1e-16).
    a2x = a0y * a1z - a0z * a1y
    a2y = a0z * a1x - a0x * a1z
    a2z = a0x * a1y - a0y * a1x
    f = face[u]
    # R = [a0 | a1 | a2] (columns)
    f[R0 + 0] = a0x
    f[R0 + 1] = a1x
    f[R0 + 2] = a2x
    f[R0 + 3] = a0y
    f[R0 + 4] = a1y
    f[R0 + 5] = a2y
    f[R0 + 6] = a0z
    f[R0 + 7] = a1z
    f[R0 + 8] = a2z
    f[S_F] = (ll + abs(a2x * e2x + a2y * e2y + a2z * e2z)) * 0.5
    f[C0 + 0] = (v0x + verts[i1, 0] + verts[i2, 0]) / 3.0
    f[C0 + 1] = (v0y + verts[i1, 1] + verts[i2, 1]) / 3.0
    f[C0 + 2] = (v0z + verts[i1, 2] + verts[i2, 2]) / 3.0
    if with_normal:
        f[N0 + 0] = e1y * e2z - e1z * e2y
        f[N0 + 1] = e1z * e2x - e1x * e2z
        f[N0 + 2] = e1x * e2y - e1y * e2x
    # matrix_to_quaternion: best-conditioned branch (argmax, first on ties), normalise, w >= 0.
    # R[i, j] is a_j[i].
    m00 = a0x
    m11 = a1y
    m22 = a2z
    r21 = a1z
    r12 = a2y
    r02 = a2x
    r20 = a0z
    r10 = a0y
    r01 = a1x
    sq0 = 1 + m00 + m11 + m22
    sq1 = 1 + m00 - m11 - m22
    sq2 = 1 - m00 + m11 - m22
    sq3 = 1 - m00 - m11 + m22
    d21 = r21 - r12
    d02 = r02 - r20
    d10 = r10 - r01
    s21 = r21 + r12
    s02 = r02 + r20
    s10 = r10 + r01
    best = 0
    top = sq0
    if sq1 > top:
        best = 1
        top = sq1
    if sq2 > top:
        best = 2
        top = sq2
    if sq3 > top:
        best = 3
    if best == 0:
        qw, qx, qy, qz = sq0, d21, d02, d10
    elif best == 1:
        qw, qx, qy, qz = d21, sq1, s10, s02
    elif best == 2:
        qw, qx, qy, qz = d02, s10, sq2, s21
    else:
        qw, qx, qy, qz = d10, s02, s21, sq3
    inv = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if qw < 0:
        inv = -inv
    qw *= inv
    qx *= inv
    qy *= inv
    qz *= inv
    f[Q0 + 0] = qw
    f[Q0 + 1] = qx
    f[Q0 + 2] = qy
    f[Q0 + 3] = qz


# Columns of the per-Gaussian local attributes (M, LOCAL_COLS) float32: one row per deformed Gaussian, read in
# one stream (the frame is bound by memory traffic: 10 separate float64 columns cost ~1.6x more, cold).
L_POS = 0  # triangle: local position (3); barycentric: barycentric coordinates (3)
L_SHIFT = 3  # barycentric only: normal_offset_scale * tanh(offset)
L_ROT = 3  # normalised local rotation (w, x, y, z) (4), at L_ROT + 1 for barycentric
L_SCALE = 7  # linear local scale (3), at L_SCALE + 1 for barycentric
LOCAL_COLS = 10
LOCAL_COLS_BARY = 11


@nb.njit(**_NBC)
def triangle_kernel(face, run_face, run_m, run_len, run_row, local, out_pos, out_rot, out_scale):
    """GaussianAvatars: position R_f p s_f + c_f, rotation quat(R_f) (x) q, scale exp(log s) s_f.

    Runs q of consecutive avatar rows ``run_row[q] ..`` on one face ``run_face[q]``, whose local
    attributes are rows ``run_m[q] ..`` of local (M, LOCAL_COLS) float32 (p, q (w, x, y, z), exp(log s))."""
    for q in range(run_face.shape[0]):
        _triangle_run(q, face, run_face, run_m, run_len, run_row, local, out_pos, out_rot, out_scale)


@nb.njit(parallel=True, **_NBC)
def triangle_kernel_parallel(face, run_face, run_m, run_len, run_row, local, out_pos, out_rot, out_scale):
    """:func:`triangle_kernel` over numba's threads (prange over runs: disjoint rows)."""
    for q in nb.prange(run_face.shape[0]):
        _triangle_run(q, face, run_face, run_m, run_len, run_row, local, out_pos, out_rot, out_scale)


@nb.njit(inline="always", **_NBC)
def _quat_product(aw, ax, ay, az, bw, bx, by, bz, out_rot, row):
    """out_rot[row] = a (x) b written (x, y, z, w)."""
    out_rot[row, 0] = aw * bx + ax * bw + ay * bz - az * by
    out_rot[row, 1] = aw * by - ax * bz + ay * bw + az * bx
    out_rot[row, 2] = aw * bz + ax * by - ay * bx + az * bw
    out_rot[row, 3] = aw * bw - ax * bx - ay * by - az * bz


@nb.njit(inline="always", **_NBC)
def _triangle_run(q, face, run_face, run_m, run_len, run_row, local, out_pos, out_rot, out_scale):
    u = np.uint64(run_face[q])  # unsigned indices: numba emits no negative-index wrap-around, which kept LLVM from
    m0 = np.uint64(run_m[q])  # optimising this loop (~20 % of the kernel, measured)
    r0 = np.uint64(run_row[q])
    f0 = face[u, R0]
    f1 = face[u, R0 + 1]
    f2 = face[u, R0 + 2]
    f3 = face[u, R0 + 3]
    f4 = face[u, R0 + 4]
    f5 = face[u, R0 + 5]
    f6 = face[u, R0 + 6]
    f7 = face[u, R0 + 7]
    f8 = face[u, R0 + 8]
    aw = face[u, Q0]
    ax = face[u, Q0 + 1]
    ay = face[u, Q0 + 2]
    az = face[u, Q0 + 3]
    s = face[u, S_F]
    cx = face[u, C0]
    cy = face[u, C0 + 1]
    cz = face[u, C0 + 2]
    for j in range(np.uint64(run_len[q])):
        g = local[m0 + j]
        row = r0 + j
        px = np.float64(g[L_POS])
        py = np.float64(g[L_POS + 1])
        pz = np.float64(g[L_POS + 2])
        out_pos[row, 0] = (f0 * px + f1 * py + f2 * pz) * s + cx
        out_pos[row, 1] = (f3 * px + f4 * py + f5 * pz) * s + cy
        out_pos[row, 2] = (f6 * px + f7 * py + f8 * pz) * s + cz
        _quat_product(aw, ax, ay, az, np.float64(g[L_ROT]), np.float64(g[L_ROT + 1]), np.float64(g[L_ROT + 2]),
                      np.float64(g[L_ROT + 3]), out_rot, row)
        out_scale[row, 0] = g[L_SCALE] * s
        out_scale[row, 1] = g[L_SCALE + 1] * s
        out_scale[row, 2] = g[L_SCALE + 2] * s


@nb.njit(**_NBC)
def barycentric_kernel(face, run_face, run_m, run_len, run_row, verts, face_vids, local, inv_canonical, out_pos,
                       out_rot, out_scale):
    """FATE: position sum_k bary_k v_k + n_f shift, rotation quat(R_f) (x) q, scale exp(log s) s_f /
    s_f_canonical (inv_canonical per used face). Runs as in :func:`triangle_kernel`; local (M, LOCAL_COLS_BARY)
    float32 (bary (3), shift, q (w, x, y, z), exp(log s))."""
    for q in range(run_face.shape[0]):
        u = np.uint64(run_face[q])  # unsigned indices (see _triangle_run)
        m0 = np.uint64(run_m[q])
        r0 = np.uint64(run_row[q])
        i0 = np.uint64(face_vids[u, 0])
        i1 = np.uint64(face_vids[u, 1])
        i2 = np.uint64(face_vids[u, 2])
        v0x = verts[i0, 0]
        v0y = verts[i0, 1]
        v0z = verts[i0, 2]
        v1x = verts[i1, 0]
        v1y = verts[i1, 1]
        v1z = verts[i1, 2]
        v2x = verts[i2, 0]
        v2y = verts[i2, 1]
        v2z = verts[i2, 2]
        nx = face[u, N0]
        ny = face[u, N0 + 1]
        nz = face[u, N0 + 2]
        aw = face[u, Q0]
        ax = face[u, Q0 + 1]
        ay = face[u, Q0 + 2]
        az = face[u, Q0 + 3]
        r = face[u, S_F] * inv_canonical[u]
        for j in range(np.uint64(run_len[q])):
            g = local[m0 + j]
            row = r0 + j
            b0 = np.float64(g[L_POS])
            b1 = np.float64(g[L_POS + 1])
            b2 = np.float64(g[L_POS + 2])
            sh = np.float64(g[L_SHIFT])
            out_pos[row, 0] = (b0 * v0x + b1 * v1x + b2 * v2x) + nx * sh
            out_pos[row, 1] = (b0 * v0y + b1 * v1y + b2 * v2y) + ny * sh
            out_pos[row, 2] = (b0 * v0z + b1 * v1z + b2 * v2z) + nz * sh
            _quat_product(aw, ax, ay, az, np.float64(g[L_ROT + 1]), np.float64(g[L_ROT + 2]),
                          np.float64(g[L_ROT + 3]), np.float64(g[L_ROT + 4]), out_rot, row)
            out_scale[row, 0] = g[L_SCALE + 1] * r
            out_scale[row, 1] = g[L_SCALE + 2] * r
            out_scale[row, 2] = g[L_SCALE + 3] * r


def runs(ids: np.ndarray, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split ascending rows ``ids`` (M,) with face slots ``slots`` (M,) into runs of consecutive rows on
    one face: (run_face, run_m, run_len, run_row), int64 each."""
    ids = np.asarray(ids, np.int64)
    slots = np.asarray(slots, np.int64)
    if ids.size == 0:
        z = np.zeros(0, np.int64)
        return z, z, z, z
    brk = np.flatnonzero((np.diff(ids) != 1) | (np.diff(slots) != 0)) + 1
    start = np.concatenate([[0], brk]).astype(np.int64)
    length = np.diff(np.concatenate([start, [ids.size]])).astype(np.int64)
    return slots[start], start, length, ids[start]
