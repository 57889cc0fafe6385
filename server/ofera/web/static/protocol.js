// The client side of the OFERA protocol v1 (PROTOCOL.md): message builders, server message checks,
// and the Gaussian state a client keeps (avatar chunks, then dense or sparse frames in f32/f16/q13, or the
// key and delta frames of a delta session, section 7.1).
import { decode, encode, MsgpackError } from "./msgpack.js";

export const PROTOCOL = 1;
export const ENDPOINT = "/v1/stream";
export const ENCODINGS = ["f32", "f16", "q13"];
/** Expression streaming (section 13): frames carry PARAMS_LENGTH float32 values, the client deforms with the rig. */
export const PARAMS = "params";
export const PARAMS_LENGTH = 68;
/** Bytes per Gaussian of position, rotation, scale in each frame encoding (section 6). */
export const FIELD_BYTES = { f32: [12, 16, 12], f16: [6, 8, 6], q13: [6, 4, 3] };
/** Close codes of the errors this client finds in what it receives (section 10; tests check them against tables.json). */
export const CLOSE_CODES = { malformed: 4000, unknown_type: 4001, bad_field: 4002, bad_length: 4003, non_finite: 4004, not_ready: 4005 };
/** Close code of a fatal error code this client does not know (section 10). */
export const CLOSE_UNKNOWN_FATAL = 4000;
export const SH_C0 = 0.28209479;

export class ProtocolError extends Error {
  constructor(code, message) {
    super(`${code}: ${message}`);
    this.code = code;
    this.detail = message;
  }
}

/** The client clock put in `bs.t` and `ping.t`: microseconds (integer, exact in a double). */
export function nowUs() {
  return Math.round((performance.timeOrigin + performance.now()) * 1000);
}

// ----- client -> server ------------------------------------------------------------------------------

/** `hello` (keys in the order of section 4.1; options left undefined are omitted). Rooms (section 12): `room`;
 * `publish` false (watch only) and `self` true are written only with a room, as is `roomToken`. */
export function helloMessage({ layout = "arkit52", avatar, encoding, coords, sparse, delta, device, token, maxGaussians,
  room, publish, self, roomToken } = {}) {
  const inRoom = room !== undefined && room !== null;
  return encode({
    type: "hello", protocol: PROTOCOL, layout, avatar, encoding, coords, sparse, delta: delta || undefined, device,
    token, max_gaussians: maxGaussians, room: inRoom ? room : undefined,
    publish: inRoom && publish === false ? false : undefined, self: inRoom && self ? true : undefined,
    room_token: inRoom ? roomToken : undefined,
  });
}

/** `resync`: a delta-session client asks for a key frame (section 7.1). */
export function resyncMessage() {
  return encode({ type: "resync" });
}

/** `bs`: weights as float32 (a Float32Array or an array of numbers); `conf` optional [lower, upper] face
 * confidence in [0, 1] (PROTOCOL.md 4.2). */
export function bsMessage(seq, t, weights, conf = null) {
  const w = weights instanceof Float32Array ? weights : Float32Array.from(weights);
  const m = { type: "bs", seq, t, w: new Uint8Array(w.buffer, w.byteOffset, w.byteLength) };
  if (conf != null) {
    const c = Float32Array.from(conf);
    if (c.length !== 2 || !c.every((v) => v >= 0 && v <= 1)) throw new RangeError("bs conf: 2 values in [0, 1]");
    m.conf = new Uint8Array(c.buffer);
  }
  return encode(m);
}

export function pingMessage(t) {
  return encode({ type: "ping", t });
}

export function byeMessage() {
  return encode({ type: "bye" });
}

// ----- server -> client ------------------------------------------------------------------------------

function isInt(v) {
  return (typeof v === "number" && Number.isInteger(v)) || typeof v === "bigint";
}

function field(msg, key, kind, optional = false) {
  const v = msg[key];
  if (v === undefined || v === null) {
    if (optional) return undefined;
    throw new ProtocolError("bad_field", `${msg.type}: missing field '${key}'`);
  }
  const ok = kind === "int" ? isInt(v) : kind === "bin" ? v instanceof Uint8Array
    : kind === "map" ? typeof v === "object" && !Array.isArray(v) && !(v instanceof Uint8Array)
      : typeof v === kind;
  if (!ok) throw new ProtocolError("bad_field", `${msg.type}: field '${key}' is not a ${kind}`);
  return kind === "int" && typeof v === "bigint" ? Number(v) : v;
}

