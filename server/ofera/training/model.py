"""The trainable avatar: Gaussians bound to the head mesh's triangles, plus per-avatar basis corrections.

Binding (GaussianAvatars' triangle-local frame; see shared REFERENCE.md section 3), per face f of the
deformed mesh (v0, v1, v2):

    a0 = n(v1 - v0); a1 = n((v1 - v0) x (v2 - v0)); a2 = -n(a1 x a0);  R_f = [a0 a1 a2] (columns)
    s_f = (|v1 - v0| + |a2 . (v2 - v0)|) / 2;   c_f = (v0 + v1 + v2) / 3
    position = R_f local_xyz s_f + c_f;  scale = exp(local_log_scale) s_f;  rotation = q(R_f) (x) n(local_rot)

Trainable attributes per Gaussian: local xyz, log scale, rotation (w, x, y, z), opacity logit, SH DC colour
(degree 0: colour = 0.28209479 dc + 0.5). Optionally (FATE-like) a per-avatar correction of the expression
basis, ``delta_exprdirs`` (V, 3, E), applied before skinning: v = LBS(v_id + (E + dE) psi, pose).
"""

from __future__ import annotations

import numpy as np
import torch

from ..head.lbs_torch import TorchHead, rot6d_to_matrix
from ..head.model import HeadModel

SH_C0 = 0.28209479177387814
BASIS_TOL = 1e-7  # m per unit coefficient: a vertex the expression basis moves (as ofera.avatar.movable)


