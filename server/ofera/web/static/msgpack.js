// A small msgpack codec for the OFERA protocol (PROTOCOL.md section 2): maps with string keys, ints,
// strings, booleans, nil, bins (Uint8Array), arrays; floats are decoded but never needed by v1.
// Encoding writes the smallest integer form, as the Python reference does (golden vectors match).
// Decoding refuses what the protocol forbids: ext types, non-string keys, trailing bytes, nesting deeper
// than 4, more than 256 entries, strings over 4096 bytes, lengths beyond the message.

export class MsgpackError extends Error {
  constructor(message) {
    super(message);
    this.code = "malformed";
  }
}

const utf8 = new TextEncoder();
const utf8Strict = new TextDecoder("utf-8", { fatal: true });
const TWO32 = 4294967296;

export const LIMITS = { depth: 4, entries: 256, strBytes: 4096 };

class Writer {
  constructor(size = 256) {
    this.buf = new Uint8Array(size);
    this.view = new DataView(this.buf.buffer);
    this.pos = 0;
  }
  ensure(n) {
    if (this.pos + n <= this.buf.length) return;
    let size = this.buf.length * 2;
    while (size < this.pos + n) size *= 2;
    const b = new Uint8Array(size);
    b.set(this.buf.subarray(0, this.pos));
    this.buf = b;
    this.view = new DataView(b.buffer);
  }
  u8(x) { this.ensure(1); this.buf[this.pos++] = x; }
  u16(x) { this.ensure(2); this.view.setUint16(this.pos, x); this.pos += 2; }
  u32(x) { this.ensure(4); this.view.setUint32(this.pos, x); this.pos += 4; }
  bytes(b) { this.ensure(b.length); this.buf.set(b, this.pos); this.pos += b.length; }

  int(v) {
    if (typeof v === "bigint") {
      if (v >= 0n && v <= 0xffffffffn) return this.int(Number(v));
      if (v < 0n && v >= -0x80000000n) return this.int(Number(v));
      this.ensure(9);
      if (v >= 0n) { this.buf[this.pos] = 0xcf; this.view.setBigUint64(this.pos + 1, v); }
      else { this.buf[this.pos] = 0xd3; this.view.setBigInt64(this.pos + 1, v); }
      this.pos += 9;
      return;
    }
    if (!Number.isSafeInteger(v)) throw new MsgpackError(`cannot encode ${v} as an integer`);
    if (v >= 0) {
      if (v < 128) this.u8(v);
      else if (v < 256) { this.u8(0xcc); this.u8(v); }
      else if (v < 65536) { this.u8(0xcd); this.u16(v); }
      else if (v < TWO32) { this.u8(0xce); this.u32(v); }
      else { this.u8(0xcf); this.u32(Math.floor(v / TWO32)); this.u32(v % TWO32); }
    } else {
      if (v >= -32) this.u8(v & 0xff);
      else if (v >= -128) { this.u8(0xd0); this.u8(v & 0xff); }
      else if (v >= -32768) { this.u8(0xd1); this.u16(v & 0xffff); }
      else if (v >= -2147483648) { this.u8(0xd2); this.u32(v >>> 0); }
      else this.int(BigInt(v));
    }
  }

  str(s) {
    const b = utf8.encode(s);
    const n = b.length;
    if (n < 32) this.u8(0xa0 | n);
    else if (n < 256) { this.u8(0xd9); this.u8(n); }
    else if (n < 65536) { this.u8(0xda); this.u16(n); }
    else { this.u8(0xdb); this.u32(n); }
    this.bytes(b);
  }

  bin(b) {
    const n = b.length;
    if (n < 256) { this.u8(0xc4); this.u8(n); }
    else if (n < 65536) { this.u8(0xc5); this.u16(n); }
    else { this.u8(0xc6); this.u32(n); }
    this.bytes(b);
  }

  value(v) {
    if (v === null || v === undefined) this.u8(0xc0);
    else if (v === true) this.u8(0xc3);
    else if (v === false) this.u8(0xc2);
    else if (typeof v === "number") {
      if (Number.isInteger(v)) this.int(v);
      else { this.ensure(9); this.buf[this.pos] = 0xcb; this.view.setFloat64(this.pos + 1, v); this.pos += 9; }
    } else if (typeof v === "bigint") this.int(v);
    else if (typeof v === "string") this.str(v);
    else if (v instanceof Uint8Array) this.bin(v);
    else if (ArrayBuffer.isView(v)) this.bin(new Uint8Array(v.buffer, v.byteOffset, v.byteLength));
    else if (v instanceof ArrayBuffer) this.bin(new Uint8Array(v));
    else if (Array.isArray(v)) {
      const n = v.length;
      if (n < 16) this.u8(0x90 | n);
      else if (n < 65536) { this.u8(0xdc); this.u16(n); }
      else { this.u8(0xdd); this.u32(n); }
      for (const x of v) this.value(x);
    } else if (typeof v === "object") {
      const entries = Object.entries(v).filter(([, x]) => x !== undefined);
      const n = entries.length;
      if (n < 16) this.u8(0x80 | n);
      else if (n < 65536) { this.u8(0xde); this.u16(n); }
      else { this.u8(0xdf); this.u32(n); }
      for (const [k, x] of entries) { this.str(k); this.value(x); }
    } else throw new MsgpackError(`cannot encode a ${typeof v}`);
  }
}