function binLength(msg, key, bytes) {
  const b = field(msg, key, "bin");
  if (b.length !== bytes) {
    throw new ProtocolError("bad_length", `${msg.type}: '${key}' has ${b.length} bytes, expected ${bytes}`);
  }
  return b;
}

// Typed views of a bin; copied when the bytes are not aligned for the element type.
function view(Type, b) {
  if (b.byteOffset % Type.BYTES_PER_ELEMENT === 0) return new Type(b.buffer, b.byteOffset, b.length / Type.BYTES_PER_ELEMENT);
  return new Type(b.slice().buffer);
}
export const f32view = (b) => view(Float32Array, b);
export const u16view = (b) => view(Uint16Array, b);
export const u32view = (b) => view(Uint32Array, b);

function checkFinite(a, what) {
  for (let i = 0; i < a.length; i++) {
    if (!Number.isFinite(a[i])) throw new ProtocolError("non_finite", `${what}: value ${i} is ${a[i]}`);
  }
}

/**
 * Decode one server message and check its fields (types, and for `avatar` the array lengths).
 * Frame arrays are left as bins: `AvatarState.applyFrame` decodes them in the session's encoding.
 */
export function decodeServerMessage(bytes) {
  let msg;
  try {
    msg = decode(bytes);
  } catch (e) {
    if (e instanceof MsgpackError) throw new ProtocolError("malformed", e.message);
    throw e;
  }
  if (typeof msg !== "object" || msg === null || Array.isArray(msg) || msg instanceof Uint8Array) {
    throw new ProtocolError("malformed", "a message is a msgpack map");
  }
  const type = msg.type;
  if (typeof type !== "string") throw new ProtocolError("bad_field", "message without a string 'type'");
  switch (type) {
    case "welcome": {
      field(msg, "protocol", "int");
      field(msg, "session", "string");
      const room = field(msg, "room", "string", true); // rooms (section 12)
      const av = field(msg, "avatar", "map", room !== undefined); // a watch-only room session has none
      const avatar = av === undefined ? null : avatarInfo(av);
      const out = {
        type, protocol: msg.protocol, session: msg.session, avatar, layout: field(msg, "layout", "string"),
        encoding: field(msg, "encoding", "string"), coords: field(msg, "coords", "string"),
        sparse: field(msg, "sparse", "boolean", true) ?? false, server: field(msg, "server", "string", true),
        delta: field(msg, "delta", "boolean", true) ?? false,
        room: room ?? null, member: room === undefined ? null : field(msg, "member", "string"),
      };
      if (!ENCODINGS.includes(out.encoding) && out.encoding !== PARAMS) throw new ProtocolError("bad_field", `welcome: unknown encoding ${out.encoding}`);
      if (out.encoding === PARAMS) out.rigBytes = field(msg, "rig_bytes", "int", true) ?? null; // section 13
      if (out.encoding === "q13") {
        const q = field(msg, "quant", "map", room !== undefined); // rooms: each join carries its avatar's
        if (q !== undefined) out.quant = quantOf(q);
      }
      return out;
    }
    case "join": { // rooms: a publishing member has an avatar (and quant for a q13 viewer), a watching one neither
      const publish = field(msg, "publish", "boolean", true) ?? true;
      const av = field(msg, "avatar", "map", !publish);
      if (av !== undefined && !publish) throw new ProtocolError("bad_field", "join: a watch-only member ('publish': false) has no 'avatar'");
      const q = field(msg, "quant", "map", true);
      return { type, member: field(msg, "member", "string"), publish, avatar: av === undefined ? null : avatarInfo(av),
        quant: q === undefined ? undefined : quantOf(q) };
    }
    case "leave":
      return { type, member: field(msg, "member", "string"), reason: field(msg, "reason", "string") };
    case "avatar": {
      const n = field(msg, "n", "int");
      const shDegree = field(msg, "sh_degree", "int");
      const k = (shDegree + 1) * (shDegree + 1);
      return {
        type, member: field(msg, "member", "string", true), count: field(msg, "count", "int"), sh_degree: shDegree, chunk: field(msg, "chunk", "int"),
        chunks: field(msg, "chunks", "int"), offset: field(msg, "offset", "int"), n,
        opacity: f32view(binLength(msg, "opacity", n * 4)), sh: f32view(binLength(msg, "sh", n * k * 12)),
        position: f32view(binLength(msg, "position", n * 12)), rotation: f32view(binLength(msg, "rotation", n * 16)),
        scale: f32view(binLength(msg, "scale", n * 12)),
      };
    }
    case "frame":
      if (msg.params !== undefined) return paramsFrame(type, msg);
      return {
        type, member: field(msg, "member", "string", true), seq: field(msg, "seq", "int"), t: field(msg, "t", "int"),
        timing: field(msg, "timing", "map", true) ?? {},
        key: field(msg, "key", "boolean", true), n: field(msg, "n", "int"), index: field(msg, "index", "bin", true),
        changed: field(msg, "changed", "bin", true), moved_position: field(msg, "moved_position", "bin", true),
        moved_rotation: field(msg, "moved_rotation", "bin", true), moved_scale: field(msg, "moved_scale", "bin", true),
        wide: field(msg, "wide", "bin", true),
        position_delta: field(msg, "position_delta", "bin", true), position: field(msg, "position", "bin"),
        rotation: field(msg, "rotation", "bin"), scale: field(msg, "scale", "bin"),
      };
    case "rig": // section 13.2: bytes [offset, offset + data.length) of the rig body (rig.js assembles and decodes it)
      return {
        type, member: field(msg, "member", "string", true), chunk: field(msg, "chunk", "int"),
        chunks: field(msg, "chunks", "int"), size: field(msg, "size", "int"), offset: field(msg, "offset", "int"),
        data: field(msg, "data", "bin"),
      };
    case "error":
      return {
        type, code: field(msg, "code", "string"), message: field(msg, "message", "string"),
        fatal: field(msg, "fatal", "boolean"), seq: field(msg, "seq", "int", true),
      };
    case "pong":
      return { type, t: field(msg, "t", "int") };
    default:
      throw new ProtocolError("unknown_type", `unknown message type '${type}'`);
  }
}

