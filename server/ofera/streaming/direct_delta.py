"""The deformation writes a solo session's delta frames (PROTOCOL.md 7.1): no float32 state in between.

A delta frame needs, per candidate Gaussian (the avatar's movable ones), its deformed position, rotation and scale
only long enough to compare them with what the client holds and to encode what moved. :class:`DirectDelta` runs
the fast path's per-Gaussian deformation (``ofera.avatar.kernels``, the same float32 arithmetic) block by block
into a scratch that stays in the cache, and the delta encoder's selection and encoding passes
(``ofera.streaming.encode_fast``, the same functions) over each block straight away: the bytes and the held codes
are those of ``DeltaEncoder.encode`` on ``FastSession.deform``'s state, without writing that state and reading it
back (5 MB a frame at 100k Gaussians). On the 2-core Zen 1 VM of December 2026 that alone gained nothing (the frame
is bound by arithmetic there, not memory); what it buys is the second core: see below (benchmarks/README.md, round
eight).

    direct = DirectDelta(fast_avatar, encoder, head=session.head_args())  # once per session: runs, blocks, faces
    if not encoder.next_is_key:                         # key frames (join, resync, key_interval) take the state
        written = session.flame_delta(y, direct)  # FastSession: its thread choice; head, frame and body in one call
        data = encoder.encode_written(seq, t, timing, written.counts[0], written.buf, written.end, start_ns)

Both cores: every block has its own list of faces (:func:`block_faces`) and its own rows of every scratch, so a block
on another core reads nothing another block writes. The serial kernel runs the blocks in order into the outputs in
place; the threaded one shares them out as it goes (:func:`deform_delta_kernel_parallel`): thread 0 from the first
block on, in place, the others from the last down into a spare set, from which their blocks are then copied into
place. Either way the outputs end in candidate order.

The plain reference is ``DeltaEncoder.encode(FastSession.deform(verts))``; tests compare them byte for byte.
Triangle binding only (the barycentric binding's positions are float64 sums of vertices: the state path runs).
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from typing import NamedTuple

import numba
import numba as nb
import numpy as np
from ofera_protocol.delta import DELTA_KEYS, ROT_FIELD64, DeltaEncoder
from ofera_protocol.fast_encodings import HEADER_ROOM

from ..avatar import kernels as K
from ..head.lbs_fast import (
    VERTEX_BLOCK,
    blend_skin_shared,
    flame_subset_lbs,
    flame_transforms,
    flame_values_arg,
    load_flame_values,
)
from ..jit import NB as _NB
from ..jit import Bound, atomic_add, cycle_counter, wait_done
from .encode_fast import (
    NO_LUT,
    NO_TABLE,
    compact_range,
    copy_rows,
    decode_moved,
    delta_body_kernel,
    encode_positions,
    encode_rotations_f16,
    encode_rotations_q13,
    encode_scales,
    flag_run,
    rotations_u64,
    write_body,
)

_NBC = {**_NB, "fastmath": {"contract"}}  # as the deformation kernels: the same fused multiply-adds, the same bits
BLOCK = 2048
"""Candidates a block deforms into the scratch before the selection runs over them (plus the last run's rest): 80 kB
of float32 scratch, in the second-level cache. Larger blocks give the selection's and encoding's SIMD loops longer runs
(a block's ~40 % of moved rotations fill few AVX-512 vectors at 256): DirectDelta.select p50 on the capture at 100k,
alternating in one process on the Intel Xeon of 5 December 2026, serial after a 13.9 ms sleep: 256 2.79 ms, 1024
2.48, 2048 2.33, 4096 2.33; two threads 1.88, 1.75, 1.71, 1.60 (benchmarks/README.md, round ten)."""


def candidate_runs(fast_ids: np.ndarray, gface: np.ndarray, rows: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Runs of consecutive candidates j (state rows ``rows`` (K,)) whose deformed rows (their places m in the fast
    path's ascending ``fast_ids`` (M,)) are consecutive and on one face (``gface`` (M,) used-face slots):
    (run_face, run_m, run_len, blocks), int64; ``blocks`` (B + 1,) the first run of each block of at least
    :data:`BLOCK` candidates (the run count last). ValueError if a candidate is not deformed by the fast path."""
    m = np.searchsorted(fast_ids, rows)
    if rows.size and (m.max() >= fast_ids.size or not np.array_equal(fast_ids[np.minimum(m, fast_ids.size - 1)],
                                                                      rows)):
        raise ValueError("a delta candidate is not among the Gaussians the fast path deforms")
    slot = gface[m]
    brk = np.flatnonzero((np.diff(m) != 1) | (np.diff(slot) != 0)) + 1
    start = np.concatenate([[0], brk]).astype(np.int64) if rows.size else np.zeros(0, np.int64)
    length = np.diff(np.append(start, rows.size)).astype(np.int64)
    blocks, count = [0], 0
    for q, n in enumerate(length):
        if count >= BLOCK:
            blocks.append(q)
            count = 0
        count += int(n)
    if blocks[-1] != start.size:
        blocks.append(int(start.size))
    return slot[start].astype(np.int64), m[start].astype(np.int64), length, np.asarray(blocks, np.int64)


def block_starts(run_len: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """(B + 1,) int64: each block's first candidate, and the candidate count last."""
    return np.concatenate([[0], np.cumsum(run_len)]).astype(np.int64)[blocks]


def block_rows(run_len: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """(K,) int64: each candidate's row in its block's scratch (its index minus the block's first)."""
    at = block_starts(run_len, blocks)
    return np.arange(at[-1], dtype=np.int64) - np.repeat(at[:-1], np.diff(at))


@nb.njit(**_NBC)
def _deform_block(q0, q1, face, run_face, run_m, run_len, local, signs, sp, sr, ss):
    """Runs q0..q1-1 into rows 0.. of the scratch (signed, as the f16 writer's); returns the rows written."""
    count = 0
    for q in range(q0, q1):
        K.signed_run(q, count, face, run_face, run_m, run_len, local, signs, sp, sr, ss)
        count += run_len[q]
    return count


@nb.njit(**_NB)
def _select_block(ja, jb, sp, sr, ss, ones3, ones4, tol, dec, flags, word, counts, lists, out_moved):
    """Flags of candidates ja..jb-1 (their values in the scratch rows 0..) and their compaction, appended to the
    selection and the lists (``counts`` so far -> after), as encode_fast._select does for a state."""
    c = jb - ja
    flag_run(sp.reshape(-1)[:3 * c], sr.reshape(-1)[:4 * c], ss.reshape(-1)[:3 * c], dec[0, ja:jb], dec[1, ja:jb],
             dec[2, ja:jb], dec[3, ja:jb], dec[4, ja:jb], dec[5, ja:jb], dec[6, ja:jb], dec[7, ja:jb],
             dec[8, ja:jb], dec[9, ja:jb], flags[ja:jb], ones3, ones4, tol)
    return compact_range(flags, word, ja, jb, counts, lists, out_moved)


@nb.njit(**_NBC)
def _delta_block(q13, b, t, base, counts, w, verts, geo, codes, held, out, scratch):
    """Block b on thread t's scratch: its faces' frames, its runs deformed into the scratch (signed, as the f16
    writer's), the selection, then one pass per attribute over what moved (q13 codes, else f16 bits), the held codes
    and their decodings updated. Its outputs continue a stream of blocks whose outputs start at candidate ``base``:
    ``counts`` (n, n_p, n_r, n_s) so far (indices into the outputs), ``w`` positions of the stream sent whole so far.
    Returns (n, n_p, n_r, n_s, w, ok) after it; ok False if an f16 value is out of range. Argument groups: see
    :meth:`DirectDelta.select`."""
    block_u, block_j, face_vids, run_face, run_m, run_len, blocks, local, brow, signs = geo
    lo, k, step, table, scale_lut, rot_lut, tol, ones3, ones4 = codes
    ids, held_p, held_r, held_s, dec, flags, work = held
    out_moved, out_wide, out_res, out_pos, out_rot, out_scale = out
    sp, sr, ss, gathered, edges, face = scratch[0][t], scratch[1][t], scratch[2][t], scratch[3], scratch[4], scratch[5]
    K.face_frames_range(block_u[b], block_u[b + 1], verts, face_vids, edges, face, False)
    ja = block_j[b]
    jb = ja + _deform_block(blocks[b], blocks[b + 1], face, run_face, run_m, run_len, local, signs, sp, sr, ss)
    word = flags[: (flags.shape[0] >> 3) << 3].view(np.uint64)
    n0, p0, r0, s0 = counts
    n, n_p, n_r, n_s = _select_block(ja, jb, sp, sr, ss, ones3, ones4, tol, dec, flags, word, counts, work,
                                     out_moved)
    # (the decodings of the codes sent are left to settle_kernel, after the frame)
    wb, ok = encode_positions(q13, sp, brow, ids, work[0, p0:], n_p - p0, ones3, lo, k, step, held_p, dec,
                              out_wide[p0:], out_res[p0 - w:], out_pos[base + w:], False)
    if q13:  # (the rotations' gather scratch: the block's own rows, which no other block uses)
        encode_rotations_q13(sr, brow, ids, work[1, r0:], n_r - r0, ones4, rot_lut, held_r, dec, gathered[4 * ja:],
                             out_rot[r0:], False)
    else:
        ok &= encode_rotations_f16(sr, brow, ids, work[1, r0:], n_r - r0, ones4, held_r, dec, out_rot[r0:], False)
    ok &= encode_scales(q13, ss, brow, ids, work[2, s0:], n_s - s0, table, scale_lut, held_s, dec, out_scale[s0:],
                        False)
    return n, n_p, n_r, n_s, w + wb, ok


FRONT, BACK = 1, 1 << 32  # a claim's increment of the shared counter: blocks taken from the front, from the back


@nb.njit(**_NBC)
def _front(q13, blocks, verts, geo, codes, held, out, scratch, claims):
    """The blocks from the first on, in order, on thread 0, into the outputs in place (one stream from candidate 0):
    all of them, or (``claims`` a (1,) int64 counter shared with :func:`_back`) each once claimed. Returns (n, n_p, w,
    n_r, n_s, ok, the number of blocks done)."""
    counts = (0, 0, 0, 0)
    w, ok, b = 0, True, 0
    while b < blocks:
        if claims.shape[0] and _claim(claims, FRONT, blocks) < 0:
            break
        n, n_p, n_r, n_s, w, okb = _delta_block(q13, b, 0, 0, counts, w, verts, geo, codes, held, out, scratch)
        counts = (n, n_p, n_r, n_s)
        ok &= okb
        b += 1
    n, n_p, n_r, n_s = counts
    return n, n_p, w, n_r, n_s, ok, b


@nb.njit(inline="always", **_NB)
def _claim(claims, step, blocks):
    """Take the next block from the front (step FRONT) or the back (BACK): its number from that end (0 = the first /
    the last), or -1 when none is left. The counter holds both ends' counts (front in the low 32 bits) in one int64,
    so a claim sees both at once: a claim succeeds only while front + back < blocks, so the two ends never take the
    same block."""
    c = atomic_add(claims, 0, step)
    front, back = c & (BACK - 1), c >> 32
    if front + back >= blocks:
        return -1
    return front if step == FRONT else back


@nb.njit(**_NBC)
def _back(q13, t, blocks, verts, geo, codes, held, spare, scratch, claims, res):
    """Blocks from the last one down, each once claimed, on thread t >= 1, each into ``spare`` from its first
    candidate (a stream of its own): res[b] = its (n, n_p, w, n_r, n_s, ok, t)."""
    block_j = geo[1]
    while True:
        x = _claim(claims, BACK, blocks)
        if x < 0:
            return
        b = blocks - 1 - x
        j = block_j[b]
        n, n_p, n_r, n_s, w, ok = _delta_block(q13, b, t, j, (j, j, j, j), 0, verts, geo, codes, held, spare, scratch)
        res[b, 0], res[b, 1], res[b, 2], res[b, 3], res[b, 4], res[b, 5], res[b, 6] = (
            n - j, n_p - j, w, n_r - j, n_s - j, ok, t)


@nb.njit(**_NBC)
def deform_delta_kernel(q13, head, verts, geo, codes, held, out, scratch, body, buf, ticks):
    """encode_fast's delta kernels (``q13``: delta_q13_kernel, else delta_f16_kernel) on the candidates deformed from
    the subset vertices ``verts`` (S, 3) float64, single-threaded: block after block into the outputs in place. First
    the head, if ``head`` holds its arguments (``SubsetLBS.flame_args``, writing ``verts``, and a (2,) int64 scratch;
    with a y of size 0 the vertices are given). Last the message body, if ``buf`` is not empty: the bytes of
    ``delta_body`` (``body``: its arguments but the buffer and the counts) at ``HEADER_ROOM``. ``ticks`` (3,) uint64:
    the cycle counter at the start, once the vertices are written and at the end. Returns (n, n_p, w, n_r, n_s, ok,
    where the body ends, the head's share of the kernel's time by those ticks)."""
    ticks[0] = cycle_counter()
    if head[0].shape[0]:
        flame_subset_lbs(*head[:16])
    ticks[1] = cycle_counter()
    n, n_p, w, n_r, n_s, ok, _ = _front(q13, geo[6].shape[0] - 1, verts, geo, codes, held, out, scratch,
                                        np.zeros(0, np.int64))
    end = _body(body, buf, n, n_p, w, n_r, n_s)
    return n, n_p, w, n_r, n_s, ok, end, K.head_share(ticks)


@nb.njit(inline="always", **_NB)
def _body(body, buf, n, n_p, w, n_r, n_s):
    """The message body (delta_body_kernel) into buf, or nothing if buf is empty; returns where it ends."""
    if buf.shape[0] == 0:
        return 0
    keys, count, id_runs, flags, moved, wide, res, pos, rot, scl, r3, r6, rr, rs, _ = body
    return delta_body_kernel(buf, HEADER_ROOM, keys, count, id_runs, flags, moved, wide, n, n_p, w, n_r, n_s, res,
                             pos, rot, scl, r3, r6, rr, rs)


@nb.njit(parallel=True, **_NBC)
def deform_delta_kernel_parallel(q13, threads, head, verts, geo, codes, held, out, spare, scratch, body, buf, claims,
                                 res, ticks):
    """:func:`deform_delta_kernel` on ``threads`` of numba's threads. The head's vertices first (if ``head`` holds its
    arguments), in blocks the threads claim (``ofera.head.lbs_fast``); each then waits for the last block to be done
    (``jit.wait_done``) and goes on to the delta blocks: one parallel region, where a head called before took one of
    its own and the Python between (head + delta p50 1288 -> 1259 and 1282 -> 1255 us in process, round seventeen).
    The threads share
    the delta blocks as they go: thread 0 takes them from the first on and writes in place (as the serial kernel), the
    others from the last down, each block into ``spare`` (arrays shaped as ``out``). Then, with a message buffer, two
    threads write the body from the outputs where they are (``encode_fast.write_body``: one the changed mask, the
    other the rest); without one, the back blocks are copied to where the front's outputs end, in block order, a loop
    per back thread (with two threads one iteration, which numba runs on the calling thread: the copies done by the
    thread that wrote them, after a spin-wait for the front's end, measured the same, round thirteen). Every value
    is computed by the same code either way: the same bytes. A split
    fixed in advance (two chunks of equal candidate counts, round eleven) left the second thread 0.30 ms p50 behind
    the first: it wakes later, and where the face moves most, more of its Gaussians are encoded. ``claims`` (1,) and
    ``res`` (B + 1, 7) int64 scratch. (A parallel loop takes arrays and scalars only: the groups are taken apart here
    and rebuilt in the loop.)"""
    ticks[0] = cycle_counter()
    y, expr, rot, coef, v_id, basis_t, pose_rows, j_id, j_expr, parents, weights, joints, a, acc, nz, _, hclaims = head
    parts = nonzero = 0
    if y.shape[0]:
        nonzero = flame_transforms(y, expr, rot, coef, pose_rows, j_id, j_expr, parents, joints, a, nz,
                                   basis_t.shape[0])
        parts = (verts.shape[0] + VERTEX_BLOCK - 1) // VERTEX_BLOCK
        hclaims[0] = hclaims[1] = 0
    else:
        ticks[1] = cycle_counter()
    block_u, block_j, face_vids, run_face, run_m, run_len, blocks, local, brow, signs = geo
    s0, s1, s2, s3, s4, s5, s6 = signs
    lo, k, step, table, scale_lut, rot_lut, tol, ones3, ones4 = codes
    ids, held_p, held_r, held_s, dec, flags, work = held
    out_moved, out_wide, out_res, out_pos, out_rot, out_scale = out
    sp_moved, sp_wide, sp_res, sp_pos, sp_rot, sp_scale = spare
    sp, sr, ss, gathered, edges, face = scratch
    count = blocks.shape[0] - 1
    claims[0] = 0
    for t in nb.prange(threads):
        if parts:
            blend_skin_shared(hclaims, coef, v_id, basis_t, weights, a, acc, nz, nonzero, verts)
            wait_done(hclaims, parts)
            if t == 0:
                ticks[1] = cycle_counter()
        g = (block_u, block_j, face_vids, run_face, run_m, run_len, blocks, local, brow, (s0, s1, s2, s3, s4, s5, s6))
        c = (lo, k, step, table, scale_lut, rot_lut, tol, ones3, ones4)
        h = (ids, held_p, held_r, held_s, dec, flags, work)
        x = (sp, sr, ss, gathered, edges, face)
        if t == 0:
            n, n_p, w, n_r, n_s, ok, done = _front(q13, count, verts, g, c, h,
                                                   (out_moved, out_wide, out_res, out_pos, out_rot, out_scale),
                                                   x, claims)
            res[count, 0], res[count, 1], res[count, 2], res[count, 3], res[count, 4], res[count, 5] = (
                n, n_p, w, n_r, n_s, ok)
            res[count, 6] = done
        else:
            _back(q13, t, count, verts, g, c, h, (sp_moved, sp_wide, sp_res, sp_pos, sp_rot, sp_scale), x,
                  claims, res)
    first = res[count, 6]  # the first block a back thread did
    if buf.shape[0]:  # the message body from the outputs where they are, on two threads (no placement)
        n, n_p, w, n_r, n_s, ok = _totals(res, first, count)
        keys, ids_count, id_runs, flags_b, moved_b, wide_b, res_b, pos_b, rot_b, scl_b, r3, r6, rr, rs, back = body
        bk_moved, bk_wide, bk_res, bk_pos, bk_rot, bk_scl = back
        for part in nb.prange(2):
            write_body(part, buf, HEADER_ROOM, keys, ids_count, id_runs, flags_b, (n, n_p, w, n_r, n_s),
                       (res[count, 0], res[count, 1], res[count, 2], res[count, 3], res[count, 4]),
                       (moved_b, wide_b, res_b, pos_b, rot_b, scl_b),
                       (bk_moved, bk_wide, bk_res, bk_pos, bk_rot, bk_scl), (res, first, count, block_j),
                       (r3, r6, rr, rs))
        totals, outputs = (n, n_p, w, n_r, n_s), (moved_b, wide_b, res_b, pos_b, rot_b, scl_b)
        end = write_body(2, buf, HEADER_ROOM, keys, ids_count, id_runs, flags_b, totals, totals, outputs, outputs,
                         (res, first, first, block_j), (r3, r6, rr, rs))  # (part 2 writes nothing: where it ends)
        return n, n_p, w, n_r, n_s, ok, end, K.head_share(ticks)
    for t in nb.prange(1, threads):
        n, n_p, w, n_r, n_s = res[count, 0], res[count, 1], res[count, 2], res[count, 3], res[count, 4]
        for b in range(first, count):  # (where each back block goes: after the front's and the back blocks before it)
            if res[b, 6] == t:
                _place_block(block_j[b], (n, n_p, w, n_r, n_s), res[b],
                             (sp_moved, sp_wide, sp_res, sp_pos, sp_rot, sp_scale),
                             (out_moved, out_wide, out_res, out_pos, out_rot, out_scale))
            n, n_p, w, n_r, n_s = n + res[b, 0], n_p + res[b, 1], w + res[b, 2], n_r + res[b, 3], n_s + res[b, 4]
    n, n_p, w, n_r, n_s, ok = _totals(res, first, count)
    return n, n_p, w, n_r, n_s, ok, 0, K.head_share(ticks)


@nb.njit(inline="always", **_NB)
def _place_block(base, at, counts, src, dst):
    """A block's outputs (``counts``: its row of the threaded kernel's ``res``, (n, n_p, w, n_r, n_s) first), from row
    ``base`` of the output group ``src``, to rows ``at`` (n, n_p, w, n_r, n_s) of ``dst``. Element by element over
    flat views (a row assignment costs tens of ns in numba)."""
    n, n_p, w, n_r, n_s = at
    cn, cp, cw, cr, cs = counts[0], counts[1], counts[2], counts[3], counts[4]
    copy_rows(src[0], dst[0], 1, base, n, cn)
    copy_rows(src[1], dst[1], 1, base, n_p, cp)
    copy_rows(src[2].reshape(-1), dst[2].reshape(-1), 3, base, n_p - w, cp - cw)
    copy_rows(src[3].reshape(-1), dst[3].reshape(-1), 3, base, w, cw)
    copy_rows(src[4].reshape(-1), dst[4].reshape(-1), dst[4].size // dst[4].shape[0], base, n_r, cr)
    copy_rows(src[5].reshape(-1), dst[5].reshape(-1), 3, base, n_s, cs)


@nb.njit(**_NB)
def _totals(res, first, count):
    """(n, n_p, w, n_r, n_s, ok) of the front's blocks (row ``count``) and the back blocks (rows first..count-1)."""
    n, n_p, w, n_r, n_s = res[count, 0], res[count, 1], res[count, 2], res[count, 3], res[count, 4]
    ok = res[count, 5] != 0
    for b in range(first, count):
        n, n_p, w, n_r, n_s = n + res[b, 0], n_p + res[b, 1], w + res[b, 2], n_r + res[b, 3], n_s + res[b, 4]
        ok &= res[b, 5] != 0
    return n, n_p, w, n_r, n_s, ok


@nb.njit(**_NB)
def settle_kernel(q13, parallel, counts, work, res, block_j, ids, held_p, held_r, held_s, lo, step, scale_lut, rot_lut,
                  dec):
    """The decodings of the codes the last kernel call sent (its encoding passes leave them: ``decode=False``), which
    the next frame's selection compares with (encode_fast.decode_moved). Its lists of what moved are ``work``'s rows
    0-2: from candidate 0 those of the serial kernel (``counts``: its (n_p, n_r, n_s)) or of the threaded kernel's
    front thread (``parallel``: res[B]), then those of each back block from its first candidate (res[b] for b from
    res[B, 6] on)."""
    count = res.shape[0] - 1
    front, first = counts, count
    if parallel:
        front, first = (res[count, 1], res[count, 3], res[count, 4]), res[count, 6]
    decode_moved(q13, work[:, 0:], front, ids, held_p, held_r, held_s, lo, step, scale_lut, rot_lut, dec)
    for b in range(first, count):
        decode_moved(q13, work[:, block_j[b]:], (res[b, 1], res[b, 3], res[b, 4]), ids, held_p, held_r, held_s, lo,
                     step, scale_lut, rot_lut, dec)


def block_faces(run_face: np.ndarray, blocks: np.ndarray, face_vids: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each block's own list of faces: (run_face renumbered into the concatenated lists, block_u (B + 1,) the first
    face of each block's list and the total last, face_vids of the concatenated lists (F, 3)). A face with Gaussians
    in two blocks is in both lists (computed twice, the same values): no thread reads a face another writes, whichever
    blocks each takes."""
    out, lists, first = np.empty_like(run_face), [], [0]
    for b in range(blocks.size - 1):
        q0, q1 = blocks[b], blocks[b + 1]
        own, inverse = np.unique(run_face[q0:q1], return_inverse=True)
        out[q0:q1] = first[-1] + inverse.reshape(-1)
        lists.append(own)
        first.append(first[-1] + own.size)
    faces = np.concatenate(lists) if lists else np.zeros(0, np.int64)
    return out, np.asarray(first, np.int64), np.ascontiguousarray(face_vids[faces], np.int64)


class DirectDelta:
    """One delta session's frames written by the deformation (see the module docstring): ``fast`` a FastAvatar
    (triangle binding), ``encoder`` the session's DeltaEncoder (the numba kernel set) whose candidates the fast
    path deforms; ``threads``: the threads a threaded frame shares its blocks among (numba's thread count by default);
    ``head``: the session's head arguments (``FastSession.head_args``), which the kernel then runs itself first
    (:meth:`head_select`). ValueError when it cannot (another binding, a candidate the fast path keeps neutral)."""

    def __init__(self, fast, encoder: DeltaEncoder, threads: int | None = None, head: tuple | None = None) -> None:
        from .encode_fast import NumbaKernels

        if getattr(fast, "binding_type", None) != "triangle":
            raise ValueError("the deformation writes delta frames for the triangle binding only")
        if not isinstance(encoder.kernels, NumbaKernels):
            raise ValueError("a direct delta session needs the numba kernel set")
        a = fast.arrays
        gface = np.repeat(a.run_face, a.run_len)  # used-face slot of each deformed Gaussian (rows of local)
        self.fast, self.encoder = fast, encoder
        self.threads = max(1, numba.config.NUMBA_NUM_THREADS if threads is None else int(threads))
        run_face, run_m, run_len, blocks = candidate_runs(a.ids, gface, encoder.rows)
        run_face, block_u, face_vids = block_faces(run_face, blocks, a.face_vids)
        block_j = block_starts(run_len, blocks)[:-1]
        signs = tuple(np.float32(x) for x in (*encoder.psign, *encoder.rsign))  # loaded once (signed_run)
        self.geo = (block_u, block_j, face_vids, run_face, run_m, run_len, blocks, a.local, block_rows(run_len, blocks),
                    signs)
        ones3, ones4 = np.ones(3, np.float32), np.ones(4, np.float32)
        self.q13 = encoder.format.encoding == "q13"
        if self.q13:
            table = encoder.kernels.table(encoder.thresholds)
            if table is None:
                raise ValueError("the q13 scale range is too narrow for the numba lookup table")
            self.codes = (encoder.lo, encoder.k, encoder.step, table, encoder.lut, ROT_FIELD64, encoder.tol, ones3,
                          ones4)
        else:  # f16: stand-ins of the q13 arguments (unused)
            unused = np.ones(3)  # lo, k, step
            self.codes = (unused, unused, unused, NO_TABLE, NO_LUT, NO_LUT, encoder.tol, ones3, ones4)
        e = encoder
        held_r, out_rot = e.held_r, e._rot
        if not self.q13:  # f16: each rotation's four half bit patterns as one uint64 (encode_rotations_f16)
            held_r, out_rot = rotations_u64(held_r), rotations_u64(out_rot)
        self.held = (e.ids, e.held_p, held_r, e.held_s, e.dec, e._flags, e._work)
        self.out = (e._moved, e._wide, e._res, e._pos, out_rot, e._scale)
        # the blocks threads 1.. take are written here, then placed (one thread never does: the outputs stand in)
        self.spare = tuple(np.zeros_like(a) for a in self.out) if self.threads > 1 else self.out
        self.claims = np.zeros(1, np.int64)
        self.res = np.zeros((blocks.size, 7), np.int64)  # a row a block, the front's last (the threaded kernel)
        rows = BLOCK + int(run_len.max(initial=0))
        self.scratch = (*(np.zeros((self.threads, rows, c), np.float32) for c in (3, 4, 3)),
                        e._work[3:].view(np.float32).reshape(-1), np.zeros((9, block_u[-1]), np.float32),
                        np.zeros((K.FACE_COLS, block_u[-1]), np.float32))
        self.ticks = np.zeros(3, np.uint64)  # the kernel's cycle counter: start, vertices written, end
        # the message body's arguments (head_select; select writes none): the encoder's, and the spare outputs as
        # flat uint8 (what the threaded kernel's other threads wrote, which the body takes from where they are)
        back = (self.spare[0], self.spare[1].view(np.uint8), *(a.reshape(-1).view(np.uint8) for a in self.spare[2:]))
        self.body = (DELTA_KEYS, e.format.count, e.id_runs, e._flags, e._moved, e._wide.view(np.uint8), *e._flat,
                     *e._row_bytes, back)
        self._no_buf = np.zeros(0, np.uint8)
        # the decodings of what a frame sent, written after it (settle): the last call's lists, until settled
        lo, _, step, _, scale_lut, rot_lut = self.codes[:6]
        self._settle = Bound(_settle_bound, (self.q13, e._work, self.res, block_j, e.ids, e.held_p, held_r, e.held_s,
                                             lo, step, scale_lut, rot_lut, e.dec))
        self._settle_lock = threading.Lock()
        self._buf: np.ndarray | None = None  # the next head_select's message buffer, if settle took it
        self._unsettled: tuple[bool, tuple[int, int, int]] | None = None
        encoder.pending = _settle_of(weakref.ref(self))  # (before the encoder's own frames: key frames, the state path)
        # no head (select): arrays of the head's types, y empty (one compiled kernel for both)
        like = fast.lbs.flame_args(np.zeros(68, np.float32), np.zeros(50, np.float32), np.zeros((5, 3, 3), np.float32))
        self._no_head = (*(np.zeros((0,) * x.ndim, x.dtype) for x in like), np.zeros(2, np.int64))
        self.head = head
        if head is None:
            return
        if len(head) != len(self._no_head) or head[0].shape != (68,) or head[15].shape != (fast.lbs.count, 3):
            raise ValueError("head must be the session's FastSession.head_args()")
        # the kernels' arguments held by numba: their 55 arrays in tuples took 35-40 us more a frame to type and unbox
        # (jit.Fixed)
        self._serial = Bound(_serial_bound, (self.q13, head, head[15], self.geo, self.codes, self.held, self.out,
                                             self.scratch, self.body, self.ticks))
        self._parallel = Bound(_parallel_bound, (self.q13, self.threads, head, head[15], self.geo, self.codes,
                                                 self.held, self.out, self.spare, self.scratch, self.body, self.claims,
                                                 self.res, self.ticks))

    @property
    def blocks(self) -> int:
        """Blocks of candidates (:data:`BLOCK`)."""
        return int(self.geo[6].size - 1)

    def settle(self) -> None:
        """Write the decodings of the codes the last frame sent into the encoder's ``dec`` (``settle_kernel``), if
        not yet done: the frame's kernel leaves them (about 0.1 ms of its time at 100k) for after the frame is on its
        way, and the next frame's selection reads them. Every kernel call here and the encoder's own ``encode``
        settle first, so a caller only chooses when the work runs (a session: once the client has read its frame,
        through ``FastSession.defer``). Thread-safe: a settle running on another thread is waited for."""
        with self._settle_lock:
            self._settle_now()

    def _settle_now(self) -> None:
        """:meth:`settle`, the lock held; with a head, the next frame's message buffer is taken from the pool too
        (31 us p50 of a cold frame's path, round eighteen)."""
        pending, self._unsettled = self._unsettled, None
        if pending is not None:
            self._settle(*pending)
            if self.head is not None and self._buf is None:
                self._buf = self.encoder.body_buffer()

    def select(self, verts: np.ndarray, parallel: bool = False) -> tuple[int, ...]:
        """Fill the encoder's selection and outputs for subset vertices ``verts`` (S, 3) float64 C-contiguous (a
        head's output), on numba's threads if ``parallel``, and update what it holds: (n, n_p, w, n_r, n_s), the
        decodings owed (:meth:`settle`). ValueError if an f16 value sent is NaN, infinite or beyond +-65504. Through
        numba's dispatcher (the kernels of :meth:`head_select`, which sessions run)."""
        self.settle()
        if parallel:
            *counts, ok, _, _ = deform_delta_kernel_parallel(self.q13, self.threads, self._no_head, verts, self.geo,
                                                             self.codes, self.held, self.out, self.spare, self.scratch,
                                                             self.body, self._no_buf, self.claims, self.res,
                                                             self.ticks)
        else:
            *counts, ok, _, _ = deform_delta_kernel(self.q13, self._no_head, verts, self.geo, self.codes, self.held,
                                                    self.out, self.scratch, self.body, self._no_buf, self.ticks)
        self._unsettled = (parallel, (counts[1], counts[3], counts[4]))
        return _checked(counts, ok)

    def head_select(self, y: np.ndarray, parallel: bool = False) -> Written:
        """:meth:`select` of the head's vertices for FLAME values y (68,) float32, the head run first and the
        message body written last by the same kernel call (``head`` given), into a buffer of the encoder's
        (``body_buffer``), for its ``encode_written``. The vertices are left in the head's buffer."""
        if self.head is None:
            raise ValueError("this DirectDelta was made without the session's head")
        y = flame_values_arg(y)
        with self._settle_lock:  # (once a session's settle ran after the last frame: nothing but its buffer to take)
            self._settle_now()
            buf, self._buf = self._buf, None
        if buf is None:
            buf = self.encoder.body_buffer()
        n, n_p, w, n_r, n_s, ok, end, share = (self._parallel if parallel else self._serial)(buf, y)
        self._unsettled = (parallel, (n_p, n_r, n_s))
        if not ok:
            raise ValueError(_OUT_OF_RANGE)
        return Written((n, n_p, w, n_r, n_s), buf, end, share)


def _settle_of(direct: weakref.ref) -> Callable[[], None]:
    """``DirectDelta.settle`` of the DirectDelta ``direct`` refers to, while it lives: what its encoder runs before
    reading its held state (``DeltaEncoder.pending``), without a reference cycle (an encoder and its DirectDelta hold
    MBs of buffers, which a cycle would keep until the next full garbage collection)."""

    def settle() -> None:
        alive = direct()
        if alive is not None:
            alive.settle()

    return settle


class Written(NamedTuple):
    """A delta frame :meth:`DirectDelta.head_select` wrote: its selection's ``counts`` (n, n_p, w, n_r, n_s), its
    message buffer ``buf`` with the body in ``HEADER_ROOM..end``, and ``head_share``, the part of the kernel's time
    until the head's vertices were written (its cycle counter; 0 on a target without one)."""

    counts: tuple[int, ...]
    buf: np.ndarray
    end: int
    head_share: float


_OUT_OF_RANGE = "a moved Gaussian has NaN, infinity or values beyond +-65504 (f16)"


def _checked(counts: list[int], ok: bool) -> tuple[int, ...]:
    if not ok:
        raise ValueError(_OUT_OF_RANGE)
    return tuple(counts)


@nb.njit(**_NBC)
def _serial_bound(fixed, buf, y):
    """:func:`deform_delta_kernel` with DirectDelta's arguments (jit.Bound), the frame's FLAME values y first copied
    into the head's buffer."""
    q13, head, verts, geo, codes, held, out, scratch, body, ticks = fixed.args
    load_flame_values(head, y)
    return deform_delta_kernel(q13, head, verts, geo, codes, held, out, scratch, body, buf, ticks)


@nb.njit(**_NB)
def _settle_bound(fixed, parallel, counts):
    """:func:`settle_kernel` with DirectDelta's arguments (jit.Bound)."""
    q13, work, res, block_j, ids, held_p, held_r, held_s, lo, step, scale_lut, rot_lut, dec = fixed.args
    settle_kernel(q13, parallel, counts, work, res, block_j, ids, held_p, held_r, held_s, lo, step, scale_lut,
                  rot_lut, dec)


@nb.njit(**_NBC)
def _parallel_bound(fixed, buf, y):
    """:func:`deform_delta_kernel_parallel` with DirectDelta's arguments (jit.Bound), the frame's FLAME values y first
    copied into the head's buffer."""
    q13, threads, head, verts, geo, codes, held, out, spare, scratch, body, claims, res, ticks = fixed.args
    load_flame_values(head, y)
    return deform_delta_kernel_parallel(q13, threads, head, verts, geo, codes, held, out, spare, scratch, body, buf,
                                        claims, res, ticks)


def warm_up(fast, threads: bool = False) -> None:
    """Compile (or load from the on-disk cache) the kernels for both delta encodings, and their parallel twin if
    ``threads``, on ``fast``'s neutral Gaussians (a key frame, then a delta frame), not on a session's second frame."""
    from ofera_protocol import FrameFormat, make_quant

    from .encode_fast import delta_encoder

    n = fast.neutral
    session = fast.session(pool_size=1)
    y = np.zeros(68, np.float32)
    y[50:] = [1, 0, 0, 0, 1, 0] * 3  # the identity rotations' 6D
    for encoding in ("q13", "f16"):
        quant = make_quant(n.position, n.scale) if encoding == "q13" else None
        encoder = delta_encoder(FrameFormat(encoding, fast.count, False, quant, delta=True),
                                candidates=fast.arrays.ids)
        encoder.encode(0, 0, {}, n.position, n.rotation, n.scale)
        direct = DirectDelta(fast, encoder, head=session.head_args())  # (the kernels bound to a head, as sessions')
        for parallel in (False, True) if threads else (False,):
            direct.head_select(y, parallel)
            direct.settle()
