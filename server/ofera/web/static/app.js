// The preview page: a protocol client of /v1/stream with sliders, presets, CSV and bsData.json playback, an orbit camera
// and a WebGL2 splat renderer. URL options: ?max=N (ask for at most N Gaussians; no automatic
// reduction), ?auto=0 (never reduce), ?enc=f32|f16|q13 (default f16), ?sparse=0, ?delta=1 (temporal deltas, f16 or
// q13: PROTOCOL.md 7.1), ?res=PIXELS (largest
// canvas side, default 480), ?minfps=15, ?fill=0 (no splat enlargement of a reduced stream),
// ?avatar=ID, ?device=NAME, ?token=T, ?ws=URL. Rooms (PROTOCOL.md 12; the Room field does the same): ?room=NAME
// joins a room (every member side by side, rooms.js), ?watch=1 watches only, ?self=1 shows one's own avatar too,
// ?roomtoken=T.
import { looksLikeJson, parseBsData } from "./bsdata.js";
import { parseFaceLog } from "./facelog.js";
import { decode } from "./msgpack.js";
import { bsMessage, byeMessage, CLOSE_CODES, CLOSE_UNKNOWN_FATAL, decodeServerMessage, ENDPOINT, helloMessage, nowUs, ProtocolError,
  resyncMessage } from "./protocol.js";
import { lookAt, perspective, SplatRenderer } from "./renderer.js";
import { RoomView } from "./rooms.js";

const params = new URLSearchParams(location.search);
const intParam = (name) => {
  const v = Number.parseInt(params.get(name) ?? "", 10);
  return Number.isFinite(v) && v > 0 ? v : null;
};
const opts = {
  encoding: ["f32", "f16", "q13", "params"].includes(params.get("enc")) ? params.get("enc") : "f16",
  sparse: params.get("sparse") !== "0",
  delta: params.get("delta") === "1",
  forcedMax: intParam("max"),
  res: intParam("res") ?? 480,
  minFps: intParam("minfps") ?? 15,
  fill: params.get("fill") !== "0",
  avatar: params.get("avatar") || "default",
  device: params.get("device") || undefined,
  token: params.get("token") || undefined,
  room: params.get("room") || null,
  publish: params.get("watch") !== "1",
  self: params.get("self") === "1",
  roomToken: params.get("roomtoken") || undefined,
  url: params.get("ws") || `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}${ENDPOINT}`,
};
opts.auto = params.get("auto") !== "0" && opts.forcedMax === null;

const MIN_GAUSSIANS = 10000; // never ask for fewer when reducing automatically
const SLOW_WINDOW_MS = 3000; // fps below minFps for this long -> reduced stream
const MEASURE_MS = 4000; // keep updating this long after an avatar arrives, to measure fps
const ACTIVE_MS = 1500; // keep updating this long after any change
const ROOM_SEND_MS = 1000 / 72; // in a room no frame answers a bs: send the newest at most this often
const ROOM_NAME = /^[A-Za-z0-9._-]{1,64}$/;

const PRESETS = {
  neutral: {},
  smile: { mouthSmileLeft: 0.85, mouthSmileRight: 0.85, cheekSquintLeft: 0.45, cheekSquintRight: 0.45, eyeSquintLeft: 0.25, eyeSquintRight: 0.25, mouthDimpleLeft: 0.2, mouthDimpleRight: 0.2 },
  "jaw open": { jawOpen: 1.0 },
  blink: { eyeBlinkLeft: 1.0, eyeBlinkRight: 1.0 },
  surprise: { browInnerUp: 0.9, browOuterUpLeft: 0.8, browOuterUpRight: 0.8, eyeWideLeft: 0.8, eyeWideRight: 0.8, jawOpen: 0.45, mouthFunnel: 0.2 },
  anger: { browDownLeft: 0.9, browDownRight: 0.9, eyeSquintLeft: 0.5, eyeSquintRight: 0.5, eyeWideLeft: 0.25, eyeWideRight: 0.25, mouthPressLeft: 0.6, mouthPressRight: 0.6, noseSneerLeft: 0.4, noseSneerRight: 0.4, mouthFrownLeft: 0.3, mouthFrownRight: 0.3 },
};
const REGION_TITLES = { eyes: "Eyes", brows: "Brows", mouth_jaw: "Mouth & jaw", cheeks_nose: "Cheeks & nose" };

const $ = (id) => document.getElementById(id);
const canvas = $("canvas");

