// Expression streaming (PROTOCOL.md 13) in the browser: the rig body (assembled from `rig` messages, decoded and
// checked), and the client-side deformation of 13.4: params (68 float32) -> the rig's Gaussians, written into the
// session's position / rotation / scale arrays (in the session's coordinates). Two implementations of 13.4, both
// in JavaScript numbers (float64) over the rig's float32 arrays, so both match `ofera_protocol.rig.deform_rig` to
// float32 rounding:
// - `deformRigReference`: the steps of 13.4 as written, one Gaussian at a time, plain and slow;
// - `RigDeformer`: the fast one the splat worker uses (tests/test_params_browser.py compares the two). At rig load
//   it keeps only the faces the Gaussians sit on and those faces' vertices (renumbered), merges the expression and
//   pose bases into one float32 basis per vertex and normalises the local rotations; per frame it blends and skins
//   those vertices, computes each face's frame and quaternion once (not once per Gaussian), then writes the
//   Gaussians, without allocating.
import { decode, MsgpackError } from "./msgpack.js";
import { f32view, HALF_TO_FLOAT, ProtocolError, u16view, u32view } from "./protocol.js";

const JOINTS = 5;
const MAX_RIG_BYTES = 64 * 1024 * 1024;

/** Collects one avatar's `rig` chunks (decoded messages), in order; `result()` is the body once complete. */
export class RigAssembler {
  constructor(expectedSize = null) {
    this.expectedSize = expectedSize;
    this.parts = [];
    this.next = 0;
    this.size = null;
    this.chunks = null;
  }

  get complete() { return this.chunks !== null && this.parts.length === this.chunks; }

  /** Add the next chunk; true once the body is complete. */
  add(c) {
    const end = c.offset + c.data.length;
    const problems = [];
    if (this.complete) problems.push("a rig chunk after the rig was complete");
    if (c.chunk !== this.parts.length) problems.push(`chunk ${c.chunk} arrived, expected ${this.parts.length}`);
    if (this.chunks !== null && (c.chunks !== this.chunks || c.size !== this.size)) problems.push("chunks / size differ from the first chunk's");
    if (c.offset !== this.next) problems.push(`offset ${c.offset} != ${this.next}`);
    if (end > c.size || (c.chunk === c.chunks - 1 && end !== c.size)) problems.push(`chunk ends at byte ${end} of a ${c.size}-byte rig`);
    if (c.size > MAX_RIG_BYTES) problems.push(`a rig of ${c.size} bytes exceeds ${MAX_RIG_BYTES}`);
    if (this.expectedSize !== null && c.size !== this.expectedSize) problems.push(`rig of ${c.size} bytes, welcome announced ${this.expectedSize}`);
    if (problems.length) throw new ProtocolError("bad_field", `bad rig chunk: ${problems.join("; ")}`);
    this.chunks = c.chunks;
    this.size = c.size;
    this.parts.push(c.data.slice());
    this.next = end;
    return this.complete;
  }

  result() {
    const out = new Uint8Array(this.size);
    let o = 0;
    for (const p of this.parts) { out.set(p, o); o += p.length; }
    return out;
  }
}

function intOf(m, key, lo, hi) {
  const v = typeof m[key] === "bigint" ? Number(m[key]) : m[key];
  if (typeof v !== "number" || !Number.isInteger(v)) throw new ProtocolError("bad_field", `rig: field '${key}' is not an int`);
  if (v < lo || v > hi) throw new ProtocolError("bad_field", `rig: field '${key}' = ${v} is outside [${lo}, ${hi}]`);
  return v;
}

function binOf(m, key, bytes) {
  const b = m[key];
  if (!(b instanceof Uint8Array)) throw new ProtocolError("bad_field", `rig: missing bin field '${key}'`);
  if (bytes !== undefined && b.length !== bytes) throw new ProtocolError("bad_length", `rig: '${key}' has ${b.length} bytes, expected ${bytes}`);
  return b;
}

