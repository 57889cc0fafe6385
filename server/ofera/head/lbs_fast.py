"""Subset LBS: the head's forward pass for only the vertices a consumer needs (numba, run time).

The streaming server deforms only the Gaussians an expression can move, and those sit on a few
thousand of the head's vertices. :class:`SubsetLBS` precomputes, for a fixed vertex subset S:

- the blend basis of S: expression directions (first ``n_expr`` components) and the pose correctives
  that are non-zero on S, one float32 row per coefficient, shape (n_expr + P, 3|S|);
- the identity template and the skinning weights of S;
- the joint regression of the expression basis (joints move with expressions).

Per frame, one numba kernel (no Python per element, no allocation) computes the joints, the 5 rigid
skinning transforms, ``v_po = v_id + B c`` four coefficients per pass (zero ones skipped), and for every
vertex of S ``v = (sum_k W_k A_k) v_po``, in float64 with fused multiply-adds (``parallel``: the same in vertex
blocks on numba's threads, the same bits). It is :func:`ofera.head.lbs.lbs` restricted to S;
:func:`subset_lbs_reference` is the plain reference (the full numpy LBS, then indexing) that tests
compare it with. The basis is stored as float32 (half the memory traffic); the relative error that adds
is below 1e-7 of each displacement (nanometres), far inside float32 output precision.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..jit import NB as _NB
from ..jit import atomic_add
from .lbs import HeadSubject, lbs

_NBC = {**_NB, "fastmath": {"contract"}}
"""The head's kernels: a product and the sum it joins fused (one rounding, FMA), nothing reassociated. Both the
serial and the threaded head compile so, the same bits; the blend's products fused took the parallel head 285 -> 265
us p50 on a cold CPU (175 -> 152 warm) on the capture at 100k, alternating in one process, outputs within 3e-17 m of
unfused (benchmarks/README.md, round sixteen)."""


@nb.njit(inline="always", **_NB)
def _transforms(expr, rot, coef, pose_rows, j_id, j_expr, parents, joints, a, n_expr):
    """Blend coefficients coef (C,) and skinning transforms a (K, 3, 4) of one frame (see _subset_lbs)."""
    n = expr.shape[0]
    k_joints = rot.shape[0]
    # Blend coefficients: expressions (zero-padded), then the used entries of the pose feature (R_k - I).
    for j in range(n_expr):
        coef[j] = expr[j] if j < n else 0.0
    for p in range(pose_rows.shape[0]):
        r = pose_rows[p]
        k = r // 9 + 1
        i = (r % 9) // 3
        c = r % 3
        coef[n_expr + p] = np.float64(rot[k, i, c]) - (1.0 if i == c else 0.0)
    # Joints of the expression-shaped head: j_id + J_E expr.
    for k in range(k_joints):
        for c in range(3):
            s = j_id[k, c]
            for j in range(min(n, j_expr.shape[2])):
                s += j_expr[k, c, j] * expr[j]
            joints[k, c] = s
    # World transforms G_k = G_parent [R_k | J_k - J_parent], then A_k = G_k with t - R(G_k) J_k.
    for k in range(k_joints):
        par = parents[k]
        for i in range(3):
            for c in range(3):
                if par < 0:
                    a[k, i, c] = rot[k, i, c]
                else:
                    a[k, i, c] = (a[par, i, 0] * rot[k, 0, c] + a[par, i, 1] * rot[k, 1, c]
                                  + a[par, i, 2] * rot[k, 2, c])
            if par < 0:
                a[k, i, 3] = joints[k, i]
            else:
                a[k, i, 3] = (a[par, i, 0] * (joints[k, 0] - joints[par, 0])
                              + a[par, i, 1] * (joints[k, 1] - joints[par, 1])
                              + a[par, i, 2] * (joints[k, 2] - joints[par, 2]) + a[par, i, 3])
    # Translations need every G_k first (children read their parent's G), so subtract R J afterwards.
    for k in range(k_joints):
        for i in range(3):
            joints_dot = a[k, i, 0] * joints[k, 0] + a[k, i, 1] * joints[k, 1] + a[k, i, 2] * joints[k, 2]
            coef_t = a[k, i, 3] - joints_dot
            a[k, i, 3] = coef_t


@nb.njit(inline="always", **_NB)
def _nonzero(coef, nz):
    """The indices of coef's non-zero entries, ascending, into nz; returns how many."""
    count = 0
    for j in range(coef.shape[0]):
        if coef[j] != 0.0:
            nz[count] = j
            count += 1
    return count


