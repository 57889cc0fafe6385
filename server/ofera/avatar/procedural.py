"""The default avatar: a procedural Gaussian head bound (triangle-local) to the default procedural head.

Deterministic (seeded) and built in a few seconds from the head's geometry and its ``vertex_labels`` /
``landmarks``. Three groups of Gaussians, all made in world space on the neutral head and then bound to
their face with :meth:`TriangleBinding.from_world`:

- surface: flat discs in the face planes, distributed by face area times a density weight (denser on the
  face and the front of the eyes), sized from the local spacing so the surface is covered; colour from
  the labels (skin, lips, brows, hair on the scalp, sclera / iris / pupil from the angle to the eye's axis,
  a dark mouth cavity with a tongue), times a baked soft light and a concavity darkening;
- hair: elongated strands a little off the scalp (0.4-3.5 mm), combed away from a crown point;
- teeth: two arches behind the lips, bound to mouth-cavity faces that follow the head (upper) or the jaw
  (lower) rigidly.

SH degree 3: DC holds the colour, degree 1 a small view-dependent sheen (brighter facing the camera), degrees
2-3 faint noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..head.model import HeadModel
from ..head.procedural import EYE_HALF_OPENING, MOUTH_Y, smoothstep
from ..head.rotations import matrix_to_quaternion
from .binding import TriangleBinding
from .frames import face_areas, face_frames, face_normals_unnormalised
from .model import GaussianAvatar
from .sh import C1, rgb_to_dc

GENERATOR_VERSION = 1
SEED = 20250607
SURFACE_COUNT, HAIR_COUNT, TEETH_COUNT = 100_000, 14_000, 1_600
SPACING_TO_SIGMA = 0.85  # in-plane standard deviation / mean spacing of the samples

SKIN = np.array([0.88, 0.68, 0.57])
LIPS = np.array([0.72, 0.36, 0.37])
BROW = np.array([0.20, 0.14, 0.10])
HAIR = np.array([0.17, 0.11, 0.075])
LASH = np.array([0.10, 0.07, 0.06])
SCLERA = np.array([0.95, 0.93, 0.91])
IRIS = np.array([0.30, 0.45, 0.58])
PUPIL = np.array([0.02, 0.02, 0.025])
MOUTH = np.array([0.20, 0.055, 0.055])
TONGUE = np.array([0.42, 0.17, 0.19])
NOSTRIL = np.array([0.30, 0.15, 0.13])
TEETH = np.array([0.93, 0.91, 0.84])
LIGHT = np.array([0.35, 0.55, 1.0]) / np.linalg.norm([0.35, 0.55, 1.0])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


@dataclass
class _Parts:
    """World-space Gaussians of one group, all (n, ...) float64."""

    face: np.ndarray
    position: np.ndarray
    axes: np.ndarray  # (n, 3, 3) rotation, columns are the Gaussian's axes
    scale: np.ndarray  # (n, 3) metres along the axes
    rgb: np.ndarray
    opacity: np.ndarray
    normal: np.ndarray  # (n, 3) surface normal, for the view-dependent sheen
    sheen: np.ndarray  # (n,) strength of the degree-1 term


class _Mesh:
    """Neutral geometry and label fields of the head, precomputed once."""

    def __init__(self, head: HeadModel) -> None:
        self.head = head
        self.v = head.v_template.astype(np.float64)
        self.f = head.faces
        self.frames, self.s_f, self.centroid = face_frames(self.v, self.f)
        self.area = face_areas(self.v, self.f)
        fn = face_normals_unnormalised(self.v, self.f)
        vn = np.zeros_like(self.v)
        for k in range(3):
            np.add.at(vn, self.f[:, k], fn)
        self.vertex_normal = _unit(vn)
        self.labels = {k: m.astype(np.float64) for k, m in head.vertex_labels.items()}
        self.concavity = self._concavity()
        self.lm = head.landmarks

    def _concavity(self) -> np.ndarray:
        """(V,) >= 0: how far each vertex sits below its neighbours' mean along its normal, per edge length."""
        f = self.f
        rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
        cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
        adj = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(self.v),) * 2)
        adj.data[:] = 1.0
        deg = np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1)
        lap = adj @ self.v / deg[:, None] - self.v
        length = np.linalg.norm(self.v[rows] - self.v[cols], axis=1)
        count = np.maximum(np.bincount(rows, None, len(self.v)), 1)
        edge = np.maximum(np.bincount(rows, length, len(self.v)) / count, 1e-9)  # mean edge length per vertex
        return np.maximum((lap * self.vertex_normal).sum(1) / edge, 0.0)

    def field(self, name: str, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """A vertex label interpolated at samples: (n,) in 0..1 (zeros when the head lacks the label)."""
        if name not in self.labels:
            return np.zeros(len(face))
        return (self.labels[name][self.f[face]] * bary).sum(axis=1)

    def interp(self, values: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Per-vertex values (V, ...) interpolated at samples."""
        return np.einsum("nk,nk...->n...", bary, values[self.f[face]])


def allocate(weights: np.ndarray, total: int) -> np.ndarray:
    """Integer counts (F,) summing to ``total`` proportional to ``weights`` (largest remainder)."""
    expected = weights / weights.sum() * total
    counts = np.floor(expected).astype(np.int64)
    rest = total - counts.sum()
    counts[np.argsort(-(expected - counts), kind="stable")[:rest]] += 1
    return counts


def sample_faces(counts: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Face ids (n,) and uniform barycentric coordinates (n, 3) for ``counts`` samples per face."""
    face = np.repeat(np.arange(len(counts)), counts)
    r1, r2 = np.sqrt(rng.random(len(face))), rng.random(len(face))
    return face, np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)


def _in_plane_axes(frames: np.ndarray, direction: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
    """Axes (n, 3, 3) = (t, normal, t x normal) with t along ``direction`` projected on the plane (else random)."""
    normal = frames[:, :, 1]
    if direction is None:
        theta = rng.uniform(0, 2 * np.pi, len(frames))
        t = frames[:, :, 0] * np.cos(theta)[:, None] + frames[:, :, 2] * np.sin(theta)[:, None]
    else:
        t = _unit(direction - (direction * normal).sum(1, keepdims=True) * normal)
    return np.stack([t, normal, np.cross(t, normal)], axis=-1)


def _lambert(normal: np.ndarray, ambient: float = 0.42, key: float = 0.62) -> np.ndarray:
    return np.minimum(ambient + key * np.maximum(normal @ LIGHT, 0.0) + 0.06 * normal[:, 1], 1.08)


def lip_masks(pos: np.ndarray, lm: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Lip colour weight (n,) in 0..1 and the dark line where the lips meet, from the canonical position.

    Upper lip: from the mouth line up to a cupid's-bow curve; lower lip: down to a fuller curve; both taper
    to the mouth corners (landmarks ``mouth_corner_left``; the mouth line is the head's ``MOUTH_Y``).
    """
    x, y, z = pos.T
    hw = abs(lm["mouth_corner_left"][0]) + 0.0012
    u = np.clip(np.abs(x) / hw, 0, 1)
    top = MOUTH_Y + 0.0066 * np.sqrt(1 - u**2) - 0.0011 * np.exp(-((x / 0.0032) ** 2))
    bottom = MOUTH_Y - 0.0088 * (1 - u**2) ** 0.6
    soft = 0.0007
    inside = smoothstep((top - y) / soft + 0.5) * smoothstep((y - bottom) / soft + 0.5)
    front = smoothstep((z - 0.05) / 0.01) * (np.abs(x) < hw)
    seam = np.exp(-(((y - MOUTH_Y) / 0.0006) ** 2)) * front * (1 - u**4)
    return inside * front, seam


def brow_mask(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Brow weight (n,) in 0..1 and the position along the brow t (0 inner .. 1 tail), canonical space."""
    x, y, z = pos.T
    t = (np.abs(x) - 0.010) / 0.046
    tc = np.clip(t, 0, 1)
    centre = 0.0458 + 0.0034 * np.sin(np.pi * (0.15 + 0.7 * tc))
    half = 0.0037 * (1 - 0.55 * tc)
    mask = smoothstep((half - np.abs(y - centre)) / 0.0009 + 0.5)
    mask *= smoothstep(t / 0.08) * smoothstep((1 - t) / 0.12) * smoothstep((z - 0.03) / 0.01)
    return mask, tc


def _eye_colours(m: _Mesh, pos: np.ndarray, side: str, rng: np.random.Generator) -> np.ndarray:
    """Sclera / iris / pupil by the angle between (p - eye centre) and the eye's forward axis (+z)."""
    centre = m.lm[f"eye_{side}"]
    d = _unit(pos - centre)
    ang = np.degrees(np.arccos(np.clip(d[:, 2], -1, 1)))
    streak = 0.8 + 0.4 * rng.random(len(pos))
    iris = IRIS[None] * streak[:, None] * (0.75 + 0.25 * smoothstep((ang - 10) / 8))[:, None]
    iris *= (1 - 0.55 * smoothstep((ang - 27.0) / 3.0))[:, None]  # dark limbal ring
    sclera = SCLERA + (np.array([-0.02, -0.10, -0.10]) * smoothstep((ang - 45) / 30)[:, None])
    rgb = np.where((ang < 31)[:, None], iris, sclera)
    rgb = np.where((ang < 11.5)[:, None], PUPIL, rgb)
    # Lid shadow on the top of the eyeball, catch-light near the pupil.
    hh = EYE_HALF_OPENING[1]
    shade = 1 - 0.45 * smoothstep((pos[:, 1] - centre[1] - 0.3 * hh) / (0.8 * hh))
    glint = np.exp(-((d[:, 0] - 0.10) ** 2 + (d[:, 1] - 0.12) ** 2) / (2 * 0.03**2))
    return np.clip(rgb * shade[:, None] + 0.8 * glint[:, None], 0, 1)


def _surface(m: _Mesh, rng: np.random.Generator, total: int = SURFACE_COUNT) -> _Parts:
    """Flat discs over the whole head, denser on the face and the front of the eyes."""
    c = m.centroid
    x, y, z = c.T
    weight = 0.7 + 2.6 * smoothstep(z / 0.04) * smoothstep((y + 0.10) / 0.02) * smoothstep((0.075 - y) / 0.02)
    face_label = {k: m.labels[k][m.f].mean(axis=1) for k in m.labels}
    if "neck" in face_label:
        weight *= 1 - 0.4 * face_label["neck"]
    eye_faces = np.zeros(len(c), bool)
    for side in ("left", "right"):
        on = face_label.get(f"eyeball_{side}", np.zeros(len(c))) > 0.99
        eye_faces |= on
        front = _unit(c - m.lm[f"eye_{side}"])[:, 2] > np.cos(np.radians(80))
        weight = np.where(on, np.where(front, 8.0, 0.3), weight)
    cavity = face_label.get("mouth_cavity", np.zeros(len(c))) > 0.99
    weight = np.where(cavity, 1.5, weight)
    counts = allocate(weight * m.area, total)
    face, bary = sample_faces(counts, rng)
    pos = m.interp(m.v, face, bary)
    density = total * weight / (weight * m.area).sum()  # samples per m^2 on each face
    sigma = SPACING_TO_SIGMA / np.sqrt(density[face])
    frames = m.frames[face]
    normal = _unit(m.interp(m.vertex_normal, face, bary))

    # Colour from the labels.
    px, py, pz = pos.T
    rgb = np.tile(SKIN, (len(face), 1)) * (1 + 0.035 * rng.standard_normal((len(face), 1)))
    for side in ("left", "right"):
        cheek = np.exp(-np.sum((pos - m.lm[f"cheek_{side}"]) ** 2, 1) / (2 * 0.016**2))
        rgb += cheek[:, None] * np.array([0.02, -0.05, -0.04])
    nose = np.exp(-np.sum((pos - m.lm["nose_tip"]) ** 2, 1) / (2 * 0.008**2))
    rgb += nose[:, None] * np.array([0.01, -0.04, -0.03])
    lips, seam = lip_masks(pos, m.lm)
    brows, brow_t = brow_mask(pos)
    scalp = smoothstep((m.field("scalp", face, bary) + 0.12 * rng.standard_normal(len(face)) - 0.3) / 0.4)
    rgb = rgb * (1 - lips[:, None]) + LIPS * lips[:, None]
    rgb *= 1 - 0.45 * seam[:, None]
    for sx in (1.0, -1.0):  # nostrils: dark ovals on the underside of the nose
        d2 = ((px - sx * 0.0062) / 0.0024) ** 2 + ((py - m.lm["nose_tip"][1] + 0.0085) / 0.0016) ** 2
        nostril = 0.8 * np.exp(-d2) * smoothstep((-normal[:, 1] - 0.1) / 0.3)
        rgb = rgb * (1 - nostril[:, None]) + NOSTRIL * nostril[:, None]
    rgb = rgb * (1 - brows[:, None]) + BROW * (0.85 + 0.3 * rng.random((len(face), 1))) * brows[:, None]
    rgb = rgb * (1 - scalp[:, None]) + HAIR * (0.8 + 0.4 * rng.random((len(face), 1))) * scalp[:, None]
    hw, hh = EYE_HALF_OPENING
    for side in ("left", "right"):
        e = m.lm[f"eye_{side}"]
        r = np.sqrt(((px - e[0]) / hw) ** 2 + ((py - e[1]) / hh) ** 2)
        lash = np.exp(-(((r - 1.05) / np.where(py > e[1], 0.10, 0.05)) ** 2)) * (pz > e[2]) * (np.abs(px - e[0]) < hw)
        rgb = rgb * (1 - 0.85 * lash[:, None]) + LASH * 0.85 * lash[:, None]
    shade = _lambert(normal) * (1 - np.clip(1.2 * m.interp(m.concavity, face, bary), 0, 0.2))
    rgb *= shade[:, None]
    opacity = rng.uniform(0.93, 0.99, len(face))
    sheen = 0.05 + 0.05 * lips

    on_eye = eye_faces[face]
    for side in ("left", "right"):
        sel = m.labels.get(f"eyeball_{side}", np.zeros(len(m.v)))[m.f[face]].min(axis=1) > 0.99
        rgb[sel] = _eye_colours(m, pos[sel], side, rng)
    sheen[on_eye] = 0.12
    opacity[on_eye] = 0.99
    in_cavity = cavity[face]
    depth = smoothstep((pz - (m.lm["mouth_centre"][2] - 0.035)) / 0.025)
    tongue = smoothstep((MOUTH_Y - 0.005 - py) / 0.006)
    mouth_rgb = (MOUTH * (1 - tongue[:, None]) + TONGUE * tongue[:, None]) * (0.35 + 0.65 * depth)[:, None]
    rgb[in_cavity] = mouth_rgb[in_cavity]
    sheen[in_cavity] = 0.0

    # Shape: discs in the face plane; brows as short hairs along the brow line.
    brow_dir = np.stack([np.sign(px) + (px == 0), 0.6 * (1 - 1.6 * brow_t), np.zeros_like(px)], axis=1)
    axes = _in_plane_axes(frames, None, rng)
    axes_brow = _in_plane_axes(frames, brow_dir, rng)
    is_brow = brows > 0.5
    axes[is_brow] = axes_brow[is_brow]
    stretch = rng.uniform(0.85, 1.18, (len(face), 2))
    scale = np.stack([sigma * stretch[:, 0], 0.12 * sigma, sigma * stretch[:, 1]], axis=1)
    scale[is_brow] *= np.array([1.8, 1.0, 0.55])
    return _Parts(face, pos, axes, scale, np.clip(rgb, 0, 1), opacity, normal, sheen)


def _hair(m: _Mesh, rng: np.random.Generator, total: int = HAIR_COUNT) -> _Parts:
    """Strands a little off the scalp, combed away from the crown."""
    scalp_face = m.labels.get("scalp", np.zeros(len(m.v)))[m.f].mean(axis=1)
    counts = allocate(m.area * scalp_face**2 + 1e-30, total)
    face, bary = sample_faces(counts, rng)
    base = m.interp(m.v, face, bary)
    normal = _unit(m.interp(m.vertex_normal, face, bary))
    strength = m.field("scalp", face, bary)
    lift = rng.uniform(0.0004, 0.0035, len(face)) * (0.4 + 0.6 * strength)
    pos = base + normal * lift[:, None]
    crown = np.array([0.0, 0.14, -0.045])
    flow = _unit(pos - crown) + 0.25 * rng.standard_normal((len(face), 3))
    t = _unit(flow - (flow * normal).sum(1, keepdims=True) * normal)
    b = np.cross(normal, t)
    axes = np.stack([t, b, normal], axis=-1)
    scale = np.stack([rng.uniform(0.003, 0.005, len(face)), rng.uniform(0.00035, 0.0006, len(face)),
                      np.full(len(face), 0.00015)], axis=1)
    tone = 0.75 + 0.55 * rng.random((len(face), 1))
    rgb = HAIR * tone * _lambert(normal, ambient=0.5, key=0.55)[:, None]
    opacity = rng.uniform(0.6, 0.95, len(face)) * (0.5 + 0.5 * strength)
    return _Parts(face, pos, axes, scale, np.clip(rgb, 0, 1), opacity, normal, np.full(len(face), 0.03))


def _teeth(m: _Mesh, rng: np.random.Generator, total: int = TEETH_COUNT) -> _Parts:
    """Upper and lower arches behind the lips, bound to cavity faces that move rigidly with head / jaw."""
    if "mouth_cavity" not in m.labels:
        return _Parts(*(np.zeros((0,) + s) for s in ((), (3,), (3, 3), (3,), (3,), (), (3,), ())))
    lm = m.lm
    zc, half_w = lm["mouth_centre"][2], abs(lm["mouth_corner_left"][0])
    zcorner = lm["mouth_corner_left"][2]
    n = total // 2
    upper = np.arange(2 * n) < n
    x = rng.uniform(-0.019, 0.019, 2 * n)
    y = np.where(upper, rng.uniform(MOUTH_Y + 0.0008, MOUTH_Y + 0.0085, 2 * n),
                 rng.uniform(MOUTH_Y - 0.0085, MOUTH_Y - 0.0012, 2 * n))
    curve = (zc - zcorner) / half_w**2
    z = zc - 0.0065 - curve * x**2 - 0.0015 * ~upper
    pos = np.stack([x, y, z], axis=1)
    t = _unit(np.stack([np.ones_like(x), np.zeros_like(x), -2 * curve * x], axis=1))
    normal = _unit(np.stack([2 * curve * x, np.zeros_like(x), np.ones_like(x)], axis=1))
    axes = np.stack([t, np.tile([0.0, 1.0, 0.0], (2 * n, 1)), normal], axis=-1)
    scale = np.tile([0.0009, 0.0012, 0.0002], (2 * n, 1))
    phase = np.abs(((x + np.where(upper, 0.0, 0.0012)) / np.where(np.abs(x) < 0.008, 0.0042, 0.0036)) % 1.0 - 0.5)
    rgb = TEETH * (0.72 + 0.28 * smoothstep((0.5 - phase) / 0.12))[:, None] * 0.88
    # Bind to the nearest cavity face skinned only to the head (upper) or only to the jaw (lower).
    cav = np.flatnonzero(m.labels["mouth_cavity"][m.f].min(axis=1) > 0.99)
    jaw = m.head.weights[m.f[cav], 2]
    face = np.empty(2 * n, np.int64)
    for sel, ok in ((upper, jaw.max(axis=1) < 1e-6), (~upper, jaw.min(axis=1) > 1 - 1e-6)):
        cand = cav[ok] if ok.any() else cav
        d = np.linalg.norm(pos[sel, None] - m.centroid[cand][None], axis=2)
        face[sel] = cand[d.argmin(axis=1)]
    return _Parts(face, pos, axes, scale, np.clip(rgb, 0, 1), np.full(2 * n, 0.97), normal, np.full(2 * n, 0.06))


def _sh(parts: _Parts, rng: np.random.Generator) -> np.ndarray:
    """(n, 16, 3): DC colour, a degree-1 sheen ``k * (-n . dir)``, faint degree-2/3 noise."""
    n = len(parts.face)
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = rgb_to_dc(parts.rgb)
    k = parts.sheen[:, None] / C1
    nx, ny, nz = parts.normal.T
    # Y1 = (-C1 y, C1 z, -C1 x); colour += k * (-n . d) with d the camera-to-Gaussian direction.
    sh[:, 1] = k * ny[:, None]
    sh[:, 2] = -k * nz[:, None]
    sh[:, 3] = k * nx[:, None]
    sh[:, 4:] = 0.004 * rng.standard_normal((n, 12, 3))
    return sh


def make_default_avatar(head: HeadModel | None = None, seed: int = SEED, count: int | None = None) -> GaussianAvatar:
    """The procedural default avatar (about 115,000 Gaussians) on ``head`` (default: the procedural head).

    ``count``: build one of about that many Gaussians instead (benchmarks), every group scaled alike."""
    if head is None:
        from ..head.io import default_head

        head = default_head()
    sizes = (SURFACE_COUNT, HAIR_COUNT, TEETH_COUNT)
    if count is not None:
        total = sum(sizes)
        teeth = 2 * max(1, round(count * TEETH_COUNT / total / 2))
        hair = max(1, round(count * HAIR_COUNT / total))
        sizes = (max(1, count - hair - teeth), hair, teeth)
    rng = np.random.default_rng(seed)
    mesh = _Mesh(head)
    groups = [_surface(mesh, rng, sizes[0]), _hair(mesh, rng, sizes[1]), _teeth(mesh, rng, sizes[2])]
    parts = _Parts(*(np.concatenate([getattr(g, k) for g in groups]) for k in _Parts.__dataclass_fields__))
    rotation = matrix_to_quaternion(parts.axes)
    binding = TriangleBinding.from_world(parts.face, parts.position, rotation, parts.scale, mesh.v, head.faces)
    return GaussianAvatar(head, binding, parts.opacity.astype(np.float32), _sh(parts, rng), name="default")
