"""Offline training (the server never imports it): the mapping's EPM and its data, and the avatar (torch, CPU).

- ``epm``: the EPM network, its training, ONNX export, evaluation and the default-EPM recipe (``epm/``).
- ``paired``: paired data (blendshapes + FLAME values), the synthetic benchmark generator and importers
  (numpy/scipy; ``paired/``).

Avatar training: the differentiable rasteriser, losses, the trainer and the MiA experiment.

- ``rasterize``: 3D Gaussian splatting in plain PyTorch (EWA projection, per-pixel front-to-back
  compositing) with the OpenCV cameras of ``ofera.avatar.camera``; an optional gsplat (CUDA) path.
- ``losses``: SSIM, PSNR, the mesh Laplacian, GaussianAvatars' regularisers, an optional VGG/LPIPS term
  from user-supplied weights.
- ``model``: the trainable avatar: Gaussians bound to the head's triangles (GaussianAvatars' binding) and
  a FATE-like per-avatar correction of the expression basis.
- ``data``: the capture folder (``LAYOUT.md``); ``trainer``: the objective, the loop, checkpoints;
  ``convert``: to and from the server's ``ofera.avatar.GaussianAvatar``.
- ``synthetic`` and ``experiment``: the MiA experiment on a synthetic capture (``ofera mia experiment``).

Imported only by the offline commands: the server never needs torch (``tests/test_architecture.py``).
"""
