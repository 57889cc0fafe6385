"""A synthetic multi-view capture of the procedural head, rendered from the paired-data rig's ground truth.

The capture is made the way the paired benchmark (``ofera.training.paired``) makes a subject, with a new
subject the EPM never saw: a rig style and identity (the "person": ARKit weights -> mesh, deliberately not
the head model), a capture-like weight sequence, the camera estimator's observed blendshapes (the
benchmark's estimator for that source: gain, bias, cross-talk, lag, jitter, dropouts), and the tracker's
FLAME fit of the rig's meshes. Images are the ground-truth avatar (Gaussians bound to the head's faces)
placed on the rig's mesh and rendered with the torch rasteriser. Frames are taken every ``stride`` frames of
the sequence; validation frames follow the training frames, and the held-out test frames come last.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..avatar.camera import Camera
from ..head.model import HeadModel
from ..head.render import vertex_colours
from .data import Capture
from .model import SH_C0, TrainableAvatar
from .rasterize import rasterize

BENCHMARK_SEED = 0  # the estimator of the paired benchmark the default EPM was trained on
TEST_SUBJECT = 1000  # subject ids of the benchmark are 0..29: this one is new to the EPM


def capture_cameras(n: int = 3, size: int = 64, distance: float = 0.45, fov_deg: float = 26.0) -> list[Camera]:
    """``n`` cameras around the face (front, left, right, then from below), looking at the face's centre."""
    target = np.array([0.0, -0.005, 0.03])
    views = [(0.0, 0.0), (-35.0, 5.0), (35.0, 5.0), (0.0, -20.0), (-20.0, -15.0), (20.0, 15.0)]
    cams = []
    for k, (yaw, pitch) in enumerate(views[:n]):
        a, b = np.radians(yaw), np.radians(pitch)
        eye = target + distance * np.array([np.sin(a) * np.cos(b), np.sin(b), np.cos(a) * np.cos(b)])
        cams.append(Camera.look_at(eye, target, fov_x_deg=fov_deg, width=size, height=size, name=f"cam{k}"))
    return cams


def visible_faces(head: HeadModel, min_normal_z: float = -0.25, min_y: float = -0.12) -> np.ndarray:
    """Faces the capture cameras can see: facing forwards-ish and above the lower neck."""
    v, f = head.v_template, head.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    c = v[f].mean(axis=1)
    return np.flatnonzero((n[:, 2] > min_normal_z) & (c[:, 1] > min_y))


def textured_colours(head: HeadModel, faces: np.ndarray, seed: int = 0) -> np.ndarray:
    """(F, 3) colours: the head's label colours with a mid-frequency pattern (1-2 cm waves), so that a misplaced
    Gaussian changes the image (skin of one flat colour would hide geometry errors)."""
    rng = np.random.default_rng(seed)
    base = vertex_colours(head)[head.faces[faces]].mean(axis=1)
    c = head.v_template[head.faces[faces]].mean(axis=1)
    pattern = np.zeros(len(faces))
    for _ in range(6):
        k = rng.normal(size=3)
        k *= rng.uniform(2 * np.pi / 0.02, 2 * np.pi / 0.008) / np.linalg.norm(k)
        pattern += np.sin(c @ k + rng.uniform(0, 2 * np.pi))
    shade = 1.0 + 0.12 * pattern / np.sqrt(6)
    return np.clip(base * shade[:, None], 0.0, 1.0)


def ground_truth_avatar(head: HeadModel, shape: np.ndarray | None, faces: np.ndarray | None = None,
                        per_face: int = 1, seed: int = 0) -> TrainableAvatar:
    faces = visible_faces(head) if faces is None else faces
    return TrainableAvatar.init_on_mesh(head, faces, textured_colours(head, faces, seed), per_face=per_face,
                                        seed=seed, correct_basis=False, opacity=0.95, scale=0.6, shape=shape)