// ----- page state ----------------------------------------------------------------------------------------

let table = null; // /static/layouts.json
let names = [];
const weights = new Float32Array(52);
const sliders = [];
let weightsDirty = true;

let renderer = null;
let room = null; // RoomView (rooms.js): the tiles of a room session
const worker = new Worker(new URL("./splat-worker.js", import.meta.url), { type: "module" });
let conn = null; // { ws, gen, state, welcome, count, maxGaussians, seq, lastSeq, lastSendMs, closing }
let connGen = 0;
let retryMs = 1000;
let fullCount = null; // Gaussians of the full avatar (from /v1/avatars or a full welcome)
let reductions = 0;

const cam = { yaw: 0, pitch: 0, dist: 0.6, target: [0, 0, 0], home: null, fovy: (30 * Math.PI) / 180 };
let viewMat = null, projMat = null;

let prepWanted = false, prepBusy = false, prepId = 0, prepSentAt = 0, prepMs = 0, spare = null;
let viewVersion = 0, drawnView = -1, prepView = -1;
let needsDraw = false, drawnSeq = -1, fresh = false;
let rafPending = false, activeUntil = 0, activeSince = null;
const updateTimes = []; // when new content was drawn
const latencies = [];
let lastBytes = 0, lastTiming = null, framesReceived = 0, framesDrawn = 0, droppedSeq = 0;
let fps = 0;
let playback = null;
let playbackConf = null; // [lower, upper] face confidence of the sample being played, sent with its bs
const errors = [];

// A debugging and testing handle (read by tests/test_browser_*.py).
const debug = {
  opts,
  get status() { return conn?.state ?? "idle"; },
  get session() { return conn?.welcome?.session ?? null; },
  get count() { return conn?.count ?? 0; },
  get fullCount() { return fullCount; },
  get maxGaussians() { return conn?.maxGaussians ?? null; },
  get encoding() { return conn?.welcome?.encoding ?? null; },
  /** What drives the avatar (welcome.avatar.expression): "flame68" (through the EPM) or "arkit51" (LAM). */
  get expression() { return conn?.welcome?.avatar?.expression ?? null; },
  get lastSentSeq() { return conn ? conn.seq - 1 : -1; },
  get lastFrameSeq() { return conn?.lastSeq ?? -1; },
  get drawnSeq() { return drawnSeq; },
  get framesReceived() { return framesReceived; },
  get framesDrawn() { return framesDrawn; },
  get fps() { return fps; },
  get prepMs() { return prepMs; },
  get reductions() { return reductions; },
  get errors() { return errors.slice(); },
  /** Streaming, every slider change sent and answered, and the newest frame drawn. */
  get settled() {
    return conn?.state === "streaming" && !weightsDirty && conn.lastSeq === conn.seq - 1 && drawnSeq === conn.lastSeq
      && drawnView === viewVersion && !prepBusy && !needsDraw;
  },
  get playing() { return playback !== null && playback.timer !== null; },
  /** Samples of the current recording never sent: passed over by a late timer or superseded under flow control. */
  get playSkipped() { return playback?.skipped ?? 0; },
  /** Rooms: {room, member, members: [{member, avatar, count, self, state, framesReceived, fps, latencyMs, ...}],
   * left: [{member, reason, at}], settled} (rooms.js); null outside a room session. */
  get room() { return conn?.welcome?.room ? room.snapshot() : null; },
  joinRoom,
  setWeight(name, value) { setWeights({ ...currentWeights(), [name]: value }); },
  setWeights,
  preset: applyPreset,
  playText(text, name = "test.csv") { return loadRecording(text, name); },
  weights: () => Array.from(weights),
  /** Milliseconds per draw of the current splats (waiting for the pixels), averaged over `n` draws. */
  benchDraw(n = 3) {
    const px = new Uint8Array(4);
    const gl = renderer.gl;
    const t0 = performance.now();
    for (let i = 0; i < n; i++) {
      renderer.draw();
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    }
    return (performance.now() - t0) / n;
  },
};
window.__ofera = debug;

function currentWeights() {
  const out = {};
  names.forEach((n, i) => { if (weights[i]) out[n] = weights[i]; });
  return out;
}

// ----- UI ------------------------------------------------------------------------------------------------

function setStatus(text, isError = false) {
  const el = $("status");
  el.textContent = text;
  el.classList.toggle("error", isError);
}