def face_frames(verts: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """verts (..., V, 3), faces (F, 3) -> R (..., F, 3, 3) (columns a0, a1, a2), s (..., F), centre (..., F, 3)."""
    v0, v1, v2 = verts[..., faces[:, 0], :], verts[..., faces[:, 1], :], verts[..., faces[:, 2], :]
    e1, e2 = v1 - v0, v2 - v0
    a0 = torch.nn.functional.normalize(e1, dim=-1)
    a1 = torch.nn.functional.normalize(torch.cross(a0, e2, dim=-1), dim=-1)
    a2 = -torch.nn.functional.normalize(torch.cross(a1, a0, dim=-1), dim=-1)
    rot = torch.stack([a0, a1, a2], dim=-1)
    s = 0.5 * (e1.norm(dim=-1) + (a2 * e2).sum(-1).abs())
    return rot, s, (v0 + v1 + v2) / 3.0


def matrix_to_quat(r: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 4) unit quaternion (w, x, y, z), best-conditioned branch per matrix, differentiable."""
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    sq = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    d21, d02, d10 = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    s21, s02, s10 = r[..., 2, 1] + r[..., 1, 2], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 0] + r[..., 0, 1]
    cand = torch.stack(
        [
            torch.stack([sq[..., 0], d21, d02, d10], -1),
            torch.stack([d21, sq[..., 1], s10, s02], -1),
            torch.stack([d02, s10, sq[..., 2], s21], -1),
            torch.stack([d10, s02, s21, sq[..., 3]], -1),
        ],
        -2,
    )
    best = torch.argmax(sq, -1)
    q = torch.gather(cand, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a (x) b, (w, x, y, z)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def split_flame_values(y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 68) FLAME values [expr 50, jaw 6D, left eye 6D, right eye 6D] -> expr (B, 50), rotations (B, 5, 3, 3)
    (root and neck identity). Torch twin of ``ofera.mapping.flame_values.split_flame_values``."""
    b = y.shape[0]
    eye = torch.eye(3, dtype=y.dtype, device=y.device).expand(b, 2, 3, 3)
    rots = rot6d_to_matrix(y[:, 50:68].reshape(b, 3, 6))
    return y[:, :50], torch.cat([eye, rots], 1)


class CorrectedHead(TorchHead):
    """:class:`TorchHead` whose expression basis carries a trainable correction ``delta_exprdirs`` (or none)."""

    def __init__(self, model: HeadModel, shape: torch.Tensor | None = None, correct_basis: bool = True,
                 dtype: torch.dtype = torch.float32):
        super().__init__(model, shape=shape, dtype=dtype)
        self.delta_exprdirs = torch.nn.Parameter(torch.zeros_like(self.exprdirs)) if correct_basis else None
        # Corrections only where the basis already moves the surface: Gaussians that no expression moves stay
        # static (the server sends them once), and the correction cannot drift into the scalp or the neck.
        moving = torch.as_tensor(np.abs(model.exprdirs).reshape(model.num_vertices, -1).max(axis=1) > BASIS_TOL)
        self.register_buffer("basis_mask", moving.to(dtype)[:, None, None], persistent=False)

    def correction(self) -> torch.Tensor | None:
        """The effective basis correction (V, 3, E): ``delta_exprdirs`` on the vertices the basis moves."""
        return None if self.delta_exprdirs is None else self.delta_exprdirs * self.basis_mask

    def forward(self, expr: torch.Tensor, rotations: torch.Tensor, corrected: bool = True) -> torch.Tensor:
        """TorchHead.forward with the corrected basis (the plain one when ``corrected`` is False)."""
        basis = None
        if corrected and self.delta_exprdirs is not None:
            basis = self.exprdirs + self.correction()
        return super().forward(expr, rotations, exprdirs=basis)


class TrainableAvatar(torch.nn.Module):
    """Gaussians bound to a head's faces (triangle-local) with optional expression-basis corrections."""

    PARAMS = ("local_xyz", "local_log_scale", "local_rot", "opacity_logit", "sh_dc")

    def __init__(self, head: HeadModel, binding: torch.Tensor, local_xyz: torch.Tensor, local_log_scale: torch.Tensor,
                 local_rot: torch.Tensor, opacity_logit: torch.Tensor, sh_dc: torch.Tensor,
                 correct_basis: bool = True, shape: torch.Tensor | None = None) -> None:
        super().__init__()
        self.head_model = head
        self.shape = None if shape is None else torch.as_tensor(shape, dtype=torch.float32).reshape(-1)
        self.head = CorrectedHead(head, shape=self.shape, correct_basis=correct_basis)
        self.register_buffer("binding", binding.long())
        self.local_xyz = torch.nn.Parameter(local_xyz.float().clone())
        self.local_log_scale = torch.nn.Parameter(local_log_scale.float().clone())
        self.local_rot = torch.nn.Parameter(local_rot.float().clone())
        self.opacity_logit = torch.nn.Parameter(opacity_logit.float().clone())
        self.sh_dc = torch.nn.Parameter(sh_dc.float().clone())

    @property
    def count(self) -> int:
        return int(self.binding.shape[0])

    # ----- construction ----------------------------------------------------------------------------------

    @classmethod
    def init_on_mesh(cls, head: HeadModel, faces: np.ndarray | None = None, colours: np.ndarray | None = None,
                     per_face: int = 1, seed: int = 0, correct_basis: bool = True,
                     opacity: float = 0.9, scale: float = 0.5, shape: np.ndarray | None = None) -> TrainableAvatar:
        """Gaussians at random barycentric points of ``faces`` (indices into head.faces; default all), flat on
        the face (normal scale / 3), ``scale`` x the face size across; colours (F, 3) per chosen face or grey."""
        rng = np.random.default_rng(seed)
        faces = np.arange(head.num_faces) if faces is None else np.asarray(faces, np.int64)
        bind = np.repeat(faces, per_face)
        bary = rng.dirichlet(np.ones(3), size=len(bind)) if per_face > 1 else np.full((len(bind), 3), 1 / 3)
        verts = torch.as_tensor(head.v_template, dtype=torch.float64)
        if shape is not None:
            shape = np.asarray(shape, np.float64).reshape(-1)
            verts = verts + torch.as_tensor(head.shapedirs[:, :, : len(shape)] @ shape)
        tri = torch.as_tensor(head.faces, dtype=torch.long)
        rot, s, centre = face_frames(verts, tri)
        pts = (verts[tri[bind]] * torch.as_tensor(bary)[..., None]).sum(1)
        local = torch.einsum("nji,nj->ni", rot[bind], pts - centre[bind]) / s[bind, None]
        log_scale = torch.log(torch.tensor([scale, scale / 3.0, scale])).expand(len(bind), 3)  # thin along a1 (normal)
        rot_id = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(len(bind), 4)
        logit = torch.full((len(bind),), float(np.log(opacity / (1 - opacity))))
        col = np.full((len(faces), 3), 0.5) if colours is None else np.asarray(colours, np.float64)
        dc = (torch.as_tensor(np.repeat(col, per_face, axis=0)) - 0.5) / SH_C0
        return cls(head, torch.as_tensor(bind), local, log_scale, rot_id, logit, dc, correct_basis,
                   None if shape is None else torch.as_tensor(shape))

    # ----- forward -----------------------------------------------------------------------------------------

    def vertices(self, flame_values: torch.Tensor, corrected: bool = True) -> torch.Tensor:
        """(B, 68) FLAME values -> deformed vertices (B, V, 3)."""
        expr, rots = split_flame_values(flame_values.float())
        return self.head(expr, rots, corrected=corrected)

    def gaussians(self, verts: torch.Tensor) -> dict[str, torch.Tensor]:
        """World-space Gaussians for one deformed mesh verts (V, 3): means, quats (wxyz), scales, opacities, colours."""
        rot, s, centre = face_frames(verts, self.head.faces)
        b = self.binding
        means = torch.einsum("nij,nj->ni", rot[b], self.local_xyz) * s[b, None] + centre[b]
        scales = torch.exp(self.local_log_scale) * s[b, None]
        quats = quat_multiply(matrix_to_quat(rot[b]), torch.nn.functional.normalize(self.local_rot, dim=-1))
        return {
            "means": means,
            "quats": quats,
            "scales": scales,
            "opacities": torch.sigmoid(self.opacity_logit),
            "colours": (SH_C0 * self.sh_dc + 0.5).clamp_min(0.0),
        }

    # ----- checkpoints: plain dicts of tensors -----------------------------------------------------------

    def attributes(self) -> dict[str, torch.Tensor]:
        out = {k: getattr(self, k).detach().clone() for k in self.PARAMS}
        out["binding"] = self.binding.clone()
        if self.head.delta_exprdirs is not None:
            out["delta_exprdirs"] = self.head.correction().detach().clone()
        if self.shape is not None:
            out["shape"] = self.shape.clone()
        return out

    @classmethod
    def from_attributes(cls, head: HeadModel, attrs: dict[str, torch.Tensor]) -> TrainableAvatar:
        missing = [k for k in (*cls.PARAMS, "binding") if k not in attrs]
        if missing:
            raise ValueError(f"avatar attributes lack {missing}")
        av = cls(head, attrs["binding"], *(attrs[k] for k in cls.PARAMS), correct_basis="delta_exprdirs" in attrs,
                 shape=attrs.get("shape"))
        if "delta_exprdirs" in attrs:
            if attrs["delta_exprdirs"].shape != av.head.exprdirs.shape:
                raise ValueError(f"delta_exprdirs {tuple(attrs['delta_exprdirs'].shape)} does not fit the head "
                                 f"{tuple(av.head.exprdirs.shape)}")
            with torch.no_grad():
                av.head.delta_exprdirs.copy_(attrs["delta_exprdirs"])
        if int(av.binding.max()) >= head.num_faces:
            raise ValueError(f"binding refers to face {int(av.binding.max())}, the head has {head.num_faces}")
        return av