/** A params frame (section 13.5): 68 finite float32 values; seq and t together or neither (stamped frames). */
function paramsFrame(type, msg) {
  const seq = field(msg, "seq", "int", true), t = field(msg, "t", "int", true);
  if ((seq === undefined) !== (t === undefined)) throw new ProtocolError("bad_field", "frame: a params frame carries 'seq' and 't' together or neither");
  const params = f32view(binLength(msg, "params", PARAMS_LENGTH * 4));
  checkFinite(params, "frame params");
  return { type, member: field(msg, "member", "string", true), seq: seq ?? null, t: t ?? null,
    timing: field(msg, "timing", "map", true) ?? null, params };
}

function avatarInfo(av) {
  return { id: field(av, "id", "string"), count: field(av, "count", "int"), sh_degree: field(av, "sh_degree", "int"),
    expression: field(av, "expression", "string", true) ?? "flame68" };
}

function quantOf(q) {
  return { pos_min: f32view(binLength(q, "pos_min", 12)).slice(), pos_max: f32view(binLength(q, "pos_max", 12)).slice(),
    log_scale: f32view(binLength(q, "log_scale", 8)).slice() };
}

// ----- frame encodings -------------------------------------------------------------------------------

/** IEEE binary16 -> float32 for all 65536 bit patterns. */
export const HALF_TO_FLOAT = (() => {
  const t = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const e = (h >> 10) & 31;
    const m = h & 1023;
    const v = e === 0 ? m * 2 ** -24 : e === 31 ? (m ? NaN : Infinity) : (1 + m / 1024) * 2 ** (e - 15);
    t[h] = h & 0x8000 ? -v : v;
  }
  return t;
})();

function decodeF16(bin, out, what) {
  const h = u16view(bin);
  for (let i = 0; i < h.length; i++) { // check first: a refused frame leaves the state untouched
    if ((h[i] & 0x7c00) === 0x7c00) throw new ProtocolError("non_finite", `${what}: value ${i} is ${HALF_TO_FLOAT[h[i]]}`);
  }
  for (let i = 0; i < h.length; i++) out[i] = HALF_TO_FLOAT[h[i]];
}

