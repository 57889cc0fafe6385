"""A shaded picture of a head mesh (matplotlib, painter's algorithm), for people to look at."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .model import HeadModel

_SKIN = np.array([0.87, 0.70, 0.60])
_PART_COLOURS = (  # later entries win
    ("scalp", (0.30, 0.22, 0.16)),
    ("brows", (0.25, 0.17, 0.12)),
    ("lips", (0.75, 0.42, 0.42)),
    ("mouth_cavity", (0.25, 0.08, 0.08)),
    ("eyeball_left", (0.95, 0.95, 0.93)),
    ("eyeball_right", (0.95, 0.95, 0.93)),
    ("iris_left", (0.30, 0.45, 0.60)),
    ("iris_right", (0.30, 0.45, 0.60)),
    ("pupil_left", (0.05, 0.05, 0.05)),
    ("pupil_right", (0.05, 0.05, 0.05)),
)


def vertex_colours(model: HeadModel) -> np.ndarray:
    """(V, 3) RGB in 0..1 from the model's vertex labels (uniform skin when it has none)."""
    col = np.tile(_SKIN, (model.num_vertices, 1))
    for label, rgb in _PART_COLOURS:
        if label in model.vertex_labels:
            col[model.vertex_labels[label]] = rgb
    return col


def look_rotation(yaw_deg: float, pitch_deg: float = 0.0) -> np.ndarray:
    """Camera rotation (3, 3) that turns the head by yaw (about y) then pitch (about x)."""
    a, b = np.radians(yaw_deg), np.radians(pitch_deg)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rx @ ry


def render_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    colours: np.ndarray,
    out: str | Path,
    views: tuple[float, ...] = (0.0, 35.0),
    size_px: int = 512,
    title: str | None = None,
) -> Path:
    """Write a PNG of the mesh seen from each yaw in ``views`` (degrees), orthographic, Lambert-shaded.

    vertices (V, 3) metres; faces (F, 3); colours (V, 3) in 0..1.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    fig, axes = plt.subplots(1, len(views), figsize=(size_px / 100 * len(views), size_px / 100), dpi=100)
    axes = np.atleast_1d(axes)
    light = np.array([-0.4, 0.5, 1.0]) / np.linalg.norm([-0.4, 0.5, 1.0])
    face_col = colours[faces].mean(axis=1)
    centre = (vertices.max(axis=0) + vertices.min(axis=0)) / 2
    half = (vertices.max(axis=0) - vertices.min(axis=0)).max() / 2 * 1.05
    for ax, yaw in zip(axes, views):
        v = (vertices - centre) @ look_rotation(yaw).T
        tri = v[faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        visible = n[:, 2] > 0  # back-face culling, camera looks along -z
        order = np.argsort(tri[visible][:, :, 2].mean(axis=1))  # far first
        shade = 0.25 + 0.75 * np.clip(n[visible] @ light, 0, 1)
        rgb = np.clip(face_col[visible] * shade[:, None], 0, 1)[order]
        ax.add_collection(PolyCollection(tri[visible][order][:, :, :2], facecolors=rgb, edgecolors=rgb, linewidths=0.2))
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_aspect("equal")
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.patch.set_facecolor("white")
    plt.tight_layout()
    out = Path(out)
    fig.savefig(out)
    plt.close(fig)
    return out


def render_head(model: HeadModel, vertices: np.ndarray, out: str | Path, **kwargs) -> Path:
    """Render deformed vertices (V, 3) of ``model`` with its label colours."""
    return render_mesh(vertices, model.faces, vertex_colours(model), out, **kwargs)