function reportError(text) {
  errors.push(text);
  if (errors.length > 20) errors.shift();
  const box = $("errors");
  const div = document.createElement("div");
  div.textContent = text;
  box.prepend(div);
  while (box.children.length > 4) box.lastChild.remove();
  console.warn(text);
}

function buildControls() {
  const box = $("sliders");
  for (const [region, list] of Object.entries(table.regions)) {
    const det = document.createElement("details");
    det.open = true;
    const sum = document.createElement("summary");
    sum.textContent = `${REGION_TITLES[region] ?? region} (${list.length})`;
    det.append(sum);
    for (const name of list) {
      const i = names.indexOf(name);
      const row = document.createElement("div");
      row.className = "row";
      const label = document.createElement("label");
      label.textContent = name;
      label.htmlFor = `bs-${name}`;
      const input = document.createElement("input");
      Object.assign(input, { type: "range", min: "0", max: "1", step: "0.01", value: "0", id: `bs-${name}` });
      input.dataset.name = name;
      const out = document.createElement("output");
      out.textContent = "0.00";
      input.addEventListener("input", () => {
        weights[i] = Number(input.value);
        playbackConf = null; // the sliders' weights, not a sample's
        out.textContent = weights[i].toFixed(2);
        row.classList.toggle("on", weights[i] > 0);
        weightsDirty = true;
        wake();
      });
      row.append(label, input, out);
      det.append(row);
      sliders[i] = { input, out, row };
    }
    box.append(det);
  }
  const presets = $("presets");
  for (const name of Object.keys(PRESETS)) {
    const b = document.createElement("button");
    b.textContent = name;
    b.addEventListener("click", () => { stopPlayback(); applyPreset(name); });
    presets.append(b);
  }
  $("file").addEventListener("change", async (ev) => {
    const f = ev.target.files[0];
    if (f) loadRecording(await f.text(), f.name);
    ev.target.value = "";
  });
  $("play").addEventListener("click", () => startPlayback());
  $("stop").addEventListener("click", () => stopPlayback());
  $("full").addEventListener("click", () => { opts.forcedMax = null; connect(null); });
  $("reconnect").addEventListener("click", () => connect(conn?.maxGaussians ?? opts.forcedMax));
  syncRoomControls();
  $("join").addEventListener("click", () => joinRoom($("room").value.trim()));
  $("room").addEventListener("keydown", (ev) => { if (ev.key === "Enter") joinRoom($("room").value.trim()); });
  $("leave").addEventListener("click", () => joinRoom(null));
  document.addEventListener("dragover", (ev) => { ev.preventDefault(); document.body.classList.add("dragging"); });
  document.addEventListener("dragleave", (ev) => { if (!ev.relatedTarget) document.body.classList.remove("dragging"); });
  document.addEventListener("drop", async (ev) => {
    ev.preventDefault();
    document.body.classList.remove("dragging");
    const f = ev.dataTransfer?.files?.[0];
    if (f) loadRecording(await f.text(), f.name);
  });
}

// ----- rooms -------------------------------------------------------------------------------------------------

/** Join room `name` (reconnecting; null: leave the room for a v1 session). Returns an error text, or null. */
function joinRoom(name, { publish = $("publish").checked, self = $("self").checked } = {}) {
  if (name !== null && !ROOM_NAME.test(name)) {
    const why = `room name '${name}': 1 to 64 letters, digits, '.', '_' or '-'`;
    reportError(why);
    return why;
  }
  Object.assign(opts, { room: name, publish, self });
  syncRoomControls();
  connect(opts.forcedMax);
  return null;
}

function syncRoomControls() {
  $("room").value = opts.room ?? "";
  $("publish").checked = opts.publish;
  $("self").checked = opts.self;
  $("leave").disabled = opts.room === null;
  document.body.classList.toggle("in-room", opts.room !== null);
}

function syncSliders() {
  for (let i = 0; i < 52; i++) {
    const s = sliders[i];
    if (!s) continue;
    const v = weights[i];
    if (Number(s.input.value) !== v) s.input.value = String(v);
    s.out.textContent = v.toFixed(2);
    s.row.classList.toggle("on", v > 0);
  }
}

function setWeights(map) {
  weights.fill(0);
  for (const [name, v] of Object.entries(map)) {
    const i = names.indexOf(name);
    if (i < 0) throw new Error(`unknown blendshape ${name}`);
    weights[i] = Math.min(1, Math.max(0, Number(v)));
  }
  syncSliders();
  playbackConf = null;
  weightsDirty = true;
  wake();
}

