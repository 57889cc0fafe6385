// Expression streaming (PROTOCOL.md 13) in the browser: the rig body (assembled from `rig` messages, decoded and
// checked), and the client-side deformation of 13.4: params (68 float32) -> the rig's Gaussians, written into the
// session's position / rotation / scale arrays (in the session's coordinates). Plain JavaScript numbers (float64)
// inside; the results go to Float32Arrays, so they match `ofera_protocol.rig.deform_rig` to float32 rounding.
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

/** 6D (two rows) at p[o..o+6) -> row-major 3x3 (PROTOCOL.md 13.4 step 2). */
function rot6d(p, o) {
  const a1x = p[o], a1y = p[o + 1], a1z = p[o + 2], a2x = p[o + 3], a2y = p[o + 4], a2z = p[o + 5];
  let n = Math.max(Math.hypot(a1x, a1y, a1z), 1e-12);
  const b1x = a1x / n, b1y = a1y / n, b1z = a1z / n;
  const d = b1x * a2x + b1y * a2y + b1z * a2z;
  const cx = a2x - d * b1x, cy = a2y - d * b1y, cz = a2z - d * b1z;
  n = Math.max(Math.hypot(cx, cy, cz), 1e-12);
  const b2x = cx / n, b2y = cy / n, b2z = cz / n;
  return [b1x, b1y, b1z, b2x, b2y, b2z, b1y * b2z - b1z * b2y, b1z * b2x - b1x * b2z, b1x * b2y - b1y * b2x];
}

const IDENTITY = [1, 0, 0, 0, 1, 0, 0, 0, 1];

/** The client-side deformation of one rig (PROTOCOL.md 13.4). */
export class RigDeformer {
  constructor(rig) {
    this.rig = rig;
    this.verts = new Float64Array(rig.vertices * 3);
    this.coef = new Float64Array(rig.poseRows.length);
    this.a = new Float64Array(JOINTS * 12); // A_k, 3 x 4 row-major
  }

  /** Steps 1-5: params (68) -> this.verts (S x 3, float64). */
  vertices(params) {
    const r = this.rig, E = r.exprDims, S = r.vertices, P = r.poseRows.length;
    const rot = [IDENTITY, IDENTITY, rot6d(params, 50), rot6d(params, 56), rot6d(params, 62)];
    const a = this.a;
    for (let k = 0; k < JOINTS; k++) {
      const R = rot[k], j = [0, 0, 0];
      for (let c = 0; c < 3; c++) {
        let s = r.joints[3 * k + c];
        for (let e = 0; e < E; e++) s += r.jointsExpr[(3 * k + c) * E + e] * params[e];
        j[c] = s;
      }
      for (let i = 0; i < 3; i++) {
        a[12 * k + 4 * i] = R[3 * i]; a[12 * k + 4 * i + 1] = R[3 * i + 1]; a[12 * k + 4 * i + 2] = R[3 * i + 2];
        a[12 * k + 4 * i + 3] = j[i] - (R[3 * i] * j[0] + R[3 * i + 1] * j[1] + R[3 * i + 2] * j[2]);
      }
    }
    for (let p = 0; p < P; p++) {
      const row = r.poseRows[p], k = 1 + Math.floor(row / 9), i = Math.floor((row % 9) / 3), j = row % 3;
      this.coef[p] = rot[k][3 * i + j] - (i === j ? 1 : 0);
    }
    const v = this.verts, T = new Float64Array(12);
    for (let s = 0; s < S; s++) {
      let x = r.template[3 * s], y = r.template[3 * s + 1], z = r.template[3 * s + 2];
      const eb = s * E * 3;
      for (let e = 0; e < E; e++) {
        const w = params[e];
        if (w !== 0) { x += r.exprBasis[eb + 3 * e] * w; y += r.exprBasis[eb + 3 * e + 1] * w; z += r.exprBasis[eb + 3 * e + 2] * w; }
      }
      const pb = s * P * 3;
      for (let p = 0; p < P; p++) {
        const c = this.coef[p];
        x += r.poseBasis[pb + 3 * p] * c; y += r.poseBasis[pb + 3 * p + 1] * c; z += r.poseBasis[pb + 3 * p + 2] * c;
      }
      T.fill(0);
      for (let k = 0; k < JOINTS; k++) {
        const w = r.weights[JOINTS * s + k];
        if (w !== 0) for (let q = 0; q < 12; q++) T[q] += w * a[12 * k + q];
      }
      v[3 * s] = T[0] * x + T[1] * y + T[2] * z + T[3];
      v[3 * s + 1] = T[4] * x + T[5] * y + T[6] * z + T[7];
      v[3 * s + 2] = T[8] * x + T[9] * y + T[10] * z + T[11];
    }
    return v;
  }