const SQRT1_2 = Math.SQRT1_2;

/** q13 position, rotation, scale of `n` Gaussians into float32 arrays (section 6.3). */
function decodeQ13(quant, n, pBin, rBin, sBin, pos, rot, scl) {
  const q = u16view(pBin);
  const lo = quant.pos_min;
  const step = [0, 1, 2].map((a) => (quant.pos_max[a] - lo[a]) / 65535);
  for (let i = 0; i < n; i++) {
    for (let a = 0; a < 3; a++) pos[3 * i + a] = lo[a] + q[3 * i + a] * step[a];
  }
  const r = u32view(rBin);
  for (let i = 0; i < n; i++) {
    const v = r[i];
    const drop = v >>> 30;
    let s0 = (v >>> 20) & 1023, s1 = (v >>> 10) & 1023, s2 = v & 1023;
    if (s0 >= 512) s0 -= 1024;
    if (s1 >= 512) s1 -= 1024;
    if (s2 >= 512) s2 -= 1024;
    const c0 = Math.max(s0 / 511, -1) * SQRT1_2, c1 = Math.max(s1 / 511, -1) * SQRT1_2, c2 = Math.max(s2 / 511, -1) * SQRT1_2;
    const d = Math.sqrt(Math.max(0, 1 - c0 * c0 - c1 * c1 - c2 * c2));
    const o = 4 * i;
    if (drop === 0) { rot[o] = d; rot[o + 1] = c0; rot[o + 2] = c1; rot[o + 3] = c2; }
    else if (drop === 1) { rot[o] = c0; rot[o + 1] = d; rot[o + 2] = c1; rot[o + 3] = c2; }
    else if (drop === 2) { rot[o] = c0; rot[o + 1] = c1; rot[o + 2] = d; rot[o + 3] = c2; }
    else { rot[o] = c0; rot[o + 1] = c1; rot[o + 2] = c2; rot[o + 3] = d; }
  }
  const [lmin, lmax] = quant.log_scale;
  const table = new Float32Array(256);
  for (let k = 0; k < 256; k++) table[k] = Math.exp(lmin + (k * (lmax - lmin)) / 255);
  for (let i = 0; i < 3 * n; i++) scl[i] = table[sBin[i]];
}

/**
 * Decode a frame's position, rotation, scale (n Gaussians) from the session's encoding into float32
 * arrays (n*3, n*4, n*3). Checks byte lengths and finiteness. Exported for tests.
 */
export function decodeFrameArrays(encoding, n, frame, quant, out) {
  const [pb, rb, sb] = FIELD_BYTES[encoding] ?? [];
  if (pb === undefined) throw new ProtocolError("bad_field", `unknown encoding ${encoding}`);
  for (const [key, bytes] of [["position", pb], ["rotation", rb], ["scale", sb]]) {
    if (frame[key].length !== n * bytes) {
      throw new ProtocolError("bad_length", `frame: '${key}' has ${frame[key].length} bytes, ${n} Gaussians in ${encoding} need ${n * bytes}`);
    }
  }
  const pos = out?.position ?? new Float32Array(n * 3);
  const rot = out?.rotation ?? new Float32Array(n * 4);
  const scl = out?.scale ?? new Float32Array(n * 3);
  if (encoding === "f32") {
    const src = [f32view(frame.position), f32view(frame.rotation), f32view(frame.scale)];
    src.forEach((a, i) => checkFinite(a, `frame ${["position", "rotation", "scale"][i]}`));
    pos.set(src[0]);
    rot.set(src[1]);
    scl.set(src[2]);
  } else if (encoding === "f16") {
    decodeF16(frame.position, pos, "frame position");
    decodeF16(frame.rotation, rot, "frame rotation");
    decodeF16(frame.scale, scl, "frame scale");
  } else {
    if (!quant) throw new ProtocolError("bad_field", "q13 frame without the welcome's quant");
    decodeQ13(quant, n, frame.position, frame.rotation, frame.scale, pos, rot, scl);
  }
  return { position: pos, rotation: rot, scale: scl };
}