@nb.njit(inline="always", **_NB)
def _blend_skin(lo, hi, coef, v_id, basis_t, weights, a, acc, nz, count, out):
    """Vertices lo..hi-1 of the subset: blend shapes, then skinning (see _subset_lbs); nz[:count] the non-zero
    coefficients, weights (5, S) by joint. Each vertex's arithmetic is the same whichever block it is in (the
    parallel twin's bits)."""
    # Blend shapes: acc[r] = v_id[r] + sum_j coef[j] B[j, r] over the non-zero coefficients in ascending order,
    # four per pass over acc (one load and store of acc per four products: the passes were bound by those stores,
    # 1.5x, measured), each product added in turn, fused with its add (_NBC; no sum reassociated: the bits of one
    # fused axpy per coefficient).
    # Unsigned indices: numba then emits no negative-index wrap-around, which kept LLVM from vectorising the
    # loops (the head took 1.5x as long, measured).
    r0 = np.uint64(3 * lo)
    r1 = np.uint64(3 * hi)
    for r in range(r0, r1):
        acc[r] = v_id[r]
    q = 0
    while q + 4 <= count:
        c0, c1, c2, c3 = coef[nz[q]], coef[nz[q + 1]], coef[nz[q + 2]], coef[nz[q + 3]]
        b0, b1, b2, b3 = basis_t[nz[q]], basis_t[nz[q + 1]], basis_t[nz[q + 2]], basis_t[nz[q + 3]]
        for r in range(r0, r1):
            s = acc[r]
            s += np.float64(b0[r]) * c0
            s += np.float64(b1[r]) * c1
            s += np.float64(b2[r]) * c2
            s += np.float64(b3[r]) * c3
            acc[r] = s
        q += 4
    while q < count:
        cj = coef[nz[q]]
        col = basis_t[nz[q]]
        for r in range(r0, r1):
            acc[r] += np.float64(col[r]) * cj
        q += 1
    _skin5(lo, hi, weights, a, acc, out)


@nb.njit(inline="always", **_NB)
def _joint_sum(u0, u1, u2, u3, u4, x0, x1, x2, x3, x4):
    """sum_k u_k x_k over the five joints, added joint by joint in order (the bits of a loop over them)."""
    t = 0.0 + u0 * x0
    t += u1 * x1
    t += u2 * x2
    t += u3 * x3
    t += u4 * x4
    return t


@nb.njit(inline="always", **_NB)
def _skin5(lo, hi, weights, a, acc, out):
    """Skinning of vertices lo..hi-1: out[s, i] = (sum_k W[k, s] A_k[i]) . (v_po[s], 1), the five joints of every
    head model (HeadModel checks it) written out, the weights by joint (5, S), one output row i per pass: straight
    code over the joints, which LLVM runs across vertices in SIMD lanes (each sum still added joint by joint in
    order: the bits of the loop over joints it replaced, 0.23 -> 0.16 ms at 5k vertices on a cold CPU,
    benchmarks/README.md, round twelve)."""
    w0, w1, w2, w3, w4 = weights[0], weights[1], weights[2], weights[3], weights[4]
    three = np.uint64(3)
    for i in range(3):
        x00, x01, x02, x03 = a[0, i, 0], a[0, i, 1], a[0, i, 2], a[0, i, 3]
        x10, x11, x12, x13 = a[1, i, 0], a[1, i, 1], a[1, i, 2], a[1, i, 3]
        x20, x21, x22, x23 = a[2, i, 0], a[2, i, 1], a[2, i, 2], a[2, i, 3]
        x30, x31, x32, x33 = a[3, i, 0], a[3, i, 1], a[3, i, 2], a[3, i, 3]
        x40, x41, x42, x43 = a[4, i, 0], a[4, i, 1], a[4, i, 2], a[4, i, 3]
        for s in range(np.uint64(lo), np.uint64(hi)):
            u0, u1, u2, u3, u4 = w0[s], w1[s], w2[s], w3[s], w4[s]
            t0 = _joint_sum(u0, u1, u2, u3, u4, x00, x10, x20, x30, x40)
            t1 = _joint_sum(u0, u1, u2, u3, u4, x01, x11, x21, x31, x41)
            t2 = _joint_sum(u0, u1, u2, u3, u4, x02, x12, x22, x32, x42)
            t3 = _joint_sum(u0, u1, u2, u3, u4, x03, x13, x23, x33, x43)
            r = three * s
            out[s, i] = t0 * acc[r] + t1 * acc[r + np.uint64(1)] + t2 * acc[r + np.uint64(2)] + t3