  /**
   * Steps 6-8: write Gaussian index[m]'s position (3), rotation (x, y, z, w) and scale (3) into the session arrays,
   * mirrored for `unity` coordinates. Returns the rig's index (the Gaussians it changed).
   */
  apply(params, position, rotation, scale, coords = "flame") {
    const r = this.rig, v = this.vertices(params), tri = r.binding === "triangle";
    const mx = coords === "unity" ? -1 : 1;
    for (let m = 0; m < r.gaussians; m++) {
      const f = 3 * r.gaussianFace[m];
      const i0 = 3 * r.face[f], i1 = 3 * r.face[f + 1], i2 = 3 * r.face[f + 2];
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
      let px, py, pz;
      if (tri) {
        const lx = r.localPosition[3 * m] * sf, ly = r.localPosition[3 * m + 1] * sf, lz = r.localPosition[3 * m + 2] * sf;
        px = a0x * lx + a1x * ly + a2x * lz + (v0x + v[i1] + v[i2]) / 3;
        py = a0y * lx + a1y * ly + a2y * lz + (v0y + v[i1 + 1] + v[i2 + 1]) / 3;
        pz = a0z * lx + a1z * ly + a2z * lz + (v0z + v[i1 + 2] + v[i2 + 2]) / 3;
      } else {
        const b0 = r.bary[3 * m], b1 = r.bary[3 * m + 1], b2 = r.bary[3 * m + 2], k = r.normalOffset[m];
        px = b0 * v0x + b1 * v[i1] + b2 * v[i2] + (e1y * e2z - e1z * e2y) * k;
        py = b0 * v0y + b1 * v[i1 + 1] + b2 * v[i2 + 1] + (e1z * e2x - e1x * e2z) * k;
        pz = b0 * v0z + b1 * v[i1 + 2] + b2 * v[i2 + 2] + (e1x * e2y - e1y * e2x) * k;
      }
      // quat(R_f), R_f columns a0 a1 a2: R00 = a0x, R01 = a1x, R02 = a2x, R10 = a0y, ...
      const R00 = a0x, R01 = a1x, R02 = a2x, R10 = a0y, R11 = a1y, R12 = a2y, R20 = a0z, R21 = a1z, R22 = a2z;
      const t = [1 + R00 + R11 + R22, 1 + R00 - R11 - R22, 1 - R00 + R11 - R22, 1 - R00 - R11 + R22];
      let b = 0;
      for (let q = 1; q < 4; q++) if (t[q] > t[b]) b = q;
      let q = b === 0 ? [t[0], R21 - R12, R02 - R20, R10 - R01]
        : b === 1 ? [R21 - R12, t[1], R10 + R01, R02 + R20]
          : b === 2 ? [R02 - R20, R10 + R01, t[2], R21 + R12] : [R10 - R01, R02 + R20, R21 + R12, t[3]];
      let ql = Math.hypot(q[0], q[1], q[2], q[3]);
      if (q[0] < 0) ql = -ql;
      const fw = q[0] / ql, fx = q[1] / ql, fy = q[2] / ql, fz = q[3] / ql;
      let lx = r.localRotation[4 * m], ly = r.localRotation[4 * m + 1], lz = r.localRotation[4 * m + 2], lw = r.localRotation[4 * m + 3];
      const ll = Math.max(Math.hypot(lx, ly, lz, lw), 1e-12);
      lx /= ll; ly /= ll; lz /= ll; lw /= ll;
      q = [fw * lw - fx * lx - fy * ly - fz * lz, fw * lx + fx * lw + fy * lz - fz * ly,
        fw * ly - fx * lz + fy * lw + fz * lx, fw * lz + fx * ly - fy * lx + fz * lw];
      ql = Math.hypot(q[0], q[1], q[2], q[3]);
      const g = r.index[m];
      position[3 * g] = mx * px; position[3 * g + 1] = py; position[3 * g + 2] = pz;
      rotation[4 * g] = q[1] / ql; rotation[4 * g + 1] = (mx * q[2]) / ql; rotation[4 * g + 2] = (mx * q[3]) / ql;
      rotation[4 * g + 3] = q[0] / ql;
      scale[3 * g] = r.localScale[3 * m] * sf; scale[3 * g + 1] = r.localScale[3 * m + 1] * sf; scale[3 * g + 2] = r.localScale[3 * m + 2] * sf;
    }
    return r.index;
  }
}
