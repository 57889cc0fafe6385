"""The fast per-frame path: subset LBS + deformation of only the Gaussians a frame can move (numba).

    fast = FastAvatar(avatar)                 # once per avatar: precomputed, read-only, shareable
    session = fast.session()                  # once per stream: scratch buffers and an output pool
    expr, rotations = session.flame(y)        # FLAME values (68,): split_flame_values, ~100x faster
    verts = session.head(expr, rotations)     # (S, 3): LBS of the vertex subset only
    state = session.deform(verts)             # GaussianState (float32, full N), from the pool
    ok = session.deform_f16(verts, draft, psign, rsign)  # or: straight into a dense f16 frame (FrameWriter.draft)

It computes what ``lbs`` + :class:`.deform.Deformer` (the REFERENCE) compute, within float rounding,
for both binding types, when root and neck are the identity (always true for FLAME values: the client
owns head pose; :meth:`FastSession.head` refuses anything else):

- Which Gaussians move: ``gaussians="exact"`` (default) takes every Gaussian whose face has a vertex
  with ANY non-zero expression row, skinning weight on the jaw or an eye, or jaw/eye pose corrective;
  all others are exactly (to 1e-16) at their neutral values in every frame. ``"movable"`` uses the
  avatar's ``movable`` (a 0.1 um/unit tolerance: a little faster, differs below a micrometre);
  ``"all"`` deforms every Gaussian (tests).
- Precomputed per avatar: the vertex subset those faces need, its blend basis (:class:`SubsetLBS`),
  the used faces as rows of the subset, runs of consecutive Gaussians on one face, and per moving
  Gaussian its local attributes as one float32 row (local position or barycentric coordinates and shift,
  normalised rotation, linear scale: one read stream).
- Per frame: one LBS kernel, one face-frame kernel (R_f, its quaternion, s_f, c_f, n_f per used
  face, float32 rows), one per-Gaussian kernel writing position / rotation / scale straight into float32 output
  arrays whose other rows already hold the neutral values.

Output buffers come from a :class:`StatePool`: a returned state is never written again while anyone
still references it or any view of its arrays (CPython reference counts), so the caller may keep it,
hand it to another thread, or drop it; dropped states are recycled, so a steady stream allocates
nothing. States are read-only.

Threads: the server's ``kernel_threads`` setting chooses (``session(parallel=...)``). ``parallel=True`` runs the face
frames and the per-Gaussian kernels (the triangle kernel, the f16 writer's blocks, a delta frame's deformation with its
selection and encoding) with prange over numba's threads; ``False`` on one thread. ``None`` ("auto", the server's
default) threads a frame's kernels only while (1) its session is the only one of the process that computed a frame in
the last :data:`ACTIVITY` window (several sessions already keep every core busy), (2) the machine is not busy
(1-minute load average below the thread count: other processes hold the cores), and (3) its own recent threaded
frames were faster per unit of work than its serial ones (:class:`ThreadChoice`: a parallel region waits for its
slowest thread, so on a loaded core it can be ten times slower than one thread, and waking numba's sleeping worker
after a 72 Hz frame's gap costs 0.15 ms p50 on the AMD EPYC VM of December 2026, where the f16 writer took 1.3 ms
serial and 2.1 ms on two threads; the choice re-checks the other mode now and then). The results are the same bits
either way (every Gaussian and face is computed by the same code, whichever thread runs it). On the Intel Xeon VM of 6
December 2026 the measurement threads both kinds of frame: a lone f16 session's compute p50 1.54-1.72 -> 1.25-1.35 ms
and e2e p99 4.6-5.0 -> 4.4-4.6 ms, a q13 delta session's compute p50 3.1-3.5 -> 2.5 ms (benchmarks/README.md, rounds
ten and eleven). Round ten kept dense frames serial under auto because there they gained nothing: the choice itself
then cost 0.16 ms a frame (numpy medians on a cold CPU), about what the second core saved.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numba
import numpy as np
from ofera_protocol.fast_encodings import FrameDraft, VaryingRows

from ..head.lbs import HeadSubject
from ..head.lbs_fast import (
    SubsetLBS,
    check_flame_values,
    flame_values_arg,
    flame_values_kernel,
    load_flame_values,
    root_neck_identity,
)
from ..jit import Bound
from ..thread_choice import ACTIVITY, Activity, ThreadChoice, load_average, use_threads
from ..thread_placement import PLACEMENT
from . import kernels as K
from .binding import BarycentricBinding, TriangleBinding, normalize_quaternions
from .deform import make_deformer
from .movable import FACE_JOINTS
from .state import GaussianState

GAUSSIAN_SETS = ("exact", "movable", "all")


def affected_vertices(head) -> np.ndarray:
    """(V,) bool: vertices that any expression, jaw or eye rotation moves at all (no tolerance)."""
    v = head.num_vertices
    expr = np.abs(head.exprdirs).reshape(v, -1).max(axis=1, initial=0.0) > 0
    joints = np.asarray(head.weights)[:, list(FACE_JOINTS)].max(axis=1) > 0
    rows = np.concatenate([np.arange(9 * (j - 1), 9 * j) for j in FACE_JOINTS])
    pose = np.abs(np.asarray(head.posedirs)[rows]).reshape(len(rows), v, 3).max(axis=(0, 2)) > 0
    return expr | joints | pose


def gaussian_selection(avatar, gaussians: str | np.ndarray = "exact") -> np.ndarray:
    """(N,) bool of the Gaussians the fast path deforms (see the module docstring)."""
    if isinstance(gaussians, np.ndarray):
        sel = np.asarray(gaussians, bool)
        if sel.shape != (avatar.count,):
            raise ValueError(f"gaussian mask has shape {sel.shape}, the avatar has ({avatar.count},)")
        return sel
    if gaussians == "all":
        return np.ones(avatar.count, bool)
    if gaussians == "movable":
        return np.asarray(avatar.movable, bool)
    if gaussians == "exact":
        face_moves = affected_vertices(avatar.head)[avatar.head.faces].any(axis=1)
        return face_moves[np.asarray(avatar.binding.face, np.int64)]
    raise ValueError(f"unknown Gaussian set {gaussians!r}; expected one of {GAUSSIAN_SETS} or a mask")


class StatePool:
    """Reusable float32 GaussianStates, every one initialised to ``template``; see the module docstring.

    ``acquire()`` returns (state, writable position, rotation, scale): a pooled state nobody references
    any more, else a new one (up to ``size`` pooled, beyond that unpooled). Thread-safe. A caller that writes
    only rows of ``varying`` passes it: every state then carries it (:class:`.state.GaussianState`).
    """

    def __init__(self, template: GaussianState, size: int = 8, varying: VaryingRows | None = None) -> None:
        self.template = template
        self.varying = varying  # what every state of the pool carries: the only rows anyone writes
        self.size = size
        self._entries: list[list] = []  # [state, (position, rotation, scale) writable bases, idle counts]
        self._lock = threading.Lock()
        self.created = 0
        self.unpooled = 0

    def _new(self) -> tuple[GaussianState, tuple[np.ndarray, ...]]:
        t = self.template
        bases = (t.position.copy(), t.rotation.copy(), t.scale.copy())
        views = []
        for b in bases:
            v = b.view()
            v.flags.writeable = False
            views.append(v)
        return GaussianState(*views, varying=self.varying), bases

    @staticmethod
    def _counts(entry: list) -> tuple[int, ...]:
        """Reference counts of an entry's state, its arrays and their bases, seen from here."""
        state, bases = entry[0], entry[1]
        return (sys.getrefcount(state), sys.getrefcount(state.position), sys.getrefcount(state.rotation),
                sys.getrefcount(state.scale), sys.getrefcount(bases[0]), sys.getrefcount(bases[1]),
                sys.getrefcount(bases[2]))

    def acquire(self) -> tuple[GaussianState, np.ndarray, np.ndarray, np.ndarray]:
        with self._lock:
            for entry in self._entries:
                if self._counts(entry) == entry[2]:
                    bases = entry[1]
                    return entry[0], bases[0], bases[1], bases[2]
            if len(self._entries) < self.size:
                entry = [*self._new(), ()]
                self._entries.append(entry)
                entry[2] = self._counts(entry)  # idle: only the pool holds it (same context as the check)
                self.created += 1
                bases = entry[1]
                return entry[0], bases[0], bases[1], bases[2]
            self.unpooled += 1
            state, bases = self._new()
            return state, bases[0], bases[1], bases[2]

    def __len__(self) -> int:
        return len(self._entries)