function finite(a, key) {
  for (let i = 0; i < a.length; i++) if (!Number.isFinite(a[i])) throw new ProtocolError("non_finite", `rig: '${key}' holds NaN or infinity`);
  return a;
}

function f32(m, key, n) { return finite(f32view(binOf(m, key, 4 * n)), key); }

function f16(m, key, n) {
  const h = u16view(binOf(m, key, 2 * n));
  const out = new Float32Array(n);
  for (let i = 0; i < n; i++) out[i] = HALF_TO_FLOAT[h[i]];
  return finite(out, key);
}

function ids(m, key, n, below, ascending) {
  const a = u32view(binOf(m, key, 4 * n));
  for (let i = 0; i < a.length; i++) {
    if (a[i] >= below || (ascending && i > 0 && a[i] <= a[i - 1])) {
      throw new ProtocolError("bad_field", `rig: '${key}' must hold ${ascending ? "strictly ascending " : ""}values below ${below}`);
    }
  }
  return a;
}

/** A rig body (PROTOCOL.md 13.3) -> its arrays, checked (lengths, finiteness, index ranges). */
export function decodeRig(body) {
  let m;
  try { m = decode(body); } catch (e) {
    if (e instanceof MsgpackError) throw new ProtocolError("malformed", `rig: ${e.message}`);
    throw e;
  }
  if (typeof m !== "object" || m === null || Array.isArray(m) || m instanceof Uint8Array) throw new ProtocolError("malformed", "rig: the body is a msgpack map");
  const binding = m.binding;
  if (binding !== "triangle" && binding !== "barycentric") throw new ProtocolError("bad_field", `rig: unknown binding ${binding}`);
  const count = intOf(m, "count", 0, 2 ** 32 - 1);
  const S = intOf(m, "vertices", 0, 2 ** 32 - 1), U = intOf(m, "faces", 0, 2 ** 32 - 1);
  const M = intOf(m, "gaussians", 0, count), E = intOf(m, "expr_dims", 0, 256);
  const poseRows = binOf(m, "pose_rows");
  const P = poseRows.length;
  for (let p = 0; p < P; p++) {
    if (poseRows[p] >= 36 || (p > 0 && poseRows[p] <= poseRows[p - 1])) throw new ProtocolError("bad_field", "rig: 'pose_rows' must be strictly ascending entries below 36");
  }
  const rig = {
    binding, count, vertices: S, faces: U, gaussians: M, exprDims: E, poseRows,
    index: ids(m, "index", M, count, true),
    joints: f32(m, "joints", JOINTS * 3), jointsExpr: f32(m, "joints_expr", JOINTS * 3 * E),
    template: f32(m, "template", S * 3), exprBasis: f32(m, "expr_basis", S * E * 3),
    poseBasis: f16(m, "pose_basis", S * P * 3), weights: f32(m, "weights", S * JOINTS),
    face: ids(m, "face", U * 3, S, false), gaussianFace: ids(m, "gaussian_face", M, U, false),
    localRotation: f16(m, "local_rotation", M * 4), localScale: f16(m, "local_scale", M * 3),
  };
  if (binding === "triangle") rig.localPosition = f32(m, "local_position", M * 3);
  else {
    rig.bary = f32(m, "bary", M * 3);
    rig.normalOffset = f32(m, "normal_offset", M);
  }
  return rig;
}

