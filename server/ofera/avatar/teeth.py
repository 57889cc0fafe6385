"""GaussianAvatars' teeth extension of FLAME: 120 vertices and 168 faces appended to the head.

Layout (the same as upstream, so face indices in a GaussianAvatars ``binding_0`` mean the same faces):
8 rows of 15 vertices, column 0 at +x (the subject's left), in this order: upper root, lower root, upper
edge, lower edge, upper root back, upper edge back, lower root back, lower edge back. Faces: upper front,
upper back, upper bottom strip, then the same three for the lower teeth, 28 each; the diagonal of each
strip flips at the middle column so the strips are mirror-symmetric. Upper teeth are skinned to the neck,
lower teeth to the jaw; no expression, pose correctives or joint regression; the identity basis is the mean
of the two lip rings' (so the teeth follow the lips' identity shape).

Placement (upstream's construction): with ``u`` the mean distance between the upper and lower lip rings,
the teeth middle line is the rings' midline set back by 1.5 u (at the rings' mean height); upper teeth
span 0.1 u .. 2.1 u above it, lower teeth the same below it and 0.4 u further back; thickness u.
Upstream reads the lip rings from FLAME's vertex masks (not available here). This module finds the mouth
opening as a boundary loop of the mesh instead: the loop nearest the ``mouth_centre`` landmark when the
head has one, otherwise the lowest loop on the front of the head; each ring is 15 points on the loop's
upper or lower half, evenly spaced by arc length from the +x corner to the -x corner (interpolated
between the loop's vertices, identity basis included). Since the inner rim
of a closed mouth has nearly coincident rings, ``u`` is at least 10 % of the mouth's width.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..head.model import HeadModel
from .errors import AvatarError

FLAME_VERTICES, FLAME_FACES = 5023, 9976
TEETH_VERTICES, TEETH_FACES = 120, 168
COLUMNS = 15
(UPPER_ROOT, LOWER_ROOT, UPPER_EDGE, LOWER_EDGE, UPPER_ROOT_BACK, UPPER_EDGE_BACK, LOWER_ROOT_BACK,
 LOWER_EDGE_BACK) = (np.arange(COLUMNS) + COLUMNS * k for k in range(8))


def _strip(a: np.ndarray, b: np.ndarray, first: tuple, second: tuple) -> np.ndarray:
    """Two triangles per column pair between vertex rows ``a`` and ``b``; patterns flip at column 7.

    ``first``/``second`` give each half's two triangles as (row, column offset) triples.
    """
    rows = {"a": a, "b": b}
    out = []
    for i in range(COLUMNS - 1):
        for tri in first if i < COLUMNS // 2 else second:
            out.append([rows[r][i + d] for r, d in tri])
    return np.array(out, np.int64)


def teeth_faces() -> np.ndarray:
    """(168, 3) faces over the 120 teeth vertices (indices 0..119), upstream's order."""
    a0, a1, b0, b1 = ("a", 0), ("a", 1), ("b", 0), ("b", 1)
    upper_front = _strip(UPPER_ROOT, UPPER_EDGE, ((a0, b1, b0), (a0, a1, b1)), ((a0, a1, b0), (a1, b1, b0)))
    upper_back = _strip(UPPER_ROOT_BACK, UPPER_EDGE_BACK, ((a0, b0, b1), (a0, b1, a1)), ((a0, b0, a1), (a1, b0, b1)))
    upper_strip = _strip(UPPER_EDGE_BACK, UPPER_EDGE, ((a0, b0, a1), (a1, b0, b1)), ((a0, b0, b1), (a0, b1, a1)))
    lower_front = _strip(LOWER_EDGE, LOWER_ROOT, ((a0, a1, b0), (a1, b1, b0)), ((a0, b1, b0), (a0, a1, b1)))
    lower_back = _strip(LOWER_ROOT_BACK, LOWER_EDGE_BACK, ((a0, b1, b0), (a0, a1, b1)), ((a0, a1, b0), (a1, b1, b0)))
    lower_strip = _strip(LOWER_EDGE_BACK, LOWER_EDGE, ((a0, a1, b0), (a1, b1, b0)), ((a0, b1, b0), (a0, a1, b1)))
    return np.concatenate([upper_front, upper_back, upper_strip, lower_front, lower_back, lower_strip])


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed loops of boundary edges, each (L,) vertex ids in the direction the faces traverse them."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(e, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = e[counts[inv.reshape(-1)] == 1]
    nxt: dict[int, list[int]] = {}
    for a, b in boundary.tolist():
        nxt.setdefault(a, []).append(b)
    loops, seen = [], set()
    for start in list(nxt):
        if start in seen:
            continue
        loop, cur = [], start
        while cur not in seen and cur in nxt and len(loop) <= len(boundary):
            seen.add(cur)
            loop.append(cur)
            cur = nxt[cur][0]
        if cur == start and len(loop) >= 4:
            loops.append(np.array(loop, np.int64))
    return loops


def find_mouth_loop(head: HeadModel) -> np.ndarray:
    """The boundary loop of the mouth opening (see the module docstring); AvatarError when there is none."""
    loops = boundary_loops(head.faces)
    v = head.v_template
    centres = [v[loop].mean(axis=0) for loop in loops]
    if loops and "mouth_centre" in head.landmarks:
        d = [np.linalg.norm(c - head.landmarks["mouth_centre"]) for c in centres]
        return loops[int(np.argmin(d))]
    z_mean, z_max = v[:, 2].mean(), v[:, 2].max()
    front = [i for i, c in enumerate(centres) if c[2] > z_mean + 0.3 * (z_max - z_mean) and len(loops[i]) >= 6]
    if not front:
        raise AvatarError(
            f"head {head.name!r}: cannot find the mouth opening (no boundary loop on the front of the head) "
            "to place GaussianAvatars' teeth; give a FLAME head"
        )
    return loops[min(front, key=lambda i: centres[i][1])]


