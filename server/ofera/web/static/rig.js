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
      pos = [0, 1, 2].map((c) => R[3 * c] * lp[0] + R[3 * c + 1] * lp[1] + R[3 * c + 2] * lp[2] + (v0[c] + v1[c] + v2[c]) / 3);
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

const FACE = 17; // per used face: R_f s_f (9, row-major) or v0 v1 v2 (9), then c_f or e1 x e2 (3), q_f (w x y z), s_f

/**
 * The fast deformation of one rig (PROTOCOL.md 13.4; agrees with `deformRigReference` to ~1e-8 m): float32 bases,
 * float64 arithmetic, only the faces the Gaussians use and their vertices. ~1 ms for the built-in avatar's rig.
 */
export class RigDeformer {
  constructor(rig) {
    this.rig = rig;
    const S = rig.vertices, E = rig.exprDims, P = rig.poseRows.length, M = rig.gaussians;
    const faceSlot = new Int32Array(rig.faces).fill(-1), vertSlot = new Int32Array(S).fill(-1);
    const faces = [], verts = [];
    this.gaussianFace = new Int32Array(M); // the Gaussian's used face
    this.index = Int32Array.from(rig.index); // int32 loads are cheaper than uint32 ones in V8's optimised loops
    for (let m = 0; m < M; m++) {
      const f = rig.gaussianFace[m];
      if (faceSlot[f] < 0) { faceSlot[f] = faces.length; faces.push(f); }
      this.gaussianFace[m] = faceSlot[f];
    }
    this.faceVerts = new Int32Array(3 * faces.length); // the used face's corners, used-vertex ids
    for (let u = 0; u < faces.length; u++) {
      for (let c = 0; c < 3; c++) {
        const s = rig.face[3 * faces[u] + c];
        if (vertSlot[s] < 0) { vertSlot[s] = verts.length; verts.push(s); }
        this.faceVerts[3 * u + c] = vertSlot[s];
      }
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
    this.localRotation = new Float64Array(4 * M); // normalised, (w, x, y, z)
    for (let m = 0; m < M; m++) {
      const x = rig.localRotation[4 * m], y = rig.localRotation[4 * m + 1], z = rig.localRotation[4 * m + 2];
      const w = rig.localRotation[4 * m + 3], n = Math.max(Math.sqrt(x * x + y * y + z * z + w * w), 1e-12);
      this.localRotation[4 * m] = w / n; this.localRotation[4 * m + 1] = x / n;
      this.localRotation[4 * m + 2] = y / n; this.localRotation[4 * m + 3] = z / n;
    }
    this.coef = new Float64Array(K);
    this.a = new Float64Array(JOINTS * 12);
    this.a2 = this.a.subarray(24); this.a3 = this.a.subarray(36); this.a4 = this.a.subarray(48);
    this.rot = new Float64Array(9);
    this.verts = new Float64Array(3 * V);
    this.face = new Float64Array(FACE * faces.length);
    this.usedVertices = V;
    this.usedFaces = faces.length;
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
    let o = 0;
    for (let u = 0; u < V; u++) {
      let x = T0[3 * u], y = T0[3 * u + 1], z = T0[3 * u + 2];
      for (let c = 0; c < K; c++, o += 3) {
        const w = coef[c];
        x += B[o] * w; y += B[o + 1] * w; z += B[o + 2] * w;
      }
      const wi = W[4 * u], w2 = W[4 * u + 1], w3 = W[4 * u + 2], w4 = W[4 * u + 3];
      for (let i = 0; i < 3; i++) {
        const b = 4 * i;
        const t0 = w2 * a2[b] + w3 * a3[b] + w4 * a4[b], t1 = w2 * a2[b + 1] + w3 * a3[b + 1] + w4 * a4[b + 1];
        const t2 = w2 * a2[b + 2] + w3 * a3[b + 2] + w4 * a4[b + 2], t3 = w2 * a2[b + 3] + w3 * a3[b + 3] + w4 * a4[b + 3];
        out[3 * u + i] = t0 * x + t1 * y + t2 * z + t3 + wi * (i === 0 ? x : i === 1 ? y : z);
      }
    }
    return out;
  }

  /** Step 6 and quat(R_f) of step 7, once per used face, into this.face (FACE numbers each). */
  frames() {
    const v = this.verts, fv = this.faceVerts, F = this.face, tri = this.rig.binding === "triangle";
    for (let u = 0, o = 0; u < this.usedFaces; u++, o += FACE) {
      const i0 = 3 * fv[3 * u], i1 = 3 * fv[3 * u + 1], i2 = 3 * fv[3 * u + 2];
      const v0x = v[i0], v0y = v[i0 + 1], v0z = v[i0 + 2];
      const e1x = v[i1] - v0x, e1y = v[i1 + 1] - v0y, e1z = v[i1 + 2] - v0z;
      const e2x = v[i2] - v0x, e2y = v[i2 + 1] - v0y, e2z = v[i2 + 2] - v0z;
      const l1 = Math.sqrt(Math.max(e1x * e1x + e1y * e1y + e1z * e1z, 1e-20));
      const a0x = e1x / l1, a0y = e1y / l1, a0z = e1z / l1;
      const nx = a0y * e2z - a0z * e2y, ny = a0z * e2x - a0x * e2z, nz = a0x * e2y - a0y * e2x;
      const ln = Math.sqrt(Math.max(nx * nx + ny * ny + nz * nz, 1e-20));
      const a1x = nx / ln, a1y = ny / ln, a1z = nz / ln;
      const a2x = a0y * a1z - a0z * a1y, a2y = a0z * a1x - a0x * a1z, a2z = a0x * a1y - a0y * a1x;
      const sf = (l1 + Math.abs(a2x * e2x + a2y * e2y + a2z * e2z)) / 2;
      if (tri) { // R_f s_f (row-major: R_f's columns are a0 a1 a2) and c_f
        F[o] = a0x * sf; F[o + 1] = a1x * sf; F[o + 2] = a2x * sf;
        F[o + 3] = a0y * sf; F[o + 4] = a1y * sf; F[o + 5] = a2y * sf;
        F[o + 6] = a0z * sf; F[o + 7] = a1z * sf; F[o + 8] = a2z * sf;
        F[o + 9] = (v0x + v[i1] + v[i2]) / 3; F[o + 10] = (v0y + v[i1 + 1] + v[i2 + 1]) / 3;
        F[o + 11] = (v0z + v[i1 + 2] + v[i2 + 2]) / 3;
      } else { // v0 v1 v2 and e1 x e2
        F[o] = v0x; F[o + 1] = v0y; F[o + 2] = v0z; F[o + 3] = v[i1]; F[o + 4] = v[i1 + 1]; F[o + 5] = v[i1 + 2];
        F[o + 6] = v[i2]; F[o + 7] = v[i2 + 1]; F[o + 8] = v[i2 + 2];
        F[o + 9] = e1y * e2z - e1z * e2y; F[o + 10] = e1z * e2x - e1x * e2z; F[o + 11] = e1x * e2y - e1y * e2x;
      }
      const tw = 1 + a0x + a1y + a2z, tx = 1 + a0x - a1y - a2z, ty = 1 - a0x + a1y - a2z, tz = 1 - a0x - a1y + a2z;
      let qw, qx, qy, qz; // R00 = a0x, R01 = a1x, R02 = a2x, R10 = a0y, R11 = a1y, R12 = a2y, R20 = a0z, R21 = a1z, R22 = a2z
      if (tw >= tx && tw >= ty && tw >= tz) { qw = tw; qx = a1z - a2y; qy = a2x - a0z; qz = a0y - a1x; }
      else if (tx >= ty && tx >= tz) { qw = a1z - a2y; qx = tx; qy = a0y + a1x; qz = a2x + a0z; }
      else if (ty >= tz) { qw = a2x - a0z; qx = a0y + a1x; qy = ty; qz = a1z + a2y; }
      else { qw = a0y - a1x; qx = a2x + a0z; qy = a1z + a2y; qz = tz; }
      const n = (qw < 0 ? -1 : 1) / Math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
      F[o + 12] = qw * n; F[o + 13] = qx * n; F[o + 14] = qy * n; F[o + 15] = qz * n; F[o + 16] = sf;
    }
  }

  /** Step 7's position of a `triangle` rig's Gaussians (R_f s_f local + c_f), then rotation and scale. */
  triangleGaussians(position, rotation, scale, mx) {
    const F = this.face, gf = this.gaussianFace, LP = this.rig.localPosition, index = this.index;
    for (let m = 0, M = gf.length; m < M; m++) {
      const o = FACE * gf[m], g = index[m], p0 = LP[3 * m], p1 = LP[3 * m + 1], p2 = LP[3 * m + 2];
      position[3 * g] = mx * (F[o] * p0 + F[o + 1] * p1 + F[o + 2] * p2 + F[o + 9]);
      position[3 * g + 1] = F[o + 3] * p0 + F[o + 4] * p1 + F[o + 5] * p2 + F[o + 10];
      position[3 * g + 2] = F[o + 6] * p0 + F[o + 7] * p1 + F[o + 8] * p2 + F[o + 11];
    }
    this.rotationsAndScales(rotation, scale, mx);
  }

  /** Step 7's position of a `barycentric` rig's Gaussians (bary . (v0, v1, v2) + (e1 x e2) offset), then the rest. */
  barycentricGaussians(position, rotation, scale, mx) {
    const F = this.face, gf = this.gaussianFace, B = this.rig.bary, K = this.rig.normalOffset, index = this.index;
    for (let m = 0, M = gf.length; m < M; m++) {
      const o = FACE * gf[m], g = index[m], b0 = B[3 * m], b1 = B[3 * m + 1], b2 = B[3 * m + 2], k = K[m];
      position[3 * g] = mx * (b0 * F[o] + b1 * F[o + 3] + b2 * F[o + 6] + F[o + 9] * k);
      position[3 * g + 1] = b0 * F[o + 1] + b1 * F[o + 4] + b2 * F[o + 7] + F[o + 10] * k;
      position[3 * g + 2] = b0 * F[o + 2] + b1 * F[o + 5] + b2 * F[o + 8] + F[o + 11] * k;
    }
    this.rotationsAndScales(rotation, scale, mx);
  }

  /** Step 7's rotation (normalize(q_f (x) local rotation), written (x, y, z, w)) and scale (local_scale s_f). */
  rotationsAndScales(rotation, scale, mx) {
    const F = this.face, gf = this.gaussianFace, LQ = this.localRotation, LS = this.rig.localScale;
    const index = this.index;
    for (let m = 0, M = gf.length; m < M; m++) {
      const o = FACE * gf[m], g = index[m];
      const fw = F[o + 12], fx = F[o + 13], fy = F[o + 14], fz = F[o + 15], sf = F[o + 16];
      const lw = LQ[4 * m], lx = LQ[4 * m + 1], ly = LQ[4 * m + 2], lz = LQ[4 * m + 3];
      const qw = fw * lw - fx * lx - fy * ly - fz * lz, qx = fw * lx + fx * lw + fy * lz - fz * ly;
      const qy = fw * ly - fx * lz + fy * lw + fz * lx, qz = fw * lz + fx * ly - fy * lx + fz * lw;
      const n = 1 / Math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
      rotation[4 * g] = qx * n; rotation[4 * g + 1] = mx * qy * n; rotation[4 * g + 2] = mx * qz * n; rotation[4 * g + 3] = qw * n;
      scale[3 * g] = LS[3 * m] * sf; scale[3 * g + 1] = LS[3 * m + 1] * sf; scale[3 * g + 2] = LS[3 * m + 2] * sf;
    }
  }

  /**
   * Steps 1-8: write Gaussian index[m]'s position (3, m), rotation (x, y, z, w) and scale (3, m) into the session
   * arrays, mirrored for `unity` coordinates. Returns the rig's index (the Gaussians it changed).
   */
  apply(params, position, rotation, scale, coords = "flame") {
    this.vertices(params);
    this.frames();
    const r = this.rig, mx = coords === "unity" ? -1 : 1;
    if (r.binding === "triangle") this.triangleGaussians(position, rotation, scale, mx);
    else this.barycentricGaussians(position, rotation, scale, mx);
    return r.index;
  }
}
