"""numba kernels of the fast deformation path (:mod:`.fast`); each mirrors the numpy reference
(:mod:`.frames`, :mod:`.deform`) formula for formula, writing float32 results in place.

Two passes per frame, one call each:

1. :func:`face_frames_kernel`: per used face, from its 3 vertices, the frame of :mod:`.frames`: the
   rotation R_f (columns a0, a1, a2), its unit quaternion (w >= 0, the branch :func:`matrix_to_quaternion`
   picks), the scale s_f, the centroid c_f and the unnormalised normal n_f (FATE), computed in float32 (the
   precision they are stored in) as float32 rows (structure of arrays) -> ``face`` (FACE_COLS[_BARY], U), in
   passes that vectorise (eight faces per instruction; for 9.5k faces 0.32 -> 0.14 ms back to back and 0.45 ->
   0.27 ms after a 13.9 ms gap against float64's four, measured on the Zen 1 VM of December 2026).
2. :func:`triangle_kernel` / :func:`barycentric_kernel`: per deformed Gaussian, the position, the
   rotation ``quat(R_f) (x) q_local`` written (x, y, z, w), and the scale, into its row of the full
   float32 output arrays. Gaussians are visited in runs of consecutive rows on one face (avatars keep
   a face's Gaussians together), so the face's values are loaded once per run.

Deviations from the reference: multiplications by reciprocals instead of divisions, fused multiply-adds,
a2 = a0 x a1 without renormalising (a0, a1 orthonormal), the centroid as v0 + (e1 + e2) / 3, and no
renormalisation of ``quat(R_f) (x) q_local`` (a product of unit quaternions); and at float32 rounding level (the
output's own precision: at most a few float32 ulps, e.g. 1.5e-8 m at 0.1 m), the face frames computed in float32
from the float64 vertices (each edge and v0 rounded once) and the per-Gaussian products of the triangle binding (and
the rotation and scale of the barycentric one) done in float32. The barycentric positions stay float64 (vertices
times barycentric weights). The quaternion of R_f is computed from its float32 entries.

Compiled with ``cache=True`` (on disk next to this file) and ``nogil=True``, so sessions computing in
a thread pool run in parallel.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..head.lbs_fast import VERTEX_BLOCK, blend_skin_shared, flame_subset_lbs, flame_transforms
from ..jit import F16_MAX, atomic_add, cycle_counter, f32_to_f16_bits, wait_done
from ..jit import NB as _NB

_NBC = {**_NB, "fastmath": {"contract"}}  # fused multiply-add allowed (no reassociation)
_EPS2 = np.float32(1e-20)  # frames._EPS2: clamp on squared lengths
_ONE, _THREE, _HALF = np.float32(1.0), np.float32(3.0), np.float32(0.5)  # float32 literals keep the passes float32

# Rows of the per-face frames (FACE_COLS[_BARY], U) float32, computed in float32.
R0 = 0  # R_f row-major, 9 values (R[i, j] at R0 + 3 i + j)
Q0 = 9  # quaternion (w, x, y, z)
S_F = 13  # scale s_f
C0 = 14  # centroid (3)
FACE_COLS = 17
N0 = 17  # unnormalised normal (3), barycentric only
FACE_COLS_BARY = 20


@nb.njit(**_NBC)
def face_frames_kernel(verts, face_vids, edges, face, with_normal):
    """verts (S, 3) f64; face_vids (U, 3) int rows of verts -> face (FACE_COLS[_BARY], U) f32, one row per
    column (structure of arrays). Scratch: edges (9, U) f32."""
    face_frames_range(0, face_vids.shape[0], verts, face_vids, edges, face, with_normal)


FACE_CHUNKS = 16
"""Chunks of faces :func:`face_frames_kernel_parallel`'s threads claim."""


