// One room member on the page (rooms.js): its own canvas, WebGL2 renderer (renderer.js) and splat worker
// (splat-worker.js, which keeps that member's Gaussians), a view of the room's shared orbit camera framed on
// this member's avatar, and the member's stream statistics: frames per second arriving and drawn, and latency
// (now - frame.t: meaningful when the source's clock is this page's, e.g. another page; a source on another
// clock shows "other clock"). Frames reach the worker paced by the drawing: one frame, then one prepare; a frame
// that arrives while the worker is busy waits, and a newer one replaces it (newest wins, counted in `skipped`:
// room frames are dense or sparse against the neutral avatar, never deltas, so any one of them is complete).
import { nowUs } from "./protocol.js";
import { lookAt, perspective, SplatRenderer } from "./renderer.js";

const STATS_MS = 1000; // fps over the last second
const LATENCIES = 30; // latency average over the last frames
const CLOCK_SKEW_MS = 60000; // |now - t| beyond this: the source's clock is not this page's

/** The room's orbit camera, shared by every tile: yaw, pitch (radians), zoom (x each tile's framing distance). */
export class SharedView {
  constructor() {
    this.yaw = 0;
    this.pitch = 0;
    this.zoom = 1;
    this.version = 0;
    this.fovy = (30 * Math.PI) / 180;
  }

  rotate(dx, dy) {
    this.yaw -= dx * 0.008;
    this.pitch = Math.min(1.45, Math.max(-1.45, this.pitch + dy * 0.008));
    this.version++;
  }

  zoomBy(deltaY) {
    this.zoom = Math.min(30, Math.max(0.1, this.zoom * Math.exp(deltaY * 0.001)));
    this.version++;
  }

  reset() {
    Object.assign(this, { yaw: 0, pitch: 0, zoom: 1 });
    this.version++;
  }
}

export class MemberTile {
  /**
   * @param {HTMLElement} parent where the tile's <figure> goes
   * @param {string} member the member id (join.member)
   * @param {object} welcome the session's welcome with this member's avatar (what the worker's AvatarState needs)
   * @param {{view: SharedView, res: number, self: boolean, full: number | null,
   *   onError: (text: string) => void}} options full: Gaussians of the full avatar, if known
   */
  constructor(parent, member, welcome, { view, res, self, full, onError }) {
    this.member = member;
    this.self = self;
    this.welcome = welcome;
    this.view = view;
    this.res = res;
    this.onError = onError;
    const n = welcome.avatar.count; // a reduced avatar's splats are enlarged to cover as the full one (app.js scaleMul)
    this.scaleMul = full && n && n < full ? Math.min(4, Math.sqrt(full / n)) : 1;
    this.state = "avatar"; // -> "streaming" once every chunk (params: and the rig) is in, "closed" after a leave
    this.params = welcome.encoding === "params"; // frames carry 68 values, the worker deforms (PROTOCOL.md 13)
    this.home = null; // { target, dist } framing this avatar
    this.el = document.createElement("figure");
    this.el.className = "tile";
    this.el.dataset.member = member;
    this.canvas = document.createElement("canvas");
    this.caption = document.createElement("figcaption");
    this.el.append(this.canvas, this.caption);
    parent.append(this.el);
    this.renderer = new SplatRenderer(this.canvas); // throws without WebGL2 (the page reports it)
    this.worker = new Worker(new URL("./splat-worker.js", import.meta.url), { type: "module" });
    this.worker.onmessage = ({ data }) => this.onWorker(data);
    this.worker.postMessage({ kind: "welcome", gen: 1, welcome });
    this.arrivals = []; // performance.now() of frames received in the last STATS_MS
    this.draws = []; // ... and of new pictures drawn
    this.latencies = [];
    this.framesReceived = 0;
    this.framesDrawn = 0;
    this.skipped = 0; // frames replaced by a newer one before the worker took them
    this.pending = null; // the newest frame not yet handed to the worker: { buffer, seq (null: unstamped) }
    this.postedSeq = -1; // the seq the worker gives the last frame handed to it (unstamped: the one before + 1)
    this.lastSeq = -1;
    this.drawnSeq = -1;
    this.lastTiming = null;
    this.prepWanted = false;
    this.prepBusy = false;
    this.drawnView = -1;
    this.prepView = -1;
    this.spare = null;
    this.needsDraw = false;
    this.resize();
    this.caption.textContent = `${member}${self ? " (you)" : ""} · receiving avatar …`;
  }

