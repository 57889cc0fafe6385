"""Fit the head model's FLAME values to meshes, the way a tracker does: batched least squares.

Given target points (T, n, 3) on known head vertices (a subject of known identity; root and neck
identity, as in the FLAME values), find per frame expr (50), jaw and eye rotations:

1. eyes: closed form. The eyeball is rigid, so its rotation about the eye joint is the orthogonal
   Procrustes (Kabsch) solution, batched SVD of 3x3 matrices.
2. jaw: variable projection. For a jaw rotation R, LBS is invertible vertex by vertex: a skin vertex
   with jaw share a moves by M = (1 - a) I + a R about the jaw joint, and M^-1 has a closed form (M acts
   on the plane normal to R's axis as the complex number (1 - a) + a e^{i theta}). Unposing the targets
   gives x(R) = E psi + residual; eliminating psi by projection leaves a 3-parameter problem per frame,
   solved by Gauss-Newton (finite differences, Levenberg damping) from the best of a coarse grid of jaw
   openings. Vertices without jaw share enter only through the jaw's pose correctives, which are
   linear in (R - I): their part of the normal equations comes from precomputed 9x9 / 9x50 products.
3. expr: ridge least squares on the unposed targets, (E^T E + ridge I)^-1 E^T x(R).

Joints are held at the subject's neutral joints (exact for the procedural head, whose expression basis
does not move joints; FLAME's expression moves them by well under a millimetre).
Everything is batched over frames with numpy: thousands of frames per second on one core.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from ofera.head.lbs import HeadSubject
from ofera.head.model import HeadModel
from ofera.head.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ofera.mapping.flame_values import join_flame_values

EYE_JOINTS = (3, 4)
JAW_JOINT = 2
_JAW_ROWS = slice(9, 18)  # pose feature rows of the jaw (joint 2 of the 4 non-root joints: neck, jaw, eyes)
_EYE_ROWS = slice(18, 36)


def fit_vertices(head: HeadModel, stride: int = 2, eye_stride: int = 5) -> np.ndarray:
    """Default vertex set for fitting (and for the rig): the face, denser at lids and lips, plus eyeballs.

    Skin vertices on the front of the face that no eye joint moves, every ``stride``-th of them but
    every one near the eyes and lips; every ``eye_stride``-th eyeball vertex.
    """
    v = head.v_template
    x, y, z = v.T
    eye_w = head.weights[:, list(EYE_JOINTS)].sum(axis=1)
    labels = head.vertex_labels
    if "skin" in labels:
        skin = labels["skin"]
    else:  # a FLAME file: no labels; the front of the face by position
        skin = eye_w < 1e-9
    face = skin & (eye_w < 1e-9) & (z > 0.005) & (y > -0.1) & (y < 0.072)
    dense = np.zeros(len(v), bool)
    if head.landmarks:
        lm = head.landmarks
        for key in ("eye_left", "eye_right"):
            dense |= np.linalg.norm(v - lm[key], axis=1) < 0.022
        dense |= np.linalg.norm((v - lm["mouth_centre"]) / [1.6, 1.0, 1.0], axis=1) < 0.02
    idx = np.arange(len(v))
    keep = face & (dense | (idx % stride == 0))
    eyes = [np.nonzero(head.weights[:, j] > 0.999)[0][::eye_stride] for j in EYE_JOINTS]
    return np.concatenate([np.nonzero(keep)[0], *eyes])


@dataclass(frozen=True)
class FitResult:
    flame: np.ndarray  # (T, 68) float64 FLAME values
    rms: np.ndarray  # (T,) metres: RMS distance over the fitted vertices between the fit and the targets
    jaw_axis_angle: np.ndarray  # (T, 3)


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotations R (T, 3, 3) minimising sum |R a_i - b_i|^2; a (m, 3) and b (T, m, 3) centred."""
    h = np.einsum("mi,tmj->tij", a, b)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.swapaxes(vt, 1, 2) @ np.swapaxes(u, 1, 2)))
    fix = np.ones((len(h), 3))
    fix[:, 2] = d
    return np.swapaxes(vt, 1, 2) @ (fix[:, :, None] * np.swapaxes(u, 1, 2))