function applyPreset(name) {
  if (!(name in PRESETS)) throw new Error(`unknown preset ${name}`);
  setWeights(PRESETS[name]);
}

// ----- playback of recordings ----------------------------------------------------------------------------

function loadRecording(text, name) {
  stopPlayback();
  try {
    const log = looksLikeJson(text) ? parseBsData(text, table) : parseFaceLog(text, table, name);
    const info = `${name}: ${log.kind}, layout ${log.layout}, ${log.rows} rows, ${log.duration.toFixed(2)} s`;
    playback = { log, name, info, start: 0, idx: -1, timer: null, skipped: 0, unsent: false };
    $("playinfo").textContent = info;
    $("play").disabled = false;
    startPlayback();
    return { rows: log.rows, layout: log.layout, duration: log.duration };
  } catch (e) {
    $("playinfo").textContent = "";
    reportError(`${e.message}`);
    return { error: e.message };
  }
}

function startPlayback() {
  if (!playback) return;
  stopPlayback(true);
  playback.start = performance.now();
  playback.idx = -1;
  playback.skipped = 0;
  playback.unsent = false;
  $("stop").disabled = false;
  playStep();
}

function stopPlayback(keep = false) {
  if (!playback?.unsent) playbackConf = null; // else the last sample, held back by flow control, keeps its own
  if (playback?.timer) clearTimeout(playback.timer);
  if (playback) playback.timer = null;
  $("stop").disabled = true;
  if (!keep && playback) $("playinfo").textContent = playback.info + skippedText(playback);
}

function skippedText(p) {
  return p.skipped ? ` · ${p.skipped} of ${p.log.rows} samples skipped (late or flow-controlled)` : "";
}

function playStep() {
  const p = playback;
  const { times, frames, rows } = p.log;
  const t = (performance.now() - p.start) / 1000;
  let idx = p.idx;
  while (idx + 1 < rows && times[idx + 1] <= t) idx++;
  if (idx !== p.idx && idx >= 0) {
    p.skipped += idx - p.idx - 1 + (p.unsent ? 1 : 0); // rows a late timer passed over; one never sent
    p.idx = idx;
    weights.set(frames.subarray(52 * idx, 52 * idx + 52));
    playbackConf = p.log.conf ? p.log.conf.subarray(2 * idx, 2 * idx + 2) : null; // a Quest log's confidences
    weightsDirty = true;
    p.unsent = true;
    p.slidersStale = true;
    maybeSend(performance.now()); // at the recorded time (flow control permitting)
    wake();
  }
  $("playinfo").textContent = `${p.info} · playing ${t.toFixed(1)} s${skippedText(p)}`;
  if (idx + 1 >= rows) {
    if ($("loop").checked && rows > 1) {
      p.timer = setTimeout(() => { p.start = performance.now(); p.idx = -1; playStep(); }, 200);
    } else {
      stopPlayback();
    }
    return;
  }
  const next = p.start + times[idx + 1] * 1000;
  p.timer = setTimeout(playStep, Math.max(0, next - performance.now()));
}

// ----- connection ----------------------------------------------------------------------------------------

function connect(maxGaussians) {
  if (conn) {
    const old = conn;
    old.closing = true;
    try { if (old.ws.readyState === WebSocket.OPEN) old.ws.send(byeMessage()); old.ws.close(1000); } catch { /* gone */ }
  }
  const gen = ++connGen;
  const ws = new WebSocket(opts.url);
  ws.binaryType = "arraybuffer";
  conn = { ws, gen, state: "connecting", welcome: null, count: 0, maxGaussians, seq: 0, lastSeq: -1, lastSendMs: 0,
    room: opts.room, publish: opts.room === null || opts.publish };
  const c = conn;
  prepBusy = false;
  room.clear();
  setStatus(`connecting to ${opts.url}${maxGaussians ? ` (at most ${maxGaussians} Gaussians)` : ""} …`);
  ws.onopen = () => {
    ws.send(helloMessage({ layout: "arkit52", avatar: opts.avatar, encoding: opts.encoding, sparse: opts.sparse,
      delta: opts.delta && c.room === null, device: opts.device, token: opts.token, maxGaussians: maxGaussians ?? undefined,
      room: c.room ?? undefined, publish: c.publish, self: opts.self, roomToken: opts.roomToken }));
  };
  ws.onmessage = (ev) => {
    if (c !== conn) return;
    try {
      onMessage(c, ev.data);
    } catch (e) {
      const fatal = c.state !== "streaming" || !(e instanceof ProtocolError);
      reportError(`${fatal ? "fatal" : "dropped a frame"}: ${e.message}`);
      if (fatal) fatalClose(c, e);
    }
  };
  ws.onclose = (ev) => {
    if (c !== conn) return;
    const was = c.state;
    c.state = "closed";
    room.clear();
    if (c.closing) return;
    const why = c.refused ?? `disconnected (${ev.reason ? `${ev.code} ${ev.reason}` : ev.code})`;
    setStatus(`${why}; retrying in ${(retryMs / 1000).toFixed(0)} s`, true);
    setTimeout(() => { if (c === conn) connect(c.maxGaussians); }, retryMs);
    retryMs = was === "streaming" ? 1000 : Math.min(retryMs * 2, 15000);
  };
}