@nb.njit(parallel=True, **_NBC)
def face_frames_kernel_parallel(verts, face_vids, edges, face, with_normal, threads, claims):
    """:func:`face_frames_kernel` over ``threads`` of numba's threads, which claim :data:`FACE_CHUNKS` chunks as they
    go (``claims`` (2,) int64 scratch): a thread that wakes late takes fewer."""
    claims[0] = claims[1] = 0
    for _t in nb.prange(threads):
        _face_chunks(verts, face_vids, edges, face, with_normal, claims)


@nb.njit(inline="always", **_NBC)
def _face_chunks(verts, face_vids, edges, face, with_normal, claims):
    """The :data:`FACE_CHUNKS` chunks of faces this thread claims (claims[0]) while any is left, each counted in
    claims[1] once done (``jit.wait_done``)."""
    n = face_vids.shape[0]
    step = (n + FACE_CHUNKS - 1) // FACE_CHUNKS
    b = atomic_add(claims, 0, 1)
    while b < FACE_CHUNKS:
        face_frames_range(min(n, b * step), min(n, (b + 1) * step), verts, face_vids, edges, face, with_normal)
        atomic_add(claims, 1, 1)
        b = atomic_add(claims, 0, 1)


@nb.njit(**_NBC)
def face_frames_range(lo, hi, verts, face_vids, edges, face, with_normal):
    """Faces lo..hi-1, in passes over the whole range. Each pass is a loop LLVM vectorises (eight faces per
    instruction): contiguous rows, no branch, at most 9 arrays written (beyond that it gives up on its alias
    checks) and not nested in another loop (a loop over blocks of faces kept it scalar, measured). Scalar, the
    square roots and divisions of one face are a chain no core overlaps: 2x slower. The bounds are taken unsigned: with
    a signed face index every access checks for a negative one (wrap-around), unless LLVM can prove it is not (a
    literal 0 start): 9.5k faces from a start of 0 passed at run time took 352 against 124 us (5 December 2026)."""
    lo, hi = np.uint64(lo), np.uint64(hi)
    _gather_edges(lo, hi, verts, face_vids, edges)
    _face_axes(lo, hi, edges, face)
    _face_scale_centroid(lo, hi, edges, face)
    _face_quaternion(lo, hi, face)
    if with_normal:
        _face_normal(lo, hi, edges, face)


@nb.njit(inline="always", **_NBC)
def _gather_edges(lo, hi, verts, face_vids, edges):
    """edges[:, u] = v0, e1 = v1 - v0, e2 = v2 - v0 of face u, each computed in float64 and rounded to float32."""
    for u in range(lo, hi):
        i0 = np.uint64(face_vids[u, 0])  # unsigned indices (see _triangle_run)
        i1 = np.uint64(face_vids[u, 1])
        i2 = np.uint64(face_vids[u, 2])
        for c in range(3):
            v0 = verts[i0, c]
            edges[c, u] = np.float32(v0)
            edges[3 + c, u] = np.float32(verts[i1, c] - v0)
            edges[6 + c, u] = np.float32(verts[i2, c] - v0)


@nb.njit(inline="always", **_NBC)
def _face_edges(edges, u):
    """(e1, e2) of face u, six float32 values."""
    return edges[3, u], edges[4, u], edges[5, u], edges[6, u], edges[7, u], edges[8, u]