/** Gaussians of one session: static attributes from `avatar`, the newest values from frames. */
export class AvatarState {
  /** `capacity` >= count: arrays are that long (the renderer's textures are padded). */
  constructor(welcome, capacity = welcome.avatar.count) {
    this.welcome = welcome;
    this.count = welcome.avatar.count;
    this.shDegree = welcome.avatar.sh_degree;
    this.encoding = welcome.encoding;
    this.sparse = welcome.sparse;
    this.quant = welcome.quant;
    this.capacity = Math.max(capacity, this.count);
    this.position = new Float32Array(this.capacity * 3);
    this.rotation = new Float32Array(this.capacity * 4);
    this.scale = new Float32Array(this.capacity * 3);
    this.color = new Uint8Array(this.capacity * 4); // RGBA8: SH degree 0 colour, opacity
    this.received = 0;
    this.nextChunk = 0;
    this.complete = false;
    this.scratch = null;
    this.delta = !!welcome.delta; // section 7.1: the codes this client holds, from key and delta frames
    this.hasKey = false;
    if (this.delta) {
      const q13 = this.encoding === "q13";
      if (!q13 && this.encoding !== "f16") throw new ProtocolError("bad_field", `no delta frames in ${this.encoding}`);
      this.posCodes = new Uint16Array(this.count * 3);
      this.rotCodes = q13 ? new Uint32Array(this.count) : new Uint16Array(this.count * 4);
      this.scaleCodes = q13 ? new Uint8Array(this.count * 3) : new Uint16Array(this.count * 3);
    }
  }

  /** Apply one `avatar` chunk (decoded); returns true when it was the last. */
  applyChunk(c) {
    if (c.count !== this.count || c.sh_degree !== this.shDegree) {
      throw new ProtocolError("bad_field", `avatar chunk: count ${c.count}, sh_degree ${c.sh_degree} differ from welcome's ${this.count}, ${this.shDegree}`);
    }
    if (c.chunk !== this.nextChunk || c.offset !== this.received || c.offset + c.n > this.count || c.chunk >= c.chunks) {
      throw new ProtocolError("bad_field", `avatar chunk ${c.chunk}/${c.chunks} at offset ${c.offset} out of order (expected chunk ${this.nextChunk} at ${this.received})`);
    }
    const o = c.offset, n = c.n, k3 = (this.shDegree + 1) * (this.shDegree + 1) * 3;
    checkFinite(c.position, "avatar position");
    checkFinite(c.rotation, "avatar rotation");
    checkFinite(c.scale, "avatar scale");
    this.position.set(c.position, o * 3);
    this.rotation.set(c.rotation, o * 4);
    this.scale.set(c.scale, o * 3);
    const col = this.color;
    for (let i = 0; i < n; i++) {
      const a = c.opacity[i];
      if (!(a >= 0 && a <= 1)) throw new ProtocolError("bad_field", `avatar opacity ${i} is ${a}, outside [0, 1]`);
      const j = 4 * (o + i);
      for (let ch = 0; ch < 3; ch++) col[j + ch] = Math.round(255 * Math.min(1, Math.max(0, SH_C0 * c.sh[i * k3 + ch] + 0.5)));
      col[j + 3] = Math.round(255 * a);
    }
    this.received += n;
    this.nextChunk += 1;
    if (c.chunk === c.chunks - 1) {
      if (this.received !== this.count) throw new ProtocolError("bad_field", `avatar: last chunk ends at ${this.received}, count is ${this.count}`);
      this.complete = true;
    }
    return this.complete;
  }