/** 6D (two rows) at p[o..o+6) -> row-major 3x3 (PROTOCOL.md 13.4 step 2) in `out` (9). */
function rot6d(p, o, out = new Array(9)) {
  const a1x = p[o], a1y = p[o + 1], a1z = p[o + 2], a2x = p[o + 3], a2y = p[o + 4], a2z = p[o + 5];
  let n = Math.max(Math.sqrt(a1x * a1x + a1y * a1y + a1z * a1z), 1e-12);
  const b1x = a1x / n, b1y = a1y / n, b1z = a1z / n;
  const d = b1x * a2x + b1y * a2y + b1z * a2z;
  const cx = a2x - d * b1x, cy = a2y - d * b1y, cz = a2z - d * b1z;
  n = Math.max(Math.sqrt(cx * cx + cy * cy + cz * cz), 1e-12);
  const b2x = cx / n, b2y = cy / n, b2z = cz / n;
  out[0] = b1x; out[1] = b1y; out[2] = b1z; out[3] = b2x; out[4] = b2y; out[5] = b2z;
  out[6] = b1y * b2z - b1z * b2y; out[7] = b1z * b2x - b1x * b2z; out[8] = b1x * b2y - b1y * b2x;
  return out;
}

const IDENTITY = [1, 0, 0, 0, 1, 0, 0, 0, 1];

/** Steps 1-3: params (68) -> the 5 joint rotations (row-major 3x3 each) and A_k (5 x 12: 3 x 4 row-major). */
function jointTransforms(rig, params) {
  const E = rig.exprDims;
  const rot = [IDENTITY, IDENTITY, rot6d(params, 50), rot6d(params, 56), rot6d(params, 62)];
  const a = new Float64Array(JOINTS * 12);
  for (let k = 0; k < JOINTS; k++) {
    const R = rot[k], j = [0, 0, 0];
    for (let c = 0; c < 3; c++) {
      let s = rig.joints[3 * k + c];
      for (let e = 0; e < E; e++) s += rig.jointsExpr[(3 * k + c) * E + e] * params[e];
      j[c] = s;
    }
    for (let i = 0; i < 3; i++) {
      a[12 * k + 4 * i] = R[3 * i]; a[12 * k + 4 * i + 1] = R[3 * i + 1]; a[12 * k + 4 * i + 2] = R[3 * i + 2];
      a[12 * k + 4 * i + 3] = j[i] - (R[3 * i] * j[0] + R[3 * i + 1] * j[1] + R[3 * i + 2] * j[2]);
    }
  }
  return { rot, a };
}

/** Step 4: the pose feature's used entries c_p (P). */
function poseCoefficients(rig, rot) {
  const P = rig.poseRows.length, coef = new Float64Array(P);
  for (let p = 0; p < P; p++) {
    const row = rig.poseRows[p], k = 1 + Math.floor(row / 9), i = Math.floor((row % 9) / 3), j = row % 3;
    coef[p] = rot[k][3 * i + j] - (i === j ? 1 : 0);
  }
  return coef;
}

/** Steps 1-5, the REFERENCE: params (68) -> every deformed rig vertex (S x 3, float64, metres). */
export function rigVerticesReference(rig, params) {
  const E = rig.exprDims, S = rig.vertices, P = rig.poseRows.length;
  const { rot, a } = jointTransforms(rig, params);
  const coef = poseCoefficients(rig, rot);
  const v = new Float64Array(S * 3);
  for (let s = 0; s < S; s++) {
    let x = rig.template[3 * s], y = rig.template[3 * s + 1], z = rig.template[3 * s + 2];
    for (let e = 0; e < E; e++) {
      const o = (s * E + e) * 3;
      x += rig.exprBasis[o] * params[e]; y += rig.exprBasis[o + 1] * params[e]; z += rig.exprBasis[o + 2] * params[e];
    }
    for (let p = 0; p < P; p++) {
      const o = (s * P + p) * 3;
      x += rig.poseBasis[o] * coef[p]; y += rig.poseBasis[o + 1] * coef[p]; z += rig.poseBasis[o + 2] * coef[p];
    }
    const T = new Float64Array(12);
    for (let k = 0; k < JOINTS; k++) for (let q = 0; q < 12; q++) T[q] += rig.weights[JOINTS * s + k] * a[12 * k + q];
    v[3 * s] = T[0] * x + T[1] * y + T[2] * z + T[3];
    v[3 * s + 1] = T[4] * x + T[5] * y + T[6] * z + T[7];
    v[3 * s + 2] = T[8] * x + T[9] * y + T[10] * z + T[11];
  }
  return v;
}

