// The page's worker: keeps the session's Gaussians (avatar chunks and frames are decoded here, off the
// main thread), and for each view prepares the splats to draw: the 3D covariance R S S^T R^T (cached,
// recomputed for the Gaussians a frame moves), its projection to a 2D covariance J W Sigma W^T J^T
// (+0.3 px^2 low-pass), the ellipse axes (eigenvectors scaled by sqrt(2 lambda)), culling (behind the
// camera, off screen, transparent), and a 16-bit counting sort of depths, farthest first.
//
// main -> worker: {kind: "welcome", gen, welcome} | {kind: "chunk" | "rig" | "frame", gen, buffer}
//                 | {kind: "prep", gen, id, view, proj, width, height, scaleMul, buffer?} | {kind: "dump", gen, id}
// worker -> main: {kind: "avatar", gen, count, lo, hi} | {kind: "error", gen, fatal, code, message}
//                 | {kind: "prepared", gen, id, seq, count, buffer} | {kind: "rig", gen, gaussians, bytes}
//                 | {kind: "dump", gen, id, seq, position, rotation, scale} (copies of the Gaussians, for tests)
// A params session (PROTOCOL.md 13): `rig` chunks follow the avatar's; each frame's 68 values are deformed here
// (rig.js), into the same arrays dense and sparse frames update.
import { AvatarState, decodeServerMessage, PARAMS, ProtocolError } from "./protocol.js";
import { decodeRig, RigAssembler, RigDeformer } from "./rig.js";

const WORDS = 7; // per visible splat while sorting: centre x, y; axis 1 x, y; axis 2 x, y (NDC); RGBA8 colour
const OUT_WORDS = 12; // per splat drawn: 4 corners of (x, y, RGBA8), see renderer.js
let gen = -1;
let state = null;
let cov = null; // 6 per Gaussian: s00 s01 s02 s11 s12 s22
let seq = -1;
let rigParts = null, rig = null; // params sessions: the rig's chunks while they arrive, then its RigDeformer
let scratch = null, depth = null, keys = null;
const counts = new Uint32Array(65536);

function covariance(first, n, index) {
  const Q = state.rotation, S = state.scale;
  for (let k = first; k < first + n; k++) {
    const i = index ? index[k] : k;
    let x = Q[4 * i], y = Q[4 * i + 1], z = Q[4 * i + 2], w = Q[4 * i + 3];
    const l = Math.hypot(x, y, z, w) || 1;
    x /= l; y /= l; z /= l; w /= l;
    const sx = S[3 * i], sy = S[3 * i + 1], sz = S[3 * i + 2];
    // M = R diag(s), rows of M:
    const m00 = (1 - 2 * (y * y + z * z)) * sx, m01 = 2 * (x * y - w * z) * sy, m02 = 2 * (x * z + w * y) * sz;
    const m10 = 2 * (x * y + w * z) * sx, m11 = (1 - 2 * (x * x + z * z)) * sy, m12 = 2 * (y * z - w * x) * sz;
    const m20 = 2 * (x * z - w * y) * sx, m21 = 2 * (y * z + w * x) * sy, m22 = (1 - 2 * (x * x + y * y)) * sz;
    const o = 6 * i;
    cov[o] = m00 * m00 + m01 * m01 + m02 * m02;
    cov[o + 1] = m00 * m10 + m01 * m11 + m02 * m12;
    cov[o + 2] = m00 * m20 + m01 * m21 + m02 * m22;
    cov[o + 3] = m10 * m10 + m11 * m11 + m12 * m12;
    cov[o + 4] = m10 * m20 + m11 * m21 + m12 * m22;
    cov[o + 5] = m20 * m20 + m21 * m21 + m22 * m22;
  }
}