  /**
   * Apply a decoded `frame`: dense (all Gaussians), sparse (those in `index`), or a delta session's key or delta
   * frame. Returns the Gaussians it changed (Uint32Array) or null for all of them.
   */
  applyFrame(f) {
    if (!this.complete) throw new ProtocolError("not_ready", "frame before the whole avatar");
    if (this.delta) {
      if (typeof f.key !== "boolean") throw new ProtocolError("bad_field", "frame: delta session frame without 'key'");
      if (!f.key) return this.applyDelta(f);
      if (f.index !== undefined || f.n !== this.count) throw new ProtocolError("bad_field", "frame: a key frame is dense");
      decodeFrameArrays(this.encoding, f.n, f, this.quant, this);
      this.posCodes.set(u16view(f.position));
      this.rotCodes.set(this.encoding === "q13" ? u32view(f.rotation) : u16view(f.rotation));
      this.scaleCodes.set(this.encoding === "q13" ? f.scale : u16view(f.scale));
      this.hasKey = true;
      return null;
    }
    if (f.index !== undefined) {
      if (!this.sparse) throw new ProtocolError("bad_field", "frame with 'index' in a non-sparse session");
      if (f.index.length !== f.n * 4) throw new ProtocolError("bad_length", `frame: index has ${f.index.length} bytes for n = ${f.n}`);
      const idx = u32view(f.index);
      for (let k = 0; k < idx.length; k++) {
        if (idx[k] >= this.count || (k > 0 && idx[k] <= idx[k - 1])) {
          throw new ProtocolError("bad_field", "frame: index must be strictly ascending and below count");
        }
      }
      const n = f.n;
      if (!this.scratch || this.scratch.n < n) {
        this.scratch = { n, position: new Float32Array(n * 3), rotation: new Float32Array(n * 4), scale: new Float32Array(n * 3) };
      }
      const s = decodeFrameArrays(this.encoding, n, f, this.quant, this.scratch);
      const P = this.position, R = this.rotation, S = this.scale;
      for (let k = 0; k < n; k++) {
        const i = idx[k];
        P[3 * i] = s.position[3 * k]; P[3 * i + 1] = s.position[3 * k + 1]; P[3 * i + 2] = s.position[3 * k + 2];
        R[4 * i] = s.rotation[4 * k]; R[4 * i + 1] = s.rotation[4 * k + 1];
        R[4 * i + 2] = s.rotation[4 * k + 2]; R[4 * i + 3] = s.rotation[4 * k + 3];
        S[3 * i] = s.scale[3 * k]; S[3 * i + 1] = s.scale[3 * k + 1]; S[3 * i + 2] = s.scale[3 * k + 2];
      }
      return idx;
    }
    if (f.n !== this.count) throw new ProtocolError("bad_length", `dense frame with n = ${f.n}, count is ${this.count}`);
    decodeFrameArrays(this.encoding, f.n, f, this.quant, this);
    return null;
  }