@nb.njit(**_NBC)
def _subset_lbs(expr, rot, coef, v_id, basis_t, pose_rows, j_id, j_expr, parents, weights, joints, a, acc, nz,
                out):
    """expr (n,) f32/f64, rot (K, 3, 3) -> out (S, 3) float64. v_id (3S,) flat; basis_t (C, 3S); weights (5, S).
    Scratch: coef (C,), joints (K, 3), a (K, 3, 4), acc (3S,), nz (C,) int64."""
    _transforms(expr, rot, coef, pose_rows, j_id, j_expr, parents, joints, a, basis_t.shape[0] - pose_rows.shape[0])
    _blend_skin(0, out.shape[0], coef, v_id, basis_t, weights, a, acc, nz, _nonzero(coef, nz), out)


VERTEX_BLOCK = 512
"""Vertices a thread of the parallel head takes at a time (:func:`_blend_skin_shared`)."""


@nb.njit(inline="always", **_NB)
def blend_skin_shared(claims, coef, v_id, basis_t, weights, a, acc, nz, count, out):
    """:func:`_blend_skin` of blocks of :data:`VERTEX_BLOCK` vertices, each claimed through ``claims`` ((2,) int64,
    0 at the start, shared by the threads of one parallel loop: [0] blocks claimed, [1] blocks done): whichever thread
    is free takes the next, so one that wakes late takes fewer (a fixed half each made the first wait for the second
    at the loop's end). Returns the number of blocks (all claimed, not all done: see ``jit.wait_done``)."""
    s = out.shape[0]
    parts = (s + VERTEX_BLOCK - 1) // VERTEX_BLOCK
    while True:
        b = atomic_add(claims, 0, 1)
        if b >= parts:
            return parts
        _blend_skin(b * VERTEX_BLOCK, min(s, (b + 1) * VERTEX_BLOCK), coef, v_id, basis_t, weights, a, acc, nz, count,
                    out)
        atomic_add(claims, 1, 1)


@nb.njit(**_NBC)
def flame_transforms(y, expr, rot, coef, pose_rows, j_id, j_expr, parents, joints, a, nz, n_basis):
    """:func:`flame_values_kernel` (y (68,) -> expr (50,), rot (5, 3, 3)), then one frame's blend coefficients and
    skinning transforms (``n_basis`` rows of the basis): what precedes the vertex blocks. Returns the count of
    non-zero coefficients (their rows in nz)."""
    flame_values_kernel(y, expr.shape[0], expr, rot)
    _transforms(expr, rot, coef, pose_rows, j_id, j_expr, parents, joints, a, n_basis - pose_rows.shape[0])
    return _nonzero(coef, nz)


@nb.njit(parallel=True, **_NBC)
def _subset_lbs_parallel(threads, expr, rot, coef, v_id, basis_t, pose_rows, j_id, j_expr, parents, weights, joints,
                         a, acc, nz, out, claims):
    """:func:`_subset_lbs` with the vertices in blocks shared by ``threads`` of numba's threads (the same bits). It
    wakes the worker for the frame's threaded deformation, whose first region then starts sooner (benchmarks/README.md,
    round eleven); with the blocks claimed as the threads go, a late worker no longer holds up the first thread
    (round thirteen). claims: (2,) int64 scratch."""
    _transforms(expr, rot, coef, pose_rows, j_id, j_expr, parents, joints, a, basis_t.shape[0] - pose_rows.shape[0])
    count = _nonzero(coef, nz)
    claims[0] = claims[1] = 0
    for _t in nb.prange(threads):
        blend_skin_shared(claims, coef, v_id, basis_t, weights, a, acc, nz, count, out)