@dataclass(frozen=True, eq=False)
class _Arrays:
    """Per-Gaussian precomputed attributes of the deformed set (read-only, shared by sessions).
    Rows m of ``local`` follow the ascending avatar rows ``ids``; runs are :func:`.kernels.runs`."""

    ids: np.ndarray  # (M,) int64 rows of the avatar
    face_vids: np.ndarray  # (U, 3) int64 rows of the vertex subset
    run_face: np.ndarray  # (R,) int64 used-face slot of each run
    run_m: np.ndarray  # (R,) int64 first row of local
    run_len: np.ndarray  # (R,) int64
    run_row: np.ndarray  # (R,) int64 first avatar row
    local: np.ndarray  # (M, LOCAL_COLS[_BARY]) float32, the columns of .kernels (L_POS ...)
    inv_canonical: np.ndarray | None = None  # barycentric: (U,) float64 1 / face_scale_canonical


class FastAvatar:
    """Precomputation for one avatar and head subject (read-only after construction; share it)."""

    def __init__(self, avatar, subject: HeadSubject | None = None, gaussians: str | np.ndarray = "exact",
                 n_expr: int | None = None) -> None:
        head = avatar.head
        self.avatar = avatar
        self.subject = subject if subject is not None else HeadSubject.create(head)
        if self.subject.model is not head:
            raise ValueError("the subject must be made from the avatar's head model")
        binding = avatar.binding
        selected = gaussian_selection(avatar, gaussians)
        ids = np.flatnonzero(selected).astype(np.int64)
        used_faces, gface = np.unique(np.asarray(binding.face, np.int64)[ids], return_inverse=True)
        vertex_ids, face_vids = np.unique(np.asarray(head.faces, np.int64)[used_faces], return_inverse=True)
        self.count = avatar.count
        self.selected = selected
        self.used_faces = used_faces
        self.lbs = SubsetLBS(self.subject, vertex_ids, n_expr)
        self.binding_type = binding.kind
        run_face, run_m, run_len, run_row = K.runs(ids, gface.reshape(-1))
        self.runs = int(run_face.size)

        common = {"ids": ids, "face_vids": face_vids.reshape(-1, 3).astype(np.int64), "run_face": run_face,
                  "run_m": run_m, "run_len": run_len, "run_row": run_row}
        rot = normalize_quaternions(binding.rotation[ids])
        scale = np.exp(binding.log_scale[ids].astype(np.float64))
        if isinstance(binding, TriangleBinding):
            local = np.concatenate([binding.position[ids], rot, scale], axis=1)
            self.arrays = _Arrays(**common, local=np.ascontiguousarray(local, np.float32))
        elif isinstance(binding, BarycentricBinding):
            shift = binding.normal_offset_scale * np.tanh(binding.offset[ids].astype(np.float64))
            local = np.concatenate([binding.bary[ids], shift.reshape(-1, 1), rot, scale], axis=1)
            canonical = binding.face_scale_canonical.astype(np.float64)[used_faces]
            self.arrays = _Arrays(**common, local=np.ascontiguousarray(local, np.float32),
                                  inv_canonical=1.0 / canonical)
        else:
            raise TypeError(f"unknown binding {type(binding).__name__}")
        # Every frame starts from the subject's neutral Gaussians (what the reference gives at v_id).
        self.neutral = make_deformer(binding, head.faces, head.num_vertices).deform(self.subject.v_id)
        self.varying = VaryingRows(ids)  # every session's states: the other rows stay neutral
        self.f16_blocks = K.f16_blocks(run_row, run_len)  # deform_f16's blocks of runs
        self._warm: set[bool] = set()  # the thread modes warm_up has run

    @property
    def moving(self) -> int:
        """Gaussians deformed per frame."""
        return int(self.arrays.ids.size)

    def session(self, pool_size: int = 8, parallel: bool | None = False) -> FastSession:
        """Per-stream buffers. ``parallel``: face frames and triangle deformation over numba's thread pool
        (prange): False (default), True, or None (automatic: while the session is alone and the machine not
        busy, see the module docstring)."""
        return FastSession(self, pool_size, parallel)

    def warm_up(self, threads: bool = False) -> None:
        """Compile (or load from the on-disk cache) every serial kernel now, not on the first frame; ``threads``: the
        parallel ones too, and numba's thread pool (else they load on a session's first threaded frame)."""
        for parallel in (False, True):
            if parallel in self._warm or (parallel and not threads):
                continue
            s = self.session(pool_size=1, parallel=parallel)
            y = np.zeros(68, np.float32)
            y[50:] = [1, 0, 0, 0, 1, 0] * 3
            expr, rot = s.flame(y)
            s.deform(s.head(expr[: self.lbs.n_expr], rot))
            if self.lbs.n_expr >= 50:
                s.flame_head(y)
            s.head(np.zeros(self.lbs.n_expr), np.broadcast_to(np.eye(3), (self.lbs.num_joints, 3, 3)))
            if s.writes_f16:
                draft = SimpleNamespace(varying=self.varying, position=np.zeros(3 * self.count, np.uint16),
                                        rotation=np.zeros(4 * self.count, np.uint16),
                                        scale=np.zeros(3 * self.count, np.uint16))
                one = np.ones(4, np.float32)
                s.deform_f16(s.head(expr[: self.lbs.n_expr], rot), draft, one[:3].copy(), one)
                if self.lbs.n_expr >= 50:
                    s.flame_f16(y, draft, one[:3].copy(), one)
            self._warm.add(parallel)