  /** An `avatar` chunk of this member (the raw message: decoded and checked in the worker). */
  chunk(buffer) {
    this.worker.postMessage({ kind: "chunk", gen: 1, buffer }, [buffer]);
  }

  /** A params session's `rig` message of this member (the worker assembles the rig; it must follow the avatar). */
  rig(buffer) {
    this.worker.postMessage({ kind: "rig", gen: 1, buffer }, [buffer]);
  }

  /** A `frame` of this member: `msg` decoded (seq, t, timing; an unstamped params frame: seq and t null), `buffer`
   * its bytes (for the worker, at the next prepare). */
  frame(msg, buffer) {
    const now = performance.now();
    if (this.pending) this.skipped++;
    this.pending = { buffer, seq: msg.seq };
    this.framesReceived++;
    this.lastSeq = msg.seq ?? this.lastSeq + 1; // unstamped params frames: counted
    if (msg.timing) this.lastTiming = msg.timing;
    this.arrivals.push(now);
    if (msg.t !== null) this.latencies.push((nowUs() - msg.t) / 1000);
    if (this.latencies.length > LATENCIES) this.latencies.shift();
    this.prepWanted = true;
  }

  close() {
    this.state = "closed";
    this.worker.terminate();
    this.renderer.gl.getExtension("WEBGL_lose_context")?.loseContext(); // contexts are few: give it back now
    this.el.remove();
  }

