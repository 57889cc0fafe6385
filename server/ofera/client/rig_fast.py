"""The fast client-side deformation of a params session (PROTOCOL.md 13.4), beside the protocol's float64 numpy
reference `ofera_protocol.rig.deform_rig` (tests/test_params_fast.py compares the two).

`FastRig(rig)` precomputes, once per rig: only the faces the Gaussians sit on and those faces' vertices
(renumbered), one float32 basis per used vertex (the expression components, then the pose rows, the float16 pose
basis decoded once), the skinning weights folded for A_0 = A_1 = [I | 0], and the local rotations normalised.
`FastRig.deform(params)` is then one numba kernel: joints and pose feature, the used vertices (blend + skin), each
used face's frame and quaternion once (not once per Gaussian), then the Gaussians. Float32 arrays in and out,
float64 scalar arithmetic inside (free on a CPU; the spec allows float32 or better).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from ofera_protocol.rig import JOINTS, Rig

from ..jit import NB

GAUSS_COLS = 12
"""Numbers per Gaussian in FastRig.gauss (float32): local position or bary (3), rotation (w, x, y, z), scale (3),
normal offset, padding."""
FACE = 17
"""Numbers per used face in the kernel's scratch: R_f s_f (9, row-major) or v0 v1 v2 (9), then c_f or e1 x e2 (3),
q_f (w, x, y, z), s_f."""


@njit(**NB)
def _rot6d(p: np.ndarray, o: int, out: np.ndarray) -> None:
    """6D p[o:o+6] (two rows) -> out (3, 3), rows b1, b2, b3 (PROTOCOL.md 13.4 step 2)."""
    a1x, a1y, a1z = float(p[o]), float(p[o + 1]), float(p[o + 2])
    a2x, a2y, a2z = float(p[o + 3]), float(p[o + 4]), float(p[o + 5])
    n = max(np.sqrt(a1x * a1x + a1y * a1y + a1z * a1z), 1e-12)
    b1x, b1y, b1z = a1x / n, a1y / n, a1z / n
    d = b1x * a2x + b1y * a2y + b1z * a2z
    cx, cy, cz = a2x - d * b1x, a2y - d * b1y, a2z - d * b1z
    n = max(np.sqrt(cx * cx + cy * cy + cz * cz), 1e-12)
    b2x, b2y, b2z = cx / n, cy / n, cz / n
    out[0, 0], out[0, 1], out[0, 2] = b1x, b1y, b1z
    out[1, 0], out[1, 1], out[1, 2] = b2x, b2y, b2z
    out[2, 0], out[2, 1], out[2, 2] = b1y * b2z - b1z * b2y, b1z * b2x - b1x * b2z, b1x * b2y - b1y * b2x


@njit(**NB)
def _deform(params, joints, joints_expr, pose_rows, template, basis, weights, face_verts, run_face, run_m, run_len,
            gauss, triangle, a, coef, verts, frame, position, rotation, scale, rows, psign, rsign):
    """PROTOCOL.md 13.4 steps 1-7 over FastRig's arrays (shapes there; the Gaussians in runs on one face, their
    attributes one float32 row each: gauss (M, GAUSS_COLS)); writes Gaussian m into row rows[m] of
    position (N, 3), rotation (N, 4) (x, y, z, w), scale (N, 3), position and rotation times psign (3,), rsign (4,)
    (the session's coords); a (5, 3, 4), coef (K,), verts (V, 3), frame (F, FACE) are scratch."""
    e_dims = joints_expr.shape[2]
    rot = np.empty((3, 3))
    a[:] = 0.0
    for k in range(2):
        for i in range(3):
            a[k, i, i] = 1.0
    for k in range(2, JOINTS):  # A_k = [R_k | J_k - R_k J_k]; 6D at 50, 56, 62
        _rot6d(params, 38 + 6 * k, rot)
        j = np.empty(3)
        for c in range(3):
            s = float(joints[k, c])
            for e in range(e_dims):
                s += float(joints_expr[k, c, e]) * float(params[e])
            j[c] = s
        for i in range(3):
            a[k, i, 0], a[k, i, 1], a[k, i, 2] = rot[i, 0], rot[i, 1], rot[i, 2]
            a[k, i, 3] = j[i] - (rot[i, 0] * j[0] + rot[i, 1] * j[1] + rot[i, 2] * j[2])
    for e in range(e_dims):
        coef[e] = params[e]
    for p in range(pose_rows.shape[0]):  # step 4: R_k[i][j] - delta_ij, k = 1 + r div 9
        r = int(pose_rows[p])
        k, i, j = 1 + r // 9, (r % 9) // 3, r % 3
        coef[e_dims + p] = a[k, i, j] - (1.0 if i == j else 0.0)
    n_comp = basis.shape[1]
    for u in range(verts.shape[0]):  # step 5 for the used vertices
        x, y, z = float(template[u, 0]), float(template[u, 1]), float(template[u, 2])
        for c in range(n_comp):
            w = coef[c]
            x += basis[u, c, 0] * w
            y += basis[u, c, 1] * w
            z += basis[u, c, 2] * w
        wi, w2, w3, w4 = weights[u, 0], weights[u, 1], weights[u, 2], weights[u, 3]
        for i in range(3):
            t0 = w2 * a[2, i, 0] + w3 * a[3, i, 0] + w4 * a[4, i, 0]
            t1 = w2 * a[2, i, 1] + w3 * a[3, i, 1] + w4 * a[4, i, 1]
            t2 = w2 * a[2, i, 2] + w3 * a[3, i, 2] + w4 * a[4, i, 2]
            t3 = w2 * a[2, i, 3] + w3 * a[3, i, 3] + w4 * a[4, i, 3]
            verts[u, i] = t0 * x + t1 * y + t2 * z + t3 + wi * (x if i == 0 else (y if i == 1 else z))
    for f in range(frame.shape[0]):  # step 6 and quat(R_f), once per used face
        i0, i1, i2 = np.uint64(face_verts[f, 0]), np.uint64(face_verts[f, 1]), np.uint64(face_verts[f, 2])
        v0x, v0y, v0z = verts[i0, 0], verts[i0, 1], verts[i0, 2]
        v1x, v1y, v1z = verts[i1, 0], verts[i1, 1], verts[i1, 2]
        v2x, v2y, v2z = verts[i2, 0], verts[i2, 1], verts[i2, 2]
        e1x, e1y, e1z = v1x - v0x, v1y - v0y, v1z - v0z
        e2x, e2y, e2z = v2x - v0x, v2y - v0y, v2z - v0z
        l1 = np.sqrt(max(e1x * e1x + e1y * e1y + e1z * e1z, 1e-20))
        inv = 1.0 / l1  # one division, then products (differs from the reference's divisions by ~1e-16)
        a0x, a0y, a0z = e1x * inv, e1y * inv, e1z * inv
        nx, ny, nz = a0y * e2z - a0z * e2y, a0z * e2x - a0x * e2z, a0x * e2y - a0y * e2x
        inv = 1.0 / np.sqrt(max(nx * nx + ny * ny + nz * nz, 1e-20))
        a1x, a1y, a1z = nx * inv, ny * inv, nz * inv
        a2x, a2y, a2z = a0y * a1z - a0z * a1y, a0z * a1x - a0x * a1z, a0x * a1y - a0y * a1x
        sf = (l1 + abs(a2x * e2x + a2y * e2y + a2z * e2z)) / 2.0
        if triangle:  # R_f s_f (R_f's columns a0 a1 a2) and c_f
            frame[f, 0], frame[f, 1], frame[f, 2] = a0x * sf, a1x * sf, a2x * sf
            frame[f, 3], frame[f, 4], frame[f, 5] = a0y * sf, a1y * sf, a2y * sf
            frame[f, 6], frame[f, 7], frame[f, 8] = a0z * sf, a1z * sf, a2z * sf
            frame[f, 9], frame[f, 10], frame[f, 11] = ((v0x + v1x + v2x) / 3.0, (v0y + v1y + v2y) / 3.0,
                                                       (v0z + v1z + v2z) / 3.0)
        else:  # v0 v1 v2 and e1 x e2
            frame[f, 0], frame[f, 1], frame[f, 2] = v0x, v0y, v0z
            frame[f, 3], frame[f, 4], frame[f, 5] = v1x, v1y, v1z
            frame[f, 6], frame[f, 7], frame[f, 8] = v2x, v2y, v2z
            frame[f, 9], frame[f, 10] = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z
            frame[f, 11] = e1x * e2y - e1y * e2x
        # R00 = a0x, R01 = a1x, R02 = a2x, R10 = a0y, R11 = a1y, R12 = a2y, R20 = a0z, R21 = a1z, R22 = a2z
        tw, tx = 1.0 + a0x + a1y + a2z, 1.0 + a0x - a1y - a2z
        ty, tz = 1.0 - a0x + a1y - a2z, 1.0 - a0x - a1y + a2z
        if tw >= tx and tw >= ty and tw >= tz:
            qw, qx, qy, qz = tw, a1z - a2y, a2x - a0z, a0y - a1x
        elif tx >= ty and tx >= tz:
            qw, qx, qy, qz = a1z - a2y, tx, a0y + a1x, a2x + a0z
        elif ty >= tz:
            qw, qx, qy, qz = a2x - a0z, a0y + a1x, ty, a1z + a2y
        else:
            qw, qx, qy, qz = a0y - a1x, a2x + a0z, a1z + a2y, tz
        n = (-1.0 if qw < 0 else 1.0) / np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        frame[f, 12], frame[f, 13], frame[f, 14], frame[f, 15], frame[f, 16] = qw * n, qx * n, qy * n, qz * n, sf
    for q in range(run_face.shape[0]):  # step 7, by runs of consecutive Gaussians on one face (its frame loaded once)
        f = np.uint64(run_face[q])
        f0, f1, f2, f3, f4, f5 = frame[f, 0], frame[f, 1], frame[f, 2], frame[f, 3], frame[f, 4], frame[f, 5]
        f6, f7, f8, f9, f10, f11 = frame[f, 6], frame[f, 7], frame[f, 8], frame[f, 9], frame[f, 10], frame[f, 11]
        fw, fx, fy, fz, sf = frame[f, 12], frame[f, 13], frame[f, 14], frame[f, 15], frame[f, 16]
        m0 = np.uint64(run_m[q])
        for j in range(np.uint64(run_len[q])):
            m = m0 + j
            g = gauss[m]
            p0, p1, p2 = float(g[0]), float(g[1]), float(g[2])
            if triangle:
                px = f0 * p0 + f1 * p1 + f2 * p2 + f9
                py = f3 * p0 + f4 * p1 + f5 * p2 + f10
                pz = f6 * p0 + f7 * p1 + f8 * p2 + f11
            else:
                k = float(g[10])
                px = p0 * f0 + p1 * f3 + p2 * f6 + f9 * k
                py = p0 * f1 + p1 * f4 + p2 * f7 + f10 * k
                pz = p0 * f2 + p1 * f5 + p2 * f8 + f11 * k
            lw, lx, ly, lz = float(g[3]), float(g[4]), float(g[5]), float(g[6])
            qw = fw * lw - fx * lx - fy * ly - fz * lz
            qx = fw * lx + fx * lw + fy * lz - fz * ly
            qy = fw * ly - fx * lz + fy * lw + fz * lx
            qz = fw * lz + fx * ly - fy * lx + fz * lw
            # q_f and the local rotation are unit: their product is unit to float32 rounding, so the reference's
            # renormalisation is left out (as the server's kernels do).
            row = np.uint64(rows[m])  # unsigned: no wrap-around code (see ofera.avatar.kernels)
            position[row, 0], position[row, 1], position[row, 2] = px * psign[0], py * psign[1], pz * psign[2]
            rotation[row, 0], rotation[row, 1] = qx * rsign[0], qy * rsign[1]
            rotation[row, 2], rotation[row, 3] = qz * rsign[2], qw * rsign[3]
            scale[row, 0], scale[row, 1], scale[row, 2] = g[7] * sf, g[8] * sf, g[9] * sf


class FastRig:
    """One rig's arrays for the fast deformation (see the module docstring). V used vertices, F used faces,
    K = E + P basis components, M Gaussians."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        faces, gaussian_face = np.unique(rig.gaussian_face.astype(np.int64), return_inverse=True)
        verts, face_verts = np.unique(rig.face.astype(np.int64)[faces], return_inverse=True)
        self.gaussian_face = gaussian_face.reshape(-1).astype(np.int32)  # (M,) used face
        self.face_verts = face_verts.reshape(-1, 3).astype(np.int32)  # (F, 3) used vertex ids
        self.template = np.ascontiguousarray(rig.template[verts], np.float32)  # (V, 3) m
        self.basis = np.ascontiguousarray(  # (V, K, 3) float32 m per unit: expression components, then pose rows
            np.concatenate([rig.expr_basis[verts], rig.pose_basis[verts].astype(np.float32)], axis=1), np.float32)
        w = rig.weights[verts].astype(np.float64)
        self.weights = np.ascontiguousarray(np.stack([w[:, 0] + w[:, 1], w[:, 2], w[:, 3], w[:, 4]], axis=1))
        lq = rig.local_rotation.astype(np.float64)
        lq = lq / np.maximum(np.linalg.norm(lq, axis=1, keepdims=True), 1e-12)
        triangle = rig.binding == "triangle"
        self.triangle = triangle
        m = self.gaussian_face.shape[0]
        no = np.zeros(m) if triangle else rig.normal_offset
        # One row per Gaussian (one read stream): local position or barycentric coordinates (3), the unit local
        # rotation (w, x, y, z), the local scale (3, face units), the normal offset (barycentric).
        self.gauss = np.ascontiguousarray(np.concatenate(
            [rig.local_position if triangle else rig.bary, lq[:, [3, 0, 1, 2]], rig.local_scale,
             np.reshape(no, (-1, 1)), np.zeros((m, 1))], axis=1), np.float32)  # (M, GAUSS_COLS)
        gf = self.gaussian_face.astype(np.int64)
        start = np.flatnonzero(np.concatenate([[True], gf[1:] != gf[:-1]])) if m else np.zeros(0, np.int64)
        self.run_face = gf[start]  # (R,) used face of each run of consecutive Gaussians
        self.run_m = start.astype(np.int64)  # (R,) its first Gaussian
        self.run_len = np.diff(np.concatenate([start, [m]])).astype(np.int64)  # (R,)
        self.joints = np.ascontiguousarray(rig.joints, np.float32)  # (5, 3) m
        self.joints_expr = np.ascontiguousarray(rig.joints_expr, np.float32)  # (5, 3, E)
        self.pose_rows = np.ascontiguousarray(rig.pose_rows, np.uint8)  # (P,)
        self._a = np.zeros((JOINTS, 3, 4))
        self._coef = np.zeros(self.basis.shape[1])
        self._verts = np.zeros((verts.size, 3))
        self._frame = np.zeros((faces.size, FACE))
        self._rows = np.arange(self.gaussian_face.shape[0], dtype=np.int64)
        self.index = rig.index.astype(np.int64)  # (M,) session ids
        self._rows_needed = int(self.index.max(initial=-1)) + 1  # rows a session's arrays must have
        identity = np.zeros(68, np.float32)
        identity[50:] = [1, 0, 0, 0, 1, 0] * 3
        self.deform(identity)  # the kernel compiled (or loaded from numba's cache) now, not on the first frame:
        identity.flags.writeable = False  # for writable params and for read-only ones (frames' msgpack buffers)
        self.deform(identity)

    def _run(self, params: np.ndarray, position: np.ndarray, rotation: np.ndarray, scale: np.ndarray,
             rows: np.ndarray, psign: np.ndarray, rsign: np.ndarray) -> None:
        params = np.ascontiguousarray(params, np.float32).reshape(-1)
        if params.shape != (68,):
            raise ValueError(f"params has shape {params.shape}, expected (68,)")
        _deform(params, self.joints, self.joints_expr, self.pose_rows, self.template, self.basis, self.weights,
                self.face_verts, self.run_face, self.run_m, self.run_len, self.gauss, self.triangle, self._a,
                self._coef, self._verts, self._frame, position, rotation, scale, rows, psign, rsign)

    def deform(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """params (68,) -> position (M, 3) m, rotation (M, 4) (x, y, z, w), scale (M, 3) m of the rig's Gaussians
        (session ids `rig.index`), float32, FLAME space: `deform_rig`'s results to ~1e-8 m."""
        m = self.gaussian_face.shape[0]
        position, scale = np.empty((m, 3), np.float32), np.empty((m, 3), np.float32)
        rotation = np.empty((m, 4), np.float32)
        self._run(params, position, rotation, scale, self._rows, _ONES[:3], _ONES)
        return position, rotation, scale

    def apply(self, params: np.ndarray, position: np.ndarray, rotation: np.ndarray, scale: np.ndarray,
              psign: np.ndarray, rsign: np.ndarray) -> None:
        """`deform` written straight into rows `rig.index` of a session's float32 arrays (N, 3), (N, 4), (N, 3),
        times the coords' signs psign (3,), rsign (4,) (ofera_protocol.fast_encodings.coord_signs): no copies."""
        for name, arr, width in (("position", position, 3), ("rotation", rotation, 4), ("scale", scale, 3)):
            if (arr.dtype != np.float32 or arr.ndim != 2 or arr.shape[1] != width or not arr.flags.c_contiguous
                    or not arr.flags.writeable or arr.shape[0] < self._rows_needed):
                raise ValueError(f"{name} must be a writable C-contiguous float32 (N, {width}) array covering "
                                 "the rig's rows")
        self._run(params, position, rotation, scale, self.index, psign, rsign)


_ONES = np.ones(4, np.float32)
