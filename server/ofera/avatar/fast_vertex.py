"""The fast per-frame path of vertex-bound (LAM) avatars: sparse morph-target blend + vertex-offset binding (numba).

    fast = FastVertexAvatar(avatar)           # once per avatar: precomputed, read-only, shareable
    session = fast.session()                  # once per stream: scratch buffers and an output pool
    verts = session.blend(weights)            # ARKit weights (51,) -> (S, 3): the moving vertices only
    state = session.deform(verts)             # GaussianState (float32, full N), from the pool

It computes what the plain numpy REFERENCE computes (:func:`morph_blend_reference`, then
:class:`.deform.VertexDeformer`), within float rounding:

- Which Gaussians move: ``gaussians="exact"`` (default) deforms every Gaussian whose vertex has a non-zero
  row in any morph target; all others are exactly at their neutral values in every frame. ``"all"`` deforms
  every Gaussian (tests); a boolean mask (N,) picks any set.
- Precomputed per avatar: the vertex subset S those Gaussians bind to, its template (float64), each morph
  target as a sparse list over S (CSR: ``indptr`` (E+1,), ``rows`` (nnz,), ``deltas`` (nnz, 3) float32; a
  LAM target touches 2-5 thousand of the 20 thousand vertices), and per moving Gaussian its slot in S and
  its offset (float64).
- Per frame: :func:`morph_blend_kernel` (``v_S = template_S + sum_j w_j delta_j`` over the non-zero
  weights only) and :func:`vertex_offset_kernel` (``position = v_S[slot] + offset`` into the rows of the
  float32 output, whose other rows and whose rotations and scales already hold the neutral values: LAM's
  rotations and scales do not change, see :mod:`.lam`).

Outputs come from :class:`.fast.StatePool` (never written again while referenced; recycled when dropped).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..head.lbs import HeadSubject
from ..jit import NB as _NB
from .binding import VertexBinding
from .deform import make_deformer
from .fast import StatePool
from .state import GaussianState

_EYE5 = np.broadcast_to(np.eye(3), (5, 3, 3))


@nb.njit(**_NB)
def morph_blend_kernel(weights, base, indptr, rows, deltas, out):
    """out (S, 3) f64 = base (S, 3) f64 + sum_j weights[j] * delta_j, delta_j = rows[indptr[j]:indptr[j+1]] of S
    with deltas (nnz, 3) f32; zero weights are skipped. weights (n,) with n <= len(indptr) - 1."""
    for i in range(base.shape[0]):
        out[i, 0] = base[i, 0]
        out[i, 1] = base[i, 1]
        out[i, 2] = base[i, 2]
    n = min(weights.shape[0], indptr.shape[0] - 1)
    for j in range(n):
        w = np.float64(weights[j])
        if w != 0.0:
            for k in range(indptr[j], indptr[j + 1]):
                r = rows[k]
                out[r, 0] += w * np.float64(deltas[k, 0])
                out[r, 1] += w * np.float64(deltas[k, 1])
                out[r, 2] += w * np.float64(deltas[k, 2])


@nb.njit(**_NB)
def vertex_offset_kernel(verts, slot, ids, offset, out_pos):
    """out_pos[ids[m]] = verts[slot[m]] + offset[m] (float32 rows of the full output); verts (S, 3) f64,
    slot (M,) int64 rows of verts, ids (M,) int64 avatar rows, offset (M, 3) f64."""
    for m in range(ids.shape[0]):
        s = slot[m]
        row = ids[m]
        out_pos[row, 0] = verts[s, 0] + offset[m, 0]
        out_pos[row, 1] = verts[s, 1] + offset[m, 1]
        out_pos[row, 2] = verts[s, 2] + offset[m, 2]


def morph_blend_reference(head, weights: np.ndarray) -> np.ndarray:
    """The plain reference of the blend: ``v_template + exprdirs[:, :, :n] . weights`` -> (V, 3) float64 (what
    :func:`ofera.head.lbs.lbs` gives for this head with identity rotations: all skinning is on the root)."""
    w = np.asarray(weights, np.float64).reshape(-1)
    return np.asarray(head.v_template, np.float64) + np.asarray(head.exprdirs, np.float64)[:, :, : w.size] @ w


def sparse_targets(exprdirs: np.ndarray, vertex_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each expression direction restricted to ``vertex_ids`` (S,) as CSR over the subset: indptr (E+1,) int64,
    rows (nnz,) int64 (0..S-1), deltas (nnz, 3) float32 (a row is kept when any of its 3 values is non-zero)."""
    sub = np.asarray(exprdirs)[np.asarray(vertex_ids, np.int64)]  # (S, 3, E)
    e = sub.shape[2]
    indptr = np.zeros(e + 1, np.int64)
    rows, deltas = [], []
    for j in range(e):
        nz = np.flatnonzero(np.any(sub[:, :, j] != 0, axis=1))
        rows.append(nz)
        deltas.append(sub[nz, :, j])
        indptr[j + 1] = indptr[j] + nz.size
    cat_rows = np.concatenate(rows).astype(np.int64) if rows else np.zeros(0, np.int64)
    cat_d = np.concatenate(deltas).astype(np.float32) if deltas else np.zeros((0, 3), np.float32)
    return indptr, cat_rows, np.ascontiguousarray(cat_d.reshape(-1, 3))