/** quat(R) of step 7 for a row-major 3x3 R: (w, x, y, z), unit, w >= 0. */
function matrixToQuaternion(R) {
  const [R00, R01, R02, R10, R11, R12, R20, R21, R22] = R;
  const t = [1 + R00 + R11 + R22, 1 + R00 - R11 - R22, 1 - R00 + R11 - R22, 1 - R00 - R11 + R22];
  let b = 0;
  for (let i = 1; i < 4; i++) if (t[i] > t[b]) b = i;
  const q = [[t[0], R21 - R12, R02 - R20, R10 - R01], [R21 - R12, t[1], R10 + R01, R02 + R20],
    [R02 - R20, R10 + R01, t[2], R21 + R12], [R10 - R01, R02 + R20, R21 + R12, t[3]]][b];
  const n = Math.hypot(...q) * (q[0] < 0 ? -1 : 1);
  return q.map((c) => c / n);
}

/**
 * PROTOCOL.md 13.4, the REFERENCE (steps as written, one Gaussian at a time, float64): params (68) -> Gaussian
 * index[m]'s position (3, m), rotation (x, y, z, w) and scale (3, m) written into the session's arrays, mirrored for
 * `unity` coordinates. Returns the rig's index (the Gaussians it changed).
 */
export function deformRigReference(rig, params, position, rotation, scale, coords = "flame") {
  const v = rigVerticesReference(rig, params), mx = coords === "unity" ? -1 : 1;
  const vertex = (i) => [v[3 * i], v[3 * i + 1], v[3 * i + 2]];
  const sub = (p, q) => [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
  const cross = (p, q) => [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]];
  const dot = (p, q) => p[0] * q[0] + p[1] * q[1] + p[2] * q[2];
  for (let m = 0; m < rig.gaussians; m++) {
    const f = 3 * rig.gaussianFace[m];
    const v0 = vertex(rig.face[f]), v1 = vertex(rig.face[f + 1]), v2 = vertex(rig.face[f + 2]);
    const e1 = sub(v1, v0), e2 = sub(v2, v0);
    const l1 = Math.sqrt(Math.max(dot(e1, e1), 1e-20));
    const a0 = e1.map((c) => c / l1), n = cross(a0, e2), ln = Math.sqrt(Math.max(dot(n, n), 1e-20));
    const a1 = n.map((c) => c / ln), a2 = cross(a0, a1);
    const R = [a0[0], a1[0], a2[0], a0[1], a1[1], a2[1], a0[2], a1[2], a2[2]]; // row-major, columns a0 a1 a2
    const sf = (l1 + Math.abs(dot(a2, e2))) / 2;
    let pos;
    if (rig.binding === "triangle") { // R_f (local_position s_f) + c_f
      const lp = [0, 1, 2].map((i) => rig.localPosition[3 * m + i] * sf);
      pos = [0, 1, 2].map((c) => R[3 * c] * lp[0] + R[3 * c + 1] * lp[1] + R[3 * c + 2] * lp[2]
        + (v0[c] + v1[c] + v2[c]) / 3);
    } else { // bary . (v0, v1, v2) + (e1 x e2) normal_offset
      const b = [0, 1, 2].map((i) => rig.bary[3 * m + i]), nrm = cross(e1, e2), k = rig.normalOffset[m];
      pos = [0, 1, 2].map((c) => b[0] * v0[c] + b[1] * v1[c] + b[2] * v2[c] + nrm[c] * k);
    }
    const [fw, fx, fy, fz] = matrixToQuaternion(R);
    let [lx, ly, lz, lw] = [0, 1, 2, 3].map((i) => rig.localRotation[4 * m + i]);
    const ll = Math.max(Math.hypot(lx, ly, lz, lw), 1e-12);
    [lx, ly, lz, lw] = [lx / ll, ly / ll, lz / ll, lw / ll];
    const q = [fw * lw - fx * lx - fy * ly - fz * lz, fw * lx + fx * lw + fy * lz - fz * ly,
      fw * ly - fx * lz + fy * lw + fz * lx, fw * lz + fx * ly - fy * lx + fz * lw];
    const ql = Math.hypot(...q), g = rig.index[m];
    position[3 * g] = mx * pos[0]; position[3 * g + 1] = pos[1]; position[3 * g + 2] = pos[2];
    rotation[4 * g] = q[1] / ql; rotation[4 * g + 1] = (mx * q[2]) / ql; rotation[4 * g + 2] = (mx * q[3]) / ql;
    rotation[4 * g + 3] = q[0] / ql;
    for (let c = 0; c < 3; c++) scale[3 * g + c] = rig.localScale[3 * m + c] * sf;
  }
  return rig.index;
}