@dataclass(frozen=True)
class Ring:
    """15 points along a lip chain, each between two chain vertices: p = (1 - w) v[i0] + w v[i1]."""

    i0: np.ndarray
    i1: np.ndarray
    w: np.ndarray

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """Interpolate per-vertex values (V, ...) at the ring's points -> (15, ...)."""
        w = self.w.reshape(-1, *([1] * (values.ndim - 1)))
        return (1 - w) * values[self.i0] + w * values[self.i1]


def _resample(chain: np.ndarray, v: np.ndarray, n: int = COLUMNS) -> Ring:
    """``n`` points evenly spaced by arc length along ``chain`` (ends included)."""
    p = v[chain]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    targets = np.linspace(0.0, s[-1], n)
    k = np.clip(np.searchsorted(s, targets, side="right") - 1, 0, len(chain) - 2)
    w = np.clip((targets - s[k]) / np.maximum(s[k + 1] - s[k], 1e-12), 0.0, 1.0)
    return Ring(chain[k], chain[k + 1], w)


def lip_rings(head: HeadModel) -> tuple[Ring, Ring]:
    """Upper and lower rings, 15 points each from the +x corner to the -x corner."""
    loop = find_mouth_loop(head)
    v = head.v_template
    loop = np.roll(loop, -int(np.argmax(v[loop, 0])))  # start at the +x corner
    k = int(np.argmin(v[loop, 0]))  # the -x corner
    # Faces lie left of their boundary edges, so seen from the front (+z) the hole is walked clockwise:
    # from the +x corner along the bottom to the -x corner, then back along the top.
    lower = loop[: k + 1]
    upper = np.concatenate([loop[k:], loop[:1]])[::-1]
    if v[upper, 1].mean() < v[lower, 1].mean() - 1e-6:  # a mesh wound the other way
        upper, lower = lower, upper
    return _resample(upper, v), _resample(lower, v)


def teeth_vertices(v_upper: np.ndarray, v_lower: np.ndarray) -> np.ndarray:
    """(120, 3) teeth vertices from the two lip rings (15, 3) each, upstream's construction."""
    unit = max(float(np.linalg.norm(v_upper - v_lower, axis=1).mean()),
               0.1 * float(np.ptp(np.concatenate([v_upper, v_lower])[:, 0])))
    middle = (v_upper + v_lower) / 2
    middle[:, 1] = middle[:, 1].mean()
    middle[:, 2] -= 1.5 * unit
    up, back = np.array([0.0, unit, 0.0]), np.array([0.0, 0.0, unit])
    upper_edge = middle + 0.1 * up
    upper_root = upper_edge + 2 * up
    lower_edge = middle - 0.1 * up - 0.4 * back
    lower_root = lower_edge - 2 * up
    rows = [upper_root, lower_root, upper_edge, lower_edge,
            upper_root - back, upper_edge - back, lower_root - back, lower_edge - back]
    return np.concatenate(rows)


def add_teeth(head: HeadModel) -> HeadModel:
    """The head with GaussianAvatars' teeth appended (V + 120 vertices, F + 168 faces)."""
    upper, lower = lip_rings(head)
    v = head.num_vertices
    teeth = teeth_vertices(upper(head.v_template), lower(head.v_template))
    is_upper = np.zeros(TEETH_VERTICES, bool)
    is_upper[np.concatenate([UPPER_ROOT, UPPER_EDGE, UPPER_ROOT_BACK, UPPER_EDGE_BACK])] = True
    weights = np.zeros((TEETH_VERTICES, head.num_joints))
    weights[is_upper, 1] = 1.0  # neck
    weights[~is_upper, 2] = 1.0  # jaw
    shape_mean = (upper(head.shapedirs) + lower(head.shapedirs)) / 2  # (15, 3, S)
    posedirs = head.posedirs.reshape(-1, v, 3)
    labels = {k: np.concatenate([m, np.zeros(TEETH_VERTICES, bool)]) for k, m in head.vertex_labels.items()}
    labels["teeth_upper"] = np.concatenate([np.zeros(v, bool), is_upper])
    labels["teeth_lower"] = np.concatenate([np.zeros(v, bool), ~is_upper])
    return replace(
        head,
        v_template=np.concatenate([head.v_template, teeth]),
        shapedirs=np.concatenate([head.shapedirs, np.tile(shape_mean, (8, 1, 1))]),
        exprdirs=np.concatenate([head.exprdirs, np.zeros((TEETH_VERTICES, 3, head.expr_dims))]),
        posedirs=np.concatenate([posedirs, np.zeros((posedirs.shape[0], TEETH_VERTICES, 3))], axis=1).reshape(
            posedirs.shape[0], -1),
        j_regressor=np.concatenate([head.j_regressor, np.zeros((head.num_joints, TEETH_VERTICES))], axis=1),
        weights=np.concatenate([head.weights, weights]),
        faces=np.concatenate([head.faces, teeth_faces() + v]),
        name=f"{head.name}+teeth",
        vertex_labels=labels,
    )
