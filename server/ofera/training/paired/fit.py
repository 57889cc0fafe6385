"""Fit the head model's FLAME values to meshes, the way a tracker does: batched least squares.

Given target points (T, n, 3) on known head vertices (a subject of known identity; root and neck
identity, as in the FLAME values), find per frame expr (50), jaw and eye rotations:

1. eyes: closed form. The eyeball is rigid, so its rotation about the eye joint is the orthogonal
   Procrustes (Kabsch) solution, batched SVD of 3x3 matrices.
2. jaw: variable projection. For a jaw rotation R, LBS is invertible vertex by vertex: a skin vertex
   with jaw share a moves by M = (1 - a) I + a R about the jaw joint, and M^-1 has a closed form (M acts
   on the plane normal to R's axis as the complex number (1 - a) + a e^{i theta}). Unposing the targets
   gives x(R) = E psi + residual; eliminating psi by projection leaves a 3-parameter problem per frame,
   solved by Gauss-Newton (finite differences, Levenberg damping) from a Kabsch estimate on the
   vertices the jaw moves rigidly; the search unposes an even subsample of the jaw-moved vertices.
   Vertices without jaw share enter only through the jaw's pose correctives, which are linear in
   (R - I): their part of the normal equations comes from precomputed 9x9 / 9x50 products.
3. expr: ridge least squares on the unposed targets, (E^T E + ridge I)^-1 E^T x(R) (the ridge is the
   tracker's expression prior).

Joints are held at the subject's neutral joints (exact for the procedural head, whose expression basis
does not move joints; FLAME's expression moves them by well under a millimetre).
Everything is batched over frames with numpy.
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
    every one near the eyes and lips; every ``eye_stride``-th eyeball vertex. Any vertex set works with
    :class:`FlameFitter`; this one also comes in its working order (faster).
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
    keep = np.nonzero(face & (dense | (idx % stride == 0)))[0]
    eyes = [np.nonzero(head.weights[:, j] > 0.999)[0][::eye_stride] for j in EYE_JOINTS]
    # In the fitter's working order (skin the jaw does not move, moved rigidly, blended; eyeballs), so
    # that it takes views instead of copies.
    share = head.weights[keep, JAW_JOINT]
    kind = np.where(share <= 1e-9, 0, np.where(share >= 1.0 - 1e-12, 1, 2))
    return np.concatenate([keep[np.argsort(kind, kind="stable")], *eyes])


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
    """Fits FLAME values to points on ``vertex_ids`` of one subject (identity ``shape``) of ``head``.

    ``fit(points (T, n, 3)) -> FitResult``; ``with_identity(shape)`` gives the fitter of another subject
    sharing all identity-free precomputation. Fit frames in chunks of a few hundred (cache-friendly).
    """

    def __init__(self, head: HeadModel, shape: np.ndarray | None = None, vertex_ids: np.ndarray | None = None,
                 ridge: float = 1e-5, iterations: int = 3, n_expr: int = 50, search_vertices: int = 120) -> None:
        """``ridge``: m^2 per unit coefficient^2, a tracker's expression prior: it keeps coefficients of the
        weak components in FLAME's usual range at a cost of hundredths of a millimetre of fit (0 = plain
        least squares, exact on the model's own meshes); ``iterations``: Gauss-Newton steps of
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
        # Working order of the skin points: not moved by the jaw (N), moved rigidly (share 1), blended.
        share = w[:, JAW_JOINT]
        kind = np.where(share <= 1e-9, 0, np.where(share >= 1.0 - 1e-12, 1, 2))
        skin_idx = np.nonzero(skin)[0]
        self._skin = skin_idx[np.argsort(kind[skin_idx], kind="stable")]  # positions in vertex_ids
        self._skin_view = slice(0, len(skin_idx)) if np.array_equal(self._skin, np.arange(len(skin_idx))) else None
        counts = np.bincount(kind[skin_idx], minlength=3)
        n_n, n_r = int(counts[0]), int(counts[1])
        ns = len(skin_idx)
        self._n = slice(0, n_n)  # within the skin points
        self._m = slice(n_n, ns)
        self._m_rigid = n_r
        sk = ids[self._skin]
        share = share[self._skin]
        self._share_m = share[self._m]
        posedirs = head.posedirs.reshape(-1, head.num_vertices, 3)[:, sk]  # (36, ns, 3)
        p_eye = posedirs[_EYE_ROWS].reshape(18, 3 * ns)
        self._p_eye = p_eye if np.any(p_eye) else None
        self._p_jaw = posedirs[_JAW_ROWS].reshape(9, 3 * ns)
        e = head.exprdirs[sk][:, :, :n_expr].reshape(3 * ns, n_expr)
        self._e = e
        self._gram = e.T @ e
        self._solve = np.linalg.solve(self._gram + ridge * np.eye(n_expr), e.T)  # (n_expr, 3 ns) ridge LS
        cn, cm = slice(0, 3 * n_n), slice(3 * n_n, 3 * ns)
        self._cn, self._cm = cn, cm

        # The jaw search: a subsample J of the jaw-moved points (unposed explicitly, rigid ones first) and
        # the points N that feel the jaw only through its pose correctives (precomputed products).
        rigid, blended = np.arange(n_r), np.arange(n_r, ns - n_n)
        if ns - n_n > search_vertices:
            k = round(search_vertices * n_r / (ns - n_n))
            rigid = rigid[np.linspace(0, n_r - 1, k).round().astype(np.int64)] if k else rigid[:0]
            blended = blended[np.linspace(0, len(blended) - 1, search_vertices - k).round().astype(np.int64)]
        self._j = np.concatenate([rigid, blended])  # within the moved points
        self._j_rigid = len(rigid)
        jcols = (3 * (n_n + self._j)[:, None] + np.arange(3)).reshape(-1)  # within the skin coordinates
        self._jcols = jcols
        self._share_j = self._share_m[self._j]
        self._p_jaw_j = self._p_jaw[:, jcols]
        p_n = self._p_jaw[:, cn]
        es = np.concatenate([e[jcols], e[cn]])
        lam, vec = np.linalg.eigh(es.T @ es)  # orthonormal basis of the expression span on the search rows
        keep = lam > lam.max() * 1e-12
        q = es @ (vec[:, keep] / np.sqrt(lam[keep]))
        self._q_j, self._q_n = q[: len(jcols)], q[len(jcols):]
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
        self._v_id = subject.v_id[ids[self._skin]]  # (ns, 3) in working order
        # Rest-space offsets of the moved points from the jaw joint (unposing is about the joint).
        self._rel_m = self._v_id[self._m] - self._joint
        self._rel_j = self._rel_m[self._j].reshape(-1)

    def with_identity(self, shape: np.ndarray | None) -> FlameFitter:
        """The same fitter for another subject (identity ``shape``), sharing every identity-free part."""
        other = copy.copy(self)
        other._set_identity(shape)
        return other

    def _evaluate(self, omega: np.ndarray, y_j: np.ndarray, static_j, c_n: dict):
        """Jaw search state at axis-angle omega (T, 3): x_J, pose feature, Q^T x, objective |(I - QQ^T) x|^2."""
        t = len(omega)
        rot = axis_angle_to_matrix(omega)
        feat = (rot - np.eye(3)).reshape(t, 9)
        x_j = unpose_split(y_j, omega, rot, self._share_j, self._j_rigid).reshape(t, -1)
        x_j -= self._rel_j
        x_j -= feat @ self._p_jaw_j
        if static_j is not None:
            x_j -= static_j
        qx = x_j @ self._q_j + c_n["qc"] - feat @ self._pq_n
        ss = np.einsum("ij,ij->i", x_j, x_j) + c_n["cc"] - 2 * np.einsum("ij,ij->i", feat, c_n["pc"]) \
            + np.einsum("ij,ij->i", feat @ self._g_n, feat)
        return x_j, feat, qx, ss - np.einsum("ij,ij->i", qx, qx)

    def fit(self, points: np.ndarray) -> FitResult:
        """points (T, n, 3) on ``vertex_ids`` (or (n, 3)) -> :class:`FitResult`."""
        pts = np.asarray(points, np.float64)
        if pts.ndim == 2:
            pts = pts[None]
        if pts.shape[1:] != (len(self.vertex_ids), 3):
            raise ValueError(f"points must be (T, {len(self.vertex_ids)}, 3) on the fitter's vertices, got {pts.shape}")
        t = len(pts)
        eyes = [_kabsch(rest, pts[:, ids] - c) for rest, ids, c in zip(self._eye_rest, self._eye, self._eye_centre)]
        static = None  # eye pose correctives on the skin (none on the procedural head)
        if self._p_eye is not None:
            static = np.concatenate([(r - np.eye(3)).reshape(t, 9) for r in eyes], axis=1) @ self._p_eye
        target = pts[:, self._skin_view] if self._skin_view is not None else pts[:, self._skin]
        y_m = target[:, self._m] - self._joint  # moved points relative to the jaw joint
        y_j = y_m[:, self._j]
        c = (target[:, self._n] - self._v_id[self._n]).reshape(t, -1)
        if static is not None:
            c -= static[:, self._cn]
        c_n = {"qc": c @ self._q_n, "cc": np.einsum("ij,ij->i", c, c), "pc": c @ self._p_n.T}
        args = (y_j, None if static is None else static[:, self._cm][:, self._jcols - self._cm.start], c_n)

        # Initial jaw: Kabsch on the points the jaw moves rigidly (expression biases it a little), or no
        # rotation, whichever projects better; then Gauss-Newton with Levenberg damping.
        omega = np.zeros((t, 3))
        state = self._evaluate(omega, *args)
        if self._m_rigid >= 3:
            rest = self._rel_m[: self._m_rigid]
            moved = y_m[:, : self._m_rigid]
            rot0 = _kabsch(rest - rest.mean(axis=0), moved - moved.mean(axis=1, keepdims=True))
            cand = matrix_to_axis_angle(rot0)
            state, omega = self._accept(self._evaluate(cand, *args), state, cand, omega)
        h = 1e-6
        for _ in range(self.iterations):
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
            dtx = (dx @ x_j[:, :, None])[..., 0] - (df @ c_n["pc"][:, :, None])[..., 0] \
                + (dfg @ feat[:, :, None])[..., 0]
            jtr = dtx - (qd @ qx[:, :, None])[..., 0]
            damp = (1e-12 + 1e-3 * np.trace(jtj, axis1=1, axis2=2) / 3)[:, None, None] * np.eye(3)
            cand = omega - np.linalg.solve(jtj + damp, jtr[..., None])[..., 0]
            state, omega = self._accept(self._evaluate(cand, *args), state, cand, omega)

        # Final: unpose every moved point with the fitted jaw, ridge least squares for expr.
        jaw = axis_angle_to_matrix(omega)
        feat = (jaw - np.eye(3)).reshape(t, 9)
        x = np.empty((t, self._e.shape[0]))
        x[:, self._cn] = c - feat @ self._p_n
        u_m = unpose_split(y_m, omega, jaw, self._share_m, self._m_rigid)
        u_m -= self._rel_m
        x[:, self._cm] = u_m.reshape(t, -1) - feat @ self._p_jaw[:, self._cm]
        if static is not None:
            x[:, self._cm] -= static[:, self._cm]
        expr = x @ self._solve.T
        flame = join_flame_values(expr, jaw, eyes[0], eyes[1]).astype(np.float64)
        # Fit residual: skin in the unposed frame (equal to the posed residual where the jaw moves points
        # rigidly, within a few percent elsewhere), eyeballs posed.
        err = np.einsum("ij,ij->i", x, x) - 2 * np.einsum("ij,ij->i", expr, x @ self._e) \
            + np.einsum("ij,ij->i", expr @ self._gram, expr)
        n = len(self._skin)
        for r, ids, rest, cen in zip(eyes, self._eye, self._eye_rest, self._eye_centre):
            err += np.sum((rest @ np.swapaxes(r, 1, 2) + cen - pts[:, ids]) ** 2, axis=(1, 2))
            n += len(ids)
        return FitResult(flame=flame, rms=np.sqrt(np.maximum(err, 0.0) / n), jaw_axis_angle=omega)

    @staticmethod
    def _accept(new: tuple, state: tuple, cand: np.ndarray, omega: np.ndarray) -> tuple[tuple, np.ndarray]:
        """Per frame, keep the candidate where it does not increase the objective."""
        ok = new[3] <= state[3]
        merged = tuple(np.where(ok[:, None], a, b) if a.ndim == 2 else np.where(ok, a, b) for a, b in zip(new, state))
        return merged, np.where(ok[:, None], cand, omega)
