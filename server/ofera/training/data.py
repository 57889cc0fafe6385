"""A training capture on disk (the folder layout is documented in LAYOUT.md next to this file)."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..avatar.camera import Camera, load_cameras, save_cameras
from ..errors import OferaError

N_FLAME = 68


class CaptureError(OferaError, ValueError):
    """A capture folder that does not follow LAYOUT.md; the message says what is wrong and where."""


@dataclass
class Capture:
    """Multi-view frames with their blendshapes (and optionally a tracker's FLAME values).

    images[cam.name]: (T, H, W, 3) uint8 (or float in [0, 1]); blendshapes (T, 51) arkit51 float32;
    tracker (T, 68) float32 or None; frames: T frame names; split: optional {"train": [...], "test": [...]}
    of frame names.
    """

    cameras: list[Camera]
    images: dict[str, np.ndarray]
    blendshapes: np.ndarray
    frames: list[str]
    tracker: np.ndarray | None = None
    split: dict[str, list[str]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        t = len(self.frames)
        if self.blendshapes.shape != (t, 51):
            raise CaptureError(f"blendshapes have shape {self.blendshapes.shape}, expected ({t}, 51)")
        if self.tracker is not None and self.tracker.shape != (t, N_FLAME):
            raise CaptureError(f"tracker FLAME values have shape {self.tracker.shape}, expected ({t}, {N_FLAME})")
        for cam in self.cameras:
            img = self.images.get(cam.name)
            if img is None:
                raise CaptureError(f"no images for camera {cam.name!r}")
            if img.shape != (t, cam.height, cam.width, 3):
                raise CaptureError(f"camera {cam.name!r}: images {img.shape}, expected ({t}, {cam.height}, "
                                   f"{cam.width}, 3) from cameras.json and the frame count")
        for key, names in self.split.items():
            unknown = sorted(set(names) - set(self.frames))
            if unknown:
                raise CaptureError(f"split {key!r} names frames not in blendshapes.csv: {unknown[:5]}")

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    def indices(self, part: str) -> np.ndarray:
        """Frame indices of split ``part`` ('train', 'val' or 'test'); without a split every frame is 'train'."""
        if part in self.split:
            pos = {f: i for i, f in enumerate(self.frames)}
            return np.array([pos[f] for f in self.split[part]], np.int64)
        if part == "train":
            return np.arange(self.num_frames)
        return np.zeros(0, np.int64)

    def image(self, cam: str, frame: int) -> np.ndarray:
        """(H, W, 3) float32 in [0, 1]."""
        img = self.images[cam][frame]
        return img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img.astype(np.float32)


def _read_blendshapes(path: Path) -> tuple[list[str], np.ndarray]:
    from ..mapping.layouts import LayoutError, layout_from_names, to_arkit51

    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise CaptureError(f"{path}: empty (expected a header 'frame,<51 arkit names>')")
    header = [h.strip() for h in rows[0]]
    if not header or header[0].lower() != "frame":
        raise CaptureError(f"{path}: the first column must be 'frame' (the frame name), got {header[:1]}")
    try:
        layout, index = layout_from_names(header[1:])
    except LayoutError as exc:
        raise CaptureError(f"{path}: {exc}") from None
    frames, values = [], []
    for n, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != len(header):
            raise CaptureError(f"{path}:{n}: {len(row)} fields, the header has {len(header)}")
        frames.append(row[0].strip())
        try:
            values.append([float(v) for v in row[1:]])
        except ValueError as exc:
            raise CaptureError(f"{path}:{n}: {exc}") from None
    table = np.asarray(values, np.float32).reshape(-1, len(header) - 1)[:, index]
    if len(set(frames)) != len(frames):
        raise CaptureError(f"{path}: duplicate frame names")
    return frames, to_arkit51(layout, table).astype(np.float32)


def _write_blendshapes(path: Path, frames: list[str], bs: np.ndarray) -> None:
    from ..mapping.layouts import ARKIT51_NAMES

    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", *ARKIT51_NAMES])
        for f, row in zip(frames, bs):
            w.writerow([f, *(f"{v:.6g}" for v in row)])


def _read_png(path: Path, background: float) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        if im.mode in ("RGBA", "LA"):
            a = np.asarray(im.convert("RGBA"), np.float32) / 255.0
            rgb = a[..., :3] * a[..., 3:] + background * (1 - a[..., 3:])
            return np.round(rgb * 255).astype(np.uint8)
        return np.asarray(im.convert("RGB"), np.uint8)


def read_capture(root: str | Path, background: float = 1.0) -> Capture:
    """Read a capture folder (LAYOUT.md). PNGs with alpha are composited over ``background`` (0..1)."""
    root = Path(root)
    if not root.is_dir():
        raise CaptureError(f"{root}: no such folder (see LAYOUT.md for a capture's layout)")
    for req in ("cameras.json", "blendshapes.csv"):
        if not (root / req).is_file():
            raise CaptureError(f"{root}: missing {req} (see server/ofera/training/LAYOUT.md)")
    try:
        cameras = load_cameras(root / "cameras.json")
    except (KeyError, ValueError, json.JSONDecodeError) as exc:
        raise CaptureError(f"{root / 'cameras.json'}: {exc}") from None
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise CaptureError(f"{root / 'cameras.json'}: camera names must be unique, got {names}")
    frames, bs = _read_blendshapes(root / "blendshapes.csv")
    images: dict[str, np.ndarray] = {}
    if (root / "images.npz").is_file():
        with np.load(root / "images.npz", allow_pickle=False) as z:
            for cam in names:
                if cam not in z.files:
                    raise CaptureError(f"{root / 'images.npz'}: no array for camera {cam!r} (has {z.files})")
                images[cam] = z[cam]
    elif (root / "frames").is_dir():
        for cam in names:
            files = [root / "frames" / cam / f"{f}.png" for f in frames]
            missing = [p for p in files if not p.is_file()]
            if missing:
                raise CaptureError(f"{missing[0]}: missing ({len(missing)} frames of camera {cam!r} missing)")
            images[cam] = np.stack([_read_png(p, background) for p in files])
    else:
        raise CaptureError(f"{root}: no images (expected frames/<camera>/<frame>.png or images.npz)")
    tracker = None
    if (root / "tracker.npz").is_file():
        with np.load(root / "tracker.npz", allow_pickle=False) as z:
            if "flame" not in z.files:
                raise CaptureError(f"{root / 'tracker.npz'}: expected an array 'flame' (T, 68)")
            tracker = z["flame"].astype(np.float32)
            if "frame" in z.files and [str(f) for f in z["frame"]] != frames:
                raise CaptureError(f"{root / 'tracker.npz'}: its 'frame' names differ from blendshapes.csv")
    split = {}
    if (root / "split.json").is_file():
        split = {k: [str(f) for f in v] for k, v in json.loads((root / "split.json").read_text()).items()}
    try:
        return Capture(cameras, images, bs, frames, tracker, split)
    except CaptureError as exc:
        raise CaptureError(f"{root}: {exc}") from None


def write_capture(capture: Capture, root: str | Path, image_format: str = "png") -> Path:
    """Write ``capture`` in the LAYOUT.md layout; ``image_format`` 'png' (frames/) or 'npz' (images.npz)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    save_cameras(capture.cameras, root / "cameras.json")
    _write_blendshapes(root / "blendshapes.csv", capture.frames, capture.blendshapes)

    def u8(a: np.ndarray) -> np.ndarray:
        return a if a.dtype == np.uint8 else np.round(np.clip(a, 0, 1) * 255).astype(np.uint8)

    if image_format == "npz":
        np.savez_compressed(root / "images.npz", **{c.name: u8(capture.images[c.name]) for c in capture.cameras})
    elif image_format == "png":
        from PIL import Image

        for cam in capture.cameras:
            folder = root / "frames" / cam.name
            folder.mkdir(parents=True, exist_ok=True)
            for f, img in zip(capture.frames, u8(capture.images[cam.name])):
                Image.fromarray(img).save(folder / f"{f}.png")
    else:
        raise ValueError(f"image format {image_format!r}: use 'png' or 'npz'")
    if capture.tracker is not None:
        np.savez(root / "tracker.npz", flame=capture.tracker.astype(np.float32), frame=np.array(capture.frames))
    if capture.split:
        (root / "split.json").write_text(json.dumps(capture.split))
    return root