/** Encode a value (objects as maps, in their key order; undefined fields are left out). */
export function encode(value) {
  const w = new Writer();
  w.value(value);
  return w.buf.slice(0, w.pos);
}

class Reader {
  constructor(bytes) {
    this.b = bytes;
    this.view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    this.pos = 0;
  }
  need(n) {
    if (this.pos + n > this.b.length) {
      throw new MsgpackError(`truncated: needs ${n} more bytes at offset ${this.pos}, message has ${this.b.length}`);
    }
  }
  u8() { this.need(1); return this.b[this.pos++]; }
  u16() { this.need(2); const x = this.view.getUint16(this.pos); this.pos += 2; return x; }
  u32() { this.need(4); const x = this.view.getUint32(this.pos); this.pos += 4; return x; }
  u64() {
    this.need(8);
    const x = this.view.getBigUint64(this.pos); this.pos += 8;
    return x <= BigInt(Number.MAX_SAFE_INTEGER) ? Number(x) : x;
  }
  i64() {
    this.need(8);
    const x = this.view.getBigInt64(this.pos); this.pos += 8;
    return x <= BigInt(Number.MAX_SAFE_INTEGER) && x >= BigInt(Number.MIN_SAFE_INTEGER) ? Number(x) : x;
  }
  raw(n) { this.need(n); const s = this.b.subarray(this.pos, this.pos + n); this.pos += n; return s; }
  str(n) {
    if (n > LIMITS.strBytes) throw new MsgpackError(`string of ${n} bytes (limit ${LIMITS.strBytes})`);
    try { return utf8Strict.decode(this.raw(n)); } catch (e) {
      if (e instanceof MsgpackError) throw e;
      throw new MsgpackError("invalid UTF-8 in a string");
    }
  }
  count(n) {
    if (n > LIMITS.entries) throw new MsgpackError(`container with ${n} entries (limit ${LIMITS.entries})`);
    return n;
  }
  array(n, depth) {
    this.count(n);
    const out = new Array(n);
    for (let i = 0; i < n; i++) out[i] = this.value(depth);
    return out;
  }
  map(n, depth) {
    this.count(n);
    const out = {};
    for (let i = 0; i < n; i++) {
      const k = this.value(depth, true);
      if (typeof k !== "string") throw new MsgpackError("map key is not a string");
      out[k] = this.value(depth);
    }
    return out;
  }
  // depth: how deep the enclosing container is (0 at the top); a container read here is depth + 1.
  value(depth = 0, isKey = false) {
    const c = this.u8();
    const container = (c >= 0x80 && c <= 0x9f) || c === 0xdc || c === 0xdd || c === 0xde || c === 0xdf;
    if (container && depth + 1 > LIMITS.depth) throw new MsgpackError(`nested more than ${LIMITS.depth} deep`);
    if (isKey && !((c >= 0xa0 && c <= 0xbf) || c === 0xd9 || c === 0xda || c === 0xdb)) {
      throw new MsgpackError("map key is not a string");
    }
    if (c < 0x80) return c;
    if (c <= 0x8f) return this.map(c & 0x0f, depth + 1);
    if (c <= 0x9f) return this.array(c & 0x0f, depth + 1);
    if (c <= 0xbf) return this.str(c & 0x1f);
    if (c >= 0xe0) return c - 256;
    switch (c) {
      case 0xc0: return null;
      case 0xc2: return false;
      case 0xc3: return true;
      case 0xc4: return this.raw(this.u8());
      case 0xc5: return this.raw(this.u16());
      case 0xc6: return this.raw(this.u32());
      case 0xca: { this.need(4); const x = this.view.getFloat32(this.pos); this.pos += 4; return x; }
      case 0xcb: { this.need(8); const x = this.view.getFloat64(this.pos); this.pos += 8; return x; }
      case 0xcc: return this.u8();
      case 0xcd: return this.u16();
      case 0xce: return this.u32();
      case 0xcf: return this.u64();
      case 0xd0: { const x = this.u8(); return x < 128 ? x : x - 256; }
      case 0xd1: { const x = this.u16(); return x < 32768 ? x : x - 65536; }
      case 0xd2: { this.need(4); const x = this.view.getInt32(this.pos); this.pos += 4; return x; }
      case 0xd3: return this.i64();
      case 0xd9: return this.str(this.u8());
      case 0xda: return this.str(this.u16());
      case 0xdb: return this.str(this.u32());
      case 0xdc: return this.array(this.u16(), depth + 1);
      case 0xdd: return this.array(this.u32(), depth + 1);
      case 0xde: return this.map(this.u16(), depth + 1);
      case 0xdf: return this.map(this.u32(), depth + 1);
      default:
        throw new MsgpackError(c === 0xc1 ? "byte 0xc1 is never used" : `ext type 0x${c.toString(16)} is not allowed`);
    }
  }
}

/** Decode one message: exactly one msgpack value, no trailing bytes. Bins are views into `bytes`. */
export function decode(bytes) {
  const b = bytes instanceof Uint8Array ? bytes : new Uint8Array(bytes);
  const r = new Reader(b);
  const v = r.value(0);
  if (r.pos !== b.length) throw new MsgpackError(`${b.length - r.pos} trailing bytes after the message`);
  return v;
}
