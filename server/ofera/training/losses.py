"""Training losses: SSIM, PSNR, mesh Laplacian, regularisers, and an optional perceptual (VGG/LPIPS) term.

Images are (..., H, W, C) float tensors in [0, 1] unless a function says otherwise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F


def _gauss_window(size: int, sigma: float, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(x: torch.Tensor, y: torch.Tensor, window: int = 11, sigma: float = 1.5, data_range: float = 1.0,
         valid: bool = True, reduce: bool = True) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) of images (..., H, W, C), Gaussian window 11, sigma 1.5.

    K1 = 0.01, K2 = 0.03. ``valid``: average only over windows fully inside the image (as scikit-image with
    ``gaussian_weights=True, use_sample_covariance=False``); otherwise zero-padded 'same' windows (as the
    3DGS training code). ``reduce``: the mean over everything; else the per-image mean (...,).
    """
    lead = x.shape[:-3]
    h, w, c = x.shape[-3:]
    a = x.reshape(-1, h, w, c).permute(0, 3, 1, 2).reshape(-1, 1, h, w)
    b = y.reshape(-1, h, w, c).permute(0, 3, 1, 2).reshape(-1, 1, h, w)
    g = _gauss_window(window, sigma, x.dtype, x.device)
    pad = 0 if valid else window // 2

    def blur(t: torch.Tensor) -> torch.Tensor:
        t = F.conv2d(t, g.view(1, 1, 1, -1), padding=(0, pad))
        return F.conv2d(t, g.view(1, 1, -1, 1), padding=(pad, 0))

    mu_a, mu_b = blur(a), blur(b)
    saa = blur(a * a) - mu_a**2
    sbb = blur(b * b) - mu_b**2
    sab = blur(a * b) - mu_a * mu_b
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2))
    per_image = s.reshape(-1, c, *s.shape[-2:]).mean(dim=(1, 2, 3))
    return per_image.mean() if reduce else per_image.reshape(lead)


def psnr(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB over the whole tensor."""
    mse = torch.mean((x - y) ** 2).clamp_min(1e-12)
    return 10.0 * torch.log10(data_range**2 / mse)


# ----- mesh Laplacian --------------------------------------------------------------------------------------


def uniform_laplacian(faces: np.ndarray, num_vertices: int) -> torch.Tensor:
    """Sparse (V, V) uniform graph Laplacian L = I - D^-1 A from triangle edges (isolated vertices: 0 row)."""
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    i = np.concatenate([e[:, 0], e[:, 1]])
    j = np.concatenate([e[:, 1], e[:, 0]])
    deg = np.bincount(i, minlength=num_vertices).astype(np.float64)
    val = -1.0 / deg[i]
    has = deg > 0
    diag = np.flatnonzero(has)
    idx = np.stack([np.concatenate([i, diag]), np.concatenate([j, diag])])
    vals = np.concatenate([val, np.ones(len(diag))])
    return torch.sparse_coo_tensor(torch.as_tensor(idx), torch.as_tensor(vals, dtype=torch.float32),
                                   (num_vertices, num_vertices), check_invariants=True).coalesce()


def laplacian_loss(lap: torch.Tensor, verts: torch.Tensor, reference: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared norm of L (verts - reference): smoothness of a mesh correction. verts (B, V, 3) or (V, 3).

    With ``reference`` None it is the Laplacian of the mesh itself."""
    d = verts if reference is None else verts - reference
    d = d.reshape(-1, *d.shape[-2:])
    lap = lap.to(d.dtype)
    out = torch.stack([torch.sparse.mm(lap, di) for di in d])
    return (out**2).sum(-1).mean()


def scale_regulariser(local_log_scale: torch.Tensor, threshold: float = 0.6) -> torch.Tensor:
    """GaussianAvatars' scale term: mean of max(0, local scale - threshold), local scale in face units."""
    return F.relu(torch.exp(local_log_scale) - threshold).mean()


def position_regulariser(local_xyz: torch.Tensor, threshold: float = 1.0) -> torch.Tensor:
    """GaussianAvatars' position term: mean of max(0, |local xyz| - threshold) (keeps Gaussians near their face)."""
    return F.relu(local_xyz.norm(dim=-1) - threshold).mean()


# ----- perceptual (optional, weights from the user) -------------------------------------------------------

_VGG16_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_VGG_TAPS = (3, 8, 15, 22, 29)  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 in torchvision's `features`


class VGGPerceptual(torch.nn.Module):
    """VGG16 features with torchvision's layer numbering (``features.N.weight``), no torchvision needed.

    Loads a user's file: a torchvision VGG16 state_dict (``vgg16-397923af.pth``) gives a VGG feature loss
    (mean L1 of the five relu features); an LPIPS file that also holds ``lin0.model.1.weight`` ...
    ``lin4.model.1.weight`` (the ``lpips`` package's vgg.pth merged with the backbone) gives LPIPS.
    Loaded with ``weights_only=True``: a weights file cannot run code.
    """

    mean = (0.485, 0.456, 0.406)
    std = (0.229, 0.224, 0.225)

    def __init__(self, state: dict[str, torch.Tensor]) -> None:
        super().__init__()
        layers: list[torch.nn.Module] = []
        c_in = 3
        for v in _VGG16_CFG:
            if v == "M":
                layers.append(torch.nn.MaxPool2d(2, 2))
            else:
                layers += [torch.nn.Conv2d(c_in, v, 3, padding=1), torch.nn.ReLU(inplace=False)]
                c_in = v
        self.features = torch.nn.Sequential(*layers)
        feats = {k[len("features."):]: v for k, v in state.items() if k.startswith("features.")}
        missing = self.features.load_state_dict(feats, strict=False).missing_keys
        if missing:
            raise ValueError(f"perceptual weights lack VGG16 layers {missing[:4]}... (need torchvision VGG16 "
                             "'features.N.weight/bias' keys)")
        lins = [state.get(f"lin{i}.model.1.weight") for i in range(5)]
        self.lins = None if any(x is None for x in lins) else [x.float() for x in lins]
        self.requires_grad_(False)
        self.eval()

    @classmethod
    def load(cls, path: str | Path) -> VGGPerceptual:
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            raise ValueError(f"{path}: expected a state_dict of tensors")
        return cls(state)

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """x, y: (B, H, W, 3) in [0, 1] -> scalar."""
        m = torch.tensor(self.mean, dtype=x.dtype).view(1, 3, 1, 1)
        s = torch.tensor(self.std, dtype=x.dtype).view(1, 3, 1, 1)
        a = (x.permute(0, 3, 1, 2) - m) / s
        b = (y.permute(0, 3, 1, 2) - m) / s
        total = x.new_zeros(())
        tap = 0
        for i, layer in enumerate(self.features):
            a, b = layer(a), layer(b)
            if i in _VGG_TAPS:
                if self.lins is None:
                    total = total + (a - b).abs().mean()
                else:
                    na = a / (a.norm(dim=1, keepdim=True) + 1e-10)
                    nb = b / (b.norm(dim=1, keepdim=True) + 1e-10)
                    total = total + ((na - nb) ** 2 * self.lins[tap].view(1, -1, 1, 1)).sum(1).mean()
                tap += 1
                if tap == len(_VGG_TAPS):
                    break
        return total
