"""An ARKit-style face rig of the 51 arkit51 shapes, built on the procedural head: the "real face".

The rig plays the part of a captured person: weights w (T, 51) -> a mesh (T, n, 3). It is placed by
the meaning of each shape (REFERENCE.md section 1) and is deliberately NOT the head model:

- its displacement fields are its own local fields (centres, radii and directions of its own), so the
  head's 50-component expression basis can represent them only approximately, like FLAME and a face;
- it is nonlinear in w, mostly in ways every subject shares (ARKit weights map nonlinearly onto anatomy):
  a shared early-and-flattening response per shape (:data:`SHARED_GAMMA`), a saturating jaw hinge
  (:data:`JAW_CURVE`), a steeply saturating eyeBlink -> lid closure, strong correctives; per-subject
  style varies these only a little (gain * w^gamma around the shared exponents), quadratic "arc" terms (a corner
  that moves up, then back along the cheek), corrective shapes on products of weights (jawOpen x
  mouthClose, mouthSmile x jawOpen, eyeBlink x eyeSquint, ...), and rotations: the jaw joint rotates
  about the rig's own pivot (jawOpen, jawLeft/Right), the upper and lower lids rotate about the eyeball
  centre through a saturating curve (eyeBlink, eyeSquint, eyeWide, and the lids follow the gaze), the
  lips roll about an axis behind them (mouthRoll*), and the eyeballs rotate (eyeLook*);
- every subject has a style (:class:`RigStyle`): gains, left/right asymmetry, response exponents,
  arc strengths, jaw range and pivot, gaze range, lid travel, and identity shape coefficients.

Fields are defined on the template (like FLAME's bases) and added to the subject's identity shape; where each
shape moves the face, which way and how far, is the table in :mod:`.rig_fields` (:func:`_build_basis` evaluates it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ofera.head.lbs import HeadSubject
from ofera.head.model import HeadModel
from ofera.head.procedural import smoothstep
from ofera.head.rotations import axis_angle_to_matrix, euler_xy_to_matrix
from ofera.mapping.layouts import ARKIT51_NAMES
from ofera.training.paired.rig_fields import FIELD_BLOCKS, Bump

N_SHAPES = len(ARKIT51_NAMES)
IDX = {name: i for i, name in enumerate(ARKIT51_NAMES)}
SIDES = (("Left", 1.0), ("Right", -1.0))  # ARKit side name, sign of x (the subject's left is +x)

# (a, b): corrective fields driven by the product of the effective weights of shapes a and b.
CORRECTIVES: tuple[tuple[str, str], ...] = (
    ("jawOpen", "mouthClose"),
    ("mouthSmileLeft", "jawOpen"),
    ("mouthSmileRight", "jawOpen"),
    ("eyeBlinkLeft", "eyeSquintLeft"),
    ("eyeBlinkRight", "eyeSquintRight"),
    ("mouthPucker", "mouthFunnel"),
    ("jawOpen", "mouthFunnel"),
    ("browDownLeft", "browInnerUp"),
    ("browDownRight", "browInnerUp"),
    ("mouthSmileLeft", "cheekSquintLeft"),
    ("mouthSmileRight", "cheekSquintRight"),
)


def _shared_gamma() -> np.ndarray:
    """(51,) response exponent that every subject shares: how ARKit's shape weights map onto anatomy.

    The soft tissue of the mouth, brows, cheeks and nose moves most in the first part of a shape's range
    and then stiffens (exponent < 1: an early response that flattens). Per-subject exponents are small
    deviations around these.
    """
    g = np.ones(N_SHAPES)
    mouth = ("mouthSmile", "mouthFrown", "mouthStretch", "mouthPucker", "mouthFunnel", "mouthDimple",
            "mouthLowerDown", "mouthUpperUp", "mouthPress", "mouthShrug", "cheekPuff")
    upper = ("browDown", "browInnerUp", "browOuterUp", "cheekSquint", "noseSneer", "eyeSquint", "eyeWide")
    for name, i in IDX.items():
        if name.startswith(mouth):
            g[i] = 0.4
        elif name.startswith(upper):
            g[i] = 0.5
    return g


SHARED_GAMMA = _shared_gamma()
JAW_CURVE = 4.0  # jaw angle = saturate(jawOpen, 4): the hinge turns early, then reaches its limit


def _lid_closure(x: np.ndarray, k: float = 3.5) -> np.ndarray:
    """eyeBlink -> lid closure (0 -> 0, 1 -> 1): steep, the lid drops over the first part of the range
    and then rests on the lower lid (a strongly saturating curve, the same for everyone)."""
    return saturate(np.clip(x, 0.0, 1.3), k)


def _unit(d) -> np.ndarray:
    d = np.asarray(d, np.float64)
    return d / np.linalg.norm(d)


def saturate(x: np.ndarray, k: float = 1.6) -> np.ndarray:
    """Saturating response: 0 -> 0, 1 -> 1, concave, flat beyond 1 (tanh(k x) / tanh(k))."""
    return np.tanh(k * np.clip(x, 0.0, None)) / np.tanh(k)


def _index(ids: np.ndarray) -> np.ndarray | slice:
    """A slice where the indices are one contiguous run (a view instead of a copy), else the indices."""
    if len(ids) and ids[-1] - ids[0] == len(ids) - 1 and np.all(np.diff(ids) == 1):
        return slice(int(ids[0]), int(ids[-1]) + 1)
    return ids


def _rotate_x(p: np.ndarray, centre: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate points p (T, m, 3) about the x axis through centre (3,) by angle (T, m) radians."""
    c, s = np.cos(angle), np.sin(angle)
    d = p - centre
    out = p.copy()
    out[..., 1] = centre[1] + c * d[..., 1] - s * d[..., 2]
    out[..., 2] = centre[2] + s * d[..., 1] + c * d[..., 2]
    return out


