"""The Python client's fast deformation of a params session (`ofera.client.rig_fast.FastRig`, PROTOCOL.md 13.4)
against the protocol's reference `deform_rig`: the golden vectors, the built-in avatar's (triangle) rig on random
FLAME values, a barycentric rig, rigs that use only some faces, degenerate 6D values, both coordinate systems
through `RigDeformer.apply`; and the two timed side by side (printed; run with -s)."""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pytest
from ofera.client.params import RigDeformer
from ofera.client.rig_fast import FastRig
from ofera_protocol import GaussianState
from ofera_protocol.rig import Rig, decode_rig, deform_rig
from test_params_rig import VECTORS, _flame_values, barycentric_rig_and_frames, rotation_error, tiny_params, tiny_rig

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def built_in_rig() -> Rig:
    """The built-in avatar's rig (triangle binding; 72,561 of its 115,600 Gaussians, 4,524 vertices)."""
    from ofera.avatar import load_avatar
    from ofera.mapping.runtime import Mapper
    from ofera.streaming.params import rig_body
    from ofera.streaming.pipeline import AvatarAssets

    return decode_rig(rig_body(AvatarAssets.create("default", load_avatar("default"), Mapper.default()), None))


def assert_matches_reference(rig: Rig, fast: FastRig, y: np.ndarray) -> None:
    """FastRig vs deform_rig on one frame: positions within 1e-6 m, rotations (up to sign) and relative scales
    within 1e-5 (PROTOCOL.md 13.7's bounds for a conforming client)."""
    p, q, s = fast.deform(y)
    pr, qr, sr = deform_rig(rig, y)
    assert p.dtype == q.dtype == s.dtype == np.float32
    assert p.shape == pr.shape and q.shape == qr.shape and s.shape == sr.shape
    assert np.abs(p - pr).max(initial=0) < 1e-6
    assert (rotation_error(q, qr) if q.size else 0) < 1e-5
    assert (np.abs(s - sr) / np.maximum(np.abs(sr), 1e-30)).max(initial=0) < 1e-5


def test_golden_vectors():
    rig = tiny_rig()
    fast = FastRig(rig)
    frames = json.loads((VECTORS / "rig_tiny_frames.json").read_text())["frames"]
    for fr, (_, y) in zip(frames, tiny_params(), strict=True):
        p, q, s = fast.deform(y)
        assert np.abs(p - np.array(fr["position"], np.float32)).max() < 1e-6
        assert rotation_error(q, np.array(fr["rotation"], np.float32)) < 1e-5
        assert (np.abs(s - fr["scale"]) / np.array(fr["scale"])).max() < 1e-5
        assert_matches_reference(rig, fast, y)


def test_some_faces_only_and_degenerate_6d():
    """Every other Gaussian of the tiny rig (faces and vertices left out of FastRig's arrays), and 6D values of
    zero (the norm clamps of 13.4 step 2) or of non-unit length."""
    rig = tiny_rig()
    keep = np.arange(0, rig.gaussians, 2)
    sub = dataclasses.replace(rig, index=rig.index[keep], gaussian_face=rig.gaussian_face[keep],
                              local_position=rig.local_position[keep], local_rotation=rig.local_rotation[keep],
                              local_scale=rig.local_scale[keep])
    fast = FastRig(sub)
    assert fast.face_verts.shape[0] < rig.faces
    rng = np.random.default_rng(3)
    for _, y in tiny_params():
        assert_matches_reference(sub, fast, y)
    y = np.zeros(68, np.float32)
    assert_matches_reference(sub, fast, y)
    y[:50] = rng.normal(0, 1, 50)
    y[50:] = rng.normal(0, 2, 18)
    assert_matches_reference(sub, fast, y)
    empty = dataclasses.replace(rig, index=rig.index[:0], gaussian_face=rig.gaussian_face[:0],
                                local_position=rig.local_position[:0], local_rotation=rig.local_rotation[:0],
                                local_scale=rig.local_scale[:0])
    assert_matches_reference(empty, FastRig(empty), y)


def test_built_in_avatar_triangle_rig(built_in_rig):
    rig = built_in_rig
    assert rig.binding == "triangle"
    fast = FastRig(rig)
    rng = np.random.default_rng(21)
    for scale in (1.0, 3.0):
        y = _flame_values(rng)
        y[:50] *= scale
        assert_matches_reference(rig, fast, y)


def test_barycentric_rig():
    body, ys, _ = barycentric_rig_and_frames(n=600, frames=2)
    rig = decode_rig(body)
    assert rig.binding == "barycentric"
    fast = FastRig(rig)
    for y in ys:
        assert_matches_reference(rig, fast, y)


@pytest.mark.parametrize("coords", ["flame", "unity"])
def test_rig_deformer_apply_fast_and_reference(coords):
    """`RigDeformer` (fast by default) and `RigDeformer(reference=True)` write the same session rows."""
    rig = tiny_rig()
    fast, ref = RigDeformer(rig), RigDeformer(rig, reference=True)
    assert fast.fast is not None and ref.fast is None
    n = rig.count

    def state() -> GaussianState:
        return GaussianState(np.zeros((n, 3)), np.zeros((n, 4)), np.ones((n, 3)))

    for _, y in tiny_params():
        a, b = state(), state()
        fast.apply(y, a, coords)
        ref.apply(y, b, coords)
        assert np.abs(a.position - b.position).max() < 1e-6
        assert rotation_error(a.rotation[rig.index], b.rotation[rig.index]) < 1e-5
        assert np.abs(a.scale - b.scale).max() < 1e-6


def test_timing_side_by_side(built_in_rig):
    """Median ms per frame, the built-in avatar's rig: the fast path over 60 frames and the reference over 10, in
    the same run (a loaded, shared machine: only their ratio is asserted)."""
    rig = built_in_rig
    rng = np.random.default_rng(5)
    ys = [_flame_values(rng) for _ in range(10)]
    t = time.perf_counter()
    fast = RigDeformer(rig)
    fast.deform(ys[0])  # numba: compiled once, then cached on disk
    setup_ms = (time.perf_counter() - t) * 1e3
    ref = RigDeformer(rig, reference=True)

    def median_ms(deformer: RigDeformer, frames: int) -> float:
        out = []
        for i in range(frames):
            t = time.perf_counter()
            deformer.deform(ys[i % len(ys)])
            out.append((time.perf_counter() - t) * 1e3)
        return float(np.median(out))

    fast_ms, ref_ms = median_ms(fast, 60), median_ms(ref, 10)
    print(f"\n[params python] {rig.gaussians} Gaussians, {rig.vertices} vertices, {rig.faces} faces: fast (numba) "
          f"{fast_ms:.2f} ms/frame (median of 60; setup + first call {setup_ms:.0f} ms), reference deform_rig "
          f"{ref_ms:.1f} ms/frame (median of 10)")
    assert fast_ms * 5 < ref_ms
