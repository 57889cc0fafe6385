"""The procedural head: a stand-in for FLAME, which cannot be shipped.

It has FLAME's structure (5 joints: root, neck, jaw, left eye, right eye; identity and expression
bases; pose correctives; skinning weights), FLAME's axes (metres, y up, face looking +z) and roughly
FLAME's size. It is generated deterministically from the construction below in about a second:

- the skin is a lofted surface: horizontal cross-sections (ellipses with separate front and back depth)
  over an ellipsoidal cranium, with facial features added as smooth displacements (brow ridge, nose,
  cheekbones, lips, chin, ears);
- the mouth is a seam: the lower lip's vertices are duplicated so the jaw can open the mouth; a dark
  mouth cavity sits behind the lips;
- each eye is a separate sphere rotating about its centre (the eye joint); the lids are holes in the skin
  that hug the eyeball;
- the expression basis is built from localised displacement fields (brows, lids, cheeks, nose, lips,
  mouth corners, chin), then orthogonalised like FLAME's PCA basis (most energy first);
- the identity basis is built the same way from global and regional shape changes.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import PchipInterpolator

from .model import FLAME_PARENTS, HeadModel

# ---- dimensions (metres) --------------------------------------------------------------------------
CRANIUM_Y, CRANIUM_HALF_HEIGHT = 0.055, 0.075  # ellipsoidal cap above the brows
EYE_X, EYE_Y, EYE_RADIUS = 0.032, 0.030, 0.0118
EYE_HALF_OPENING = (0.0125, 0.0052)  # half width, half height of the lid opening
MOUTH_Y, MOUTH_HALF_WIDTH = -0.034, 0.024
JAW_PIVOT = np.array([0.0, -0.006, -0.002])
N_COLUMNS = 104
N_EXPR, N_SHAPE = 50, 20

# Cross-section profile below the cranium: y -> half width, front depth, back depth, centre z.
_PROFILE_Y = np.array([0.055, 0.030, 0.000, -0.030, -0.055, -0.075, -0.090, -0.120, -0.170])
_PROFILE = np.array(
    [
        [0.076, 0.092, 0.105, -0.010],
        [0.075, 0.090, 0.100, -0.010],
        [0.073, 0.093, 0.092, -0.010],
        [0.066, 0.090, 0.082, -0.012],
        [0.056, 0.082, 0.070, -0.015],
        [0.042, 0.068, 0.060, -0.018],
        [0.050, 0.032, 0.055, -0.020],
        [0.054, 0.045, 0.050, -0.025],
        [0.058, 0.050, 0.052, -0.025],
    ]
)


def _bump(d2: np.ndarray, radius: float) -> np.ndarray:
    """Smooth Gaussian falloff of squared distance d2 (m^2) with the given radius (m)."""
    return np.exp(-d2 / (2.0 * radius**2))


def smoothstep(x: np.ndarray) -> np.ndarray:
    """Hermite step clipped to [0, 1]: 0 below 0, 1 above 1, 3t^2 - 2t^3 between (the procedural models' falloff)."""
    t = np.clip(x, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _rows() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per row: y, half width, front depth, back depth, centre z (top to bottom, pole excluded)."""
    phi = np.linspace(0.0, np.pi / 2, 16)[1:]
    cap_y = CRANIUM_Y + CRANIUM_HALF_HEIGHT * np.cos(phi)
    cap_s = np.sin(phi)
    top = _PROFILE[0]
    face_y = np.concatenate([np.arange(CRANIUM_Y - 0.0028, -0.095, -0.0028), np.arange(-0.103, -0.171, -0.0085)])
    face_y[np.argmin(np.abs(face_y - MOUTH_Y))] = MOUTH_Y  # one row exactly on the lip line
    prof = PchipInterpolator(_PROFILE_Y[::-1], _PROFILE[::-1])(face_y)
    y = np.concatenate([cap_y, face_y])
    w = np.concatenate([top[0] * cap_s, prof[:, 0]])
    zf = np.concatenate([top[1] * cap_s, prof[:, 1]])
    zb = np.concatenate([top[2] * cap_s, prof[:, 2]])
    zc = np.concatenate([np.full_like(cap_y, top[3]), prof[:, 3]])
    return y, w, zf, zb, zc


def _skin_grid() -> tuple[np.ndarray, np.ndarray, int]:
    """Lofted skin: vertices (R*C + 1, 3) with the top pole last, faces, and the lip row index."""
    y, w, zf, zb, zc = _rows()
    u = np.arange(N_COLUMNS) / N_COLUMNS * 2.0 - 1.0  # [-1, 1), 0 = front
    theta = np.pi * (0.55 * u + 0.45 * u**3)  # denser columns on the face
    s, c = np.sin(theta), np.cos(theta)
    depth = np.where(c[None] > 0, zf[:, None], zb[:, None])
    pts = np.stack(
        [w[:, None] * s[None], np.broadcast_to(y[:, None], depth.shape), zc[:, None] + depth * c[None]], axis=-1
    ).reshape(-1, 3)
    pole = np.array([[0.0, CRANIUM_Y + CRANIUM_HALF_HEIGHT, _PROFILE[0, 3]]])
    verts = np.concatenate([pts, pole])
    n_rows, pole_idx = len(y), len(pts)
    idx = np.arange(n_rows * N_COLUMNS).reshape(n_rows, N_COLUMNS)
    nxt = np.roll(idx, -1, axis=1)
    a, b, cc, d = idx[:-1], nxt[:-1], idx[1:], nxt[1:]
    # Counter-clockwise from outside: the column angle increases towards +x at the front.
    quads = np.concatenate([np.stack([a, cc, b], -1).reshape(-1, 3), np.stack([b, cc, d], -1).reshape(-1, 3)])
    cap = np.stack([np.full(N_COLUMNS, pole_idx), idx[0], nxt[0]], -1)
    faces = np.concatenate([cap, quads])
    lip_row = int(np.argmin(np.abs(y - MOUTH_Y)))
    return verts, faces, lip_row


def _features(p: np.ndarray) -> np.ndarray:
    """Outward displacement (m) of the base surface that adds the face: (V, 3) points -> (V,)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    front = smoothstep((z - 0.0) / 0.04)
    ax = np.abs(x)
    d = np.zeros(len(p))
    d += 0.006 * _bump((y - 0.047) ** 2 * 6 + (ax - 0.03) ** 2 * 0.6, 0.006) * front  # brow ridge
    d += 0.006 * _bump((ax - 0.048) ** 2 + (y - 0.004) ** 2, 0.012) * front  # cheekbones
    # Nose: a ridge that grows towards the tip, with alae at its base.
    t = np.clip((0.038 - y) / 0.045, 0.0, 1.0)
    ridge = (0.004 + 0.020 * t**1.4) * _bump(x**2, 0.005 + 0.004 * t) * smoothstep((y + 0.012) / 0.006)
    d += ridge * front
    d += 0.006 * _bump((ax - 0.014) ** 2 + (y + 0.004) ** 2, 0.0055) * front  # alae
    d += 0.005 * _bump(x**2 * 0.35 + (y - (MOUTH_Y + 0.005)) ** 2, 0.004) * front  # upper lip
    d += 0.0045 * _bump(x**2 * 0.4 + (y - (MOUTH_Y - 0.006)) ** 2, 0.004) * front  # lower lip
    d -= 0.003 * _bump(x**2 * 0.5 + (y - (MOUTH_Y - 0.017)) ** 2, 0.004) * front  # mentolabial fold
    d += 0.006 * _bump(x**2 * 0.5 + (y + 0.066) ** 2, 0.008) * front  # chin
    # Ears: flat ovals on the sides, just behind the jaw pivot.
    side = smoothstep((ax - 0.05) / 0.015)
    d += 0.016 * _bump((y - 0.008) ** 2 * 0.35 + (z + 0.012) ** 2, 0.0095) * side
    return d


def _outward(p: np.ndarray) -> np.ndarray:
    """Approximate outward direction of the skin: horizontal radial with some vertical on the cap."""
    n = p - np.array([0.0, 0.0, -0.012])
    n[:, 1] = np.where(p[:, 1] > CRANIUM_Y, (p[:, 1] - CRANIUM_Y) * 1.3, 0.15 * n[:, 1])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _eye_centres(skin: np.ndarray) -> np.ndarray:
    """Eye centres (2, 3): left (+x) then right, set back so the cornea meets the lid surface."""
    out = []
    for sx in (1.0, -1.0):
        near = np.argmin((skin[:, 0] - sx * EYE_X) ** 2 + (skin[:, 1] - EYE_Y) ** 2 + 10 * (skin[:, 2] < 0))
        out.append([sx * EYE_X, EYE_Y, skin[near, 2] - EYE_RADIUS - 0.002])
    return np.array(out)


def _fit_sockets(skin: np.ndarray, eyes: np.ndarray) -> np.ndarray:
    """Pull the skin round each eye onto the eyeball (+1.5 mm), so the lids hug it."""
    skin = skin.copy()
    for e in eyes:
        dx, dy = skin[:, 0] - e[0], skin[:, 1] - e[1]
        r2 = dx**2 + dy**2
        target = e[2] + np.sqrt(np.maximum(EYE_RADIUS**2 - r2, 0.0)) + 0.0015
        m = 1.0 - smoothstep((np.sqrt(r2 / EYE_RADIUS**2 * 1.0) - 0.95) / 0.7)
        m *= skin[:, 2] > 0
        skin[:, 2] = (1 - m) * skin[:, 2] + m * target
    return skin


def _eye_opening(p: np.ndarray, eyes: np.ndarray) -> np.ndarray:
    """(N,) True where a point lies inside a lid opening."""
    hw, hh = EYE_HALF_OPENING
    inside = np.zeros(len(p), bool)
    for e in eyes:
        inside |= ((p[:, 0] - e[0]) / hw) ** 2 + ((p[:, 1] - e[1]) / hh) ** 2 < 1.0
    return inside & (p[:, 2] > 0)


def _sphere(centre: np.ndarray, radius: float, n_lat: int = 12, n_lon: int = 18) -> tuple[np.ndarray, np.ndarray]:
    """UV sphere with its poles on the z axis (the front pole is the pupil)."""
    lat = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack(
        [np.sin(lat)[:, None] * np.cos(lon), np.sin(lat)[:, None] * np.sin(lon), np.cos(lat)[:, None] + 0 * lon], -1
    ).reshape(-1, 3)
    verts = np.concatenate([[[0, 0, 1]], ring, [[0, 0, -1]]]) * radius + centre
    idx = 1 + np.arange((n_lat - 1) * n_lon).reshape(n_lat - 1, n_lon)
    nxt = np.roll(idx, -1, axis=1)
    last = len(verts) - 1
    faces = [np.stack([np.zeros(n_lon, int), idx[0], nxt[0]], -1)]
    faces += [np.stack([idx[:-1], idx[1:], nxt[:-1]], -1).reshape(-1, 3)]
    faces += [np.stack([nxt[:-1], idx[1:], nxt[1:]], -1).reshape(-1, 3)]
    faces += [np.stack([np.full(n_lon, last), nxt[-1], idx[-1]], -1)]
    return verts, np.concatenate(faces)


def _mouth_cavity(lip_z: float) -> tuple[np.ndarray, np.ndarray]:
    """A dark half-shell behind the lips (normals facing forward, towards the viewer)."""
    v, f = _sphere(np.zeros(3), 1.0, n_lat=8, n_lon=16)
    keep = v[:, 2] <= 0.05
    v = v * np.array([0.022, 0.016, 0.022]) + np.array([0.0, MOUTH_Y - 0.003, lip_z - 0.014])
    # Keep the back half, flip it so its inside faces +z.
    remap = -np.ones(len(keep), int)
    remap[keep] = np.arange(keep.sum())
    f = f[keep[f].all(axis=1)][:, ::-1]
    return v[keep], remap[f]


def _split_mouth(verts: np.ndarray, faces: np.ndarray, lip_row: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Duplicate the lip-line vertices between the corners; the band below uses the copies.

    Returns vertices, faces and the indices of the lower-lip copies.
    """
    row = np.arange(lip_row * N_COLUMNS, (lip_row + 1) * N_COLUMNS)
    p = verts[row]
    seam = row[(np.abs(p[:, 0]) < MOUTH_HALF_WIDTH) & (p[:, 2] > 0)]
    twins = np.arange(len(verts), len(verts) + len(seam))
    lookup = dict(zip(seam.tolist(), twins.tolist()))
    below = np.arange((lip_row + 1) * N_COLUMNS, (lip_row + 2) * N_COLUMNS)
    uses_below = np.isin(faces, below).any(axis=1)
    faces = faces.copy()
    for fi in np.nonzero(uses_below & np.isin(faces, seam).any(axis=1))[0]:
        faces[fi] = [lookup.get(int(i), int(i)) for i in faces[fi]]
    return np.concatenate([verts, verts[seam]]), faces, twins


def _skinning(verts: np.ndarray, parts: dict[str, np.ndarray], lower_lip: np.ndarray) -> np.ndarray:
    """Weights (V, 5): root/neck blend down the neck, jaw on the lower face, eyes on the eyeballs."""
    x, y, z = verts.T
    w = np.zeros((len(verts), 5))
    head = smoothstep((y + 0.135) / 0.04)
    # Jaw region: below a line from the lip line at the front up to the pivot, in front of the ear,
    # fading on the throat.
    z_corner, z_pivot = 0.06, JAW_PIVOT[2] + 0.012
    t = np.clip((z_corner - z) / (z_corner - z_pivot), 0.0, 1.0)
    y_line = MOUTH_Y + (JAW_PIVOT[1] - 0.012 - MOUTH_Y) * t
    # At the lips the boundary is sharp and strictly below the lip line (the upper lip stays with the
    # head); over the cheeks it is soft, so opening the jaw stretches the skin instead of creasing it.
    lip_side = 1.0 - smoothstep((np.abs(x) - 0.02) / 0.012)
    below = smoothstep((y_line - y) / 0.01 + 0.6) * (y < y_line - 1e-6)
    jaw = lip_side * below + (1.0 - lip_side) * smoothstep((y_line - y) / 0.016 + 0.5)
    jaw *= smoothstep((z - z_pivot) / 0.02)
    jaw *= smoothstep((z - 0.012) / 0.03 + 0.4 * smoothstep((y + 0.08) / 0.01))
    jaw *= smoothstep((y + 0.11) / 0.02)
    jaw[lower_lip] = 1.0
    jaw[parts["mouth_cavity"]] = smoothstep((MOUTH_Y - 0.002 - y[parts["mouth_cavity"]]) / 0.004)
    w[:, 0] = 1.0 - head
    w[:, 1] = head * (1.0 - jaw)
    w[:, 2] = head * jaw
    for k, part in ((3, "eyeball_left"), (4, "eyeball_right")):
        w[parts[part]] = 0.0
        w[parts[part], k] = 1.0
    return w


def _regressor(verts: np.ndarray, parts: dict[str, np.ndarray], skin_rows: int) -> np.ndarray:
    """J (5, V): each joint is the mean of a symmetric vertex set."""
    j = np.zeros((5, len(verts)))

    def ring_at(y0: float) -> np.ndarray:
        skin = np.arange(skin_rows * N_COLUMNS)
        ys = verts[skin, 1]
        target = ys[np.argmin(np.abs(ys - y0))]
        return skin[np.abs(ys - target) < 1e-9]

    j[0, ring_at(-0.17)] = 1.0
    j[1, ring_at(-0.105)] = 1.0
    # Jaw: the two side vertices nearest the pivot's left and right projections onto the skin.
    for sx in (1.0, -1.0):
        target = JAW_PIVOT + np.array([sx * 0.07, 0.0, 0.0])
        j[2, np.argmin(np.sum((verts[: skin_rows * N_COLUMNS] - target) ** 2, axis=1))] = 1.0
    j[3, parts["eyeball_left"]] = 1.0
    j[4, parts["eyeball_right"]] = 1.0
    return j / j.sum(axis=1, keepdims=True)


def _expression_fields(v: np.ndarray, lm: dict[str, np.ndarray], movable: np.ndarray) -> np.ndarray:
    """Localised displacement fields (V, 3, N): each one muscle-like motion at unit activation."""
    x, y, z = v.T
    front = smoothstep(z / 0.03)
    fields = []

    def add(centre, radius, direction, amp, squash=(1.0, 1.0), extra=None):
        c = np.asarray(centre)
        d2 = ((x - c[0]) / squash[0]) ** 2 + ((y - c[1]) / squash[1]) ** 2 + (z - c[2]) ** 2
        f = _bump(d2, radius) * front
        if extra is not None:
            f = f * extra
        fields.append(f[:, None] * np.asarray(direction, float)[None] * amp)

    mouth_l, mouth_r = lm["mouth_corner_left"], lm["mouth_corner_right"]
    upper = y > MOUTH_Y - 0.0005
    upper_lid = (y > EYE_Y) * 1.0
    lower_lid = (y <= EYE_Y) * 1.0
    upper_lip_mask = upper * 1.0
    lower_lip_mask = (~upper) * 1.0
    for s, side in ((1, "left"), (-1, "right")):
        eye = lm[f"eye_{side}"]
        # Brows: inner up, outer up, down-and-in.
        add(lm[f"brow_inner_{side}"], 0.010, (0, 1, 0.1), 0.006)
        add(lm[f"brow_outer_{side}"], 0.011, (0, 1, 0), 0.006)
        add(lm[f"brow_inner_{side}"] + [s * 0.008, 0, 0], 0.012, (-s * 0.5, -1, 0.2), 0.005)
        # Lids: upper lid closes over the eyeball (down and slightly out), lower lid rises, lid widen.
        lid_h = 2 * EYE_HALF_OPENING[1]
        add(eye + [0, EYE_HALF_OPENING[1], 0], 0.0065, (0, -1, 0.12), lid_h, (1.7, 1.0), upper_lid)
        add(eye - [0, EYE_HALF_OPENING[1], 0], 0.0055, (0, 1, 0.1), 0.0035, (1.8, 1.0), lower_lid)
        add(eye + [0, EYE_HALF_OPENING[1] + 0.002, 0], 0.006, (0, 1, 0.05), 0.003, (1.7, 1.0), upper_lid)
        # Cheeks: raise (squint), puff.
        add(lm[f"cheek_{side}"], 0.012, (0, 0.8, 0.4), 0.005)
        add(lm[f"cheek_{side}"] + [0, -0.03, -0.005], 0.015, (s * 0.8, 0, 0.6), 0.007)
        # Nose: wrinkle (side of the nose up).
        add(lm["nose_tip"] + [s * 0.012, 0.008, -0.01], 0.007, (0, 1, 0.2), 0.004)
        # Mouth corners: smile, frown, stretch, dimple (back).
        corner = mouth_l if s == 1 else mouth_r
        add(corner, 0.010, (s * 0.6, 1, -0.3), 0.007)
        add(corner, 0.010, (s * 0.2, -1, 0), 0.006)
        add(corner, 0.010, (s * 1, -0.2, -0.2), 0.007)
        add(corner, 0.008, (s * 0.3, 0, -1), 0.005)
        # Lips, one side: upper lip up, lower lip down, press.
        lip_side = lm["upper_lip"] + [s * 0.011, 0, 0]
        add(lip_side, 0.008, (0, 1, 0.3), 0.005, extra=upper_lip_mask)
        add(lm["lower_lip"] + [s * 0.011, 0, 0], 0.008, (0, -1, 0.2), 0.005, extra=lower_lip_mask)
        add(lm["lower_lip"] + [s * 0.01, 0.003, 0], 0.007, (0, 1, -0.4), 0.003, extra=lower_lip_mask)
    # Symmetric lip shapes: pucker, funnel, roll in (upper, lower), shrug (upper, lower), lips sideways.
    mouth = lm["mouth_centre"]
    towards_centre = np.stack([-x, np.zeros_like(x), np.zeros_like(x)], 1) / 0.025
    pucker = _bump(((x - mouth[0]) / 1.6) ** 2 + (y - mouth[1]) ** 2, 0.010) * front
    fields.append((towards_centre * 0.004 + np.array([0, 0, 0.006])) * pucker[:, None])
    funnel = pucker * np.sign(y - MOUTH_Y + 1e-9)
    funnel_dir = np.stack([np.ones_like(x), np.sign(funnel), np.ones_like(x)], 1)
    fields.append(np.array([0, 0.003, 0.004]) * np.abs(funnel)[:, None] * funnel_dir)
    add(lm["upper_lip"], 0.006, (0, -0.5, -1), 0.004, (2.2, 1.0), upper_lip_mask)
    add(lm["lower_lip"], 0.006, (0, 0.5, -1), 0.004, (2.2, 1.0), lower_lip_mask)
    add(lm["upper_lip"], 0.007, (0, 0.2, 1), 0.003, (2.2, 1.0), upper_lip_mask)
    add(lm["chin"] + [0, 0.01, 0], 0.010, (0, 1, 0.5), 0.005, (1.6, 1.0))
    add(mouth, 0.012, (1, 0, 0), 0.006, (1.8, 1.0))
    add(mouth, 0.012, (-1, 0, 0), 0.006, (1.8, 1.0))
    # Larger-scale motions: forehead raise, nostril flare, chin thrust, lip press together.
    add(lm["brow_inner_left"] * [0, 1, 1] + [0, 0.02, 0], 0.02, (0, 1, 0), 0.004, (2.5, 1.0))
    add(lm["nose_tip"] + [0, -0.006, -0.008], 0.009, (0, 0, 0), 0.0)
    fields[-1] = (np.stack([np.sign(x), np.zeros_like(x), np.zeros_like(x)], 1) * 0.002
                  * (_bump((np.abs(x) - 0.015) ** 2 + (y - lm["nose_tip"][1] + 0.005) ** 2, 0.005) * front)[:, None])
    add(lm["chin"], 0.014, (0, 0, 1), 0.004)
    add(mouth, 0.008, (0, 0, -1), 0.003, (2.0, 1.0))
    add((lm["brow_inner_left"] + lm["brow_inner_right"]) / 2, 0.008, (0, -1, 0.3), 0.003)  # procerus
    add(lm["chin"] + [0, -0.004, 0], 0.006, (0, 0.3, -1), 0.002)  # chin dimple
    add(lm["upper_lip"] + [0, 0.006, 0], 0.006, (0, 0.5, 0.8), 0.003, (1.5, 1.0))  # philtrum raise
    for s, side in ((1, "left"), (-1, "right")):
        add(lm[f"eye_{side}"] - [0, EYE_HALF_OPENING[1] + 0.003, 0], 0.006, (-s * 0.3, 0.6, 0.3), 0.003, (1.8, 1.0))
        add(lm[f"cheek_{side}"] + [0, -0.028, -0.008], 0.012, (-s, 0, -0.3), 0.005)  # cheek suck
        add(lm[f"mouth_corner_{side}"], 0.006, (-s * 0.4, 0.8, 0.3), 0.004)  # sharp corner lift
    out = np.stack(fields, axis=-1)  # (V, 3, n)
    return out * movable[:, None, None]


def _orthogonalise(fields: np.ndarray, n: int, scale: float) -> np.ndarray:
    """FLAME-style basis from fields (V, 3, m): SVD, most energy first, deterministic signs, n columns."""
    v = fields.shape[0]
    u, s, _ = np.linalg.svd(fields.reshape(v * 3, -1), full_matrices=False)
    u = u[:, :n] * s[:n] * scale
    # An SVD fixes each column up to its sign, and LAPACK's choice differs between CPUs. The sign of the largest
    # entry does not settle it: the head is symmetric, so in 18 of the 50 expression columns (7 of the 20 identity
    # ones) the largest entries are a mirrored pair of opposite signs whose order rounding decides. It did: 8
    # columns flipped between an Intel and an AMD CPU, and with them the FLAME values an EPM trained on one meant.
    # A fixed random direction is far from orthogonal to any column (|probe . u| / |u| >= 0.0026 here).
    probe = np.random.default_rng(0).standard_normal(u.shape[0])
    sign = np.where(probe @ u < 0, -1.0, 1.0)
    return (u * sign).reshape(v, 3, -1)


def _identity_fields(v: np.ndarray, lm: dict[str, np.ndarray], rigid_parts: list[np.ndarray]) -> np.ndarray:
    """Identity shape changes (V, 3, m): global proportions and regional features."""
    x, y, z = v.T
    fields = [
        np.stack([x, 0 * x, 0 * x], 1) * 0.06,
        np.stack([0 * x, y, 0 * x], 1) * 0.05,
        np.stack([0 * x, 0 * x, z], 1) * 0.05,
    ]
    front = smoothstep(z / 0.03)
    low = smoothstep((-0.02 - y) / 0.03)
    fields.append(np.stack([x * low, 0 * x, 0 * x], 1) * 0.12)  # jaw width
    fields.append(np.stack([0 * x, (y - 0.0) * low, 0 * x], 1) * 0.12)  # lower face length
    fields.append(np.stack([x * (1 - low) * (y > 0.05), 0 * x, 0 * x], 1) * 0.1)  # cranium width
    nose = _bump(x**2 + (y - lm["nose_tip"][1] - 0.01) ** 2, 0.012) * front
    fields.append(np.stack([0 * x, 0 * x, nose], 1) * 0.006)  # nose protrusion
    fields.append(np.stack([x * nose, 0 * x, 0 * x], 1) * 0.3)  # nose width
    fields.append(np.stack([0 * x, -nose, 0 * x], 1) * 0.004)  # nose length
    for key, amp in (("chin", 0.005), ("cheek_left", 0.004), ("cheek_right", 0.004), ("upper_lip", 0.002),
                     ("lower_lip", 0.002), ("brow_inner_left", 0.003), ("brow_inner_right", 0.003)):
        c = lm[key]
        f = _bump((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2, 0.012) * front
        fields.append(np.stack([0 * x, 0 * x, f], 1) * amp)
    fields.append(np.stack([0 * x, 0 * x, front * (1 - np.abs(x) / 0.08).clip(0, 1)], 1) * 0.006)  # face depth
    brow = smoothstep((y - 0.04) / 0.03) * front
    fields.append(np.stack([0 * x, 0 * x, -brow * (y - 0.04)], 1) * 0.15)  # forehead slope
    back = smoothstep(-z / 0.04)
    fields.append(np.stack([0 * x, 0 * x, -back], 1) * 0.008)  # back of the head
    top = smoothstep((y - 0.08) / 0.03)
    fields.append(np.stack([0 * x, top, 0 * x], 1) * 0.008)  # crown height
    neck = smoothstep((-0.09 - y) / 0.02)
    fields.append(np.stack([x * neck, 0 * x, (z + 0.025) * neck], 1) * 0.15)  # neck thickness
    out = np.stack(fields, axis=-1)
    for part in rigid_parts:  # eyeballs and mouth move rigidly with their centre
        out[part] = out[part].mean(axis=0, keepdims=True)
    return out


def _pose_correctives(v: np.ndarray, lm: dict[str, np.ndarray], movable: np.ndarray) -> np.ndarray:
    """P (36, 3V): the jaw's opening hollows the cheeks and stretches the lip corners inwards."""
    x, y, z = v.T
    nv = len(v)
    p = np.zeros((36, nv, 3))
    front = smoothstep(z / 0.03)
    cheek = sum(_bump((x - lm[f"mouth_corner_{s}"][0] * 1.6) ** 2 + (y - MOUTH_Y - 0.004) ** 2, 0.012)
                for s in ("left", "right"))
    hollow = np.stack([-np.sign(x) * 0.006, np.zeros(nv), -0.002 * np.ones(nv)], 1) * (cheek * front * movable)[:, None]
    # Jaw is joint 2 -> rows 9..17 of the feature; about x, (R - I)[2, 1] = sin(a), (R - I)[1, 2] = -sin(a).
    p[9 + 7] = hollow / 2
    p[9 + 5] = -hollow / 2
    # Neck turn (joint 1, rows 0..8): the throat bulges on the side turned away.
    throat = _bump(x**2 + (y + 0.11) ** 2 + (z - 0.03) ** 2, 0.02)
    p[0 + 2] = np.stack([throat * 0.004, np.zeros(nv), np.zeros(nv)], 1) / 2
    p[0 + 6] = -p[0 + 2]
    return p.reshape(36, nv * 3)


def _landmarks(v: np.ndarray, eyes: np.ndarray) -> dict[str, np.ndarray]:
    def surface(x0: float, y0: float) -> np.ndarray:
        i = np.argmin((v[:, 0] - x0) ** 2 + (v[:, 1] - y0) ** 2 - 1e-3 * v[:, 2])
        return v[i].copy()

    lm = {
        "eye_left": eyes[0], "eye_right": eyes[1],
        "nose_tip": surface(0.0, -0.004),
        "mouth_centre": surface(0.0, MOUTH_Y),
        "upper_lip": surface(0.0, MOUTH_Y + 0.005),
        "lower_lip": surface(0.0, MOUTH_Y - 0.006),
        "chin": surface(0.0, -0.066),
        "jaw_pivot": JAW_PIVOT.copy(),
    }
    for s, side in ((1, "left"), (-1, "right")):
        lm[f"mouth_corner_{side}"] = surface(s * (MOUTH_HALF_WIDTH - 0.001), MOUTH_Y)
        lm[f"brow_inner_{side}"] = surface(s * 0.016, 0.048)
        lm[f"brow_outer_{side}"] = surface(s * 0.046, 0.046)
        lm[f"cheek_{side}"] = surface(s * 0.042, 0.006)
    return lm


def make_procedural_head(name: str = "procedural-head") -> HeadModel:
    """Build the stand-in head deterministically (no randomness). About 8,000 vertices."""
    skin, faces, lip_row = _skin_grid()
    skin += _outward(skin) * _features(skin)[:, None]
    eyes = _eye_centres(skin)
    skin = _fit_sockets(skin, eyes)
    centroid = skin[faces].mean(axis=1)
    faces = faces[~_eye_opening(centroid, eyes)]
    skin_rows = (len(skin) - 1) // N_COLUMNS
    skin, faces, lower_lip = _split_mouth(skin, faces, lip_row)

    verts, all_faces, parts = [skin], [faces], {}
    n = len(skin)
    for side, centre in (("left", eyes[0]), ("right", eyes[1])):
        ev, ef = _sphere(centre, EYE_RADIUS)
        parts[f"eyeball_{side}"] = np.arange(n, n + len(ev))
        verts.append(ev)
        all_faces.append(ef + n)
        n += len(ev)
    lip_z = skin[lower_lip, 2].max()
    cv, cf = _mouth_cavity(lip_z)
    parts["mouth_cavity"] = np.arange(n, n + len(cv))
    verts.append(cv)
    all_faces.append(cf + n)
    v = np.concatenate(verts)
    f = np.concatenate(all_faces).astype(np.int64)
    nv = len(v)

    lm = _landmarks(v[: len(skin)], eyes)
    masks = {k: np.isin(np.arange(nv), idx) for k, idx in parts.items()}
    skin_mask = np.arange(nv) < len(skin)
    labels = _labels(v, masks, skin_mask, lower_lip, eyes)
    movable = (skin_mask & (v[:, 1] > -0.095) & (v[:, 2] > -0.02)).astype(float)
    expr = _orthogonalise(_expression_fields(v, lm, movable), N_EXPR, 1.0 / np.sqrt(6.0))
    ident = _orthogonalise(
        _identity_fields(v, lm, [parts["eyeball_left"], parts["eyeball_right"], parts["mouth_cavity"]]),
        N_SHAPE, 0.5,
    )
    return HeadModel(
        v_template=v,
        shapedirs=ident,
        exprdirs=expr,
        posedirs=_pose_correctives(v, lm, movable),
        j_regressor=_regressor(v, parts, skin_rows),
        parents=FLAME_PARENTS.copy(),
        weights=_skinning(v, parts, lower_lip),
        faces=f,
        name=name,
        landmarks=lm,
        vertex_labels=labels,
    )


def _labels(v: np.ndarray, parts: dict[str, np.ndarray], skin: np.ndarray, lower_lip: np.ndarray,
            eyes: np.ndarray) -> dict[str, np.ndarray]:
    """Semantic vertex masks used to colour the default avatar and to place rig shapes."""
    x, y, z = v.T
    labels = dict(parts)
    labels["skin"] = skin
    for side, e in (("left", eyes[0]), ("right", eyes[1])):
        d = v - e
        cos = d[:, 2] / np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        labels[f"iris_{side}"] = parts[f"eyeball_{side}"] & (cos > np.cos(np.radians(38)))
        labels[f"pupil_{side}"] = parts[f"eyeball_{side}"] & (cos > np.cos(np.radians(16)))
    lips = skin & (z > 0.04) & (((x / 0.026) ** 2 + ((y - MOUTH_Y) / 0.0068) ** 2) < 1.0)
    lips[lower_lip] = True
    labels["lips"] = lips
    brow_y = 0.047 + 0.002 * np.cos(np.abs(x) / 0.05 * np.pi)
    labels["brows"] = skin & (z > 0.03) & (np.abs(y - brow_y) < 0.0045) & (np.abs(x) > 0.008) & (np.abs(x) < 0.058)
    # Hairline: above the forehead at the front, over the ears at the side, down to the nape at the back.
    hairline = np.where(z > 0.0, 0.085 - 0.25 * np.clip(np.abs(x) - 0.03, 0, None),
                        0.02 + 0.6 * z.clip(-0.12, 0) + 0.04)
    labels["scalp"] = skin & (y > np.minimum(hairline, 0.085)) & ~((np.abs(x) > 0.06) & (y < 0.03))
    labels["neck"] = skin & (y < -0.09)
    return labels