@nb.njit(inline="always", **_NBC)
def _face_axes(lo, hi, edges, face):
    """R_f = [a0 | a1 | a2]: a0 = normalize(e1), a1 = normalize(a0 x e2), a2 = a0 x a1."""
    for u in range(lo, hi):
        e1x, e1y, e1z, e2x, e2y, e2z = _face_edges(edges, u)
        ll = e1x * e1x + e1y * e1y + e1z * e1z
        inv = _ONE / math.sqrt(ll if ll > _EPS2 else _EPS2)
        a0x = e1x * inv
        a0y = e1y * inv
        a0z = e1z * inv
        cx = a0y * e2z - a0z * e2y
        cy = a0z * e2x - a0x * e2z
        cz = a0x * e2y - a0y * e2x
        cc = cx * cx + cy * cy + cz * cz
        inv = _ONE / math.sqrt(cc if cc > _EPS2 else _EPS2)
        a1x = cx * inv
        a1y = cy * inv
        a1z = cz * inv
        # a2 = -normalize(cross(a1, a0)) = a0 x a1: a0 and a1 are orthonormal, so the cross product is
        # unit to rounding (the reference's renormalisation changes it by ~1e-16).
        face[R0 + 0, u] = a0x
        face[R0 + 1, u] = a1x
        face[R0 + 2, u] = a0y * a1z - a0z * a1y
        face[R0 + 3, u] = a0y
        face[R0 + 4, u] = a1y
        face[R0 + 5, u] = a0z * a1x - a0x * a1z
        face[R0 + 6, u] = a0z
        face[R0 + 7, u] = a1z
        face[R0 + 8, u] = a0x * a1y - a0y * a1x


@nb.njit(inline="always", **_NBC)
def _face_scale_centroid(lo, hi, edges, face):
    """s_f = (|e1| + |a2 . e2|) / 2 and the centroid c_f = v0 + (e1 + e2) / 3."""
    for u in range(lo, hi):
        e1x, e1y, e1z, e2x, e2y, e2z = _face_edges(edges, u)
        ll = e1x * e1x + e1y * e1y + e1z * e1z
        ll = math.sqrt(ll if ll > _EPS2 else _EPS2)
        h = face[R0 + 2, u] * e2x + face[R0 + 5, u] * e2y + face[R0 + 8, u] * e2z
        face[S_F, u] = (ll + (h if h >= 0 else -h)) * _HALF
        face[C0 + 0, u] = edges[0, u] + (e1x + e2x) / _THREE
        face[C0 + 1, u] = edges[1, u] + (e1y + e2y) / _THREE
        face[C0 + 2, u] = edges[2, u] + (e1z + e2z) / _THREE


@nb.njit(inline="always", **_NBC)
def _face_normal(lo, hi, edges, face):
    """FATE's unnormalised normal n_f = e1 x e2."""
    for u in range(lo, hi):
        e1x, e1y, e1z, e2x, e2y, e2z = _face_edges(edges, u)
        face[N0 + 0, u] = e1y * e2z - e1z * e2y
        face[N0 + 1, u] = e1z * e2x - e1x * e2z
        face[N0 + 2, u] = e1x * e2y - e1y * e2x


@nb.njit(inline="always", **_NBC)
def _face_quaternion(lo, hi, face):
    """matrix_to_quaternion of R_f: the best-conditioned branch (argmax, first on ties), normalised, w >= 0,
    chosen with selects (no branch: the loop vectorises). R[i, j] is a_j[i]."""
    for u in range(lo, hi):
        m00 = face[R0 + 0, u]
        r01 = face[R0 + 1, u]
        r02 = face[R0 + 2, u]
        r10 = face[R0 + 3, u]
        m11 = face[R0 + 4, u]
        r12 = face[R0 + 5, u]
        r20 = face[R0 + 6, u]
        r21 = face[R0 + 7, u]
        m22 = face[R0 + 8, u]
        sq0 = _ONE + m00 + m11 + m22
        sq1 = _ONE + m00 - m11 - m22
        sq2 = _ONE - m00 + m11 - m22
        sq3 = _ONE - m00 - m11 + m22
        d21 = r21 - r12
        d02 = r02 - r20
        d10 = r10 - r01
        s21 = r21 + r12
        s02 = r02 + r20
        s10 = r10 + r01
        qw, qx, qy, qz, top = sq0, d21, d02, d10, sq0
        pick = sq1 > top
        qw, qx, qy, qz = (d21 if pick else qw), (sq1 if pick else qx), (s10 if pick else qy), (s02 if pick else qz)
        top = sq1 if pick else top
        pick = sq2 > top
        qw, qx, qy, qz = (d02 if pick else qw), (s10 if pick else qx), (sq2 if pick else qy), (s21 if pick else qz)
        top = sq2 if pick else top
        pick = sq3 > top
        qw, qx, qy, qz = (d10 if pick else qw), (s02 if pick else qx), (s21 if pick else qy), (sq3 if pick else qz)
        inv = _ONE / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        inv = -inv if qw < 0 else inv
        face[Q0 + 0, u] = qw * inv
        face[Q0 + 1, u] = qx * inv
        face[Q0 + 2, u] = qy * inv
        face[Q0 + 3, u] = qz * inv


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