@dataclass(frozen=True)
class RigBasis:
    """Everything about the rig that is the same for all subjects (template-attached, per vertex)."""

    linear: np.ndarray  # (51, V, 3) metres at unit effective weight
    quadratic: np.ndarray  # (51, V, 3) metres per unit of effective weight squared
    corrective: np.ndarray  # (C, V, 3) metres per unit of the product of two effective weights
    upper_lid: np.ndarray  # (2, V) rotation share of each vertex in the left/right upper lid
    lower_lid: np.ndarray  # (2, V)
    roll: np.ndarray  # (2, V) lower / upper lip roll share
    roll_axis: np.ndarray  # (2, 3) points on the lower / upper roll axes (x axis direction)
    jaw: np.ndarray  # (V,) jaw share of each vertex (the rig's own, not the head's skinning weights)
    eyeball: np.ndarray  # (2, V) bool
    close_lift: float  # lip gap (m) that a 0.36 rad jaw opening makes (the mouthClose corrective's scale)

    @classmethod
    def build(cls, head: HeadModel) -> RigBasis:
        if not head.landmarks or not head.vertex_labels:
            raise ValueError("the paired-data rig needs a procedural head (landmarks and vertex labels)")
        return _build_basis(head)

    def take(self, ids: np.ndarray) -> RigBasis:
        """The basis restricted to vertices ``ids`` (evaluate only what is needed)."""
        return RigBasis(
            self.linear[:, ids], self.quadratic[:, ids], self.corrective[:, ids], self.upper_lid[:, ids],
            self.lower_lid[:, ids], self.roll[:, ids], self.roll_axis, self.jaw[ids], self.eyeball[:, ids],
            self.close_lift,
        )


def _lip_sides(head: HeadModel) -> np.ndarray:
    """(V,) True on the lower-lip side of the mouth seam (below the lip line, or the seam's twins)."""
    v = head.v_template
    y_line = head.landmarks["mouth_centre"][1]
    skin = np.nonzero(head.vertex_labels["skin"])[0]
    keys = np.round(v[skin] * 1e7).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    twin = np.zeros(len(v), bool)
    twin[skin] = first[inverse.reshape(-1)] != np.arange(len(skin))  # later copy of a position
    return (v[:, 1] < y_line - 1e-6) | twin