function prepare({ view: V, proj: P, width, height, scaleMul, buffer }) {
  const n = state.count;
  if (!scratch || scratch.length < n * WORDS) {
    scratch = new Float32Array(n * WORDS);
    depth = new Float32Array(n);
    keys = new Uint16Array(n);
  }
  const scratchU = new Uint32Array(scratch.buffer);
  const colors = new Uint32Array(state.color.buffer, 0, n);
  const pos = state.position;
  const fx = (P[0] * width) / 2, fy = (P[5] * height) / 2;
  const sx = 2 / width, sy = 2 / height;
  const mul2 = scaleMul * scaleMul;
  const near = 1e-3;
  let m = 0, lo = Infinity, hi = -Infinity;
  for (let i = 0; i < n; i++) {
    if ((colors[i] >>> 24) < 1) continue; // opacity below 1/255 (RGBA8 little-endian: alpha is the top byte)
    const x = pos[3 * i], y = pos[3 * i + 1], z = pos[3 * i + 2];
    const cx = V[0] * x + V[4] * y + V[8] * z + V[12];
    const cy = V[1] * x + V[5] * y + V[9] * z + V[13];
    const tz = -(V[2] * x + V[6] * y + V[10] * z + V[14]);
    if (tz < near) continue;
    const nx = (P[0] * cx) / tz, ny = (P[5] * cy) / tz;
    if (nx < -1.3 || nx > 1.3 || ny < -1.3 || ny > 1.3) continue;
    // T = J W: rows t0 = j0 W, t1 = j1 W with j0 = (fx/tz, 0, fx cx/tz^2), j1 = (0, fy/tz, fy cy/tz^2)
    const a0 = fx / tz, a2 = (fx * cx) / (tz * tz), b1 = fy / tz, b2 = (fy * cy) / (tz * tz);
    const t00 = a0 * V[0] + a2 * V[2], t01 = a0 * V[4] + a2 * V[6], t02 = a0 * V[8] + a2 * V[10];
    const t10 = b1 * V[1] + b2 * V[2], t11 = b1 * V[5] + b2 * V[6], t12 = b1 * V[9] + b2 * V[10];
    const o = 6 * i;
    const s00 = cov[o] * mul2, s01 = cov[o + 1] * mul2, s02 = cov[o + 2] * mul2;
    const s11 = cov[o + 3] * mul2, s12 = cov[o + 4] * mul2, s22 = cov[o + 5] * mul2;
    const u0 = s00 * t10 + s01 * t11 + s02 * t12; // Sigma t1
    const u1 = s01 * t10 + s11 * t11 + s12 * t12;
    const u2 = s02 * t10 + s12 * t11 + s22 * t12;
    const a = t00 * (s00 * t00 + s01 * t01 + s02 * t02) + t01 * (s01 * t00 + s11 * t01 + s12 * t02)
      + t02 * (s02 * t00 + s12 * t01 + s22 * t02) + 0.3;
    const b = t00 * u0 + t01 * u1 + t02 * u2;
    const c = t10 * u0 + t11 * u1 + t12 * u2 + 0.3;
    const mid = 0.5 * (a + c);
    const rad = Math.hypot(0.5 * (a - c), b);
    const l1 = mid + rad, l2 = Math.max(mid - rad, 0.1);
    let dx = b, dy = l1 - a;
    const dl = Math.hypot(dx, dy);
    if (dl < 1e-9) { dx = 1; dy = 0; } else { dx /= dl; dy /= dl; }
    const r1 = Math.min(Math.sqrt(2 * l1), 1024), r2 = Math.min(Math.sqrt(2 * l2), 1024);
    const w = WORDS * m;
    scratch[w] = nx;
    scratch[w + 1] = ny;
    scratch[w + 2] = r1 * dx * sx;
    scratch[w + 3] = r1 * dy * sy;
    scratch[w + 4] = r2 * dy * sx;
    scratch[w + 5] = -r2 * dx * sy;
    scratchU[w + 6] = colors[i];
    depth[m] = tz;
    if (tz < lo) lo = tz;
    if (tz > hi) hi = tz;
    m++;
  }
  // Counting sort on 16-bit keys, farthest (largest tz) first.
  const scale = hi > lo ? 65535 / (hi - lo) : 0;
  counts.fill(0);
  for (let k = 0; k < m; k++) {
    const key = ((hi - depth[k]) * scale) | 0;
    keys[k] = key;
    counts[key]++;
  }
  let sum = 0;
  for (let k = 0; k < 65536; k++) { const c0 = counts[k]; counts[k] = sum; sum += c0; }
  const bytes = m * OUT_WORDS * 4;
  const out = buffer && buffer.byteLength >= bytes ? buffer : new ArrayBuffer(Math.max(bytes, 4));
  const outF = new Float32Array(out, 0, m * OUT_WORDS);
  const outU = new Uint32Array(out, 0, m * OUT_WORDS);
  for (let k = 0; k < m; k++) {
    const d = OUT_WORDS * counts[keys[k]]++;
    const s = WORDS * k;
    const x = scratch[s], y = scratch[s + 1], ax = scratch[s + 2], ay = scratch[s + 3], bx = scratch[s + 4], by = scratch[s + 5];
    const col = scratchU[s + 6];
    // corners (-2,-2), (2,-2), (-2,2), (2,2) in the (axis 1, axis 2) frame
    outF[d] = x - 2 * ax - 2 * bx; outF[d + 1] = y - 2 * ay - 2 * by; outU[d + 2] = col;
    outF[d + 3] = x + 2 * ax - 2 * bx; outF[d + 4] = y + 2 * ay - 2 * by; outU[d + 5] = col;
    outF[d + 6] = x - 2 * ax + 2 * bx; outF[d + 7] = y - 2 * ay + 2 * by; outU[d + 8] = col;
    outF[d + 9] = x + 2 * ax + 2 * bx; outF[d + 10] = y + 2 * ay + 2 * by; outU[d + 11] = col;
  }
  return { out, count: m };
}