@nb.njit(**_NBC)
def flame_subset_lbs(y, expr, rot, coef, v_id, basis_t, pose_rows, j_id, j_expr, parents, weights, joints, a, acc, nz,
                     out):
    """:func:`flame_values_kernel` (y (68,) -> expr (50,), rot (5, 3, 3)) then :func:`_subset_lbs` of them, in one
    call: no check of rotations that are the identity by construction (root and neck), no second dispatch."""
    flame_values_kernel(y, expr.shape[0], expr, rot)
    _subset_lbs(expr, rot, coef, v_id, basis_t, pose_rows, j_id, j_expr, parents, weights, joints, a, acc, nz, out)


@nb.njit(parallel=True, **_NBC)
def flame_subset_lbs_parallel(threads, y, expr, rot, coef, v_id, basis_t, pose_rows, j_id, j_expr, parents, weights,
                              joints, a, acc, nz, out, claims):
    """:func:`flame_subset_lbs` with the blocks of :func:`_subset_lbs_parallel` (a parallel loop of its own: a
    parallel function called from another runs serially)."""
    count = flame_transforms(y, expr, rot, coef, pose_rows, j_id, j_expr, parents, joints, a, nz, basis_t.shape[0])
    claims[0] = claims[1] = 0
    for _t in nb.prange(threads):
        blend_skin_shared(claims, coef, v_id, basis_t, weights, a, acc, nz, count, out)


@nb.njit(**_NB)
def root_neck_identity(rot):
    """Whether rotations (K >= 2, 3, 3) have root and neck exactly the identity (one call: np.array_equal's several
    numpy calls cost ~0.1 ms on a cold CPU)."""
    for k in range(2):
        for i in range(3):
            for c in range(3):
                if rot[k, i, c] != (1.0 if i == c else 0.0):
                    return False
    return True


@nb.njit(**_NB)
def flame_values_kernel(y, n_expr, expr, rot):
    """FLAME values y (68,) -> expr (n_expr,) and rotations (5, 3, 3): root and neck identity; jaw and eyes
    from their 6D (pytorch3d rows: Gram-Schmidt of the two rows, third = cross), computed in float64."""
    for j in range(n_expr):
        expr[j] = y[j]
    for k in range(2):
        for i in range(3):
            for c in range(3):
                rot[k, i, c] = 1.0 if i == c else 0.0
    for k in range(3):
        o = n_expr + 6 * k
        a1x = np.float64(y[o])
        a1y = np.float64(y[o + 1])
        a1z = np.float64(y[o + 2])
        a2x = np.float64(y[o + 3])
        a2y = np.float64(y[o + 4])
        a2z = np.float64(y[o + 5])
        n = max(np.sqrt(a1x * a1x + a1y * a1y + a1z * a1z), 1e-12)
        b1x = a1x / n
        b1y = a1y / n
        b1z = a1z / n
        d = b1x * a2x + b1y * a2y + b1z * a2z
        cx = a2x - d * b1x
        cy = a2y - d * b1y
        cz = a2z - d * b1z
        n = max(np.sqrt(cx * cx + cy * cy + cz * cz), 1e-12)
        b2x = cx / n
        b2y = cy / n
        b2z = cz / n
        r = rot[k + 2]
        r[0, 0] = b1x
        r[0, 1] = b1y
        r[0, 2] = b1z
        r[1, 0] = b2x
        r[1, 1] = b2y
        r[1, 2] = b2z
        r[2, 0] = b1y * b2z - b1z * b2y
        r[2, 1] = b1z * b2x - b1x * b2z
        r[2, 2] = b1x * b2y - b1y * b2x


def check_flame_values(y) -> None:
    """ValueError naming the shape unless y holds one frame's 68 FLAME values (50 expression coefficients, then the
    jaw's and the eyes' 6D rotations)."""
    if np.shape(y) != (68,):
        raise ValueError(f"FLAME values must have 68 entries, got shape {np.shape(y)}")