// numbers per Gaussian (in face order): its point p (local_position or bary), w (1 or normal_offset), its normalised
// local rotation (w, x, y, z), local_scale
const GAUSSIAN = 11;

/**
 * The fast deformation of one rig (PROTOCOL.md 13.4; agrees with `deformRigReference` to ~1e-8 m): float32 bases,
 * float64 arithmetic, only the faces the Gaussians use and their vertices, the Gaussians grouped by face (each face's
 * frame computed once, then applied to its Gaussians). 2-4 ms per frame for the built-in avatar's rig here (2 shared
 * cores), most of it the 72,561 Gaussians of step 7.
 */
export class RigDeformer {
  constructor(rig) {
    this.rig = rig;
    const S = rig.vertices, E = rig.exprDims, P = rig.poseRows.length, M = rig.gaussians;
    const faceSlot = new Int32Array(rig.faces).fill(-1), vertSlot = new Int32Array(S).fill(-1);
    const faces = [], verts = [], used = new Int32Array(M); // used: the Gaussian's used face
    for (let m = 0; m < M; m++) {
      const f = rig.gaussianFace[m];
      if (faceSlot[f] < 0) { faceSlot[f] = faces.length; faces.push(f); }
      used[m] = faceSlot[f];
    }
    const F = faces.length;
    this.faceVerts = new Int32Array(3 * F); // the used face's corners, used-vertex ids
    for (let u = 0; u < F; u++) {
      for (let c = 0; c < 3; c++) {
        const s = rig.face[3 * faces[u] + c];
        if (vertSlot[s] < 0) { vertSlot[s] = verts.length; verts.push(s); }
        this.faceVerts[3 * u + c] = vertSlot[s];
      }
    }
    // the Gaussians grouped by used face: face u's are rows faceStart[u] .. faceStart[u + 1] - 1 of index / gaussian
    this.faceStart = new Int32Array(F + 1);
    for (let m = 0; m < M; m++) this.faceStart[used[m] + 1]++;
    for (let u = 0; u < F; u++) this.faceStart[u + 1] += this.faceStart[u];
    const next = this.faceStart.slice(0, F), order = new Int32Array(M);
    for (let m = 0; m < M; m++) order[next[used[m]]++] = m;
    const tri = rig.binding === "triangle", point = tri ? rig.localPosition : rig.bary;
    this.index = new Int32Array(M); // session Gaussian id, in face order
    this.gaussian = new Float64Array(GAUSSIAN * M);
    for (let j = 0; j < M; j++) {
      const m = order[j], o = GAUSSIAN * j, lq = rig.localRotation.subarray(4 * m, 4 * m + 4);
      const n = Math.max(Math.sqrt(lq[0] * lq[0] + lq[1] * lq[1] + lq[2] * lq[2] + lq[3] * lq[3]), 1e-12);
      this.index[j] = rig.index[m];
      this.gaussian.set(point.subarray(3 * m, 3 * m + 3), o);
      this.gaussian[o + 3] = tri ? 1 : rig.normalOffset[m];
      this.gaussian[o + 4] = lq[3] / n; this.gaussian[o + 5] = lq[0] / n;
      this.gaussian[o + 6] = lq[1] / n; this.gaussian[o + 7] = lq[2] / n;
      this.gaussian.set(rig.localScale.subarray(3 * m, 3 * m + 3), o + 8);
    }
    const V = verts.length, K = E + P;
    this.K = K;
    this.template = new Float32Array(3 * V);
    this.basis = new Float32Array(3 * K * V); // per used vertex: (expression components, then pose rows) x xyz
    this.weights = new Float64Array(4 * V); // w_0 + w_1 (A_0 = A_1 = [I | 0]), w_2, w_3, w_4
    for (let u = 0; u < V; u++) {
      const s = verts[u];
      this.template.set(rig.template.subarray(3 * s, 3 * s + 3), 3 * u);
      this.basis.set(rig.exprBasis.subarray(3 * E * s, 3 * E * (s + 1)), 3 * K * u);
      this.basis.set(rig.poseBasis.subarray(3 * P * s, 3 * P * (s + 1)), 3 * K * u + 3 * E);
      const w = rig.weights.subarray(JOINTS * s, JOINTS * (s + 1));
      this.weights[4 * u] = w[0] + w[1];
      this.weights[4 * u + 1] = w[2]; this.weights[4 * u + 2] = w[3]; this.weights[4 * u + 3] = w[4];
    }
    this.coef = new Float64Array(K);
    this.a = new Float64Array(JOINTS * 12);
    this.a2 = this.a.subarray(24); this.a3 = this.a.subarray(36); this.a4 = this.a.subarray(48);
    this.rot = new Float64Array(9);
    this.verts = new Float64Array(3 * V);
    this.usedVertices = V;
    this.usedFaces = F;
  }