def _build_basis(head: HeadModel) -> RigBasis:
    v = head.v_template.astype(np.float64)
    nv = len(v)
    x, y, z = v.T
    lm = {k: np.asarray(p, np.float64) for k, p in head.landmarks.items()}
    labels = head.vertex_labels
    skin = labels["skin"].astype(float)
    face = skin * smoothstep((z - 0.0) / 0.03)  # fields act on the front of the skin only
    lower = _lip_sides(head).astype(float)
    upper = 1.0 - lower

    lin = np.zeros((N_SHAPES, nv, 3))
    quad = np.zeros((N_SHAPES, nv, 3))
    corr = np.zeros((len(CORRECTIVES), nv, 3))
    upper_lid = np.zeros((2, nv))
    lower_lid = np.zeros((2, nv))
    for k, (side, _) in enumerate(SIDES):  # the lids: rotation shares about the eye centre (rig.lid_angles)
        eye = lm[f"eye_{side.lower()}"]
        hx = 1.0 - smoothstep((np.abs(x - eye[0]) / 0.0150 - 0.35) / 0.6)
        front_of_eye = skin * (z > eye[2])
        upper_lid[k] = hx * (1.0 - smoothstep((y - eye[1] - 0.0055) / 0.0085)) * (y > eye[1] - 0.0005) * front_of_eye
        lower_lid[k] = hx * (1.0 - smoothstep((eye[1] - 0.0055 - y) / 0.007)) * (y <= eye[1] - 0.0005) * front_of_eye
    # The lip gap (m) a 0.36 rad jaw opening makes: the scale of the mouthClose corrective.
    close_lift = 0.36 * float(np.linalg.norm((lm["lower_lip"] - lm["jaw_pivot"])[1:]))
    width = lm["mouth_corner_left"][0]
    towards_mid = np.stack([-np.sign(x) * np.clip(np.abs(x) / width, 0, 1.2), np.zeros(nv), np.zeros(nv)], 1)
    masks = {"lower": lower, "upper": upper}
    targets = {"linear": lin, "quadratic": quad, "corrective": corr}

    def bump(c: np.ndarray, radius: float, squash=(1.0, 1.0, 1.0)) -> np.ndarray:
        d2 = ((x - c[0]) / squash[0]) ** 2 + ((y - c[1]) / squash[1]) ** 2 + ((z - c[2]) / squash[2]) ** 2
        return np.exp(-d2 / (2.0 * radius**2)) * face

    def add(row: Bump, k: int, side: str, s: float) -> None:
        names = (row.at,) if isinstance(row.at, str) else row.at
        centres = [lm[n.format(side=side.lower())] for n in names]
        centre = centres[0] if len(centres) == 1 else (centres[0] + centres[1]) / 2
        offset = row.offset if s > 0 else (-row.offset[0] if row.offset[0] else row.offset[0], *row.offset[1:])
        weight = bump(centre + np.asarray(offset, np.float64), row.radius, row.squash)
        if row.power != 1:
            weight = weight**row.power
        eye = lm.get(f"eye_{side.lower()}")  # the side's eye centre (sided rows)
        if row.mask == "ring":
            weight = weight * (1.0 - upper_lid[k]) * (1.0 - lower_lid[k])
        elif row.mask == "orbit":
            weight = weight * (1.0 - smoothstep(1.2 - np.hypot(x - eye[0], y - eye[1]) / 0.010))
        elif row.mask:
            weight = weight * masks[row.mask]
        amp = row.amp * close_lift if row.of_close_lift else row.amp
        if row.direction == "towards_mid":
            value = weight[:, None] * towards_mid * amp
        elif row.direction == "towards_eye":
            towards_eye = np.stack([eye[0] - x, eye[1] - y, np.zeros(nv)], 1)
            towards_eye /= np.maximum(np.linalg.norm(towards_eye, axis=1, keepdims=True), 1e-6)
            value = weight[:, None] * towards_eye * amp
        else:
            d = row.direction
            value = weight[:, None] * _unit((d[0] * s if d[0] else d[0], *d[1:]))[None] * amp
        target = row.target.format(side=side)
        i = CORRECTIVES.index(tuple(target.split("*"))) if row.term == "corrective" else IDX[target]
        targets[row.term][i] += value

    for sided, rows in FIELD_BLOCKS:
        for k, (side, s) in enumerate(SIDES if sided else (("", 1.0),)):
            for row in rows:
                add(row, k, side, s)

    # --- lip roll rotation shares and axes ------------------------------------------------------------
    mouth, ul, ll = lm["mouth_centre"], lm["upper_lip"], lm["lower_lip"]
    roll = np.stack([bump(ll, 0.006, (2.4, 1.0, 1.0)) * lower, bump(ul, 0.006, (2.4, 1.0, 1.0)) * upper])
    roll_axis = np.stack([ll + [0, 0.001, -0.007], ul + [0, -0.001, -0.007]])
    # --- the rig's own jaw share: the head's jaw skinning, broadened -------------------------------
    jaw = np.clip(head.weights[:, 2], 0.0, 1.0) ** 0.8 * skin + head.weights[:, 2] * (1 - skin)
    # A real upper lip stays with the skull when the jaw opens (the head's skinning lets it follow half way).
    upper_lip = upper * (np.abs(x) < 1.3 * width) * (np.abs(y - mouth[1]) < 0.012) * (z > mouth[2] - 0.03)
    jaw = np.where(upper_lip > 0, 0.3 * jaw, jaw)
    eyeball = np.stack([labels["eyeball_left"], labels["eyeball_right"]])
    no_eye = ~eyeball.any(axis=0)
    return RigBasis(
        linear=lin * no_eye[None, :, None],
        quadratic=quad * no_eye[None, :, None],
        corrective=corr * no_eye[None, :, None],
        upper_lid=upper_lid * no_eye,
        lower_lid=lower_lid * no_eye,
        roll=roll * no_eye,
        roll_axis=roll_axis,
        jaw=jaw * no_eye,
        eyeball=eyeball,
        close_lift=close_lift,
    )


