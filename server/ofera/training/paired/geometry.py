"""Geometry for evaluation: meshes from FLAME values (batched LBS) and face-region vertex masks."""

from __future__ import annotations

import numpy as np

from ofera.head.lbs import HeadSubject, pose_feature, rigid_transforms
from ofera.head.model import HeadModel
from ofera.mapping.flame_values import split_flame_values

REGIONS: tuple[str, ...] = ("eyes", "brows", "mouth_and_jaw")


def vertices_from_flame(head: HeadModel, flame: np.ndarray, shape: np.ndarray | None = None,
                        vertex_ids: np.ndarray | None = None, chunk: int = 256,
                        dtype: type = np.float32) -> np.ndarray:
    """Head vertices (T, V or len(vertex_ids), 3) for FLAME values (T, 68) of one identity ``shape``.

    Root and neck are identity (as in the FLAME values). The same forward pass as ``ofera.head.lbs``,
    evaluated only on ``vertex_ids`` (all vertices by default) and in chunks of frames, so a test split
    of thousands of frames fits in memory. ``shape`` (S,) or None (mean head).
    """
    flame = np.atleast_2d(np.asarray(flame))
    subject = HeadSubject.create(head, shape)
    ids = np.arange(head.num_vertices) if vertex_ids is None else np.asarray(vertex_ids, np.int64)
    e_ids = head.exprdirs[ids]  # (n, 3, E)
    p_ids = head.posedirs.reshape(-1, head.num_vertices, 3)[:, ids].reshape(head.posedirs.shape[0], -1)
    w_ids = head.weights[ids]
    v_id = subject.v_id[ids]
    out = np.empty((len(flame), len(ids), 3), dtype=dtype)
    for start in range(0, len(flame), chunk):
        expr, rot = split_flame_values(flame[start:start + chunk].astype(np.float64))
        b, n = expr.shape
        v = v_id[None] + np.einsum("vce,be->bvc", e_ids[:, :, :n], expr)
        joints = subject.j_id[None] + np.einsum("kce,be->bkc", subject.j_expr[:, :, :n], expr)
        v = v + (pose_feature(rot) @ p_ids).reshape(b, -1, 3)
        a = rigid_transforms(rot, joints, head.parents)  # (B, K, 4, 4)
        r = np.einsum("vk,bkij->bvij", w_ids, a[:, :, :3, :3])
        t = np.einsum("vk,bki->bvi", w_ids, a[:, :, :3, 3])
        out[start:start + b] = np.einsum("bvij,bvj->bvi", r, v) + t
    return out


def region_masks(head: HeadModel) -> dict[str, np.ndarray]:
    """Boolean vertex masks (V,) for per-region errors: ``eyes``, ``brows``, ``mouth_and_jaw``, ``face``.

    From the head's labels and landmarks (procedural head): eyes = eyeballs and the lids around them;
    brows = brow and lower forehead above the lids; mouth_and_jaw = lips, chin, jaw and the cheeks
    beside the mouth; face = their union.
    """
    if not head.landmarks or not head.vertex_labels:
        raise ValueError("region masks need a head with landmarks and vertex labels (the procedural head)")
    v = head.v_template
    x, y, z = v.T
    lab, lm = head.vertex_labels, head.landmarks
    skin = lab["skin"] & (z > 0.0)
    eye_y = lm["eye_left"][1]
    near_eye = np.zeros(len(v), bool)
    for key in ("eye_left", "eye_right"):
        d = (v - lm[key]) / np.array([1.0, 1.3, 1.0])
        near_eye |= np.linalg.norm(d[:, :2], axis=1) < 0.019
    eyes = lab["eyeball_left"] | lab["eyeball_right"] | (skin & near_eye & (y < eye_y + 0.013))
    brows = skin & ~eyes & (y > eye_y + 0.006) & (y < 0.078) & (np.abs(x) < 0.062)
    mouth_top = lm["nose_tip"][1] - 0.012
    mouth = skin & (y < mouth_top) & (y > -0.092) & (np.abs(x) < 0.055)
    mouth |= lab["lips"] | (lab["skin"] & (head.weights[:, 2] > 0.3) & (y > -0.092) & (z > -0.01))
    return {"eyes": eyes, "brows": brows, "mouth_and_jaw": mouth & ~eyes, "face": eyes | brows | mouth}