  /** Steps 1-4 into this.a (A_k, 5 x 12) and this.coef (ψ, then c_p). */
  transforms(params) {
    const r = this.rig, E = r.exprDims, a = this.a, coef = this.coef;
    for (let e = 0; e < E; e++) coef[e] = params[e];
    a.fill(0);
    a[0] = a[5] = a[10] = a[12] = a[17] = a[22] = 1;
    for (let k = 2; k < JOINTS; k++) {
      const R = rot6d(params, 38 + 6 * k, this.rot); // 50, 56, 62
      let jx = r.joints[3 * k], jy = r.joints[3 * k + 1], jz = r.joints[3 * k + 2];
      const o = 3 * k * E;
      for (let e = 0; e < E; e++) {
        const w = params[e];
        jx += r.jointsExpr[o + e] * w; jy += r.jointsExpr[o + E + e] * w; jz += r.jointsExpr[o + 2 * E + e] * w;
      }
      for (let i = 0; i < 3; i++) {
        const b = 12 * k + 4 * i, R0 = R[3 * i], R1 = R[3 * i + 1], R2 = R[3 * i + 2];
        a[b] = R0; a[b + 1] = R1; a[b + 2] = R2;
        a[b + 3] = (i === 0 ? jx : i === 1 ? jy : jz) - (R0 * jx + R1 * jy + R2 * jz);
      }
    }
    for (let p = 0; p < r.poseRows.length; p++) {
      const row = r.poseRows[p], k = 1 + ((row / 9) | 0), i = ((row % 9) / 3) | 0, j = row % 3;
      coef[E + p] = a[12 * k + 4 * i + j] - (i === j ? 1 : 0);
    }
  }

