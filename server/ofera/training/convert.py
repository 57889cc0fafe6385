"""Between the trainable avatar (torch) and the server's :class:`ofera.avatar.GaussianAvatar` (numpy)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from .model import TrainableAvatar


def from_gaussian_avatar(avatar, correct_basis: bool = True) -> TrainableAvatar:
    """A trainable copy of a GaussianAvatar (triangle binding kept; a barycentric one is re-bound to its faces
    on the neutral mesh). Only the SH DC term is trained (degree 0)."""
    from ..avatar.binding import TriangleBinding

    b = avatar.binding
    if not isinstance(b, TriangleBinding):
        st = avatar.neutral()
        b = TriangleBinding.from_world(b.face, st.position, st.rotation_wxyz(), st.scale, avatar.head.v_template,
                                       avatar.head.faces)
    op = np.clip(avatar.opacity.astype(np.float64), 1e-4, 1 - 1e-4)
    return TrainableAvatar(
        avatar.head,
        torch.as_tensor(b.face, dtype=torch.long),
        torch.as_tensor(b.position),
        torch.as_tensor(b.log_scale),
        torch.as_tensor(b.rotation),
        torch.as_tensor(np.log(op / (1 - op)), dtype=torch.float32),
        torch.as_tensor(avatar.sh[:, 0, :]),
        correct_basis=correct_basis,
    )


def to_gaussian_avatar(trained: TrainableAvatar, name: str = "trained"):
    """The server's avatar: identity and the learned expression-basis correction baked into the head model
    (v_template = identity-shaped template, exprdirs = exprdirs + delta_exprdirs), SH degree 0."""
    from ..avatar.binding import TriangleBinding
    from ..avatar.model import GaussianAvatar

    head = trained.head_model
    v_id = trained.head.v_id.detach().double().numpy()
    exprdirs = head.exprdirs.astype(np.float64)
    if trained.head.delta_exprdirs is not None:
        exprdirs = exprdirs + trained.head.correction().detach().double().numpy()
    baked = replace(head, v_template=v_id, exprdirs=exprdirs, name=f"{head.name}+{name}")
    a = trained.attributes()
    binding = TriangleBinding(a["binding"].numpy().astype(np.int64), a["local_xyz"].numpy(),
                              a["local_rot"].numpy(), a["local_log_scale"].numpy())
    colour_dc = a["sh_dc"].numpy().astype(np.float32)  # both sides: colour = C0 * dc + 0.5
    return GaussianAvatar(baked, binding, torch.sigmoid(a["opacity_logit"]).numpy().astype(np.float32),
                          colour_dc[:, None, :], name=name)