_F32 = np.dtype(np.float32)  # (numpy's dtype of a built-in type is one object: an identity test)


def flame_values_arg(y) -> np.ndarray:
    """FLAME values y (68,), any numeric dtype (checked), as the C-contiguous float32 vector a bound kernel that runs
    the head itself takes each call (itself where it is one, else a copy); the kernel copies it into its head's
    buffer (:func:`load_flame_values`). Attribute checks only: numpy's ``shape`` and a slice assignment cost 37 us
    p50 on a cold CPU (benchmarks/README.md, round eighteen)."""
    if type(y) is np.ndarray and y.dtype is _F32 and y.shape == (68,) and y.strides == (4,):
        return y
    y = np.ascontiguousarray(y, np.float32)
    check_flame_values(y)
    return y


@nb.njit(**_NB)
def load_flame_values(head, y):
    """y (68,) into the head arguments' FLAME values (``head[0]``, ``FastSession.head_args``)."""
    dst = head[0]
    for i in range(dst.shape[0]):
        dst[i] = y[i]


class SubsetLBS:
    """LBS of a fixed vertex subset of one subject (see the module docstring).

    ``forward(expr (n,), rotations (K, 3, 3)) -> (S, 3) float64`` writes into a buffer owned by this
    object (reused every call: copy it to keep it). Not thread-safe: one instance per session; the
    precomputed arrays can be shared with :meth:`clone`.
    """

    def __init__(self, subject: HeadSubject, vertex_ids: np.ndarray, n_expr: int | None = None) -> None:
        model = subject.model
        ids = np.asarray(vertex_ids, np.int64).reshape(-1)
        if ids.size and (ids.min() < 0 or ids.max() >= model.num_vertices):
            raise ValueError(f"vertex ids must be in 0..{model.num_vertices - 1}")
        n_expr = model.expr_dims if n_expr is None else int(n_expr)
        if not 0 <= n_expr <= model.expr_dims:
            raise ValueError(f"n_expr {n_expr} outside 0..{model.expr_dims}")
        self.vertex_ids = ids
        self.n_expr = n_expr
        self.num_joints = model.num_joints
        s = ids.size
        expr_rows = np.asarray(model.exprdirs[ids, :, :n_expr], np.float64).reshape(3 * s, n_expr)
        pose = np.asarray(model.posedirs, np.float64).reshape(-1, model.num_vertices, 3)[:, ids, :]  # (36, S, 3)
        used = np.flatnonzero(np.abs(pose).reshape(pose.shape[0], -1).max(axis=1, initial=0.0) > 0)
        self.pose_rows = used.astype(np.int64)
        basis = np.concatenate([expr_rows.T, pose[used].reshape(len(used), 3 * s)], axis=0)
        self.basis_t = np.ascontiguousarray(basis, np.float32)  # (C, 3S): one row per coefficient
        self.v_id = np.ascontiguousarray(subject.v_id[ids], np.float64).reshape(-1)
        self.weights = np.ascontiguousarray(model.weights[ids].T, np.float64)  # (5, S): by joint (_skin5)
        self.j_id = np.ascontiguousarray(subject.j_id, np.float64)
        self.j_expr = np.ascontiguousarray(subject.j_expr[:, :, :n_expr], np.float64)
        self.parents = np.asarray(model.parents, np.int64)
        self._alloc()

    def _alloc(self) -> None:
        k = self.num_joints
        self._coef = np.zeros(self.basis_t.shape[0], np.float64)
        self._acc = np.zeros(3 * self.vertex_ids.size, np.float64)
        self._nz = np.zeros(self.basis_t.shape[0], np.int64)
        self._joints = np.zeros((k, 3), np.float64)
        self._a = np.zeros((k, 3, 4), np.float64)
        self.out = np.zeros((self.vertex_ids.size, 3), np.float64)
        self._claims = np.zeros(2, np.int64)  # the parallel kernels' shared block counters (claimed, done)
        self.threads = nb.get_num_threads()  # read once (a slow call on a cold CPU: see FastSession.threads)

    def clone(self) -> SubsetLBS:
        """Another instance sharing the (read-only) precomputed arrays, with its own scratch buffers."""
        other = object.__new__(SubsetLBS)
        other.__dict__.update(self.__dict__)
        other._alloc()
        return other

    @property
    def count(self) -> int:
        return int(self.vertex_ids.size)

    def forward_flame(self, y: np.ndarray, expr: np.ndarray, rot: np.ndarray, parallel: bool = False) -> np.ndarray:
        """FLAME values y (68,) float32 -> vertices (S, 3), as :meth:`forward` of their split (root and neck the
        identity), in one numba call; the split is left in expr (50,) and rot (5, 3, 3) float32. Needs n_expr >= 50.
        ``parallel``: as :meth:`forward`."""
        if self.n_expr < expr.shape[0]:
            raise ValueError(f"{expr.shape[0]} expression coefficients, this subset LBS uses {self.n_expr}")
        args = self.flame_args(y, expr, rot)
        if parallel:
            flame_subset_lbs_parallel(self.threads, *args, self._claims)
        else:
            flame_subset_lbs(*args)
        return self.out

    def flame_args(self, y: np.ndarray, expr: np.ndarray, rot: np.ndarray) -> tuple:
        """The arguments of :func:`flame_subset_lbs` for FLAME values y (68,) float32 and split buffers expr (50,),
        rot (5, 3, 3) float32: (y, expr, rot, coefficients, template, basis, pose rows, joint regressors, parents,
        weights, its scratch, out); a kernel that runs the head itself takes them (ofera.streaming.direct_delta)."""
        return (y, expr, rot, self._coef, self.v_id, self.basis_t, self.pose_rows, self.j_id, self.j_expr, self.parents,
                self.weights, self._joints, self._a, self._acc, self._nz, self.out)

    def forward(self, expr: np.ndarray, rotations: np.ndarray, parallel: bool = False) -> np.ndarray:
        """expr (n,) with n <= n_expr, rotations (K, 3, 3) (root, neck, jaw, eyes) -> vertices (S, 3). ``parallel``:
        the vertices in blocks on numba's threads, the same bits (no faster alone at 5k vertices: the blend is
        bound by reading the basis, 3 MB; it wakes the threads of a threaded deformation that follows)."""
        expr, rot = _floats(expr, 1), _floats(rotations, 3)  # (no numpy call for what the fast session passes)
        if expr.shape[0] > self.n_expr:
            raise ValueError(f"{expr.shape[0]} expression coefficients, this subset LBS uses {self.n_expr}")
        if rot.shape != (self.num_joints, 3, 3):
            raise ValueError(f"rotations must be ({self.num_joints}, 3, 3), got {rot.shape}")
        args = (expr, rot, self._coef, self.v_id, self.basis_t, self.pose_rows, self.j_id, self.j_expr, self.parents,
                self.weights, self._joints, self._a, self._acc, self._nz, self.out)
        if parallel:
            _subset_lbs_parallel(self.threads, *args, self._claims)
        else:
            _subset_lbs(*args)
        return self.out


_FLOATS = (np.dtype(np.float32), np.dtype(np.float64))


def _floats(a, ndim: int) -> np.ndarray:
    """``a`` as a C-contiguous float32 / float64 array of ``ndim`` dimensions (1: flattened; 3: (.., 3, 3)), itself
    when it already is one (other dtypes become float64)."""
    if isinstance(a, np.ndarray) and a.ndim == ndim and a.dtype in _FLOATS and a.flags.c_contiguous:
        return a
    a = np.asarray(a)
    if a.dtype not in _FLOATS:
        a = a.astype(np.float64)
    return np.ascontiguousarray(a.reshape(-1) if ndim == 1 else a.reshape(-1, 3, 3))


def subset_lbs_reference(subject: HeadSubject, expr: np.ndarray, rotations: np.ndarray,
                         vertex_ids: np.ndarray) -> np.ndarray:
    """The plain reference: the full numpy :func:`lbs` of one frame, then the subset (S, 3) float64."""
    verts, _ = lbs(subject, np.asarray(expr)[None], np.asarray(rotations)[None])
    return verts[0][np.asarray(vertex_ids, np.int64)]