@dataclass(frozen=True)
class RigStyle:
    """One subject's way of making the shapes (drawn by :meth:`random`)."""

    gain: np.ndarray  # (51,) response gain per shape (left/right asymmetry included)
    gamma: np.ndarray  # (51,) response exponent: effective = gain * w ** gamma
    arc: np.ndarray  # (51,) strength of the quadratic arc term
    corrective: np.ndarray  # (C,) strength of each corrective
    jaw_open: float  # radians at full jawOpen
    jaw_side: float  # radians at full jawLeft / jawRight
    jaw_forward: float  # metres at full jawForward
    pivot_offset: np.ndarray  # (3,) metres, rig jaw pivot relative to the landmark
    gaze_yaw: float  # radians at full eyeLookIn/Out
    gaze_pitch: float  # radians at full eyeLookUp/Down
    lid_close: float  # upper-lid rotation (radians) of a full blink
    shape: np.ndarray  # (S,) identity coefficients of the head model

    @classmethod
    def random(cls, rng: np.random.Generator, n_shape: int, expressiveness: float = 1.0) -> RigStyle:
        gain = np.exp(rng.normal(0.0, 0.09, N_SHAPES)) * expressiveness
        for name in ARKIT51_NAMES:  # left/right asymmetry
            if name.endswith("Left"):
                a = rng.normal(0.0, 0.05)
                gain[IDX[name]] *= 1.0 + a
                gain[IDX[name[:-4] + "Right"]] *= 1.0 - a
        return cls(
            gain=gain,
            gamma=SHARED_GAMMA * np.exp(rng.normal(0.0, 0.075, N_SHAPES)),
            arc=rng.uniform(0.75, 1.25, N_SHAPES),
            corrective=rng.uniform(0.85, 1.15, len(CORRECTIVES)),
            jaw_open=float(rng.uniform(0.33, 0.39)),
            jaw_side=float(rng.uniform(0.09, 0.115)),
            jaw_forward=float(rng.uniform(0.003, 0.006)),
            pivot_offset=np.array([0.0, *rng.normal(0.0, 0.001, 2)]),
            gaze_yaw=float(rng.uniform(0.50, 0.62)),
            gaze_pitch=float(rng.uniform(0.38, 0.48)),
            lid_close=float(rng.uniform(0.60, 0.66)),
            shape=rng.normal(0.0, 1.0, n_shape),
        )

    @classmethod
    def neutral(cls, n_shape: int) -> RigStyle:
        """Unit gains, the shared exponents, mean identity: the rig as designed."""
        return cls(np.ones(N_SHAPES), SHARED_GAMMA.copy(), np.ones(N_SHAPES), np.ones(len(CORRECTIVES)), 0.36, 0.10,
                   0.0045, np.zeros(3), 0.55, 0.42, 0.62, np.zeros(n_shape))