def _f64(a: np.ndarray) -> np.ndarray:
    """``a`` as a C-contiguous float64 array: itself when it is one (head's output; no numpy call on the frame path)."""
    if isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous:
        return a
    return np.ascontiguousarray(a, np.float64)


class FastSession:
    """Per-stream buffers of a :class:`FastAvatar`. Not thread-safe: one frame at a time."""

    def __init__(self, fast: FastAvatar, pool_size: int = 8, parallel: bool | None = False,
                 activity: Activity = ACTIVITY) -> None:
        self.fast = fast
        self.parallel = parallel  # None: automatic (use_threads of the sessions active in `activity`)
        self.activity = activity
        self.choice = ThreadChoice()
        self.placement = PLACEMENT  # where a threaded frame's workers run (away from the calling thread's CPU)
        self.threaded = False  # whether the last frame ran on numba's threads
        # numba's thread count, read once: numba.get_num_threads() took 37 us p50 on a cold CPU (round thirteen), and a
        # frame asked it up to four times. A parallel kernel told of more threads than run is still right (they
        # claim their work), only not faster.
        self.threads = numba.get_num_threads()
        self._frame: tuple[bool, int] | None = None  # the frame under way: (its thread choice, its start in ns)
        # Where an automatic frame's time goes to the thread choice: None, at once; else defer((fn, args)), whose taker
        # runs fn(*args) later (the server's Source: once the client read the frame; a cold record took 16 us p50). A
        # queue's append, not the taker's own method: that would be a reference cycle (Source -> pipeline -> here)
        self.defer: Callable[[tuple[Callable[..., Any], tuple]], None] | None = None
        self.lbs = fast.lbs.clone()
        cols = K.FACE_COLS_BARY if fast.binding_type == "barycentric" else K.FACE_COLS
        self.face = np.zeros((cols, fast.used_faces.size), np.float32)  # face frames, one row per column
        self.edges = np.zeros((9, fast.used_faces.size), np.float32)  # face_frames_kernel's scratch
        self.pool = StatePool(fast.neutral, pool_size, fast.varying)
        self._expr = np.zeros(50, np.float32)
        self._rot = np.zeros((5, 3, 3), np.float32)
        self._half_scratch: dict[bool, tuple[np.ndarray, ...]] | None = None  # deform_f16's, by threads
        self._claims = np.zeros(1, np.int64)  # the threaded kernels' shared block counter
        self._face_claims = np.zeros(2, np.int64)  # the threaded face frames' chunks claimed and done
        self._flame_f16: dict[tuple, Bound] = {}  # flame_f16's kernels bound to this session, by (threads, signs)
        # the last sign arrays flame_f16 was given and their kernel, by threads: a session passes the same two arrays
        # every frame, whose key by value (asarray, tobytes) took 11 us p50 of a cold frame's path (round eighteen)
        self._flame_f16_last: dict[bool, tuple[np.ndarray, np.ndarray, Bound]] = {}
        self._ticks = np.zeros(3, np.uint64)  # their cycle counter: start, vertices written, end
        self._head_values = np.zeros(68, np.float32)  # FLAME values for a kernel that runs the head (head_args)
        self._head_claims = np.zeros(2, np.int64)  # its vertex blocks claimed and done

    def flame_head(self, y: np.ndarray) -> np.ndarray:
        """:meth:`head` of :meth:`flame` (y (68,) FLAME values -> (S, 3) float64), the same values in one numba call
        (the split is left in the buffers :meth:`flame` returns), on the frame's threads if it has them (see
        :meth:`_start`). A delta frame's head too since its kernel's threads share the blocks as they go: head +
        deform + encode p50 1.58-1.66 -> 1.44-1.55 ms in four alternating pairs (round thirteen; with the kernel's
        fixed split of round eleven it was slower)."""
        par = self._start()
        return self.lbs.forward_flame(self._values(y), self._expr, self._rot, par)

    def _values(self, y: np.ndarray) -> np.ndarray:
        """y as a writable float32 vector: what the pipeline passes, else a copy. A read-only array (a remote room
        member's values, decoded from the bus) would compile another specialisation of each kernel taking y on its
        first frame: a threaded one took the first 0.8 s of a room across two servers (clean-clone CI, round eleven)."""
        if not (isinstance(y, np.ndarray) and y.dtype == np.float32 and y.ndim == 1 and y.flags.writeable):
            y = np.array(y, np.float32).reshape(-1)
        check_flame_values(y)
        return y

    def flame(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """FLAME values (68,) -> (expr (50,), rotations (5, 3, 3)) float32, like
        :func:`ofera.mapping.flame_values.split_flame_values` (to float rounding) in one numba call
        (about 100x faster); buffers reused by the next call."""
        flame_values_kernel(self._values(y), 50, self._expr, self._rot)
        return self._expr, self._rot

    def head(self, expr: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """Subset LBS: expr (n,), rotations (5, 3, 3) with root and neck the identity -> (S, 3) float64
        (a buffer reused by the next call)."""
        rot = rotations if isinstance(rotations, np.ndarray) else np.asarray(rotations)
        if rot.shape != (5, 3, 3):
            rot = rot.reshape(5, 3, 3) if rot.size == 45 and rot.shape[-2:] == (3, 3) else None
        if rot is None or not root_neck_identity(rot):
            raise ValueError("the fast path needs rotations (5, 3, 3) with root and neck the identity "
                             "(FLAME values: the client owns head pose); use the reference lbs otherwise")
        return self.lbs.forward(expr, rot, self._start())

    def _threads(self) -> bool:
        """This frame's thread choice: ``parallel``, or automatic (None; see the module docstring). Every automatic
        frame counts as this session's activity, threaded or not."""
        par = self.parallel
        if par is None:  # note the activity first; the load average (a system call) only where threads may run
            par = use_threads(self.activity.note(id(self)), self.threads, load_average) \
                and self.choice.choose()
        self.threaded = par
        if par:
            self.placement.before_parallel()
        return par

    def _start(self) -> bool:
        """A frame starts (its head): its thread choice, which its deformation keeps. The head runs on the threads
        the deformation will use: that wakes them for it (benchmarks/README.md, round eleven)."""
        self._frame = (self._threads(), time.perf_counter_ns())
        return self._frame[0]

    def _begin(self) -> bool:
        """The thread choice of the frame under way: its head's, or a new one for a deformation called alone."""
        return self._frame[0] if self._frame is not None else self._start()

    def _end(self, work: int) -> None:
        """The frame is done: an automatic one's time since :meth:`_begin` is recorded for ``work`` Gaussians."""
        frame, self._frame = self._frame, None
        if frame is not None and self.parallel is None:
            sample = (frame[0], time.perf_counter_ns() - frame[1], max(work, 1))  # (an avatar nothing moves)
            if self.defer is None:
                self.choice.record(*sample)
            else:
                self.defer((self.choice.record, sample))

    def _verts(self, verts: np.ndarray) -> np.ndarray:
        verts = _f64(verts)
        if verts.shape != (self.fast.lbs.count, 3):
            raise ValueError(f"vertices have shape {verts.shape}, the subset has ({self.fast.lbs.count}, 3)")
        return verts

    def head_args(self) -> tuple:
        """The arguments of this session's head (``SubsetLBS.flame_args`` of its buffers, its vertex block counters)
        for a kernel that runs the head itself before what it does with the vertices
        (``ofera.streaming.direct_delta.DirectDelta``, made with them: :meth:`flame_delta`)."""
        return (*self.lbs.flame_args(self._head_values, self._expr, self._rot), self._head_claims)

    def flame_delta(self, y: np.ndarray, direct) -> Any:
        """:meth:`flame_head` of FLAME values y (68,) and a delta frame from its vertices in one kernel call with this
        frame's thread choice (as :meth:`deform`, timed for the automatic choice): ``direct`` a ``DirectDelta`` made
        with :meth:`head_args`. Returns what its ``head_select`` returns (a ``direct_delta.Written``)."""
        written = direct.head_select(y, self._start())  # (which checks and copies y)
        self._end(self.fast.arrays.ids.shape[0] + 2 * written.counts[0])  # what changed is encoded: twice a deform
        return written

    def deform(self, verts: np.ndarray) -> GaussianState:
        """Subset vertices (S, 3) -> full GaussianState (float32, read-only, pooled)."""
        a = self.fast.arrays
        verts = self._verts(verts)
        state, pos, rot, scale = self.pool.acquire()
        bary = a.inv_canonical is not None
        par = self._begin()
        self._face_frames(verts, par, bary)
        if bary:
            K.barycentric_kernel(self.face, a.run_face, a.run_m, a.run_len, a.run_row, verts, a.face_vids, a.local,
                                 a.inv_canonical, pos, rot, scale)
        else:
            kernel = K.triangle_kernel_parallel if par else K.triangle_kernel
            kernel(self.face, a.run_face, a.run_m, a.run_len, a.run_row, a.local, pos, rot, scale)
        self._end(a.ids.shape[0])
        return state

    def _face_frames(self, verts: np.ndarray, parallel: bool, with_normal: bool) -> None:
        """The used faces' frames into ``self.face``, on numba's threads if ``parallel``."""
        a = self.fast.arrays
        if parallel:
            K.face_frames_kernel_parallel(verts, a.face_vids, self.edges, self.face, with_normal, self.threads,
                                          self._face_claims)
        else:
            K.face_frames_kernel(verts, a.face_vids, self.edges, self.face, with_normal)

    @property
    def writes_f16(self) -> bool:
        """Whether :meth:`deform_f16` can run (the triangle binding's kernel)."""
        return self.fast.binding_type == "triangle"

    def deform_f16(self, verts: np.ndarray, draft: FrameDraft, psign: np.ndarray, rsign: np.ndarray) -> bool:
        """Subset vertices (S, 3) -> the deformed Gaussians straight into a dense f16 frame's fields (a
        ``FrameWriter.draft`` of ``self.fast.varying``, whose other rows hold the neutral Gaussians), in wire
        coordinates (psign (3,), rsign (4,)): the bits the f16 encoding of :meth:`deform`'s state gives, with no
        float32 state written and read back. False if a value is out of the half range (the draft is then
        garbage: drop it). Triangle binding only (:attr:`writes_f16`); threads as :meth:`deform` (the same bits)."""
        a = self.fast.arrays
        verts = self._verts(verts)
        self._check_draft(draft)
        par = self._begin()
        args = (a.run_face, a.run_m, a.run_len, a.run_row, a.local, psign, rsign, *self._f16_scratch(par),
                draft.position, draft.rotation, draft.scale)
        self._face_frames(verts, par, False)
        if par:
            ok = K.triangle_f16_kernel_parallel(self.face, self.fast.f16_blocks, self.threads, self._claims, *args)
        else:
            ok = K.triangle_f16_kernel(self.face, *args)
        self._end(a.ids.shape[0])
        return bool(ok)

    def flame_f16(self, y: np.ndarray, draft: FrameDraft, psign: np.ndarray, rsign: np.ndarray) -> tuple[bool, float]:
        """:meth:`flame_head` of FLAME values y (68,) and :meth:`deform_f16` of its vertices (the same bits) in one
        kernel call, its threads sharing the head's vertex blocks, the face frames and the f16 blocks in one parallel
        region (``kernels.flame_f16_kernel_parallel``). Returns (ok, the head's share of the call's time, by the
        kernel's cycle counter). The kernels are bound to this session's buffers and the signs' values (psign (3,),
        rsign (4,); read when a sign array is first passed); the draft's fields are passed each call (uint16, as
        ``FrameWriter.draft`` makes them)."""
        self._check_draft(draft)
        fields = (draft.position, draft.rotation, draft.scale)
        if not all(_writable_u16(f) for f in fields):  # (what the bound kernels were compiled for: unchecked)
            raise ValueError("the draft's fields must be writable C-contiguous uint16 vectors (FrameWriter.draft)")
        y = flame_values_arg(y)
        par = self._start()
        last = self._flame_f16_last.get(par)
        if last is not None and last[0] is psign and last[1] is rsign:
            bound = last[2]
        else:
            p, r = np.asarray(psign, np.float32), np.asarray(rsign, np.float32)
            key = (par, p.tobytes(), r.tobytes())
            bound = self._flame_f16.get(key)
            if bound is None:  # (two coordinate systems, threads or not: four keys at most)
                bound = self._flame_f16[key] = self._bind_flame_f16(par, p, r)
            self._flame_f16_last[par] = (psign, rsign, bound)
        ok, share = bound(*fields, y)
        self._end(self.fast.arrays.ids.shape[0])
        return bool(ok), share

    def _bind_flame_f16(self, parallel: bool, psign: np.ndarray, rsign: np.ndarray) -> Bound:
        a = self.fast.arrays
        psign, rsign = (np.ascontiguousarray(x, np.float32) for x in (psign, rsign))
        runs = (a.run_face, a.run_m, a.run_len, a.run_row, a.local, psign, rsign, *self._f16_scratch(parallel))
        if parallel:
            return Bound(_flame_f16_parallel_bound, (self.head_args(), a.face_vids, self.edges, self.face,
                                                     self.fast.f16_blocks, self.threads, self._face_claims,
                                                     self._claims, *runs, self._ticks))
        return Bound(_flame_f16_bound, (self.head_args(), a.face_vids, self.edges, self.face, *runs, self._ticks))

    def _check_draft(self, draft: FrameDraft) -> None:
        if not self.writes_f16:
            raise ValueError("deform_f16 needs the triangle binding")
        if draft.varying is not self.fast.varying:
            raise ValueError("the draft was not laid out for this avatar's varying rows")

    def _f16_scratch(self, parallel: bool) -> tuple[np.ndarray, ...]:
        """The f16 kernels' float32 scratch: (threads, rows, 3 | 4 | 3), or thread 0's for the serial kernel."""
        if self._half_scratch is None:
            a = self.fast.arrays
            shape = (numba.config.NUMBA_NUM_THREADS, K.F16_BLOCK + int(a.run_len.max(initial=0)))
            per_thread = tuple(np.zeros((*shape, k), np.float32) for k in (3, 4, 3))
            self._half_scratch = {True: per_thread, False: tuple(x[0] for x in per_thread)}
        return self._half_scratch[parallel]

    def run(self, expr: np.ndarray, rotations: np.ndarray) -> GaussianState:
        return self.deform(self.head(expr, rotations))


_U16 = np.dtype(np.uint16)


def _writable_u16(f) -> bool:
    """Whether ``f`` is a writable C-contiguous uint16 vector, by attributes (with numpy's dtype comparison and two
    flags objects per field the draft's check took 25 us p50 of a cold frame's path, round eighteen)."""
    return type(f) is np.ndarray and f.dtype is _U16 and f.strides == (2,) and f.flags.writeable


@numba.njit(**K._NBC)
def _flame_f16_bound(fixed, out_pos, out_rot, out_scale, y):
    """:func:`kernels.flame_f16_kernel` with a session's arguments (jit.Bound), a draft's fields and the frame's FLAME
    values y (copied into the head's buffer first)."""
    head, face_vids, edges, face, run_face, run_m, run_len, run_row, local, psign, rsign, sp, sr, ss, ticks = fixed.args
    load_flame_values(head, y)
    return K.flame_f16_kernel(head, face_vids, edges, face, run_face, run_m, run_len, run_row, local, psign, rsign, sp,
                              sr, ss, out_pos, out_rot, out_scale, ticks)


@numba.njit(**K._NBC)
def _flame_f16_parallel_bound(fixed, out_pos, out_rot, out_scale, y):
    """:func:`kernels.flame_f16_kernel_parallel` with a session's arguments (jit.Bound), a draft's fields and the
    frame's FLAME values y (copied into the head's buffer first)."""
    (head, face_vids, edges, face, blocks, threads, face_claims, claims, run_face, run_m, run_len, run_row, local,
     psign, rsign, sp, sr, ss, ticks) = fixed.args
    load_flame_values(head, y)
    return K.flame_f16_kernel_parallel(head, face_vids, edges, face, blocks, threads, face_claims, claims, run_face,
                                       run_m, run_len, run_row, local, psign, rsign, sp, sr, ss, out_pos, out_rot,
                                       out_scale, ticks)


def reference_frame(avatar, subject: HeadSubject, expr: np.ndarray, rotations: np.ndarray) -> GaussianState:
    """The plain reference of :meth:`FastSession.run`: full numpy LBS, then the reference deformer."""
    from ..head.lbs import lbs

    verts, _ = lbs(subject, np.asarray(expr)[None], np.asarray(rotations)[None])
    return avatar.deformer().deform(verts[0])