F16_BLOCK = 256
"""Rows a block of the f16 writer computes into its float32 scratch before it converts them to half in one go."""


def f16_blocks(run_row: np.ndarray, run_len: np.ndarray) -> np.ndarray:
    """(B + 1,) int64: the first run of each block of :func:`triangle_f16_kernel` (and the run count last). A block
    is consecutive runs on consecutive rows, grown run by run while it holds fewer than :data:`F16_BLOCK` rows
    (so at most F16_BLOCK + the longest run)."""
    starts = [0]
    count = 0
    for q in range(run_row.shape[0]):
        if count and (run_row[q] != run_row[starts[-1]] + count or count >= F16_BLOCK):
            starts.append(q)
            count = 0
        count += int(run_len[q])
    starts.append(int(run_row.shape[0]))
    return np.asarray(starts if run_row.shape[0] else [0], np.int64)


@nb.njit(**_NBC)
def triangle_f16_kernel(face, run_face, run_m, run_len, run_row, local, psign, rsign, scratch_pos, scratch_rot,
                        scratch_scale, out_pos, out_rot, out_scale):
    """:func:`triangle_kernel`'s values times the wire's coordinate signs, written as IEEE half bits straight into a
    dense f16 frame's fields (out_pos (N 3,), out_rot (N 4,), out_scale (N 3,) uint16): the bits the f16 encoding of
    triangle_kernel's state gives (the same float32 arithmetic, one rounding to half), without the state. False if
    any value is NaN, infinite or beyond +-65504 (the rows are then unspecified).

    Block by block (:func:`f16_blocks`): its runs are computed into the float32 scratch (F16_BLOCK + the longest
    run, 3 | 4 | 3), which stays in the first-level cache, then converted by flat loops that vectorise: converting
    each value as it is computed (one scalar conversion and a 2-byte store each) made the kernel 1.5x slower than
    the float32 one, and gained nothing over writing the state."""
    ok = True
    signs = (psign[0], psign[1], psign[2], rsign[0], rsign[1], rsign[2], rsign[3])  # values: never reloaded
    runs = run_face.shape[0]
    q = 0
    while q < runs:  # the blocks of f16_blocks, found on the way (reading `blocks` was 2-8 % slower, cold)
        first = run_row[q]
        count = 0
        while q < runs and run_row[q] == first + count and count < F16_BLOCK:
            signed_run(q, count, face, run_face, run_m, run_len, local, signs, scratch_pos, scratch_rot, scratch_scale)
            count += run_len[q]
            q += 1
        ok &= _to_half(count, first, scratch_pos, out_pos)
        ok &= _to_half(count, first, scratch_rot, out_rot)
        ok &= _to_half(count, first, scratch_scale, out_scale)
    return ok


@nb.njit(parallel=True, **_NBC)
def triangle_f16_kernel_parallel(face, blocks, threads, claims, run_face, run_m, run_len, run_row, local, psign, rsign,
                                 scratch_pos, scratch_rot, scratch_scale, out_pos, out_rot, out_scale):
    """:func:`triangle_f16_kernel` over ``threads`` of numba's threads, which claim its blocks (``blocks``,
    :func:`f16_blocks`: disjoint rows) as they go (``claims`` (1,) int64 scratch; a fixed half each made the first
    thread wait for a worker that woke late), the scratch (>= threads, .., 3 | 4 | 3) one per thread. Same arguments,
    and ``blocks``, ``threads``, ``claims`` second to fourth."""
    s0, s1, s2, s3, s4, s5, s6 = psign[0], psign[1], psign[2], rsign[0], rsign[1], rsign[2], rsign[3]
    bad = 0
    claims[0] = 0
    for t in nb.prange(threads):
        bad += _f16_blocks(face, blocks, claims, run_face, run_m, run_len, run_row, local, (s0, s1, s2, s3, s4, s5, s6),
                           scratch_pos[t], scratch_rot[t], scratch_scale[t], out_pos, out_rot, out_scale)
    return bad == 0