class Rig:
    """One subject's rig on (a subset of) the head's vertices: ``rig.mesh(w (T, 51)) -> (T, n, 3)``."""

    def __init__(self, head: HeadModel, style: RigStyle, vertex_ids: np.ndarray | None = None,
                 basis: RigBasis | None = None) -> None:
        basis = RigBasis.build(head) if basis is None else basis
        ids = np.arange(head.num_vertices) if vertex_ids is None else np.asarray(vertex_ids, np.int64)
        self.head, self.style, self.vertex_ids = head, style, ids
        subject = HeadSubject.create(head, style.shape)
        self.subject = subject
        self.rest = subject.v_id[ids]  # (n, 3) identity-shaped template
        b = basis.take(ids)
        n = len(ids)
        self._fields = np.concatenate([  # linear, quadratic (arc) and corrective fields, one matrix
            b.linear.reshape(N_SHAPES, 3 * n),
            (b.quadratic * style.arc[:, None, None]).reshape(N_SHAPES, 3 * n),
            (b.corrective * style.corrective[:, None, None]).reshape(len(CORRECTIVES), 3 * n),
        ])
        self._corr_pairs = np.array([[IDX[a], IDX[c]] for a, c in CORRECTIVES])
        self._close_gain = style.jaw_open / 0.36  # the mouthClose corrective closes this subject's gap
        shift = subject.v_id - head.v_template  # identity moves the rotation centres with the face
        self._eye_centre = subject.j_id[3:5]
        # Sparse subsets: only vertices that a rotation moves are touched.
        self._lids = [(np.nonzero(b.upper_lid[k] > 2e-3)[0], np.nonzero(b.lower_lid[k] > 2e-3)[0]) for k in range(2)]
        self._upper_share = [b.upper_lid[k, i] for k, (i, _) in enumerate(self._lids)]
        self._lower_share = [b.lower_lid[k, j] for k, (_, j) in enumerate(self._lids)]
        self._roll = [np.nonzero(b.roll[k] > 2e-3)[0] for k in range(2)]
        self._roll_share = [b.roll[k, i] for k, i in enumerate(self._roll)]
        lip_shift = [shift[int(np.argmin(np.sum((head.v_template - a) ** 2, axis=1)))] for a in b.roll_axis]
        self._roll_axis = b.roll_axis + np.array(lip_shift)
        jaw_ids = np.nonzero(b.jaw > 1e-6)[0]
        self._jaw_share = b.jaw[jaw_ids]
        self._jaw_ids = _index(jaw_ids)
        landmark = head.landmarks["jaw_pivot"]
        near = int(np.argmin(np.sum((head.v_template - landmark) ** 2, axis=1)))
        self._pivot = landmark + shift[near] + style.pivot_offset
        self._eyeballs = [_index(np.nonzero(b.eyeball[k])[0]) for k in range(2)]

    # --- the parts of the rig --------------------------------------------------------------------

    def effective(self, w: np.ndarray) -> np.ndarray:
        """Subject response (T, 51): gain * w ** gamma, limited to [0, 1.3]."""
        w = np.clip(np.asarray(w, np.float64), 0.0, 1.0)
        return np.clip(self.style.gain * w**self.style.gamma, 0.0, 1.3)

    def jaw_rotation(self, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rig jaw rotation (T, 3, 3) about its pivot and jaw translation (T, 3) from effective weights."""
        st = self.style
        o = np.clip(e[:, IDX["jawOpen"]], 0.0, 1.3)
        pitch = st.jaw_open * saturate(o, JAW_CURVE)  # shared curve: early rotation, then the limit
        yaw = st.jaw_side * (e[:, IDX["jawLeft"]] - e[:, IDX["jawRight"]])
        aa = np.stack([pitch, yaw, 0.15 * yaw], axis=1)
        trans = np.stack([0.002 * yaw / st.jaw_side, np.zeros_like(o), st.jaw_forward * e[:, IDX["jawForward"]]], 1)
        return axis_angle_to_matrix(aa), trans

    def eye_rotations(self, e: np.ndarray) -> np.ndarray:
        """(T, 2, 3, 3) left and right eyeball rotations (about their centres) from effective weights."""
        st = self.style
        out = []
        for side, s in SIDES:
            look_out, look_in = e[:, IDX[f"eyeLookOut{side}"]], e[:, IDX[f"eyeLookIn{side}"]]
            yaw = st.gaze_yaw * s * (np.minimum(look_out, 1.0) - np.minimum(look_in, 1.0))
            pitch = st.gaze_pitch * (np.minimum(e[:, IDX[f"eyeLookDown{side}"]], 1.0)
                                     - np.minimum(e[:, IDX[f"eyeLookUp{side}"]], 1.0))
            out.append(euler_xy_to_matrix(yaw, pitch))
        return np.stack(out, axis=1)

    def lid_angles(self, e: np.ndarray) -> np.ndarray:
        """(T, 2, 2) upper / lower lid rotation (radians, + = down) per side through a saturating curve."""
        st = self.style
        out = np.zeros((len(e), 2, 2))
        for k, (side, _) in enumerate(SIDES):
            blink, squint = e[:, IDX[f"eyeBlink{side}"]], e[:, IDX[f"eyeSquint{side}"]]
            wide = e[:, IDX[f"eyeWide{side}"]]
            down, up = e[:, IDX[f"eyeLookDown{side}"]], e[:, IDX[f"eyeLookUp{side}"]]
            closure = _lid_closure(blink + 0.25 * squint)
            out[:, k, 0] = np.minimum(st.lid_close * closure + 0.30 * down - 0.15 * up - 0.22 * wide * (1 - closure),
                                      st.lid_close * 1.05)
            out[:, k, 1] = -(0.10 * closure + 0.22 * saturate(squint) + 0.08 * e[:, IDX[f"cheekSquint{side}"]]) \
                + 0.10 * down
        return out

    # --- the mesh -----------------------------------------------------------------------------------

    def mesh(self, w: np.ndarray) -> np.ndarray:
        """Rig mesh (T, n, 3) float64 for weights w (T, 51) (or (51,)) in arkit51 order."""
        w = np.atleast_2d(w)
        if w.shape[-1] != N_SHAPES:
            raise ValueError(f"rig weights must be (T, {N_SHAPES}) arkit51, got {w.shape}")
        e = self.effective(w)
        t, n = len(e), len(self.vertex_ids)
        products = e[:, self._corr_pairs[:, 0]] * e[:, self._corr_pairs[:, 1]]
        ci = CORRECTIVES.index(("jawOpen", "mouthClose"))
        # mouthClose acts only while the jaw is open (lips together), at most as far as the jaw opened.
        products[:, ci] = saturate(np.minimum(e[:, IDX["mouthClose"]], e[:, IDX["jawOpen"]]), JAW_CURVE) \
            * smoothstep(e[:, IDX["jawOpen"]] / 0.15) * self._close_gain
        p = (np.concatenate([e, e * e, products], axis=1) @ self._fields).reshape(t, n, 3)
        p += self.rest
        lids = self.lid_angles(e)
        for k in range(2):
            centre = self._eye_centre[k]
            up_ids, low_ids = self._lids[k]
            p[:, up_ids] = _rotate_x(p[:, up_ids], centre, lids[:, k, 0:1] * self._upper_share[k])
            p[:, low_ids] = _rotate_x(p[:, low_ids], centre, lids[:, k, 1:2] * self._lower_share[k])
        for k, (name, sign) in enumerate((("mouthRollLower", -1.0), ("mouthRollUpper", 1.0))):
            angle = sign * 0.9 * saturate(e[:, IDX[name]], 1.2)
            ids = self._roll[k]
            p[:, ids] = _rotate_x(p[:, ids], self._roll_axis[k], angle[:, None] * self._roll_share[k])
        rot, trans = self.jaw_rotation(e)
        ids, share = self._jaw_ids, self._jaw_share
        moved = (p[:, ids] - self._pivot) @ np.swapaxes(rot - np.eye(3), 1, 2)  # rows: (R - I) (p - pivot)
        moved += trans[:, None, :]
        p[:, ids] += share[None, :, None] * moved
        eyes = self.eye_rotations(e)
        for k in range(2):
            ids, c = self._eyeballs[k], self._eye_centre[k]
            p[:, ids] = c + (p[:, ids] - c) @ np.swapaxes(eyes[:, k], 1, 2)
        return p