function fatalClose(c, e) {
  setStatus(`protocol error: ${e.message}`, true);
  c.closing = true;
  c.state = "closed";
  try { c.ws.close(CLOSE_CODES[e.code] ?? CLOSE_UNKNOWN_FATAL, e.code ?? "internal"); } catch { /* gone */ }
}

function intField(msg, key) {
  const v = msg[key];
  if (typeof v !== "number" || !Number.isInteger(v)) throw new ProtocolError("bad_field", `${msg.type}: '${key}' is not an int`);
  return v;
}

// Avatar chunks and frames are checked and applied in the worker; here only what the page needs.
function onMessage(c, buffer) {
  const bytes = new Uint8Array(buffer);
  let msg;
  try { msg = decode(bytes); } catch (e) { throw new ProtocolError("malformed", e.message); }
  const type = msg?.type;
  if (type !== "avatar" && type !== "frame") msg = decodeServerMessage(bytes);
  if (type === "error") {
    reportError(`server ${msg.fatal ? "fatal " : ""}error ${msg.code}: ${msg.message}`);
    if (msg.fatal) {
      c.refused = `server refused: ${msg.code}: ${msg.message}`;
      setStatus(c.refused, true);
      if (c.state !== "streaming") retryMs = 15000;
    }
    return;
  }
  if (type === "pong") return;
  if (c.room !== null) {
    onRoomMessage(c, type, msg, buffer);
    return;
  }
  if (c.state === "connecting") {
    if (type !== "welcome") throw new ProtocolError("not_ready", `expected welcome, got ${type}`);
    c.welcome = msg;
    c.count = msg.avatar.count;
    c.state = "avatar";
    if (c.maxGaussians === null || c.maxGaussians === undefined) fullCount = msg.avatar.count;
    if (c.maxGaussians && msg.avatar.count > c.maxGaussians) {
      reportError(`the server ignored max_gaussians ${c.maxGaussians} (welcome count ${msg.avatar.count})`);
    }
    worker.postMessage({ kind: "welcome", gen: c.gen, welcome: msg });
    setStatus(`receiving avatar: ${msg.avatar.count} Gaussians …`);
    return;
  }
  if (type === "rig") { // params sessions (PROTOCOL.md 13): after the avatar's chunks; assembled in the worker
    if (c.welcome.encoding !== "params") throw new ProtocolError("bad_field", "a rig message outside a params session");
    worker.postMessage({ kind: "rig", gen: c.gen, buffer }, [buffer]);
    return;
  }
  if (c.state === "avatar") {
    if (type !== "avatar") throw new ProtocolError("not_ready", `expected an avatar chunk, got ${type}`);
    setStatus(`receiving avatar: chunk ${intField(msg, "chunk") + 1}/${intField(msg, "chunks")}`);
    worker.postMessage({ kind: "chunk", gen: c.gen, buffer }, [buffer]);
    return;
  }
  if (type !== "frame") throw new ProtocolError("bad_field", `unexpected ${type} while streaming`);
  const stamped = msg.params === undefined || msg.seq !== undefined; // params frames: seq and t once a second
  const seq = stamped ? intField(msg, "seq") : c.lastSeq + 1, t = stamped ? intField(msg, "t") : null;
  lastBytes = bytes.length;
  worker.postMessage({ kind: "frame", gen: c.gen, buffer }, [buffer]);
  if (c.lastSeq >= 0 && seq > c.lastSeq + 1) droppedSeq += seq - c.lastSeq - 1;
  c.lastSeq = seq;
  framesReceived++;
  if (msg.timing) lastTiming = msg.timing; // unstamped params frames carry none
  if (t !== null) latencies.push((nowUs() - t) / 1000);
  if (latencies.length > 30) latencies.shift();
  prepWanted = true;
  wake();
}