  /** A delta frame (section 7.1): checked whole, then the carried codes replaced and those Gaussians decoded. */
  applyDelta(f) {
    if (!this.hasKey) throw new ProtocolError("not_ready", "frame: a delta frame before any key frame (send resync)");
    const n = f.n, count = this.count, q13 = this.encoding === "q13";
    const changed = maskIds(f.changed, count, "changed");
    if (changed.length !== n) throw new ProtocolError("bad_field", `frame: n = ${n} but 'changed' marks ${changed.length}`);
    const moved = ["moved_position", "moved_rotation", "moved_scale"].map((k) => maskBits(f[k], n, k));
    for (let j = 0; j < n; j++) {
      if (!moved[0][j] && !moved[1][j] && !moved[2][j]) throw new ProtocolError("bad_field", "frame: a changed Gaussian carries nothing");
    }
    const [np, nr, ns] = moved.map((m) => m.reduce((a, b) => a + b, 0));
    const wide = maskBits(f.wide, np, "wide");
    const nw = wide.reduce((a, b) => a + b, 0);
    const [pb, rb, sb] = FIELD_BYTES[this.encoding];
    for (const [key, bytes] of [["position_delta", (np - nw) * 3], ["position", nw * pb], ["rotation", nr * rb], ["scale", ns * sb]]) {
      if (!(f[key] instanceof Uint8Array)) throw new ProtocolError("bad_field", `frame: delta frame without '${key}'`);
      if (f[key].length !== bytes) throw new ProtocolError("bad_length", `frame: '${key}' has ${f[key].length} bytes, expected ${bytes}`);
    }
    const rw = q13 ? 1 : 4;
    // the carried Gaussians' codes after this frame: held codes, then what the frame carries
    const pos = new Uint16Array(n * 3), rot = q13 ? new Uint32Array(n) : new Uint16Array(n * 4);
    const scl = q13 ? new Uint8Array(n * 3) : new Uint16Array(n * 3);
    const change = new Int8Array(f.position_delta.buffer, f.position_delta.byteOffset, f.position_delta.length);
    const whole = u16view(f.position), rots = q13 ? u32view(f.rotation) : u16view(f.rotation);
    const scales = q13 ? f.scale : u16view(f.scale);
    for (let j = 0, p = 0, k = 0, w = 0, r = 0, s = 0; j < n; j++) {
      const i = changed[j];
      for (let c = 0; c < 3; c++) pos[3 * j + c] = this.posCodes[3 * i + c];
      for (let c = 0; c < rw; c++) rot[rw * j + c] = this.rotCodes[rw * i + c];
      for (let c = 0; c < 3; c++) scl[3 * j + c] = this.scaleCodes[3 * i + c];
      if (moved[0][j]) {
        if (wide[p++]) {
          for (let c = 0; c < 3; c++) pos[3 * j + c] = whole[3 * w + c];
          w++;
        } else {
          for (let c = 0; c < 3; c++) {
            const v = pos[3 * j + c] + change[3 * k + c];
            if (v < 0 || v > 65535) throw new ProtocolError("bad_field", "frame: 'position_delta' takes a code outside 0..65535");
            pos[3 * j + c] = v;
          }
          k++;
        }
      }
      if (moved[1][j]) { for (let c = 0; c < rw; c++) rot[rw * j + c] = rots[rw * r + c]; r++; }
      if (moved[2][j]) { for (let c = 0; c < 3; c++) scl[3 * j + c] = scales[3 * s + c]; s++; }
    }
    if (!this.deltaScratch || this.deltaScratch.n < n) {
      this.deltaScratch = { n, position: new Float32Array(n * 3), rotation: new Float32Array(n * 4), scale: new Float32Array(n * 3) };
    }
    const bytes = (a) => new Uint8Array(a.buffer, a.byteOffset, a.byteLength);
    const d = decodeFrameArrays(this.encoding, n, { position: bytes(pos), rotation: bytes(rot), scale: bytes(scl) },
      this.quant, this.deltaScratch); // f16: refuses NaN / infinity before anything changed
    const P = this.position, R = this.rotation, S = this.scale;
    for (let j = 0; j < n; j++) {
      const i = changed[j];
      for (let c = 0; c < 3; c++) {
        this.posCodes[3 * i + c] = pos[3 * j + c];
        this.scaleCodes[3 * i + c] = scl[3 * j + c];
        P[3 * i + c] = d.position[3 * j + c];
        S[3 * i + c] = d.scale[3 * j + c];
      }
      for (let c = 0; c < rw; c++) this.rotCodes[rw * i + c] = rot[rw * j + c];
      for (let c = 0; c < 4; c++) R[4 * i + c] = d.rotation[4 * j + c];
    }
    return changed;
  }
}

/** A section 7.1 bitmask over `n` entries (LSB first) as 0/1 bytes, checking its length and padding. */
function maskBits(bin, n, what) {
  if (!(bin instanceof Uint8Array)) throw new ProtocolError("bad_field", `frame: delta frame without '${what}'`);
  if (bin.length !== ((n + 7) >> 3)) throw new ProtocolError("bad_length", `frame: '${what}' has ${bin.length} bytes for ${n} entries`);
  const out = new Uint8Array(n);
  for (let i = 0; i < 8 * bin.length; i++) {
    const bit = (bin[i >> 3] >> (i & 7)) & 1;
    if (i < n) out[i] = bit;
    else if (bit) throw new ProtocolError("bad_field", `frame: '${what}' has bits set beyond its ${n} entries`);
  }
  return out;
}

/** The set bits of a section 7.1 bitmask over `n` entries (LSB first), checking its length and padding. */
function maskIds(bin, n, what) {
  if (!(bin instanceof Uint8Array)) throw new ProtocolError("bad_field", `frame: delta frame without '${what}'`);
  if (bin.length !== ((n + 7) >> 3)) throw new ProtocolError("bad_length", `frame: '${what}' has ${bin.length} bytes for ${n} entries`);
  const ids = [];
  for (let b = 0; b < bin.length; b++) {
    let v = bin[b];
    while (v) {
      const bit = 31 - Math.clz32(v & -v);
      const i = 8 * b + bit;
      if (i >= n) throw new ProtocolError("bad_field", `frame: '${what}' has bits set beyond its ${n} entries`);
      ids.push(i);
      v &= v - 1;
    }
  }
  return Uint32Array.from(ids);
}