def degraded_copy(avatar: TrainableAvatar, seed: int = 1, correct_basis: bool = True) -> TrainableAvatar:
    """The training start: the ground truth with washed-out, noisy colours, jittered positions, wrong sizes
    and lower opacity (and no basis correction yet)."""
    g = torch.Generator().manual_seed(seed)
    a = avatar.attributes()
    colour = SH_C0 * a["sh_dc"] + 0.5
    colour = 0.5 * colour + 0.5 * colour.mean(0) + 0.05 * torch.randn(colour.shape, generator=g)
    attrs = {
        "binding": a["binding"],
        "local_xyz": a["local_xyz"] + 0.15 * torch.randn(a["local_xyz"].shape, generator=g),
        "local_log_scale": a["local_log_scale"] + 0.25 + 0.2 * torch.randn(a["local_log_scale"].shape, generator=g),
        "local_rot": a["local_rot"] + 0.1 * torch.randn(a["local_rot"].shape, generator=g),
        "opacity_logit": a["opacity_logit"] - 1.5,
        "sh_dc": (colour.clamp(0, 1) - 0.5) / SH_C0,
    }
    if "shape" in a:
        attrs["shape"] = a["shape"]
    if correct_basis:
        attrs["delta_exprdirs"] = torch.zeros_like(avatar.head.exprdirs)
    return TrainableAvatar.from_attributes(avatar.head_model, attrs)


def render_on_meshes(avatar: TrainableAvatar, meshes: np.ndarray, cameras: list[Camera],
                     background: float = 1.0) -> dict[str, np.ndarray]:
    """Render ``avatar`` placed on each mesh (T, V, 3) -> {camera: (T, H, W, 3) uint8}."""
    out = {c.name: [] for c in cameras}
    with torch.no_grad():
        for m in meshes:
            g = avatar.gaussians(torch.as_tensor(m, dtype=torch.float32))
            for cam in cameras:
                img = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], g["colours"], cam,
                                background=background).image
                out[cam.name].append(np.round(img.clamp(0, 1).numpy() * 255).astype(np.uint8))
    return {k: np.stack(v) for k, v in out.items()}


@dataclass
class SyntheticScene:
    head: HeadModel
    shape: np.ndarray  # (S,) the subject's identity coefficients
    capture: Capture  # images, observed blendshapes, tracker (the FLAME fit of the rig meshes), split
    gt_avatar: TrainableAvatar
    rig_weights: np.ndarray  # (T, 51) the true weights that drove the rig
    rig_meshes: np.ndarray  # (T, V, 3)
    fit_rms: np.ndarray  # (T,) metres


def make_scene(head: HeadModel, n_train: int, n_test: int, cameras: list[Camera], seed: int = 0,
               per_face: int = 1, background: float = 1.0, source: int = 0, stride: int = 4,
               fps: float = 30.0, n_val: int = 0) -> SyntheticScene:
    """A new subject (``TEST_SUBJECT`` + seed) of paired-benchmark source ``source``; see the module docstring.

    Frames in time order: ``n_train`` training, ``n_val`` validation (for choosing hyperparameters), then
    ``n_test`` held-out test frames."""
    from .paired.benchmark import SOURCES
    from .paired.fit import FlameFitter
    from .paired.observe import estimator_params, observe_camera
    from .paired.rig import Rig, RigBasis, RigStyle
    from .paired.sequences import generate_weights

    src = SOURCES[source]
    seeds = np.random.SeedSequence([BENCHMARK_SEED, TEST_SUBJECT + seed]).spawn(4)
    rngs = [np.random.default_rng(s) for s in seeds]
    style = RigStyle.random(rngs[0], head.shape_dims)
    frames = (n_train + n_val + n_test) * stride
    w = generate_weights(rngs[1], frames, fps, src.sequence)
    estimator = estimator_params(np.random.default_rng([BENCHMARK_SEED, 0x50C, source]), src.noise)
    bs = observe_camera(rngs[2], w, fps, src.noise, estimator)
    pick = np.arange(0, frames, stride)
    w, bs = w[pick], bs[pick].astype(np.float32)
    meshes = Rig(head, style, None, RigBasis.build(head)).mesh(w)
    fitter = FlameFitter(head, shape=style.shape)
    fit = fitter.fit(meshes[:, fitter.vertex_ids])
    gt = ground_truth_avatar(head, style.shape, per_face=per_face, seed=seed)
    images = render_on_meshes(gt, meshes, cameras, background)
    names = [f"{i * stride:06d}" for i in range(len(pick))]
    capture = Capture(cameras, images, bs, names, tracker=fit.flame.astype(np.float32),
                      split={"train": names[:n_train], "val": names[n_train:n_train + n_val],
                             "test": names[n_train + n_val:]})
    return SyntheticScene(head, style.shape, capture, gt, w, meshes, fit.rms)