// A room session (PROTOCOL.md 12): streaming from welcome on; every avatar, one's own too (self), comes with a join,
// its chunks and frames carry `member` (checked and applied in that member's worker, rooms.js).
function onRoomMessage(c, type, msg, buffer) {
  if (c.state === "connecting") {
    if (type !== "welcome") throw new ProtocolError("not_ready", `expected welcome, got ${type}`);
    if (msg.room === null) {
      throw new ProtocolError("bad_field", `asked to join room '${c.room}', the server answered with a v1 welcome (no rooms there?)`);
    }
    c.welcome = msg;
    c.state = "streaming";
    retryMs = 1000;
    room.start(msg);
    setStatus(`room ${msg.room} · you are ${msg.member}, ${c.publish ? `publishing ${msg.avatar.id}` : "watching"} · ${msg.encoding}${msg.sparse ? " sparse" : ""} · session ${msg.session}`);
    weightsDirty = c.publish; // the sliders' expression is the first bs
    wake();
    return;
  }
  if (type === "join") room.join(msg);
  else if (type === "leave") room.leave(msg);
  else if (type === "avatar" || type === "frame" || type === "rig") {
    if (typeof msg.member !== "string") throw new ProtocolError("bad_field", `${type} without 'member' in a room session`);
    if (type === "avatar") room.chunk(msg.member, buffer);
    else if (type === "rig") room.rig(msg.member, buffer); // params sessions (PROTOCOL.md 13.6)
    else if (msg.params !== undefined && msg.seq === undefined) room.frame(msg.member, { seq: null, t: null }, buffer); // unstamped
    else room.frame(msg.member, { seq: intField(msg, "seq"), t: intField(msg, "t"), timing: msg.timing }, buffer);
  } else {
    throw new ProtocolError("bad_field", `unexpected ${type} in a room session`);
  }
  wake();
}

worker.onmessage = ({ data }) => {
  const c = conn;
  if (data.kind === "prepared") prepBusy = false;
  if (!c || data.gen !== c.gen || data.stale) { schedule(); return; }
  if (data.kind === "avatar") {
    c.state = "streaming";
    retryMs = 1000;
    if (!cam.home) frameCamera(data.lo, data.hi);
    const w = c.welcome;
    setStatus(`streaming ${w.avatar.id}: ${c.count}${fullCount && c.count < fullCount ? ` of ${fullCount}` : ""} Gaussians, ${w.encoding}${w.sparse ? " sparse" : ""} · session ${w.session}`);
    weightsDirty = true; // the first frame shows the sliders' expression
    drawnSeq = -1;
    prepWanted = true;
    activeSince = null;
    wake(MEASURE_MS);
  } else if (data.kind === "error") {
    reportError(`${data.fatal ? "fatal" : "dropped a frame"}: ${data.code}: ${data.message}`);
    if (data.fatal) fatalClose(c, new ProtocolError(data.code, data.message));
    else if (c.welcome?.delta && c.ws.readyState === WebSocket.OPEN) c.ws.send(resyncMessage()); // a lost delta frame
  } else if (data.kind === "prepared") {
    prepMs = performance.now() - prepSentAt;
    renderer.setSplats(data.buffer, data.count);
    spare = data.buffer;
    drawnSeq = data.seq;
    drawnView = prepView;
    needsDraw = fresh = true;
    schedule();
  }
};

function maybeSend(now) {
  const c = conn;
  if (!c || c.state !== "streaming" || !weightsDirty || c.ws.readyState !== WebSocket.OPEN) return;
  if (c.room !== null) { // no frame answers a bs (one's own come only with self): pace by time and the socket
    if (!c.publish || c.ws.bufferedAmount > 0 || now - c.lastSendMs < ROOM_SEND_MS) return;
  } else {
    const outstanding = c.seq - 1 - c.lastSeq; // sent, not answered (the server may skip some)
    if (outstanding >= 2 && now - c.lastSendMs < 1000) return;
  }
  c.ws.send(bsMessage(c.seq, nowUs(), weights, playbackConf));
  if (playback?.unsent) {
    playback.unsent = false;
    if (playback.timer === null) playbackConf = null; // the recording's last sample is out
  }
  c.seq += 1;
  c.lastSendMs = now;
  weightsDirty = false;
}

