"""The head model: FLAME-structured LBS, FLAME loader, procedural stand-in, renderer."""

from .io import default_head, load_head
from .lbs import HeadSubject, forward, lbs, pose_rotations
from .model import JOINT_NAMES, HeadModel, HeadModelError

__all__ = [
    "JOINT_NAMES",
    "HeadModel",
    "HeadModelError",
    "HeadSubject",
    "default_head",
    "forward",
    "lbs",
    "load_head",
    "pose_rotations",
]
