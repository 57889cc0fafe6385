"""FLAME's forward pass in numpy (run time). The torch twin is ``lbs_torch.py``; tests compare them.

    v_id  = v_template + S . beta                     once per subject         (V, 3)
    v_sh  = v_id + E[:, :, :n] . psi                  per frame                (B, V, 3)
    J     = J_regressor @ v_sh                        (B, K, 3), from precomputed J(v_id) and J(E)
    feat  = concat_k=1..K-1 (R_k - I) row-major       (B, 36)
    v_po  = v_sh + feat @ P                           pose correctives         (B, V, 3)
    G_0 = [R_0 | J_0],  G_k = G_parent(k) @ [R_k | J_k - J_parent(k)]
    A_k = G_k with translation t(G_k) - R(G_k) J_k    (B, K, 4, 4)
    v   = sum_k W[v, k] A_k v_po + transl             (B, V, 3)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import HeadModel
from .rotations import axis_angle_to_matrix, rot6d_to_matrix


@dataclass(frozen=True)
class HeadSubject:
    """A head model with its identity fixed; holds everything that does not change per frame."""

    model: HeadModel
    v_id: np.ndarray  # (V, 3) identity-shaped template
    j_id: np.ndarray  # (K, 3) joints of v_id
    j_expr: np.ndarray  # (K, 3, E) joint motion per expression coefficient
    expr_rows: np.ndarray  # (E, 3V) the expression basis as contiguous rows, for one matmul per batch

    @classmethod
    def create(cls, model: HeadModel, shape: np.ndarray | None = None) -> HeadSubject:
        """``shape``: (S',) identity coefficients, S' <= S; None is the mean head."""
        v_id = model.v_template.astype(np.float64)
        if shape is not None:
            shape = np.asarray(shape, np.float64).reshape(-1)
            if shape.size > model.shape_dims:
                raise ValueError(f"{shape.size} shape coefficients, the model has {model.shape_dims}")
            v_id = v_id + model.shapedirs[:, :, : shape.size] @ shape
        j_id = model.j_regressor @ v_id
        j_expr = np.einsum("kv,vce->kce", model.j_regressor, model.exprdirs)
        expr_rows = np.ascontiguousarray(model.exprdirs.reshape(-1, model.expr_dims).T)
        return cls(model, v_id, j_id, j_expr, expr_rows)


def as_rotation_matrices(r: np.ndarray | None, batch: int) -> np.ndarray:
    """Accept (B, 3, 3) matrices, (B, 6) 6D, (B, 3) axis-angle (or unbatched), None = identity -> (B, 3, 3)."""
    if r is None:
        return np.broadcast_to(np.eye(3), (batch, 3, 3))
    r = np.asarray(r, dtype=np.float64)
    if r.shape[-2:] == (3, 3):
        m = r
    elif r.shape[-1] == 6:
        m = rot6d_to_matrix(r)
    elif r.shape[-1] == 3:
        m = axis_angle_to_matrix(r)
    else:
        raise ValueError(f"rotation of shape {r.shape}: expected (..., 3, 3), (..., 6) or (..., 3)")
    return np.broadcast_to(m.reshape(-1, 3, 3), (batch, 3, 3))


def pose_rotations(
    batch: int,
    jaw: np.ndarray | None = None,
    left_eye: np.ndarray | None = None,
    right_eye: np.ndarray | None = None,
    neck: np.ndarray | None = None,
    root: np.ndarray | None = None,
) -> np.ndarray:
    """Stack per-joint rotations in joint order (root, neck, jaw, left eye, right eye) -> (B, 5, 3, 3)."""
    parts = (root, neck, jaw, left_eye, right_eye)
    return np.stack([as_rotation_matrices(p, batch) for p in parts], axis=1)


def pose_feature(rotations: np.ndarray) -> np.ndarray:
    """(B, K, 3, 3) -> (B, 9 (K-1)): (R_k - I) of the non-root joints, flattened row-major."""
    b, k = rotations.shape[:2]
    return (rotations[:, 1:] - np.eye(3)).reshape(b, (k - 1) * 9)


def rigid_transforms(rotations: np.ndarray, joints: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """Skinning transforms A (B, K, 4, 4) from rotations (B, K, 3, 3) and rest joints (B, K, 3)."""
    b, k = joints.shape[:2]
    rel = joints.copy()
    rel[:, 1:] -= joints[:, parents[1:]]
    local = np.zeros((b, k, 4, 4))
    local[:, :, :3, :3] = rotations
    local[:, :, :3, 3] = rel
    local[:, :, 3, 3] = 1.0
    chain = [local[:, 0]]
    for i in range(1, k):
        chain.append(chain[parents[i]] @ local[:, i])
    g = np.stack(chain, axis=1)  # (B, K, 4, 4) world transform of each joint
    a = g.copy()
    a[:, :, :3, 3] -= np.einsum("bkij,bkj->bki", g[:, :, :3, :3], joints)
    return a


def lbs(
    subject: HeadSubject,
    expr: np.ndarray,
    rotations: np.ndarray,
    transl: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Deform the subject's head.

    expr: (B, n) expression coefficients, n <= E. rotations: (B, K, 3, 3) from :func:`pose_rotations`.
    transl: (B, 3) metres or None. Returns vertices (B, V, 3) and posed joints (B, K, 3), float64.
    """
    model = subject.model
    expr = np.atleast_2d(np.asarray(expr, np.float64))
    b, n = expr.shape
    if n > model.expr_dims:
        raise ValueError(f"{n} expression coefficients, the model has {model.expr_dims}")
    nv, k = model.num_vertices, model.num_joints
    v_sh = subject.v_id[None] + (expr @ subject.expr_rows[:n]).reshape(b, nv, 3)  # (B, V, 3)
    joints = subject.j_id[None] + np.einsum("kce,be->bkc", subject.j_expr[:, :, :n], expr)  # (B, K, 3)
    v_po = v_sh + (pose_feature(rotations) @ model.posedirs).reshape(b, nv, 3)
    a = rigid_transforms(rotations, joints, model.parents)  # (B, K, 4, 4)
    t = (model.weights @ a[:, :, :3, :].reshape(b, k, 12)).reshape(b, nv, 3, 4)  # blended transforms
    verts = np.einsum("bvij,bvj->bvi", t[..., :3], v_po) + t[..., 3]
    posed_joints = np.einsum("bkij,bkj->bki", a[..., :3, :3], joints) + a[..., :3, 3]
    if transl is not None:
        shift = np.asarray(transl, np.float64).reshape(-1, 1, 3)
        verts, posed_joints = verts + shift, posed_joints + shift
    return verts, posed_joints


def _rotation_batch(r: np.ndarray | None) -> int:
    """How many rotations ``r`` holds in any accepted form (1 for None)."""
    if r is None:
        return 1
    r = np.asarray(r)
    return int(np.prod(r.shape[:-2] if r.shape[-2:] == (3, 3) else r.shape[:-1]))


def forward(
    model: HeadModel,
    expr: np.ndarray | None = None,
    jaw: np.ndarray | None = None,
    left_eye: np.ndarray | None = None,
    right_eye: np.ndarray | None = None,
    neck: np.ndarray | None = None,
    root: np.ndarray | None = None,
    shape: np.ndarray | None = None,
    transl: np.ndarray | None = None,
) -> np.ndarray:
    """One-call convenience: vertices (B, V, 3). Rotations in any form :func:`as_rotation_matrices` takes."""
    subject = HeadSubject.create(model, shape)
    expr = np.zeros((1, 0)) if expr is None else np.atleast_2d(np.asarray(expr, np.float64))
    batch = max(expr.shape[0], *(_rotation_batch(r) for r in (jaw, left_eye, right_eye, neck, root)))
    expr = np.broadcast_to(expr, (batch, expr.shape[1]))
    rot = pose_rotations(batch, jaw, left_eye, right_eye, neck, root)
    return lbs(subject, expr, rot, transl)[0]