class FastVertexAvatar:
    """Precomputation for one vertex-bound avatar (read-only after construction; share it). The same interface
    as :class:`.fast.FastAvatar` where the pipeline needs it: ``session()``, ``warm_up()``, ``neutral``,
    ``selected``, ``deformed_count``."""

    binding_type = "vertex"

    def __init__(self, avatar, subject: HeadSubject | None = None, gaussians: str | np.ndarray = "exact") -> None:
        binding = avatar.binding
        if not isinstance(binding, VertexBinding):
            raise TypeError(f"FastVertexAvatar needs a vertex binding, got {type(binding).__name__}")
        head = avatar.head
        self.avatar = avatar
        self.subject = subject if subject is not None else HeadSubject.create(head)
        if self.subject.model is not head:
            raise ValueError("the subject must be made from the avatar's head model")
        if np.any(np.asarray(head.weights)[:, 1:]) or np.any(np.asarray(head.posedirs)):
            raise ValueError(f"{head.name}: the vertex fast path takes a morph-target head (all skinning on the root, "
                             "no pose correctives); use the reference deformer with lbs")
        vb = np.asarray(binding.vertex, np.int64)
        exprdirs = np.asarray(head.exprdirs)
        if isinstance(gaussians, np.ndarray):
            selected = np.asarray(gaussians, bool)
            if selected.shape != (avatar.count,):
                raise ValueError(f"gaussian mask has shape {selected.shape}, the avatar has ({avatar.count},)")
        elif gaussians == "all":
            selected = np.ones(avatar.count, bool)
        elif gaussians == "exact":
            selected = np.any(exprdirs.reshape(head.num_vertices, -1) != 0, axis=1)[vb]
        else:
            raise ValueError(f"unknown Gaussian set {gaussians!r}; expected 'exact', 'all' or a mask")
        ids = np.flatnonzero(selected).astype(np.int64)
        vertex_ids, slot = np.unique(vb[ids], return_inverse=True)
        self.count = avatar.count
        self.selected = selected
        self.ids = ids
        self.vertex_ids = vertex_ids.astype(np.int64)
        self.slot = slot.reshape(-1).astype(np.int64)
        self.n_expr = int(head.expr_dims)
        self.base = np.ascontiguousarray(self.subject.v_id[self.vertex_ids], np.float64)
        self.indptr, self.rows, self.deltas = sparse_targets(exprdirs, self.vertex_ids)
        self.offset = np.ascontiguousarray(binding.offset[ids], np.float64)
        self.neutral = make_deformer(binding, head.faces, head.num_vertices).deform(self.subject.v_id)
        self._warm = False

    @property
    def moving(self) -> int:
        """Gaussians deformed per frame."""
        return int(self.ids.size)

    deformed_count = moving

    def session(self, pool_size: int = 8, parallel: bool | None = False) -> FastVertexSession:
        """Per-stream buffers (``parallel`` is accepted for interface parity and ignored: both kernels are
        memory-bound and well under a millisecond)."""
        return FastVertexSession(self, pool_size)

    def warm_up(self, threads: bool = False) -> None:
        """Compile (or load from the on-disk cache) both kernels now, not on the first frame (``threads``: accepted
        for interface parity; both kernels are serial)."""
        if not self._warm:
            s = self.session(pool_size=1)
            w = np.zeros(self.n_expr, np.float32)
            w[: min(1, w.size)] = 0.5
            s.deform(s.blend(w))
            self._warm = True


class FastVertexSession:
    """Per-stream buffers of a :class:`FastVertexAvatar`. Not thread-safe: one frame at a time."""

    def __init__(self, fast: FastVertexAvatar, pool_size: int = 8) -> None:
        self.fast = fast
        self.pool = StatePool(fast.neutral, pool_size)
        self._verts = np.zeros((fast.vertex_ids.size, 3), np.float64)

    def blend(self, weights: np.ndarray) -> np.ndarray:
        """Morph weights (n,), n <= 51 (the ``arkit51`` order) -> moving vertices (S, 3) float64 (a buffer reused
        by the next call)."""
        w = np.ascontiguousarray(weights, np.float32).reshape(-1)
        if w.size > self.fast.n_expr:
            raise ValueError(f"{w.size} morph weights, the head has {self.fast.n_expr} targets")
        f = self.fast
        morph_blend_kernel(w, f.base, f.indptr, f.rows, f.deltas, self._verts)
        return self._verts

    def head(self, expr: np.ndarray, rotations: np.ndarray | None = None) -> np.ndarray:
        """:meth:`blend`, with the :class:`.fast.FastSession` signature: ``rotations`` must be the identity (an
        ARKit morph head has no jaw or eye joints: jawOpen and the eye shapes are morph targets)."""
        if rotations is not None and not np.array_equal(np.asarray(rotations).reshape(-1, 3, 3), _EYE5):
            raise ValueError("a morph-target (arkit51) head takes no joint rotations; jaw and eyes are ARKit weights")
        return self.blend(expr)

    def deform(self, verts: np.ndarray) -> GaussianState:
        """Moving vertices (S, 3) -> full GaussianState (float32, read-only, pooled)."""
        f = self.fast
        verts = np.ascontiguousarray(verts, np.float64)
        if verts.shape != (f.vertex_ids.size, 3):
            raise ValueError(f"vertices have shape {verts.shape}, the subset has ({f.vertex_ids.size}, 3)")
        state, pos, _, _ = self.pool.acquire()
        vertex_offset_kernel(verts, f.slot, f.ids, f.offset, pos)
        return state

    def run(self, weights: np.ndarray) -> GaussianState:
        return self.deform(self.blend(weights))


def reference_vertex_frame(avatar, weights: np.ndarray) -> GaussianState:
    """The plain reference of :meth:`FastVertexSession.run`: numpy blend of every vertex, then the reference
    deformer."""
    return avatar.deformer().deform(morph_blend_reference(avatar.head, weights))
