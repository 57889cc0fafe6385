"""Paired data: blendshapes paired with FLAME values (the EPM's training data).

- :class:`PairedData` (``data``): the npz container, subject-disjoint train/val/test splits.
- :func:`make_benchmark` (``benchmark``): the synthetic benchmark built on the procedural head: an
  ARKit-style nonlinear rig per subject (``rig``), capture-like sequences (``sequences``), FLAME values
  fitted to the rig's meshes as a tracker does (``fit``), camera-style estimates and a simulated
  headset stream (``observe``).
- :func:`vertices_from_flame`, :func:`region_masks` (``geometry``): meshes and face regions for evaluation.
- importers (``importers``): a blendshape CSV aligned with metrical-tracker, VHAP/GaussianAvatars or
  INSTA tracker outputs.
"""

from ofera.training.paired.benchmark import SOURCES, make_benchmark
from ofera.training.paired.data import SPLITS, PairedData, PairedDataError, concat
from ofera.training.paired.fit import FitResult, FlameFitter, fit_vertices
from ofera.training.paired.geometry import REGIONS, region_masks, vertices_from_flame
from ofera.training.paired.importers import import_insta, import_metrical_tracker, import_vhap, read_blendshape_csv

__all__ = [
    "REGIONS",
    "SOURCES",
    "SPLITS",
    "FitResult",
    "FlameFitter",
    "PairedData",
    "PairedDataError",
    "concat",
    "fit_vertices",
    "import_insta",
    "import_metrical_tracker",
    "import_vhap",
    "make_benchmark",
    "read_blendshape_csv",
    "region_masks",
    "vertices_from_flame",
]