  onWorker(data) {
    if (this.state === "closed") return;
    if (data.kind === "prepared") this.prepBusy = false;
    if (data.stale) return;
    if (data.kind === "rig") {
      this.state = "streaming"; // a params member: its frames can be deformed now
      this.prepWanted = true;
    } else if (data.kind === "avatar") {
      if (!this.params) this.state = "streaming";
      const { lo, hi } = data;
      const size = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 1e-3);
      this.home = {
        target: [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2 + 0.08 * (hi[1] - lo[1]), (lo[2] + hi[2]) / 2],
        dist: (0.62 * size) / Math.tan(this.view.fovy / 2),
      };
      this.prepWanted = true;
    } else if (data.kind === "error") {
      this.onError(`member ${this.member}: ${data.fatal ? "its avatar is unusable" : "dropped a frame"}: ${data.code}: ${data.message}`);
      if (data.fatal) this.state = "failed";
    } else if (data.kind === "prepared") {
      this.renderer.setSplats(data.buffer, data.count);
      this.spare = data.buffer;
      if (data.seq !== this.drawnSeq) this.draws.push(performance.now());
      this.drawnSeq = data.seq;
      this.drawnView = this.prepView;
      this.needsDraw = true;
    }
  }

  resize() {
    const r = this.canvas.getBoundingClientRect();
    const k = Math.min(window.devicePixelRatio || 1, this.res / Math.max(r.width, r.height, 1));
    const w = Math.max(1, Math.round(r.width * k)), h = Math.max(1, Math.round(r.height * k));
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
      this.prepWanted = true;
    }
  }

  matrices() {
    const v = this.view, home = this.home;
    const dist = home.dist * v.zoom, cp = Math.cos(v.pitch), t = home.target;
    const eye = [t[0] + dist * cp * Math.sin(v.yaw), t[1] + dist * Math.sin(v.pitch), t[2] + dist * cp * Math.cos(v.yaw)];
    return [lookAt(eye, t), perspective(v.fovy, this.canvas.width / this.canvas.height, Math.max(0.005, dist * 0.05), dist * 20)];
  }

  /** One display step: ask the worker for splats when something changed, draw what it prepared. True while busy. */
  tick(now) {
    if (this.state !== "streaming") return false;
    if (this.drawnView !== this.view.version) this.prepWanted = true;
    if ((this.prepWanted || this.pending) && !this.prepBusy) {
      if (this.pending) {
        const { buffer, seq } = this.pending;
        this.worker.postMessage({ kind: "frame", gen: 1, buffer }, [buffer]);
        this.postedSeq = seq ?? this.postedSeq + 1;
        this.pending = null;
      }
      const [view, proj] = this.matrices();
      this.prepBusy = true;
      this.prepWanted = false;
      this.prepView = this.view.version;
      this.worker.postMessage({ kind: "prep", gen: 1, id: 0, view, proj, width: this.canvas.width,
        height: this.canvas.height, scaleMul: this.scaleMul, buffer: this.spare }, this.spare ? [this.spare] : []);
      this.spare = null;
    }
    if (this.needsDraw) {
      this.renderer.draw();
      this.needsDraw = false;
      this.framesDrawn++;
    }
    const since = now - STATS_MS;
    while (this.arrivals.length && this.arrivals[0] < since) this.arrivals.shift();
    while (this.draws.length && this.draws[0] < since) this.draws.shift();
    return this.prepBusy || this.prepWanted || this.needsDraw || this.pending !== null;
  }

  /** Frames per second arriving from this member (over the last second). */
  get fps() { return (this.arrivals.length * 1000) / STATS_MS; }

  /** New pictures per second drawn for this member. */
  get drawFps() { return (this.draws.length * 1000) / STATS_MS; }

  /** Mean latency in ms (now - frame.t) over the last frames; null before any frame or when the clocks differ. */
  get latencyMs() {
    if (!this.latencies.length) return null;
    const mean = this.latencies.reduce((s, x) => s + x, 0) / this.latencies.length;
    return Math.abs(mean) < CLOCK_SKEW_MS ? mean : null;
  }

  /** Streaming, the newest frame drawn in the current view. */
  get settled() {
    return this.state === "streaming" && this.drawnSeq === this.postedSeq && this.drawnView === this.view.version
      && !this.prepBusy && !this.prepWanted && !this.needsDraw && !this.pending;
  }

  /** "last ms (avg mean)", "other clock" (the source's clock is not this page's) or "-" (no frame yet). */
  latencyText() {
    const mean = this.latencyMs;
    if (!this.latencies.length) return "-";
    if (mean === null) return "other clock";
    return `${this.latencies[this.latencies.length - 1].toFixed(1)} ms (avg ${mean.toFixed(1)})`;
  }

  updateCaption() {
    const latText = this.latencyText();
    const server = this.lastTiming?.total !== undefined ? ` · server ${(this.lastTiming.total / 1000).toFixed(1)} ms` : "";
    const head = `${this.member}${this.self ? " (you)" : ""}`;
    this.caption.textContent = this.state === "streaming"
      ? `${head} · ${this.fps.toFixed(0)} fps (drawn ${this.drawFps.toFixed(0)}) · latency ${latText}${server}`
      : `${head} · ${this.state === "avatar" ? "receiving avatar …" : this.state}`;
  }

  /** What tests read (window.__ofera.room.members). */
  snapshot() {
    return { member: this.member, avatar: this.welcome.avatar.id, count: this.welcome.avatar.count, self: this.self,
      state: this.state, framesReceived: this.framesReceived, framesDrawn: this.framesDrawn, skipped: this.skipped,
      lastSeq: this.lastSeq, drawnSeq: this.drawnSeq, fps: this.fps, drawFps: this.drawFps, latencyMs: this.latencyMs,
      settled: this.settled };
  }
}