  /** Steps 1-5 for the used vertices: params (68) -> this.verts (used vertices x 3, float64, metres). */
  vertices(params) {
    this.transforms(params);
    const V = this.usedVertices, K = this.K, B = this.basis, T0 = this.template, W = this.weights;
    const coef = this.coef, a2 = this.a2, a3 = this.a3, a4 = this.a4, out = this.verts;
    const K2 = K - (K % 2);
    let o = 0;
    for (let u = 0; u < V; u++) {
      let x = T0[3 * u], y = T0[3 * u + 1], z = T0[3 * u + 2], x1 = 0, y1 = 0, z1 = 0; // two sums: more ILP
      let c = 0;
      for (; c < K2; c += 2, o += 6) {
        const w = coef[c], w1 = coef[c + 1];
        x += B[o] * w; y += B[o + 1] * w; z += B[o + 2] * w;
        x1 += B[o + 3] * w1; y1 += B[o + 4] * w1; z1 += B[o + 5] * w1;
      }
      if (c < K) { const w = coef[c]; x += B[o] * w; y += B[o + 1] * w; z += B[o + 2] * w; o += 3; }
      x += x1; y += y1; z += z1;
      const wi = W[4 * u], w2 = W[4 * u + 1], w3 = W[4 * u + 2], w4 = W[4 * u + 3];
      for (let i = 0; i < 3; i++) {
        const b = 4 * i;
        const t0 = w2 * a2[b] + w3 * a3[b] + w4 * a4[b], t1 = w2 * a2[b + 1] + w3 * a3[b + 1] + w4 * a4[b + 1];
        const t2 = w2 * a2[b + 2] + w3 * a3[b + 2] + w4 * a4[b + 2];
        const t3 = w2 * a2[b + 3] + w3 * a3[b + 3] + w4 * a4[b + 3];
        out[3 * u + i] = t0 * x + t1 * y + t2 * z + t3 + wi * (i === 0 ? x : i === 1 ? y : z);
      }
    }
    return out;
  }