@nb.njit(inline="always", **_NBC)
def _f16_blocks(face, blocks, claims, run_face, run_m, run_len, run_row, local, signs, scratch_pos, scratch_rot,
                scratch_scale, out_pos, out_rot, out_scale):
    """The blocks of :func:`triangle_f16_kernel_parallel` this thread claims (claims[0]) while any is left, on its own
    scratch; returns how many had a value out of the half range."""
    bad = 0
    b = atomic_add(claims, 0, 1)
    while b < blocks.shape[0] - 1:
        first = run_row[blocks[b]]
        count = 0
        for q in range(blocks[b], blocks[b + 1]):
            signed_run(q, count, face, run_face, run_m, run_len, local, signs, scratch_pos, scratch_rot,
                       scratch_scale)
            count += run_len[q]
        ok = _to_half(count, first, scratch_pos, out_pos)
        ok &= _to_half(count, first, scratch_rot, out_rot)
        ok &= _to_half(count, first, scratch_scale, out_scale)
        bad += 0 if ok else 1
        b = atomic_add(claims, 0, 1)
    return bad


@nb.njit(**_NBC)
def flame_f16_kernel(head, face_vids, edges, face, run_face, run_m, run_len, run_row, local, psign, rsign,
                     scratch_pos, scratch_rot, scratch_scale, out_pos, out_rot, out_scale, ticks):
    """The head of FLAME values (``head``: ``FastSession.head_args``, its vertices into head[15]), the used faces'
    frames, then :func:`triangle_f16_kernel` into a dense f16 frame's fields, in one call. ``ticks`` (3,) uint64 the
    cycle counter at the start, once the vertices are written and at the end. Returns (ok, the head's share of the
    call's time by those ticks)."""
    ticks[0] = cycle_counter()
    flame_subset_lbs(*head[:16])
    ticks[1] = cycle_counter()
    face_frames_range(0, face_vids.shape[0], head[15], face_vids, edges, face, False)
    ok = triangle_f16_kernel(face, run_face, run_m, run_len, run_row, local, psign, rsign, scratch_pos, scratch_rot,
                             scratch_scale, out_pos, out_rot, out_scale)
    return ok, head_share(ticks)


@nb.njit(parallel=True, **_NBC)
def flame_f16_kernel_parallel(head, face_vids, edges, face, blocks, threads, face_claims, claims, run_face, run_m,
                              run_len, run_row, local, psign, rsign, scratch_pos, scratch_rot, scratch_scale, out_pos,
                              out_rot, out_scale, ticks):
    """:func:`flame_f16_kernel` on ``threads`` of numba's threads, in one parallel region: the head's vertex blocks,
    then the face chunks, then the f16 blocks, each claimed as the threads go, each stage started once the one before
    is done (``jit.wait_done``: a thread waits only for work a running thread claimed). Before round seventeen the
    head, the face frames and the f16 kernel each took a region of their own, with Python and numba's dispatch
    between them: head + frame p50 1246 -> 1161 us threaded (benchmarks/README.md). ``face_claims`` (2,), ``claims``
    (1,) int64 scratch. Returns (ok, the head's share)."""
    ticks[0] = cycle_counter()
    y, expr, rot, coef, v_id, basis_t, pose_rows, j_id, j_expr, parents, weights, joints, a, acc, nz, verts, hc = head
    nonzero = flame_transforms(y, expr, rot, coef, pose_rows, j_id, j_expr, parents, joints, a, nz, basis_t.shape[0])
    parts = (verts.shape[0] + VERTEX_BLOCK - 1) // VERTEX_BLOCK
    hc[0] = hc[1] = face_claims[0] = face_claims[1] = claims[0] = 0
    s0, s1, s2, s3, s4, s5, s6 = psign[0], psign[1], psign[2], rsign[0], rsign[1], rsign[2], rsign[3]
    bad = 0
    for t in nb.prange(threads):
        blend_skin_shared(hc, coef, v_id, basis_t, weights, a, acc, nz, nonzero, verts)
        wait_done(hc, parts)
        if t == 0:
            ticks[1] = cycle_counter()
        _face_chunks(verts, face_vids, edges, face, False, face_claims)
        wait_done(face_claims, FACE_CHUNKS)
        bad += _f16_blocks(face, blocks, claims, run_face, run_m, run_len, run_row, local, (s0, s1, s2, s3, s4, s5, s6),
                           scratch_pos[t], scratch_rot[t], scratch_scale[t], out_pos, out_rot, out_scale)
    return bad == 0, head_share(ticks)


