"""The per-frame pipeline: layout adapter -> BDA -> EPM -> FLAME values -> LBS -> Gaussian deformation.

`Pipeline.run(weights) -> (GaussianState, timings)` is the whole computation of one frame, in FLAME
space; the server and `offline_pipeline` call the same code, so a streamed f32 frame equals the
offline result bit for bit. One Pipeline per session (the layout adapter, the mapper's bound buffers
and the deformer hold per-call state); the heavy parts (avatar, head subject, ONNX session) are shared
through `AvatarAssets`, which `registry.AvatarRegistry` loads once per avatar (`registry.offline_pipeline`
runs one frame through the same registry and Pipeline).

An avatar's expression space is its own (`AvatarAssets.expression`): FLAME-bound avatars ("flame68") go
through the EPM; ARKit-bound ones ("arkit51", LAM imports: a head of 51 ARKit morph targets) take the
BDA-aligned ARKit weights directly as morph weights and skip the EPM. Layout adapters and the BDA apply to both.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from ofera_protocol import Avatar as WireAvatar
from ofera_protocol import Quant, make_quant, mirror_x_position, mirror_x_rotation, mirror_x_sh
from ofera_protocol.fast_encodings import FrameDraft, VaryingRows

from ..avatar.model import GaussianAvatar
from ..avatar.state import GaussianState
from ..head import HeadSubject, lbs
from ..mapping.bda import BDA
from ..mapping.flame_values import split_flame_values
from ..mapping.layouts import LayoutAdapter
from ..mapping.runtime import Mapper
from .confidence import DEFAULT_THRESHOLD, RegionHold

if TYPE_CHECKING:  # (imported at run time by the fast path alone: numba)
    from ..mapping.map_fast import FastEpm, FastLayout

KERNEL_THREADS: dict[str, bool | None] = {"serial": False, "auto": None, "parallel": True}
"""The kernel_threads setting -> `AvatarAssets.parallel` (`ofera.avatar.fast.FastAvatar.session`'s `parallel`)."""

STAGES: tuple[str, ...] = ("layout", "bda", "epm", "head", "deform")
"""Stage names of `Pipeline.run` timings, in order (microseconds): layout adapter, BDA, EPM (with the
split into expression and rotations; ~0 for an arkit51 avatar, which skips it), head model (LBS; arkit51:
the morph-target blend), Gaussian deformation."""
_IDENTITY5 = np.broadcast_to(np.eye(3), (5, 3, 3))  # joint rotations of an arkit51 avatar's head (no joints move)


class FastStream(Protocol):
    """One stream's buffers of a fast path (`ofera.avatar.fast.FastSession`, `.fast_vertex.FastVertexSession`)."""

    def head(self, expr: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """(E,) expression (arkit51: morph weights), (5, 3, 3) joint rotations -> the vertices the deform needs."""
        ...

    def deform(self, verts: np.ndarray) -> GaussianState:
        """Vertices from `head` -> the Gaussians of the frame (a pooled, read-only state)."""
        ...


class FastPath(Protocol):
    """An avatar's shared, read-only fast path (`ofera.avatar.fast.FastAvatar`, `.fast_vertex.FastVertexAvatar`)."""

    def session(self, pool_size: int = 8, parallel: bool | None = False) -> FastStream: ...

    def warm_up(self, threads: bool = False) -> None: ...


@dataclass
class AvatarAssets:
    """Everything shared by the sessions of one avatar: loaded once, read-only afterwards."""

    id: str
    avatar: GaussianAvatar
    subject: HeadSubject
    mapper: Mapper | None  # the avatar's EPM (its ONNX session is shared; each Pipeline binds its own buffers);
    # None for an arkit51 avatar (driven by the aligned ARKit weights themselves: no EPM)
    bda: BDA  # the avatar's own BDA (sibling <id>.bda.npz) or identity; a device profile overrides it
    fast: FastPath | None = None  # shared, read-only; None: the numpy reference
    parallel: bool | None = False  # the fast path's threads per session: False, True, None (auto); KERNEL_THREADS
    _cache: dict[tuple, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def create(cls, avatar_id: str, avatar: GaussianAvatar, mapper: Mapper | None, bda: BDA | None = None,
               fast: bool = True, parallel: bool | None = False) -> AvatarAssets:
        """`fast`: deform with `ofera.avatar.fast` (subset LBS + numba kernels; vertex-bound avatars:
        `ofera.avatar.fast_vertex`) instead of the reference; `parallel`: its sessions' threads (False: one, True:
        numba's, None: automatic; `ofera.avatar.fast`)."""
        subject = HeadSubject.create(avatar.head)  # the avatar's identity is baked into its head's template
        if mapper is None and getattr(avatar, "expression", "flame68") != "arkit51":
            raise ValueError(f"avatar {avatar_id!r} is driven by FLAME values and needs an EPM")
        fast_avatar: FastPath | None = None
        vertex_bound = getattr(avatar, "binding_type", None) == "vertex"
        if fast and vertex_bound and getattr(avatar, "expression", "flame68") == "arkit51":
            from ..avatar.fast_vertex import FastVertexAvatar

            fast_avatar = FastVertexAvatar(avatar, subject)
        elif fast and not vertex_bound:  # (a vertex-bound FLAME avatar has no fast path: the reference runs)
            from ..avatar.fast import FastAvatar

            fast_avatar = FastAvatar(avatar, subject)
        return cls(avatar_id, avatar, subject, mapper, bda if bda is not None else BDA.identity(), fast_avatar,
                   parallel)

    @property
    def count(self) -> int:
        return int(self.avatar.count)

    @property
    def expression(self) -> str:
        """What drives the avatar (welcome.avatar.expression): "flame68" (BDA -> EPM -> FLAME values) or "arkit51"
        (the BDA-aligned ARKit weights are the morph weights of its head; the EPM is skipped)."""
        return str(getattr(self.avatar, "expression", "flame68"))

    @property
    def sh_degree(self) -> int:
        return int(self.avatar.sh_degree)

    def subset(self, max_gaussians: int | None) -> np.ndarray | None:
        """For a client that renders at most `max_gaussians`: the ids (ascending, int64) of a subset spread
        over the whole surface, or None when the whole avatar fits.

        A deterministic weighted sample without replacement (Efraimidis-Spirakis keys u^(1/w), fixed
        seed) with weight = opacity x footprint (product of the two largest neutral scales): big, opaque
        splats are kept preferentially, yet every region keeps its share, unlike a plain top-k by
        opacity, which would keep mostly the (fully opaque) eyes."""
        if max_gaussians is None or max_gaussians >= self.count:
            return None
        key = ("subset", max_gaussians)
        if key not in self._cache:
            scale = np.sort(np.asarray(self.avatar.neutral().scale, np.float64), axis=1)
            weight = np.asarray(self.avatar.opacity, np.float64) * scale[:, 1] * scale[:, 2] + 1e-30
            u = np.random.default_rng(0x0FE7A).random(self.count)
            keys = np.log(u) / weight  # log of u^(1/w): monotonic, no underflow
            self._cache[key] = np.sort(np.argpartition(-keys, max_gaussians - 1)[:max_gaussians]).astype(np.int64)
        return self._cache[key]

    def wire_avatar(self, coords: str, max_gaussians: int | None = None) -> WireAvatar:
        """The static avatar message content (neutral pose, opacity, SH) in `coords`, cached; reduced to
        `subset(max_gaussians)` if given."""
        key = ("wire", coords, max_gaussians)
        cached = self._cache.get(key)
        if cached is not None:
            return cached
        n = self.avatar.neutral()
        pos, rot, scale, sh, opacity = n.position, n.rotation, n.scale, self.avatar.sh, self.avatar.opacity
        if coords == "unity":
            pos, rot, sh = mirror_x_position(pos), mirror_x_rotation(rot), mirror_x_sh(sh)
        elif coords != "flame":
            raise ValueError(f"unknown coords {coords!r}")
        sub = self.subset(max_gaussians)
        if sub is not None:
            pos, rot, scale, sh, opacity = pos[sub], rot[sub], scale[sub], sh[sub], opacity[sub]
        wire = WireAvatar(*(np.ascontiguousarray(a, np.float32) for a in (opacity, sh, pos, rot, scale)))
        self._cache[key] = wire
        return wire

    def quant(self, coords: str, max_gaussians: int | None = None) -> Quant:
        """q13 parameters of a session (from its neutral avatar), cached so sessions share encodings."""
        key = ("quant", coords, max_gaussians)
        if key not in self._cache:
            wire = self.wire_avatar(coords, max_gaussians)
            self._cache[key] = make_quant(wire.position, wire.scale)
        return self._cache[key]

    def movable(self) -> np.ndarray:
        """(N,) bool: the Gaussians an expression can move (all, if the avatar does not say)."""
        movable = getattr(self.avatar, "movable", None)
        return np.ones(self.count, bool) if movable is None else np.asarray(movable, bool)

    def selection(self, sparse: bool, max_gaussians: int | None) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(gather, index) of a session's frames: `gather` picks from the full state the Gaussians a frame
        carries (None: all, in order); `index` is the frame's wire `index` in the session's numbering
        (None: dense). Sparse frames carry the movable Gaussians, every frame (right whatever is dropped)."""
        key = ("selection", sparse, max_gaussians)
        if key not in self._cache:
            sub = self.subset(max_gaussians)
            if not sparse:
                sel = (sub, None)
            else:
                moving = self.movable() if sub is None else self.movable()[sub]
                index = np.flatnonzero(moving)
                gather = index if sub is None else sub[index]
                sel = (gather, index.astype(np.uint32))
            self._cache[key] = sel
        return self._cache[key]

    def pipeline(self, layout: str, bda: BDA | None = None, confidence_threshold: float = DEFAULT_THRESHOLD
                 ) -> Pipeline:
        return Pipeline(self, layout, bda, confidence_threshold)


class Pipeline:
    """One session's pipeline for one avatar and one blendshape layout. Not thread-safe: run one frame
    at a time (the session does)."""

    def __init__(self, assets: AvatarAssets, layout: str, bda: BDA | None = None,
                 confidence_threshold: float = DEFAULT_THRESHOLD) -> None:
        self.assets = assets
        self.layout = layout
        self.adapter = LayoutAdapter(layout)
        self.hold = RegionHold(confidence_threshold)  # bs.conf: low-confidence regions keep their last values
        self.bda = bda if bda is not None else assets.bda
        self._bda_identity = self.bda.is_identity  # (a property comparing W with the identity: read once)
        base = assets.mapper
        # The BDA runs as its own stage; the mapper gets an identity BDA (a clamp, a no-op on [0, 1]).
        # An arkit51 avatar has no mapper: its head's morph weights are the aligned ARKit weights.
        self.arkit = assets.expression == "arkit51"
        self.mapper = Mapper(base.session, None, source=base.source) if not self.arkit else None
        # Head model + deformation: the fast path's per-stream buffers, or the reference deformer.
        self.fast = assets.fast.session(parallel=assets.parallel) if assets.fast is not None else None
        # The fast path's map: the layout's product and the EPM's graph, one numba call each (mapping.map_fast; ONNX
        # Runtime, the reference, runs a graph that has no program). Imported here, as the fast paths are: numba is
        # imported only once the server has pinned its CPUs (streaming.affinity).
        self.layout_fast: FastLayout | None = None
        self.epm: FastEpm | None = None
        if self.fast is not None:
            from ..mapping.map_fast import FastEpm, FastLayout

            self.layout_fast = FastLayout(self.adapter, keep=self.hold.last)
            self.epm = FastEpm(base.program) if not self.arkit and base.program is not None else None
        self.deformer = assets.avatar.deformer() if self.fast is None else None
        if self.arkit and self.fast is None:  # the reference morph-target blend (numpy)
            from ..avatar.fast_vertex import morph_blend_reference

            self._morph = morph_blend_reference
        self._x51 = np.zeros(51, np.float32)
        self._y = np.zeros(68, np.float32)
        self.values: np.ndarray | None = None  # the last `run`'s expression values

    @property
    def values_length(self) -> int:
        """Length of this avatar's expression values (`map`'s output): 68 FLAME values, or 51 ARKit morph weights."""
        return 51 if self.arkit else 68

    def map(self, weights: np.ndarray, conf: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, int]]:
        """Blendshape weights (L,) in the session's layout and optional `conf` (2,) [lower, upper] face confidence
        (a region below the threshold keeps its last confident values: streaming.confidence) -> this avatar's
        expression values (`values_length`,) float32 (the EPM's 68 FLAME values; arkit51: the 51 BDA-aligned
        weights, which are its morph weights) and the layout, bda and epm stage durations (us). The values are a
        fresh array (the caller's: rooms publish them, params frames carry them)."""
        clock = time.perf_counter_ns
        t0 = clock()
        if self.layout_fast is not None and conf is None:  # the hold's memory refreshed in the same call (as hold does)
            x = self.layout_fast(weights, True)
        else:
            x = self.hold(self.adapter(weights) if self.layout_fast is None else self.layout_fast(weights), conf)
        t1 = clock()
        # x is in [0, 1] already: an identity BDA (the default) gives x itself, to the bit (34 us cold, round nineteen)
        a = x if self._bda_identity else self.bda.apply(x, out=self._x51)
        t2 = clock()
        # arkit51: the "epm" stage is skipped (0 us): the BDA output (clamped to [0, 1]) is the morph weights
        values = (a.copy() if self.arkit else self.epm(a, self._y).copy() if self.epm is not None
                  else self.mapper.map(a, out=self._y).copy())
        t3 = clock()
        return values, {"layout": (t1 - t0) // 1000, "bda": (t2 - t1) // 1000, "epm": (t3 - t2) // 1000}

    def deform_values(self, values: np.ndarray) -> tuple[GaussianState, dict[str, int]]:
        """Expression values from `map` (here, or on another server: rooms) -> (GaussianState in FLAME space, the
        head and deform stage durations in us). The returned state is the caller's: never written again while
        referenced (fresh arrays on the reference path, a pooled read-only state on the fast path)."""
        clock = time.perf_counter_ns
        t3 = clock()
        if self.fast is not None:  # FLAME values: the fast path's split and LBS in one numba call; arkit51: morphs
            verts = (self.fast.head(np.asarray(values, np.float32), _IDENTITY5) if self.arkit
                     else self.fast.flame_head(values))
            t4 = clock()
            state = self.fast.deform(verts)
        else:
            if self.arkit:  # what lbs gives: no joints move
                verts = self._morph(self.assets.avatar.head, np.asarray(values, np.float32))
            else:
                expr, rotations = split_flame_values(np.asarray(values, np.float32))
                verts = lbs(self.assets.subject, expr[None], rotations[None])[0][0]
            t4 = clock()
            state = self.deformer.deform(verts)
        t5 = clock()
        return state, {"head": (t4 - t3) // 1000, "deform": (t5 - t4) // 1000}

    @property
    def writes_f16(self) -> bool:
        """Whether :meth:`deform_values_f16` can run (the fast path, triangle binding)."""
        return self.fast is not None and not self.arkit and self.fast.writes_f16

    @property
    def varying(self) -> VaryingRows | None:
        """The rows the fast path writes (what :meth:`deform_values_f16` needs its draft laid out for)."""
        return getattr(self.assets.fast, "varying", None)

    @property
    def neutral(self) -> GaussianState | None:
        """The fast path's neutral Gaussians (every frame's values outside :attr:`varying`)."""
        return getattr(self.assets.fast, "neutral", None)

    def deform_values_f16(self, values: np.ndarray, draft: FrameDraft, psign: np.ndarray, rsign: np.ndarray
                          ) -> tuple[bool, dict[str, int]]:
        """:meth:`deform_values` written straight into a dense f16 frame (``FrameWriter.draft`` of :attr:`varying`,
        wire signs psign, rsign): (False if a value is beyond the half range, the head and deform durations in us).
        The bits are those of the f16 encoding of deform_values' state; no state is made. One kernel call runs the
        head and the rest: its time is split as :meth:`deform_values_delta`'s."""
        clock = time.perf_counter_ns
        t3 = clock()
        ok, share = self.fast.flame_f16(values, draft, psign, rsign)
        spent = clock() - t3
        head = int(spent * share)
        return ok, {"head": head // 1000, "deform": (spent - head) // 1000}

    def deform_values_delta(self, values: np.ndarray, direct: Any) -> tuple[tuple[int, ...], dict[str, int]]:
        """:meth:`deform_values` straight into a delta frame (``direct``: a ``direct_delta.DirectDelta`` of this
        pipeline's fast path and the session's encoder, which it updates, made with the fast session's ``head_args``):
        (what it wrote, a ``direct_delta.Written`` for the encoder's ``encode_written``; the head and deform durations
        in us: "deform" is the deformation with the selection, the encoding passes it runs on the way and the message
        body). No state is made. One kernel call runs the head and the rest: the call's time is split between the two
        by the kernel's own clock (its cycle counter where the vertices were all written; the call's entry and return
        go with it)."""
        clock = time.perf_counter_ns
        t3 = clock()
        written = self.fast.flame_delta(values, direct)
        spent = clock() - t3
        head = int(spent * written.head_share)
        return written, {"head": head // 1000, "deform": (spent - head) // 1000}

    def run(self, weights: np.ndarray, conf: np.ndarray | None = None) -> tuple[GaussianState, dict[str, int]]:
        """`map` then `deform_values`: weights (L,) [and conf (2,)] -> (GaussianState in FLAME space, the STAGES'
        durations in us); `self.values` keeps the frame's expression values."""
        self.values, mapped = self.map(weights, conf)
        state, deformed = self.deform_values(self.values)
        return state, {**mapped, **deformed}

    def warm_up(self, frames: int = 3) -> None:
        """Run a few frames so that first-use costs (allocation, ONNX graph set-up) are paid now."""
        if self.assets.fast is not None:
            self.assets.fast.warm_up(threads=self.assets.parallel is not False)  # auto may thread any frame
        w = np.zeros(self.adapter.layout.length, np.float32)
        for _ in range(frames):
            self.run(w)

