"""The per-frame pipeline: layout adapter -> BDA -> EPM -> FLAME values -> LBS -> Gaussian deformation.

`Pipeline.run(weights) -> (GaussianState, timings)` is the whole computation of one frame, in FLAME
space; the server and `offline_pipeline` call the same code, so a streamed f32 frame equals the
offline result bit for bit. One Pipeline per session (the layout adapter, the mapper's bound buffers
and the deformer hold per-call state); the heavy parts (avatar, head subject, ONNX session) are shared
through `AvatarAssets`, which `registry.AvatarRegistry` loads once per avatar.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from ofera_protocol import Avatar as WireAvatar
from ofera_protocol import Quant, make_quant, mirror_x_position, mirror_x_rotation, mirror_x_sh

from ..head import HeadSubject, lbs
from ..mapping.bda import BDA
from ..mapping.flame_values import split_flame_values
from ..mapping.layouts import LayoutAdapter
from ..mapping.runtime import Mapper

STAGES: tuple[str, ...] = ("layout", "bda", "epm", "head", "deform")
"""Stage names of `Pipeline.run` timings, in order (microseconds): layout adapter, BDA, EPM (with the
split into expression and rotations), head model (LBS), Gaussian deformation."""


@dataclass
class AvatarAssets:
    """Everything shared by the sessions of one avatar: loaded once, read-only afterwards."""

    id: str
    avatar: Any  # ofera.avatar.GaussianAvatar
    subject: HeadSubject
    mapper: Mapper  # the avatar's EPM (its ONNX session is shared; each Pipeline binds its own buffers)
    bda: BDA  # the avatar's own BDA (sibling <id>.bda.npz) or identity; a device profile overrides it
    fast: Any = None  # ofera.avatar.fast.FastAvatar (shared, read-only), or None: the numpy reference
    _cache: dict[tuple, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def create(cls, avatar_id: str, avatar: Any, mapper: Mapper, bda: BDA | None = None,
               fast: bool = True) -> AvatarAssets:
        """`fast`: deform with `ofera.avatar.fast` (subset LBS + numba kernels) instead of the reference."""
        subject = HeadSubject.create(avatar.head)  # the avatar's identity is baked into its head's template
        fast_avatar = None
        if fast:
            from ..avatar.fast import FastAvatar

            fast_avatar = FastAvatar(avatar, subject)
        return cls(avatar_id, avatar, subject, mapper, bda if bda is not None else BDA.identity(), fast_avatar)

    @property
    def count(self) -> int:
        return int(self.avatar.count)

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

    def pipeline(self, layout: str, bda: BDA | None = None) -> Pipeline:
        return Pipeline(self, layout, bda)


class Pipeline:
    """One session's pipeline for one avatar and one blendshape layout. Not thread-safe: run one frame
    at a time (the session does)."""

    def __init__(self, assets: AvatarAssets, layout: str, bda: BDA | None = None) -> None:
        self.assets = assets
        self.layout = layout
        self.adapter = LayoutAdapter(layout)
        self.bda = bda if bda is not None else assets.bda
        base = assets.mapper
        # The BDA runs as its own stage; the mapper gets an identity BDA (a clamp, a no-op on [0, 1]).
        self.mapper = Mapper(base.session, None, source=base.source)
        # Head model + deformation: the fast path's per-stream buffers, or the reference deformer.
        self.fast = assets.fast.session() if assets.fast is not None else None
        self.deformer = assets.avatar.deformer() if self.fast is None else None
        self._x51 = np.zeros(51, np.float32)
        self._y = np.zeros(68, np.float32)

    def run(self, weights: np.ndarray) -> tuple[Any, dict[str, int]]:
        """Blendshape weights (L,) in the session's layout -> (GaussianState in FLAME space, stage
        durations in microseconds). The returned state is the caller's: never written again while referenced
        (fresh arrays on the reference path, a pooled read-only state on the fast path)."""
        clock = time.perf_counter_ns
        t0 = clock()
        x = self.adapter(weights)
        t1 = clock()
        a = self.bda.apply(x, out=self._x51)
        t2 = clock()
        y = self.mapper.map(a, out=self._y)
        expr, rotations = split_flame_values(y)
        t3 = clock()
        if self.fast is not None:
            verts = self.fast.head(expr, rotations)
            t4 = clock()
            state = self.fast.deform(verts)
        else:
            verts = lbs(self.assets.subject, expr[None], rotations[None])[0][0]
            t4 = clock()
            state = self.deformer.deform(verts)
        t5 = clock()
        ts = (t0, t1, t2, t3, t4, t5)
        return state, {name: (ts[i + 1] - ts[i]) // 1000 for i, name in enumerate(STAGES)}

    def warm_up(self, frames: int = 3) -> None:
        """Run a few frames so that first-use costs (allocation, ONNX graph set-up) are paid now."""
        if self.assets.fast is not None:
            self.assets.fast.warm_up()  # compiles (or loads cached) numba kernels
        w = np.zeros(self.adapter.layout.length, np.float32)
        for _ in range(frames):
            self.run(w)


def offline_pipeline(avatar_id: str, layout: str, weights: np.ndarray, *, settings: Any = None,
                     device: str | None = None) -> tuple[Any, dict[str, int]]:
    """The server's computation for one frame, without a server: same registry, same Pipeline.

    `settings` (streaming.config.Settings) selects the avatars / devices directories like the
    server's; None uses the defaults (environment included).
    """
    from .registry import registry_for

    reg = registry_for(settings)
    assets = reg.get(avatar_id)
    bda = reg.device_bda(device) if device else None
    return Pipeline(assets, layout, bda).run(np.asarray(weights, np.float32))