@nb.njit(inline="always", **_NB)
def head_share(ticks):
    """A kernel that ran the head ends: ticks[2] = now; (vertices - start) / (end - start) of ticks (3,) uint64, 0
    without a cycle counter."""
    ticks[2] = cycle_counter()
    return (ticks[1] - ticks[0]) / (ticks[2] - ticks[0]) if ticks[2] > ticks[0] else 0.0


@nb.njit(inline="always", **_NBC)
def signed_run(q, count, face, run_face, run_m, run_len, local, signs, scratch_pos, scratch_rot, scratch_scale):
    """Run q's Gaussians (:func:`_triangle_gaussian`) times the wire signs into rows count.. of a block's float32
    scratch: the f16 writer's, and the direct delta frames' (ofera.streaming.direct_delta). The signs are a tuple:
    loaded once, where array elements would be reloaded after every store to the scratch, which might alias them."""
    p0, p1, p2, q0, q1, q2, q3 = signs
    u = np.uint64(run_face[q])
    m0 = np.uint64(run_m[q])
    f = _face_of_run(face, u)
    for j in range(np.uint64(run_len[q])):
        x, y, z, rx, ry, rz, rw, sx, sy, sz = _triangle_gaussian(f, local[m0 + j])
        c = np.uint64(count) + j
        scratch_pos[c, 0] = x * p0
        scratch_pos[c, 1] = y * p1
        scratch_pos[c, 2] = z * p2
        scratch_rot[c, 0] = rx * q0
        scratch_rot[c, 1] = ry * q1
        scratch_rot[c, 2] = rz * q2
        scratch_rot[c, 3] = rw * q3
        scratch_scale[c, 0] = sx
        scratch_scale[c, 1] = sy
        scratch_scale[c, 2] = sz


@nb.njit(inline="always", **_NBC)
def _to_half(count, first, scratch, out):
    """Rows 0..count-1 of scratch (.., k) float32 -> half bits at rows first.. of out (N k,); False if any is
    beyond the half range."""
    k = np.uint64(scratch.shape[1])
    flat = scratch.reshape(-1)
    base = np.uint64(first) * k
    ok = True
    for i in range(np.uint64(count) * k):
        v = flat[i]
        ok &= abs(v) <= F16_MAX
        out[base + i] = f32_to_f16_bits(v)
    return ok


@nb.njit(inline="always", **_NBC)
def _face_of_run(face, u):
    """The 17 float32 frame values of used face u (R_f row-major, q_f (w, x, y, z), s_f, c_f)."""
    return (face[R0, u], face[R0 + 1, u], face[R0 + 2, u], face[R0 + 3, u], face[R0 + 4, u], face[R0 + 5, u],
            face[R0 + 6, u], face[R0 + 7, u], face[R0 + 8, u], face[Q0, u], face[Q0 + 1, u], face[Q0 + 2, u],
            face[Q0 + 3, u], face[S_F, u], face[C0, u], face[C0 + 1, u], face[C0 + 2, u])


