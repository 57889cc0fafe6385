"""Blendshape layouts (ARKit, MediaPipe, Meta OVR, Live Link) and their linear maps to ARKit.

A layout is an ordered list of blendshape names. Every layout converts to the canonical `arkit51`
order (ARKit without tongueOut, the model input) or to `arkit52` through a precomputed
`(N, K)` float32 matrix M: ``arkit = clip(M @ w, 0, 1)``. For ARKit-family layouts M selects and
permutes; for Meta OVR layouts M is Meta's v10 retargeting (arkit_retarget_a2e_v10.json) plus Meta's
older 1:1 fill for the eight eyeLook shapes and tongueOut.

Names match case-insensitively with underscores removed, so ``eyeBlinkLeft == EyeBlinkLeft`` and
``BROW_LOWERER_L == BrowLowererL`` (Unity's OVRFaceExpressions spelling).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from ofera_protocol.layouts import (  # noqa: F401 - re-exported: the names in wire order are the protocol's (4.1)
    ARKIT51_NAMES,
    ARKIT52_NAMES,
    LAYOUT_NAMES,
    LIVELINK61_NAMES,
    MEDIAPIPE52_NAMES,
    OVR63_NAMES,
    OVR70_NAMES,
)

from ..errors import OferaError


def normalize_name(name: str) -> str:
    """Matching key of a blendshape name: lowercase, underscores and surrounding spaces removed."""
    return name.strip().replace("_", "").lower()


class LayoutError(OferaError, ValueError):
    """An unknown layout name, or names that do not match a layout."""


@dataclass(frozen=True)
class Layout:
    """An ordered blendshape layout; `family` is "arkit" (ARKit names) or "ovr" (Meta names)."""

    name: str
    names: tuple[str, ...]
    family: str
    _index: dict[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        index: dict[str, int] = {}
        for i, n in enumerate(self.names):
            if normalize_name(n) in index:
                raise LayoutError(f"layout {self.name!r}: duplicate name {n!r}")
            index[normalize_name(n)] = i
        object.__setattr__(self, "_index", index)

    @property
    def length(self) -> int:
        """Number of values K per frame."""
        return len(self.names)

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and normalize_name(name) in self._index

    def index(self, name: str) -> int:
        """Position of `name` (any spelling accepted by `normalize_name`)."""
        try:
            return self._index[normalize_name(name)]
        except KeyError:
            raise LayoutError(f"{name!r} is not a name of layout {self.name!r}") from None


FAMILIES: dict[str, str] = {"arkit52": "arkit", "arkit51": "arkit", "mediapipe52": "arkit", "ovr63": "ovr",
                             "ovr70": "ovr", "livelink61": "arkit"}
"""Layout name -> "arkit" (ARKit names) or "ovr" (Meta names)."""

LAYOUTS: dict[str, Layout] = {name: Layout(name, names, FAMILIES[name]) for name, names in LAYOUT_NAMES.items()}
"""Registry of the known layouts by name (the protocol's, ``ofera_protocol.layouts``)."""

TARGET_LAYOUTS: tuple[str, ...] = ("arkit51", "arkit52")
"""Layouts that every layout converts to."""


def get_layout(layout: str | Layout) -> Layout:
    """The registered layout called `layout` (case-insensitive); a `Layout` is returned as is."""
    if isinstance(layout, Layout):
        return layout
    try:
        return LAYOUTS[layout.strip().lower()]
    except KeyError:
        raise LayoutError(f"unknown layout {layout!r}; valid layouts: {', '.join(LAYOUTS)}") from None


def _listing(names: Sequence[str], limit: int = 12) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def layout_from_names(names: Sequence[str], layout: str | Layout | None = None) -> tuple[Layout, np.ndarray]:
    """Detect the layout of column `names` (or check them against `layout`).

    Returns the layout and `column_index` (K,) int64 with ``names[column_index[j]] == layout.names[j]``
    (up to spelling), so ``table[:, column_index]`` is in layout order. Names must match a layout
    exactly as a set; otherwise `LayoutError` names the unknown and missing names of the closest one.
    """
    keys = [normalize_name(n) for n in names]
    position: dict[str, int] = {}
    for i, key in enumerate(keys):
        if key in position:
            raise LayoutError(f"duplicate column {names[i]!r} (also column {position[key] + 1})")
        position[key] = i
    candidates = [get_layout(layout)] if layout is not None else list(LAYOUTS.values())
    best: tuple[int, Layout, list[str], list[str]] | None = None
    for cand in candidates:
        unknown = [n for n, k in zip(names, keys, strict=True) if k not in cand._index]
        missing = [n for n in cand.names if normalize_name(n) not in position]
        if not unknown and not missing:
            index = np.array([position[normalize_name(n)] for n in cand.names], dtype=np.int64)
            return cand, index
        if best is None or len(unknown) + len(missing) < best[0]:
            best = (len(unknown) + len(missing), cand, unknown, missing)
    assert best is not None
    _, cand, unknown, missing = best
    problems = "; ".join(
        f"{label} names: {_listing(found)}" for label, found in (("unknown", unknown), ("missing", missing)) if found
    )
    if layout is not None:
        raise LayoutError(f"names do not match layout {cand.name!r}: {problems}")
    raise LayoutError(
        f"names match no layout; closest is {cand.name!r} with {problems} (layouts: {', '.join(LAYOUTS)})"
    )


def _sided(arkit_stem: str, *drivers: tuple[str, float]) -> dict[str, tuple[tuple[str, float], ...]]:
    """ARKit `<stem>Left/Right` driven by OVR `<driver>_L/_R` of the same side."""
    return {f"{arkit_stem}{side}": tuple((f"{ovr}_{side[0]}", w) for ovr, w in drivers) for side in ("Left", "Right")}


OVR_TO_ARKIT: dict[str, tuple[tuple[str, float], ...]] = {
    **_sided("browDown", ("BROW_LOWERER", 1.0)),
    "browInnerUp": (("INNER_BROW_RAISER_L", 1.0), ("INNER_BROW_RAISER_R", 1.0)),
    **_sided("browOuterUp", ("OUTER_BROW_RAISER", 1.5)),
    "cheekPuff": (("CHEEK_PUFF_L", 1.0), ("CHEEK_PUFF_R", 1.0)),
    **_sided("cheekSquint", ("CHEEK_RAISER", 1.0), ("LIP_CORNER_PULLER", 1.0)),
    **_sided("eyeBlink", ("EYES_CLOSED", 1.0)),
    **_sided("eyeSquint", ("LID_TIGHTENER", 1.0), ("LIP_CORNER_PULLER", 0.25)),
    **_sided("eyeWide", ("UPPER_LID_RAISER", 1.0)),
    "jawOpen": (("JAW_DROP", 1.0),),
    "jawForward": (("JAW_THRUST", 1.0),),
    "jawLeft": (("JAW_SIDEWAYS_LEFT", 1.0),),
    "jawRight": (("JAW_SIDEWAYS_RIGHT", 1.0),),
    "mouthClose": (("LIPS_TOWARD", 1.0),),
    "mouthFunnel": (
        ("LIP_FUNNELER_LB", 0.75),
        ("LIP_FUNNELER_LT", 0.75),
        ("LIP_FUNNELER_RB", 0.75),
        ("LIP_FUNNELER_RT", 0.75),
        ("LIP_PUCKER_L", 0.75),
        ("LIP_PUCKER_R", 0.75),
    ),
    "mouthPucker": (("LIP_PUCKER_L", 0.75), ("LIP_PUCKER_R", 0.75)),
    "mouthRollLower": (("LIP_SUCK_LB", 0.5), ("LIP_SUCK_RB", 0.5)),
    "mouthRollUpper": (("LIP_SUCK_LT", 0.5), ("LIP_SUCK_RT", 0.5)),
    "mouthShrugLower": (("CHIN_RAISER_B", 1.0),),
    "mouthShrugUpper": (("CHIN_RAISER_T", 1.0),),
    **_sided("mouthSmile", ("LIP_CORNER_PULLER", 1.0)),
    **_sided("mouthFrown", ("LIP_CORNER_DEPRESSOR", 1.0)),
    **_sided("mouthDimple", ("DIMPLER", 1.0)),
    **_sided("mouthStretch", ("LIP_STRETCHER", 1.0)),
    **_sided("mouthPress", ("LIP_PRESSOR", 1.0)),
    **_sided("mouthLowerDown", ("LOWER_LIP_DEPRESSOR", 1.0)),
    **_sided("mouthUpperUp", ("UPPER_LIP_RAISER", 1.0)),
    "mouthLeft": (("MOUTH_LEFT", 1.0),),
    "mouthRight": (("MOUTH_RIGHT", 1.0),),
    **_sided("noseSneer", ("NOSE_WRINKLER", 1.0)),
    # Not in v10: Meta's older 1:1 mapping. "In" for the left eye is looking right, and vice versa.
    "eyeLookInLeft": (("EYES_LOOK_RIGHT_L", 1.0),),
    "eyeLookOutLeft": (("EYES_LOOK_LEFT_L", 1.0),),
    "eyeLookInRight": (("EYES_LOOK_LEFT_R", 1.0),),
    "eyeLookOutRight": (("EYES_LOOK_RIGHT_R", 1.0),),
    **_sided("eyeLookUp", ("EYES_LOOK_UP", 1.0)),
    **_sided("eyeLookDown", ("EYES_LOOK_DOWN", 1.0)),
    "tongueOut": (("TONGUE_OUT", 1.0),),
}
"""ARKit name -> OVR drivers (name, weight); arkit = clamp(sum(weight * ovr), 0, 1)."""


def _target(dst: str | Layout) -> Layout:
    target = get_layout(dst)
    if target.name not in TARGET_LAYOUTS or LAYOUTS[target.name] != target:
        raise LayoutError(f"cannot convert to {target.name!r}; targets: {', '.join(TARGET_LAYOUTS)}")
    return target


@lru_cache(maxsize=64)
def _matrix(src: Layout, dst: Layout) -> np.ndarray:
    m = np.zeros((dst.length, src.length), dtype=np.float32)
    for row, name in enumerate(dst.names):
        if src.family == "arkit":
            drivers: tuple[tuple[str, float], ...] = ((name, 1.0),)
        else:
            drivers = OVR_TO_ARKIT[name]
        for driver, weight in drivers:
            if driver in src:
                m[row, src.index(driver)] += weight
    m.setflags(write=False)
    return m


def conversion_matrix(layout: str | Layout, dst: str | Layout = "arkit51") -> np.ndarray:
    """Read-only (N, K) float32 M with ``dst = clip(M @ w, 0, 1)``; N = 51 or 52, K = layout length."""
    return _matrix(get_layout(layout), _target(dst))


def _as_frames(layout: Layout, w: np.ndarray) -> np.ndarray:
    if w.ndim not in (1, 2) or w.shape[-1] != layout.length:
        raise ValueError(
            f"expected weights of shape ({layout.length},) or (B, {layout.length}) for layout "
            f"{layout.name!r}, got {w.shape}"
        )
    return w


def convert(layout: str | Layout, w: np.ndarray, dst: str | Layout = "arkit51") -> np.ndarray:
    """Weights (K,) or (B, K) in `layout` -> (N,) or (B, N) float32 in `dst`, clamped to [0, 1]."""
    src = get_layout(layout)
    w = _as_frames(src, np.asarray(w, dtype=np.float32))
    out = w @ conversion_matrix(src, dst).T
    return np.clip(out, 0.0, 1.0, out=out)


def to_arkit51(layout: str | Layout, w: np.ndarray) -> np.ndarray:
    """Weights (K,) or (B, K) in `layout` -> (51,) or (B, 51) float32 arkit51, clamped to [0, 1]."""
    return convert(layout, w, "arkit51")


def convert_reference(layout: str | Layout, w: np.ndarray, dst: str | Layout = "arkit51") -> np.ndarray:
    """Plain per-name implementation of `convert` (dict lookups, no matrix), for tests."""
    src, target = get_layout(layout), _target(dst)
    w = _as_frames(src, np.asarray(w, dtype=np.float64))
    if w.ndim == 2:
        return np.stack([convert_reference(src, row, target) for row in w]).astype(np.float32)
    values = {normalize_name(n): float(v) for n, v in zip(src.names, w, strict=True)}
    out = []
    for name in target.names:
        if src.family == "arkit":
            total = values.get(normalize_name(name), 0.0)
        else:
            total = sum(wt * values.get(normalize_name(drv), 0.0) for drv, wt in OVR_TO_ARKIT[name])
        out.append(min(1.0, max(0.0, total)))
    return np.array(out, dtype=np.float32)


_ZERO, _ONE = np.float32(0.0), np.float32(1.0)


class LayoutAdapter:
    """Hot-path converter from one layout to arkit51/arkit52 with a precomputed matrix.

    ``adapter(w)`` writes into ``adapter.out`` (N,) and returns it (overwritten by the next call: copy
    to keep); pass `out` for batches (B, N) or your own buffer. Input (K,) or (B, K), float32 ideally.
    """

    def __init__(self, layout: str | Layout, dst: str | Layout = "arkit51") -> None:
        self.layout = get_layout(layout)
        self.target = _target(dst)
        self._mt = np.ascontiguousarray(conversion_matrix(self.layout, self.target).T)  # (K, N)
        self.out = np.zeros(self.target.length, dtype=np.float32)

    @property
    def mt(self) -> np.ndarray:
        """(K, N) float32: the conversion matrix, transposed (``w @ mt``; the fast path's kernel reads it)."""
        return self._mt

    def __call__(self, w: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        w = np.asarray(w, dtype=np.float32)
        if w.shape[-1] != self.layout.length:
            raise ValueError(f"expected {self.layout.length} values for {self.layout.name!r}, got {w.shape}")
        if out is None:
            out = self.out
        np.dot(w, self._mt, out=out)
        np.maximum(out, _ZERO, out=out)  # two ufuncs with float32 scalars: ~3x faster than np.clip here
        return np.minimum(out, _ONE, out=out)


_REGION_OF_PREFIX = {
    "eye": "eyes",
    "brow": "brows",
    "jaw": "mouth_jaw",
    "mouth": "mouth_jaw",
    "tongue": "mouth_jaw",
    "cheek": "cheeks_nose",
    "nose": "cheeks_nose",
}

ARKIT_REGIONS: dict[str, tuple[str, ...]] = {
    region: tuple(n for n in ARKIT52_NAMES if any(n.startswith(p) for p, r in _REGION_OF_PREFIX.items() if r == region))
    for region in ("eyes", "brows", "mouth_jaw", "cheeks_nose")
}
"""ARKit names by face region: eyes (14), brows (5), mouth_jaw (28, with tongueOut), cheeks_nose (5)."""


def region_indices(region: str, layout: str | Layout = "arkit51") -> np.ndarray:
    """Indices (int64) in an ARKit-family `layout` of the names of `region` that it contains."""
    lay = get_layout(layout)
    if region not in ARKIT_REGIONS:
        raise LayoutError(f"unknown region {region!r}; regions: {', '.join(ARKIT_REGIONS)}")
    return np.array([lay.index(n) for n in ARKIT_REGIONS[region] if n in lay], dtype=np.int64)