function scaleMul() {
  const n = conn?.count ?? 0;
  return opts.fill && fullCount && n && n < fullCount ? Math.min(4, Math.sqrt(fullCount / n)) : 1;
}

function requestPrep() {
  const [view, proj] = matrices();
  prepBusy = true;
  prepWanted = false;
  prepSentAt = performance.now();
  prepView = viewVersion;
  const msg = { kind: "prep", gen: conn.gen, id: ++prepId, view, proj, width: canvas.width, height: canvas.height,
    scaleMul: scaleMul(), buffer: spare };
  worker.postMessage(msg, spare ? [spare] : []);
  spare = null;
}

// ----- camera ---------------------------------------------------------------------------------------------

function frameCamera(lo, hi) {
  const size = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 1e-3);
  const target = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2 + 0.08 * (hi[1] - lo[1]), (lo[2] + hi[2]) / 2];
  cam.home = { target, dist: (0.62 * size) / Math.tan(cam.fovy / 2), yaw: 0, pitch: 0 };
  resetCamera();
}

function resetCamera() {
  if (!cam.home) return;
  Object.assign(cam, { target: cam.home.target.slice(), dist: cam.home.dist, yaw: cam.home.yaw, pitch: cam.home.pitch });
  viewChanged();
}

function viewChanged() {
  viewMat = null;
  viewVersion++;
  prepWanted = true;
  wake();
}

function matrices() {
  if (!viewMat) {
    const cp = Math.cos(cam.pitch);
    const eye = [cam.target[0] + cam.dist * cp * Math.sin(cam.yaw), cam.target[1] + cam.dist * Math.sin(cam.pitch),
      cam.target[2] + cam.dist * cp * Math.cos(cam.yaw)];
    viewMat = lookAt(eye, cam.target);
    projMat = perspective(cam.fovy, canvas.width / canvas.height, Math.max(0.005, cam.dist * 0.05), cam.dist * 20);
  }
  return [viewMat, projMat];
}

function setupCameraInput() {
  let drag = null;
  canvas.addEventListener("pointerdown", (ev) => { drag = { x: ev.clientX, y: ev.clientY }; canvas.setPointerCapture(ev.pointerId); });
  canvas.addEventListener("pointermove", (ev) => {
    if (!drag) return;
    cam.yaw -= (ev.clientX - drag.x) * 0.008;
    cam.pitch = Math.min(1.45, Math.max(-1.45, cam.pitch + (ev.clientY - drag.y) * 0.008));
    drag = { x: ev.clientX, y: ev.clientY };
    viewChanged();
  });
  const end = () => { drag = null; };
  canvas.addEventListener("pointerup", end);
  canvas.addEventListener("pointercancel", end);
  canvas.addEventListener("wheel", (ev) => {
    ev.preventDefault();
    cam.dist = Math.min(20, Math.max(0.05, cam.dist * Math.exp(ev.deltaY * 0.001)));
    viewChanged();
  }, { passive: false });
  canvas.addEventListener("dblclick", resetCamera);
}

function resize() {
  const r = canvas.getBoundingClientRect();
  const k = Math.min(window.devicePixelRatio || 1, opts.res / Math.max(r.width, r.height, 1));
  const w = Math.max(1, Math.round(r.width * k)), h = Math.max(1, Math.round(r.height * k));
  if (canvas.width !== w || canvas.height !== h) {
    canvas.width = w;
    canvas.height = h;
    viewChanged();
  }
}

// ----- the display loop ----------------------------------------------------------------------------------
// While something changes (and for a while after), the loop keeps the worker preparing splats for the
// current view and draws each result: the rate of new pictures is the page's fps. Idle, it stops.

function wake(ms = ACTIVE_MS) {
  activeUntil = Math.max(activeUntil, performance.now() + ms);
  schedule();
}

function schedule() {
  if (!rafPending) {
    rafPending = true;
    requestAnimationFrame(tick);
  }
}