def _axis_terms(omega: np.ndarray, share: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit axis (T, 3) and the complex factor c = p + i q = (1 - a) + a e^{i theta}, (T, n) each."""
    theta = np.sqrt(np.sum(omega * omega, axis=1))
    axis = omega / np.maximum(theta, 1e-12)[:, None]
    axis[theta < 1e-12] = (1.0, 0.0, 0.0)
    p = 1.0 - share[None] + share[None] * np.cos(theta)[:, None]
    q = share[None] * np.sin(theta)[:, None]
    return axis, p, q


def _cross(n: np.ndarray, y: np.ndarray) -> np.ndarray:
    """n (T, 1, 3) x y (T, m, 3), without np.cross's overhead."""
    out = np.empty_like(y)
    out[..., 0] = n[..., 1] * y[..., 2] - n[..., 2] * y[..., 1]
    out[..., 1] = n[..., 2] * y[..., 0] - n[..., 0] * y[..., 2]
    out[..., 2] = n[..., 0] * y[..., 1] - n[..., 1] * y[..., 0]
    return out


def unpose_blend(y: np.ndarray, omega: np.ndarray, share: np.ndarray) -> np.ndarray:
    """Solve ((1 - a) I + a R) u = y for u: y (T, n, 3), omega (T, 3) axis-angle of R, share a (n,)."""
    axis, p, q = _axis_terms(omega, share)
    n = axis[:, None, :]
    along = y @ axis[:, :, None]  # (T, n, 1)
    den = p * p + q * q
    pp, qq = (p / den)[..., None], (q / den)[..., None]
    return pp * y + (1.0 - pp) * along * n - qq * _cross(n, y)


def unpose_split(y: np.ndarray, omega: np.ndarray, rot: np.ndarray, share: np.ndarray, n_rigid: int) -> np.ndarray:
    """:func:`unpose_blend` for vertices ordered rigid first (share 1: u = R^T y, a matrix product)."""
    out = np.empty_like(y)
    np.matmul(y[:, :n_rigid], rot, out=out[:, :n_rigid])  # rows: u^T = y^T R
    out[:, n_rigid:] = unpose_blend(y[:, n_rigid:], omega, share[n_rigid:])
    return out


def pose_blend(u: np.ndarray, omega: np.ndarray, share: np.ndarray) -> np.ndarray:
    """((1 - a) I + a R) u, the forward twin of :func:`unpose_blend`."""
    axis, p, q = _axis_terms(omega, share)
    n = axis[:, None, :]
    along = u @ axis[:, :, None]
    return p[..., None] * u + (1.0 - p[..., None]) * along * n + q[..., None] * _cross(n, u)


class FlameFitter:
    """Fits FLAME values to points on ``vertex_ids`` of one subject (identity ``shape``) of ``head``."""

    def __init__(self, head: HeadModel, shape: np.ndarray | None = None, vertex_ids: np.ndarray | None = None,
                 ridge: float = 1e-8, iterations: int = 3, n_expr: int = 50, search_vertices: int = 120) -> None:
        """``ridge``: m^2 per unit coefficient^2 (1e-8 = (0.1 mm)^2); ``iterations``: Gauss-Newton steps of
        the jaw search; ``search_vertices``: how many jaw-moved vertices it unposes (the final solve uses all)."""
        ids = fit_vertices(head) if vertex_ids is None else np.asarray(vertex_ids, np.int64)
        w = head.weights[ids]
        eye_share = w[:, list(EYE_JOINTS)]
        rigid_eye = [eye_share[:, k] > 0.999 for k in range(2)]
        skin = eye_share.sum(axis=1) < 1e-9
        if not np.all(skin | rigid_eye[0] | rigid_eye[1]):
            raise ValueError("fit vertices must be either eyeball vertices or vertices that no eye joint moves")
        if rigid_eye[0].sum() < 3 or rigid_eye[1].sum() < 3:
            raise ValueError("fit vertices need at least 3 vertices on each eyeball")
        self.head, self.vertex_ids, self.iterations = head, ids, iterations
        self._eye = [np.nonzero(m)[0] for m in rigid_eye]
        self._skin = np.nonzero(skin)[0]
        sk = ids[self._skin]
        ns = len(sk)
        share = w[self._skin, JAW_JOINT]
        posedirs = head.posedirs.reshape(-1, head.num_vertices, 3)[:, sk]  # (36, ns, 3)
        self._p_eye = posedirs[_EYE_ROWS].reshape(18, 3 * ns)
        self._p_jaw = posedirs[_JAW_ROWS].reshape(9, 3 * ns)
        e = head.exprdirs[sk][:, :, :n_expr].reshape(3 * ns, n_expr)
        self._e = e
        # Ridge least squares: (E^T E + ridge I)^-1 E^T.
        self._solve = np.linalg.solve(e.T @ e + ridge * np.eye(e.shape[1]), e.T)  # (n_expr, 3 ns)
        self._jaw_share = share

        # The jaw search: jaw-moved vertices J (a subsample, unposed explicitly) and the others N (they
        # feel the jaw only through its pose correctives, so they enter through precomputed products).
        rigid, blended = np.nonzero(share >= 1.0 - 1e-12)[0], np.nonzero((share > 1e-9) & (share < 1.0 - 1e-12))[0]
        self._moved, self._moved_rigid = np.concatenate([rigid, blended]), len(rigid)
        if len(rigid) + len(blended) > search_vertices:  # an even subsample of each kind
            k = round(search_vertices * len(rigid) / (len(rigid) + len(blended)))
            rigid = rigid[np.linspace(0, len(rigid) - 1, k).round().astype(np.int64)] if k else rigid[:0]
            blended = blended[np.linspace(0, len(blended) - 1, search_vertices - k).round().astype(np.int64)]
        moved = np.concatenate([rigid, blended])
        self._search_rigid = len(rigid)
        others = np.nonzero(share <= 1e-9)[0]
        cols = lambda idx: (3 * idx[:, None] + np.arange(3)).reshape(-1)  # noqa: E731
        self._jset, self._jcols, self._ncols = moved, cols(moved), cols(others)
        self._nset = others
        self._share = share[moved]
        self._p_jaw_j = self._p_jaw[:, self._jcols]
        p_n = self._p_jaw[:, self._ncols]
        search_rows = np.concatenate([self._jcols, self._ncols])
        es = e[search_rows]
        lam, vec = np.linalg.eigh(es.T @ es)  # orthonormal basis of the expression span (search rows)
        keep = lam > lam.max() * 1e-12
        q = es @ (vec[:, keep] / np.sqrt(lam[keep]))
        self._q_j, self._q_n = q[: len(self._jcols)], q[len(self._jcols):]
        self._p_n = p_n
        self._g_n = p_n @ p_n.T  # (9, 9)
        self._pq_n = p_n @ self._q_n  # (9, rank)
        self._set_identity(shape)

    def _set_identity(self, shape: np.ndarray | None) -> None:
        subject = HeadSubject.create(self.head, shape)
        ids = self.vertex_ids
        self.shape = None if shape is None else np.asarray(shape, np.float64)
        self._eye_centre = subject.j_id[list(EYE_JOINTS)]
        self._eye_rest = [subject.v_id[ids[m]] - c for m, c in zip(self._eye, self._eye_centre)]
        self._joint = subject.j_id[JAW_JOINT]
        self._v_id = subject.v_id[ids[self._skin]]  # (ns, 3)
        self._v_id_j = self._v_id[self._jset]

    def with_identity(self, shape: np.ndarray | None) -> FlameFitter:
        """The same fitter for another subject (identity ``shape``), sharing every identity-free part."""
        other = copy.copy(self)
        other._set_identity(shape)
        return other

    def _evaluate(self, omega: np.ndarray, target_j: np.ndarray, static_j: np.ndarray, c_n: dict):
        """Jaw search state at axis-angle omega (T, 3): x_J, pose feature, Q^T x, objective |(I - QQ^T) x|^2."""
        t = len(omega)
        rot = axis_angle_to_matrix(omega)
        u = unpose_split(target_j, omega, rot, self._share, self._search_rigid)
        feat = (rot - np.eye(3)).reshape(t, 9)
        x_j = (u - self._v_id_j).reshape(t, -1) - feat @ self._p_jaw_j - static_j
        qx = x_j @ self._q_j + c_n["qc"] - feat @ self._pq_n
        ss = np.sum(x_j * x_j, axis=1) + c_n["cc"] - 2 * np.sum(feat * c_n["pc"], axis=1) \
            + np.sum((feat @ self._g_n) * feat, axis=1)
        return x_j, feat, qx, ss - np.sum(qx * qx, axis=1)

    def fit(self, points: np.ndarray) -> FitResult:
        """points (T, n, 3) on ``vertex_ids`` (or (n, 3)) -> :class:`FitResult`."""
        pts = np.asarray(points, np.float64)
        if pts.ndim == 2:
            pts = pts[None]
        if pts.shape[1:] != (len(self.vertex_ids), 3):
            raise ValueError(f"points must be (T, {len(self.vertex_ids)}, 3) on the fitter's vertices, got {pts.shape}")
        t = len(pts)
        eyes = [_kabsch(rest, pts[:, ids] - c) for rest, ids, c in zip(self._eye_rest, self._eye, self._eye_centre)]
        feat_eye = np.concatenate([(r - np.eye(3)).reshape(t, 9) for r in eyes], axis=1)
        static = feat_eye @ self._p_eye  # (T, 3 ns) eye pose correctives, known now
        target = pts[:, self._skin]
        # Unposing is about the jaw joint: shift once, add the joint back in the rest-space offsets.
        target_j = target[:, self._jset] - self._joint
        static_j = static[:, self._jcols] - np.tile(self._joint, len(self._jset))
        c = (target[:, self._nset] - self._v_id[self._nset]).reshape(t, -1) - static[:, self._ncols]
        c_n = {"qc": c @ self._q_n, "cc": np.sum(c * c, axis=1), "pc": c @ self._p_n.T}
        args = (target_j, static_j, c_n)

        # Initial jaw: Kabsch on the vertices the jaw moves rigidly (expression biases it a little), or
        # no rotation, whichever projects better; then Gauss-Newton.
        omega = np.zeros((t, 3))
        state = self._evaluate(omega, *args)
        if self._moved_rigid >= 3:
            rigid = self._moved[: self._moved_rigid]
            rest = self._v_id[rigid] - self._v_id[rigid].mean(axis=0)
            cand = matrix_to_axis_angle(_kabsch(rest, target[:, rigid] - target[:, rigid].mean(axis=1, keepdims=True)))
            new = self._evaluate(cand, *args)
            better = new[3] < state[3]
            omega[better] = cand[better]
            state = tuple(np.where(better[:, None], a, b) if a.ndim == 2 else np.where(better, a, b)
                          for a, b in zip(new, state))
        h = 1e-6
        for _ in range(self.iterations):  # Gauss-Newton on the projected residual, Levenberg damping
            x_j, feat, qx, obj = state
            d_x, d_f = [], []
            for k in range(3):
                step = omega.copy()
                step[:, k] += h
                x_k, f_k, _, _ = self._evaluate(step, *args)
                d_x.append((x_k - x_j) / h)
                d_f.append((f_k - feat) / h)
            dx = np.stack(d_x, axis=1)  # (T, 3, 3 nJ)
            df = np.stack(d_f, axis=1)  # (T, 3, 9)
            qd = dx @ self._q_j - df @ self._pq_n  # (T, 3, r) = (Q^T D)^T
            dfg = df @ self._g_n
            jtj = dx @ np.swapaxes(dx, 1, 2) + dfg @ np.swapaxes(df, 1, 2) - qd @ np.swapaxes(qd, 1, 2)
            # D^T x with D_N = -dF P_N and x_N = c - F P_N: -dF P_N c + dF G F.
            dtx = (dx @ x_j[:, :, None])[..., 0] - (df @ c_n["pc"][:, :, None])[..., 0] + (dfg @ feat[:, :, None])[..., 0]
            jtr = dtx - (qd @ qx[:, :, None])[..., 0]
            damp = (1e-12 + 1e-3 * np.trace(jtj, axis1=1, axis2=2) / 3)[:, None, None] * np.eye(3)
            cand = omega - np.linalg.solve(jtj + damp, jtr[..., None])[..., 0]
            new = self._evaluate(cand, *args)
            ok = new[3] <= obj
            omega[ok] = cand[ok]
            state = tuple(np.where(ok[:, None], a, b) if a.ndim == 2 else np.where(ok, a, b)
                          for a, b in zip(new, state))

        # Final: unpose every skin vertex with the fitted jaw (only jaw-moved ones need it), ridge solve.
        jaw = axis_angle_to_matrix(omega)
        feat = (jaw - np.eye(3)).reshape(t, 9)
        moved, share = self._moved, self._jaw_share[self._moved]
        u = target.copy()
        u[:, moved] = unpose_split(target[:, moved] - self._joint, omega, jaw, share, self._moved_rigid) + self._joint
        x = (u - self._v_id).reshape(t, -1) - feat @ self._p_jaw - static
        expr = x @ self._solve.T
        flame = join_flame_values(expr, jaw, eyes[0], eyes[1]).astype(np.float64)
        # Fit residual over the fitted vertices: skin in the unposed frame (equal to the posed residual
        # where the jaw moves vertices rigidly, within a few percent elsewhere), eyeballs posed.
        err = np.sum((x - expr @ self._e.T) ** 2, axis=1)
        n = len(self._skin)
        for r, ids, rest, cen in zip(eyes, self._eye, self._eye_rest, self._eye_centre):
            err += np.sum((rest @ np.swapaxes(r, 1, 2) + cen - pts[:, ids]) ** 2, axis=(1, 2))
            n += len(ids)
        return FitResult(flame=flame, rms=np.sqrt(err / n), jaw_axis_angle=omega)