function fail(e, fatal) {
  self.postMessage({ kind: "error", gen, fatal, code: e.code ?? "internal", message: e.message });
}

self.onmessage = ({ data }) => {
  if (data.kind === "welcome") {
    gen = data.gen;
    state = new AvatarState(data.welcome);
    cov = new Float32Array(state.count * 6);
    seq = -1;
    rig = null;
    rigParts = data.welcome.encoding === PARAMS ? new RigAssembler(data.welcome.rigBytes ?? null) : null;
    return;
  }
  if (data.kind === "prep" && (data.gen !== gen || !state?.complete)) { // always answered
    self.postMessage({ kind: "prepared", gen: data.gen, id: data.id, seq: -1, count: 0, stale: true });
    return;
  }
  if (data.gen !== gen || !state) return; // from an older connection
  if (data.kind === "chunk") {
    try {
      const c = decodeServerMessage(new Uint8Array(data.buffer));
      const first = state.received;
      const done = state.applyChunk(c);
      covariance(first, c.n, null);
      if (done) {
        const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
        for (let i = 0; i < state.count; i++) {
          for (let k = 0; k < 3; k++) {
            const v = state.position[3 * i + k];
            if (v < lo[k]) lo[k] = v;
            if (v > hi[k]) hi[k] = v;
          }
        }
        self.postMessage({ kind: "avatar", gen, count: state.count, lo, hi });
      }
    } catch (e) {
      fail(e, true);
    }
  } else if (data.kind === "rig") {
    try {
      const c = decodeServerMessage(new Uint8Array(data.buffer));
      if (c.type !== "rig" || !rigParts || !state.complete) throw new ProtocolError("not_ready", "a rig chunk outside a params session's handshake");
      if (rigParts.add(c)) {
        const body = rigParts.result();
        const r = decodeRig(body);
        if (r.count !== state.count) throw new ProtocolError("bad_field", `rig for ${r.count} Gaussians, the avatar has ${state.count}`);
        rig = new RigDeformer(r);
        rigParts = null;
        self.postMessage({ kind: "rig", gen, gaussians: r.gaussians, bytes: body.length });
      }
    } catch (e) {
      fail(e, true);
    }
  } else if (data.kind === "frame") {
    try {
      const f = decodeServerMessage(new Uint8Array(data.buffer));
      let changed;
      if (f.params !== undefined) { // params: the client deforms (the rig's Gaussians; the rest stay as sent)
        if (!rig) throw new ProtocolError("not_ready", "a params frame before the rig was complete");
        changed = rig.apply(f.params, state.position, state.rotation, state.scale, state.welcome.coords);
      } else {
        changed = state.applyFrame(f); // the Gaussians it moved (sparse and delta frames), null: all
      }
      if (changed) covariance(0, changed.length, changed);
      else covariance(0, state.count, null);
      seq = f.seq ?? seq + 1; // an unstamped params frame answers the next bs (the page sends one at a time)
    } catch (e) {
      fail(e, false); // a bad frame is dropped; the session goes on (a delta session: the page sends resync)
    }
  } else if (data.kind === "dump") {
    self.postMessage({ kind: "dump", gen, id: data.id, seq, position: state.position.slice(0, 3 * state.count),
      rotation: state.rotation.slice(0, 4 * state.count), scale: state.scale.slice(0, 3 * state.count) });
  } else if (data.kind === "prep") {
    const { out, count } = prepare(data);
    self.postMessage({ kind: "prepared", gen, id: data.id, seq, count, buffer: out }, [out]);
  }
};