function tick(now) {
  rafPending = false;
  maybeSend(now);
  if (playback?.slidersStale) { playback.slidersStale = false; syncSliders(); }
  const c = conn;
  const streaming = c?.state === "streaming" && c.room === null; // a room session draws in its tiles (rooms.js)
  const active = now < activeUntil;
  if (streaming && (prepWanted || active) && !prepBusy) requestPrep();
  const roomBusy = room.tick(now);
  if (needsDraw) {
    renderer.draw();
    needsDraw = false;
    framesDrawn++;
    if (fresh) { updateTimes.push(now); fresh = false; }
  }
  measure(now, active && streaming);
  updateHud(now);
  if (active || needsDraw || (weightsDirty && c?.publish !== false) || prepBusy || prepWanted || roomBusy) {
    rafPending = true;
    requestAnimationFrame(tick);
  } else {
    activeSince = null;
  }
}

function measure(now, running) {
  while (updateTimes.length && updateTimes[0] < now - SLOW_WINDOW_MS) updateTimes.shift();
  if (!running) { activeSince = null; return; }
  if (activeSince === null) activeSince = now;
  const since = Math.max(activeSince, now - 1000);
  if (now - since >= 250) fps = (updateTimes.filter((t) => t > since).length * 1000) / (now - since);
  const c = conn;
  if (!opts.auto || c?.state !== "streaming" || now - activeSince < SLOW_WINDOW_MS) return;
  const windowFps = (updateTimes.filter((t) => t > now - SLOW_WINDOW_MS).length * 1000) / SLOW_WINDOW_MS;
  if (windowFps >= opts.minFps) return;
  const count = c.count;
  if (count <= MIN_GAUSSIANS) return;
  const ratio = Math.min(0.7, Math.max(0.2, windowFps / (opts.minFps * 1.3)));
  const target = Math.max(MIN_GAUSSIANS, Math.floor(count * ratio));
  reductions++;
  reportError(`${windowFps.toFixed(1)} fps < ${opts.minFps} for ${SLOW_WINDOW_MS / 1000} s: reconnecting for at most ${target} Gaussians (of ${count})`);
  activeSince = null;
  updateTimes.length = 0;
  connect(target);
}

let hudAt = 0;
function updateHud(now) {
  if (now - hudAt < 250) return;
  hudAt = now;
  const c = conn;
  const lat = latencies.length ? latencies.reduce((s, x) => s + x, 0) / latencies.length : null;
  const lines = [
    `fps      ${fps.toFixed(1)}${activeSince === null ? " (idle)" : ""} · prepare ${prepMs.toFixed(0)} ms`,
    `latency  ${lat === null ? "-" : `${latencies[latencies.length - 1].toFixed(1)} ms (avg ${lat.toFixed(1)})`}`,
    `frame    ${lastBytes ? `${(lastBytes / 1024).toFixed(1)} KiB` : "-"}${lastTiming?.total !== undefined ? ` · server ${(lastTiming.total / 1000).toFixed(1)} ms` : ""}`,
    `gauss.   ${c?.count || "-"}${fullCount && c?.count && c.count < fullCount ? ` / ${fullCount}` : ""}  ${c?.welcome ? `${c.welcome.encoding}${c.welcome.sparse ? " sparse" : ""} · ${c.welcome.avatar.expression}` : ""}`,
    `frames   ${framesReceived} recv · ${droppedSeq} skipped`,
  ];
  $("hud").textContent = lines.join("\n");
}

// ----- start ---------------------------------------------------------------------------------------------

async function main() {
  try {
    renderer = new SplatRenderer(canvas);
  } catch (e) {
    setStatus(`WebGL2 is not available: ${e.message}`, true);
    return;
  }
  room = new RoomView({ grid: $("tiles"), list: $("members"), res: opts.res, onError: reportError });
  room.onViewChange = () => wake();
  table = await (await fetch(new URL("./layouts.json", import.meta.url))).json();
  names = table.arkit52;
  buildControls();
  setupCameraInput();
  new ResizeObserver(() => { resize(); wake(); }).observe(canvas);
  resize();
  try {
    const info = await (await fetch("/v1/avatars")).json();
    const id = opts.avatar === "default" ? info.default : opts.avatar;
    const entry = info.avatars?.find((a) => a.id === id);
    if (entry?.count) fullCount = entry.count;
    if (opts.fill) { // room tiles enlarge the splats of a reduced avatar as the one view does (scaleMul)
      for (const a of info.avatars ?? []) if (a.count) room.fullCounts.set(a.id, a.count);
      if (room.fullCounts.has(info.default)) room.fullCounts.set("default", room.fullCounts.get(info.default));
    }
  } catch { /* not essential: learnt from the first full welcome instead */ }
  connect(opts.forcedMax);
}

main();
