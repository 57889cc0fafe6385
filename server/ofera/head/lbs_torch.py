"""FLAME's forward pass in torch, for training (differentiable). Same maths as ``lbs.py``.

Imported only by training code: the server never needs torch.
"""

from __future__ import annotations

import torch

from .model import HeadModel


def rot6d_to_matrix(d6: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> (..., 3, 3), pytorch3d rows convention (see ``rotations.py``)."""
    b1 = torch.nn.functional.normalize(d6[..., 0:3], dim=-1)
    a2 = d6[..., 3:6]
    b2 = torch.nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    return torch.stack([b1, b2, torch.cross(b1, b2, dim=-1)], dim=-2)


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis * angle -> (..., 3, 3) (Rodrigues); smooth at zero through the epsilon."""
    theta = torch.sqrt((aa * aa).sum(-1, keepdim=True) + 1e-16)[..., None]  # (..., 1, 1)
    k = aa / theta[..., 0]
    zero = torch.zeros_like(k[..., 0])
    kmat = torch.stack(
        [zero, -k[..., 2], k[..., 1], k[..., 2], zero, -k[..., 0], -k[..., 1], k[..., 0], zero], dim=-1
    ).reshape(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device)
    return eye + torch.sin(theta) * kmat + (1 - torch.cos(theta)) * kmat @ kmat


class TorchHead(torch.nn.Module):
    """A :class:`HeadModel` as torch buffers; ``forward`` deforms a batch."""

    def __init__(self, model: HeadModel, shape: torch.Tensor | None = None, dtype: torch.dtype = torch.float32):
        super().__init__()

        def buf(name: str, arr) -> None:
            self.register_buffer(name, torch.as_tensor(arr, dtype=dtype), persistent=False)

        buf("v_template", model.v_template)
        buf("shapedirs", model.shapedirs)
        buf("exprdirs", model.exprdirs)
        buf("posedirs", model.posedirs)
        buf("j_regressor", model.j_regressor)
        buf("weights", model.weights)
        self.register_buffer("faces", torch.as_tensor(model.faces, dtype=torch.long), persistent=False)
        self.parents = [int(p) for p in model.parents]
        v_id = self.v_template
        if shape is not None:
            v_id = v_id + torch.einsum("vcs,s->vc", self.shapedirs[:, :, : shape.shape[-1]], shape.to(dtype))
        self.register_buffer("v_id", v_id, persistent=False)

    def forward(self, expr: torch.Tensor, rotations: torch.Tensor, transl: torch.Tensor | None = None,
                exprdirs: torch.Tensor | None = None) -> torch.Tensor:
        """expr (B, n); rotations (B, K, 3, 3) in joint order; transl (B, 3) -> vertices (B, V, 3).

        ``exprdirs`` (V, 3, >=n) replaces the model's expression basis (e.g. a trained, corrected one)."""
        b, n = expr.shape
        k = len(self.parents)
        basis = self.exprdirs if exprdirs is None else exprdirs
        v_sh = self.v_id + torch.einsum("vce,be->bvc", basis[:, :, :n], expr)
        joints = torch.einsum("kv,bvc->bkc", self.j_regressor, v_sh)
        eye = torch.eye(3, dtype=expr.dtype, device=expr.device)
        feat = (rotations[:, 1:] - eye).reshape(b, (k - 1) * 9)
        v_po = v_sh + (feat @ self.posedirs).reshape(b, -1, 3)
        # World transforms of the chain, then remove each joint's rest position.
        rel = torch.cat([joints[:, :1], joints[:, 1:] - joints[:, self.parents[1:]]], dim=1)
        rot_chain, trans_chain = [rotations[:, 0]], [rel[:, 0]]
        for i in range(1, k):
            p = self.parents[i]
            rot_chain.append(rot_chain[p] @ rotations[:, i])
            trans_chain.append(trans_chain[p] + (rot_chain[p] @ rel[:, i, :, None])[..., 0])
        g_rot = torch.stack(rot_chain, dim=1)  # (B, K, 3, 3)
        g_t = torch.stack(trans_chain, dim=1) - (g_rot @ joints[..., None])[..., 0]  # (B, K, 3)
        t_rot = torch.einsum("vk,bkij->bvij", self.weights, g_rot)
        t_t = torch.einsum("vk,bki->bvi", self.weights, g_t)
        verts = (t_rot @ v_po[..., None])[..., 0] + t_t
        if transl is not None:
            verts = verts + transl[:, None, :]
        return verts