  /**
   * Steps 6-8: per used face its frame (step 6) and q_f = quat(R_f), then its Gaussians' position (3, m), rotation
   * (x, y, z, w) and scale (3, m) written at their session id into the session arrays, mirrored for `unity` (mx = -1).
   * A Gaussian's position is X p + t w with, per face, X = R_f s_f and t = c_f (`triangle`: p = local_position, w = 1)
   * or X = (v0 v1 v2) as columns and t = e1 x e2 (`barycentric`: p = bary, w = normal_offset).
   */
  gaussians(position, rotation, scale, mx) {
    const v = this.verts, fv = this.faceVerts, start = this.faceStart, G = this.gaussian, index = this.index;
    const tri = this.rig.binding === "triangle";
    for (let u = 0, F = this.usedFaces; u < F; u++) {
      const i0 = 3 * fv[3 * u], i1 = 3 * fv[3 * u + 1], i2 = 3 * fv[3 * u + 2];
      const v0x = v[i0], v0y = v[i0 + 1], v0z = v[i0 + 2], v1x = v[i1], v1y = v[i1 + 1], v1z = v[i1 + 2];
      const v2x = v[i2], v2y = v[i2 + 1], v2z = v[i2 + 2];
      const e1x = v1x - v0x, e1y = v1y - v0y, e1z = v1z - v0z, e2x = v2x - v0x, e2y = v2y - v0y, e2z = v2z - v0z;
      const l1 = Math.sqrt(Math.max(e1x * e1x + e1y * e1y + e1z * e1z, 1e-20));
      const a0x = e1x / l1, a0y = e1y / l1, a0z = e1z / l1;
      const nx = a0y * e2z - a0z * e2y, ny = a0z * e2x - a0x * e2z, nz = a0x * e2y - a0y * e2x;
      const ln = Math.sqrt(Math.max(nx * nx + ny * ny + nz * nz, 1e-20));
      const a1x = nx / ln, a1y = ny / ln, a1z = nz / ln;
      const a2x = a0y * a1z - a0z * a1y, a2y = a0z * a1x - a0x * a1z, a2z = a0x * a1y - a0y * a1x;
      const sf = (l1 + Math.abs(a2x * e2x + a2y * e2y + a2z * e2z)) / 2;
      // quat(R_f): R00 = a0x, R01 = a1x, R02 = a2x, R10 = a0y, R11 = a1y, R12 = a2y, R20 = a0z, R21 = a1z, R22 = a2z
      const tw = 1 + a0x + a1y + a2z, tx = 1 + a0x - a1y - a2z, ty = 1 - a0x + a1y - a2z, tz = 1 - a0x - a1y + a2z;
      let qw, qx, qy, qz;
      if (tw >= tx && tw >= ty && tw >= tz) { qw = tw; qx = a1z - a2y; qy = a2x - a0z; qz = a0y - a1x; }
      else if (tx >= ty && tx >= tz) { qw = a1z - a2y; qx = tx; qy = a0y + a1x; qz = a2x + a0z; }
      else if (ty >= tz) { qw = a2x - a0z; qx = a0y + a1x; qy = ty; qz = a1z + a2y; }
      else { qw = a0y - a1x; qx = a2x + a0z; qy = a1z + a2y; qz = tz; }
      const qn = (qw < 0 ? -1 : 1) / Math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
      const fw = qw * qn, fx = qx * qn, fy = qy * qn, fz = qz * qn;
      let x00, x01, x02, x10, x11, x12, x20, x21, x22, tx0, tx1, tx2;
      if (tri) {
        x00 = a0x * sf; x01 = a1x * sf; x02 = a2x * sf; x10 = a0y * sf; x11 = a1y * sf; x12 = a2y * sf;
        x20 = a0z * sf; x21 = a1z * sf; x22 = a2z * sf;
        tx0 = (v0x + v1x + v2x) / 3; tx1 = (v0y + v1y + v2y) / 3; tx2 = (v0z + v1z + v2z) / 3;
      } else {
        x00 = v0x; x01 = v1x; x02 = v2x; x10 = v0y; x11 = v1y; x12 = v2y; x20 = v0z; x21 = v1z; x22 = v2z;
        tx0 = e1y * e2z - e1z * e2y; tx1 = e1z * e2x - e1x * e2z; tx2 = e1x * e2y - e1y * e2x;
      }
      for (let j = start[u], o = GAUSSIAN * j, end = start[u + 1]; j < end; j++, o += GAUSSIAN) {
        const g = index[j], p0 = G[o], p1 = G[o + 1], p2 = G[o + 2], w = G[o + 3];
        position[3 * g] = mx * (x00 * p0 + x01 * p1 + x02 * p2 + tx0 * w);
        position[3 * g + 1] = x10 * p0 + x11 * p1 + x12 * p2 + tx1 * w;
        position[3 * g + 2] = x20 * p0 + x21 * p1 + x22 * p2 + tx2 * w;
        const lw = G[o + 4], lx = G[o + 5], ly = G[o + 6], lz = G[o + 7];
        const rw = fw * lw - fx * lx - fy * ly - fz * lz, rx = fw * lx + fx * lw + fy * lz - fz * ly;
        const ry = fw * ly - fx * lz + fy * lw + fz * lx, rz = fw * lz + fx * ly - fy * lx + fz * lw;
        const rn = 1 / Math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz);
        rotation[4 * g] = rx * rn; rotation[4 * g + 1] = mx * ry * rn; rotation[4 * g + 2] = mx * rz * rn;
        rotation[4 * g + 3] = rw * rn;
        scale[3 * g] = G[o + 8] * sf; scale[3 * g + 1] = G[o + 9] * sf; scale[3 * g + 2] = G[o + 10] * sf;
      }
    }
  }

  /**
   * Steps 1-8: write Gaussian index[m]'s position (3, m), rotation (x, y, z, w) and scale (3, m) into the session
   * arrays, mirrored for `unity` coordinates. Returns the rig's index (the Gaussians it changed).
   */
  apply(params, position, rotation, scale, coords = "flame") {
    this.vertices(params);
    this.gaussians(position, rotation, scale, coords === "unity" ? -1 : 1);
    return this.rig.index;
  }
}