@nb.njit(inline="always", **_NBC)
def _triangle_gaussian(f, g):
    """One Gaussian of the triangle binding in float32 (the face frame's float64 values rounded once, the output's
    own precision): f = _face_of_run(..), g = its row of local -> position (3), rotation (x, y, z, w), scale (3).
    Both writers use this function, so they compute the same bits."""
    f0, f1, f2, f3, f4, f5, f6, f7, f8, aw, ax, ay, az, s, cx, cy, cz = f
    px = g[L_POS]
    py = g[L_POS + 1]
    pz = g[L_POS + 2]
    bw = g[L_ROT]
    bx = g[L_ROT + 1]
    by = g[L_ROT + 2]
    bz = g[L_ROT + 3]
    return ((f0 * px + f1 * py + f2 * pz) * s + cx, (f3 * px + f4 * py + f5 * pz) * s + cy,
            (f6 * px + f7 * py + f8 * pz) * s + cz,
            aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz,
            g[L_SCALE] * s, g[L_SCALE + 1] * s, g[L_SCALE + 2] * s)


@nb.njit(inline="always", **_NBC)
def _triangle_run(q, face, run_face, run_m, run_len, run_row, local, out_pos, out_rot, out_scale):
    """One run of :func:`triangle_kernel`."""
    u = np.uint64(run_face[q])  # unsigned indices: numba emits no negative-index wrap-around, which kept LLVM from
    m0 = np.uint64(run_m[q])  # optimising this loop (~20 % of the kernel, measured)
    r0 = np.uint64(run_row[q])
    f = _face_of_run(face, u)
    for j in range(np.uint64(run_len[q])):
        row = r0 + j
        x, y, z, rx, ry, rz, rw, sx, sy, sz = _triangle_gaussian(f, local[m0 + j])
        out_pos[row, 0] = x
        out_pos[row, 1] = y
        out_pos[row, 2] = z
        out_rot[row, 0] = rx
        out_rot[row, 1] = ry
        out_rot[row, 2] = rz
        out_rot[row, 3] = rw
        out_scale[row, 0] = sx
        out_scale[row, 1] = sy
        out_scale[row, 2] = sz


@nb.njit(inline="always", **_NBC)
def _quat_product(aw, ax, ay, az, bw, bx, by, bz, out_rot, row):
    """out_rot[row] = a (x) b written (x, y, z, w)."""
    out_rot[row, 0] = aw * bx + ax * bw + ay * bz - az * by
    out_rot[row, 1] = aw * by - ax * bz + ay * bw + az * bx
    out_rot[row, 2] = aw * bz + ax * by - ay * bx + az * bw
    out_rot[row, 3] = aw * bw - ax * bx - ay * by - az * bz


@nb.njit(**_NBC)
def barycentric_kernel(face, run_face, run_m, run_len, run_row, verts, face_vids, local, inv_canonical, out_pos,
                       out_rot, out_scale):
    """FATE: position sum_k bary_k v_k + n_f shift, rotation quat(R_f) (x) q, scale exp(log s) s_f /
    s_f_canonical (inv_canonical per used face). Runs as in :func:`triangle_kernel`; local (M, LOCAL_COLS_BARY)
    float32 (bary (3), shift, q (w, x, y, z), exp(log s)). Positions in float64 from the float64 vertices."""
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
        nx = np.float64(face[N0, u])
        ny = np.float64(face[N0 + 1, u])
        nz = np.float64(face[N0 + 2, u])
        aw = face[Q0, u]
        ax = face[Q0 + 1, u]
        ay = face[Q0 + 2, u]
        az = face[Q0 + 3, u]
        r = np.float32(face[S_F, u] * inv_canonical[u])
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
            _quat_product(aw, ax, ay, az, g[L_ROT + 1], g[L_ROT + 2], g[L_ROT + 3], g[L_ROT + 4], out_rot, row)
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
