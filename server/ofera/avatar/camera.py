"""The pinhole camera of both renderers (the numpy preview, ``ofera.avatar.render``, and the torch training
rasteriser, ``ofera.training.rasterize``) and its ``cameras.json`` file.

OpenCV convention: ``p_cam = R @ p + t`` maps world to camera, camera axes x right, y down, z forward (a
visible point has z > 0); ``K`` (3, 3) intrinsics in pixels, ``(u, v) = (fx x / z + cx, fy y / z + cy)``;
pixel (i, j) covers [i, i+1) x [j, j+1), its centre at (i + 0.5, j + 0.5).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: ``K`` (3, 3) intrinsics (pixels), ``R`` (3, 3) and ``t`` (3,) world -> camera,
    ``width`` and ``height`` in pixels, a ``name`` (the capture folder's camera name)."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    name: str = "cam"

    @classmethod
    def look_at(cls, eye, target, up=(0.0, 1.0, 0.0), *, fov_y_deg: float | None = None,
                fov_x_deg: float | None = None, width: int = 512, height: int = 512, name: str = "cam") -> Camera:
        """A camera at ``eye`` looking at ``target`` with world ``up`` pointing up in the image; square pixels,
        principal point at the image centre. The field of view is vertical (``fov_y_deg``, default 25 degrees)
        or horizontal (``fov_x_deg``): give one."""
        if fov_y_deg is not None and fov_x_deg is not None:
            raise ValueError("give fov_y_deg or fov_x_deg, not both")
        eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
        forward = target - eye
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rot = np.stack([right, down, forward])  # rows: camera axes in world coordinates
        if fov_x_deg is not None:
            f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
        else:
            f = 0.5 * height / np.tan(np.radians(25.0 if fov_y_deg is None else fov_y_deg) / 2)
        k = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
        return cls(k, rot, -rot @ eye, int(width), int(height), name)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates (3,)."""
        return -self.R.T @ self.t

    def scaled(self, factor: float) -> Camera:
        """The same camera at ``factor`` times the resolution."""
        k = self.K.copy()
        k[:2] *= factor
        return Camera(k, self.R, self.t, round(self.width * factor), round(self.height * factor), self.name)

    def to_json(self) -> dict:
        return {"name": self.name, "width": self.width, "height": self.height, "K": np.asarray(self.K).tolist(),
                "R": np.asarray(self.R).tolist(), "t": np.asarray(self.t).tolist()}

    @classmethod
    def from_json(cls, d: dict) -> Camera:
        k, r, t = (np.asarray(d[key], np.float64) for key in ("K", "R", "t"))
        if k.shape != (3, 3) or r.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"camera {d.get('name', '?')}: K and R must be 3x3 and t 3 values")
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0:
            raise ValueError(f"camera {d.get('name', '?')}: R is not a rotation matrix")
        return cls(k, r, t, int(d["width"]), int(d["height"]), str(d.get("name", "cam")))


def save_cameras(cameras: list[Camera], path: str | Path) -> None:
    Path(path).write_text(json.dumps({"convention": "opencv", "cameras": [c.to_json() for c in cameras]}, indent=1))


def load_cameras(path: str | Path) -> list[Camera]:
    d = json.loads(Path(path).read_text())
    if d.get("convention", "opencv") != "opencv":
        raise ValueError(f"{path}: convention {d['convention']!r} unsupported (write OpenCV: x right, y down, z fwd)")
    return [Camera.from_json(c) for c in d["cameras"]]
