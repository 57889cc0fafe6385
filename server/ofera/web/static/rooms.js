// The room half of the preview page (PROTOCOL.md section 12): who is in the room (join / leave), and one tile
// per publishing member (member-tile.js: its own canvas, renderer and splat worker), side by side, all turned
// by one orbit camera. app.js owns the connection and hands this the room's messages.
import { ProtocolError } from "./protocol.js";
import { MemberTile, SharedView } from "./member-tile.js";

const LIST_MS = 250; // member list and captions refresh

export class RoomView {
  /**
   * @param {{grid: HTMLElement, list: HTMLElement, res: number, onError: (text: string) => void}} options
   * grid: where the tiles go; list: the <ul> of members.
   */
  constructor({ grid, list, res, onError }) {
    this.grid = grid;
    this.list = list;
    this.res = res;
    this.onError = onError;
    this.view = new SharedView();
    this.welcome = null; // the session's (room, member: this client's id)
    this.members = new Map(); // member id -> { join, tile (null: watch-only, or `unshown`: no renderer for it) }
    this.left = []; // the latest departures: { member, reason, at (Date.now() when it arrived) }
    this.listAt = 0;
    this.fullCounts = new Map(); // avatar id -> Gaussians of the full avatar (app.js, from /v1/avatars)
    this.onViewChange = null; // called when the tiles need drawing again (the page wakes its display loop)
    this.resizer = new ResizeObserver(() => { this.resize(); this.onViewChange?.(); }); // tiles reflow as members come and go
    this.setupInput();
  }

  get room() { return this.welcome?.room ?? null; }
  get self() { return this.welcome?.member ?? null; }

  /** A new session (its welcome): everyone of the previous session is gone. */
  start(welcome) {
    this.clear();
    this.welcome = welcome;
    this.left = [];
    this.renderList(true);
  }

  /** The session ended (or the page left the room). */
  clear() {
    for (const m of this.members.values()) this.closeTile(m.tile);
    this.members.clear();
    this.welcome = null;
    this.renderList(true);
  }

  /** `join`: a member is in the room; a publishing member's avatar chunks follow. A repeated join replaces it. */
  join(msg) {
    const old = this.members.get(msg.member);
    if (old) this.closeTile(old.tile);
    let tile = null, unshown = null;
    if (msg.avatar) {
      const welcome = { ...this.welcome, avatar: msg.avatar, quant: msg.quant ?? this.welcome.quant };
      try {
        tile = new MemberTile(this.grid, msg.member, welcome, { view: this.view, res: this.res,
          self: msg.member === this.self, full: this.fullCounts.get(msg.avatar.id) ?? null, onError: this.onError });
        this.resizer.observe(tile.canvas);
      } catch (e) { // e.g. the browser's WebGL contexts are used up: listed, not drawn, the session goes on
        unshown = e.message;
        this.onError(`member ${msg.member}: not shown: ${e.message}`);
      }
    }
    this.members.set(msg.member, { join: msg, tile, unshown });
    this.renderList(true);
  }

  /** `leave`: the member's tile goes. A leave for a member this page does not know is ignored. */
  leave(msg) {
    const m = this.members.get(msg.member);
    if (!m) return;
    this.closeTile(m.tile);
    this.members.delete(msg.member);
    this.left.unshift({ member: msg.member, reason: msg.reason, at: Date.now() }); // at: wall clock, ms
    this.left.length = Math.min(this.left.length, 5);
    this.renderList(true);
  }

  closeTile(tile) {
    if (!tile) return;
    this.resizer.unobserve(tile.canvas);
    tile.close();
  }

  /** The member's tile; null for a member this page cannot show (its messages are dropped quietly). */
  tileOf(member, what) {
    const m = this.members.get(member);
    if (!m) throw new ProtocolError("not_ready", `${what} for member '${member}' before its join`);
    if (m.unshown) return null;
    if (!m.tile) throw new ProtocolError("bad_field", `${what} for member '${member}', who has no avatar (watch-only)`);
    return m.tile;
  }

  /** An `avatar` chunk carrying `member` (raw bytes, handed to that member's worker). */
  chunk(member, buffer) {
    this.tileOf(member, "an avatar chunk")?.chunk(buffer);
  }

  /** A params session's `rig` message carrying `member` (PROTOCOL.md 13.6; assembled in that member's worker). */
  rig(member, buffer) {
    this.tileOf(member, "a rig message")?.rig(buffer);
  }

  /** A `frame` carrying `member`: `msg` decoded for seq, t and timing; `buffer` goes to that member's worker. */
  frame(member, msg, buffer) {
    this.tileOf(member, "a frame")?.frame(msg, buffer);
  }

  /** One display step for every tile; true while any of them has work left. */
  tick(now) {
    let busy = false;
    for (const m of this.members.values()) if (m.tile) busy = m.tile.tick(now) || busy;
    if (now - this.listAt >= LIST_MS) {
      this.listAt = now;
      this.renderList(false);
    }
    return busy;
  }

  resize() {
    for (const m of this.members.values()) m.tile?.resize();
  }

  /** Every tile has drawn its member's newest frame in the current view. */
  get settled() {
    for (const m of this.members.values()) if (m.tile && !m.tile.settled) return false;
    return true;
  }

  renderList(structural) {
    for (const m of this.members.values()) m.tile?.updateCaption();
    if (!structural && this.list.children.length === this.members.size + (this.left.length ? 1 : 0)) {
      for (const li of this.list.querySelectorAll("li[data-member]")) {
        const m = this.members.get(li.dataset.member);
        if (m) li.querySelector(".stats").textContent = statsText(m);
      }
      return;
    }
    this.list.replaceChildren();
    for (const [id, m] of this.members) {
      const li = document.createElement("li");
      li.dataset.member = id;
      const name = document.createElement("b");
      name.textContent = id + (id === this.self ? " (you)" : "");
      const what = document.createElement("span");
      what.className = "small";
      what.textContent = m.join.avatar ? ` ${m.join.avatar.id}, ${m.join.avatar.count} Gaussians` : " watching";
      const stats = document.createElement("div");
      stats.className = "stats small";
      stats.textContent = statsText(m);
      li.append(name, what, stats);
      this.list.append(li);
    }
    if (this.left.length) {
      const li = document.createElement("li");
      li.className = "small left";
      li.textContent = "left: " + this.left.map((l) => `${l.member} (${l.reason})`).join(", ");
      this.list.append(li);
    }
  }

  /** What tests read (window.__ofera.room). */
  snapshot() {
    return {
      room: this.room, member: this.self,
      members: [...this.members.entries()].map(([id, m]) => m.tile?.snapshot()
        ?? { member: id, avatar: m.join.avatar?.id ?? null, count: m.join.avatar?.count ?? 0, self: id === this.self,
          state: m.unshown ? "unshown" : "watching", publish: m.join.publish }),
      left: this.left.slice(), settled: this.settled,
    };
  }

  // One orbit camera for every tile: drag on any tile turns them all, the wheel zooms, a double click resets.
  setupInput() {
    let drag = null;
    const onTile = (ev) => ev.target instanceof HTMLCanvasElement && this.grid.contains(ev.target);
    this.grid.addEventListener("pointerdown", (ev) => {
      if (!onTile(ev)) return;
      drag = { x: ev.clientX, y: ev.clientY };
      ev.target.setPointerCapture(ev.pointerId);
    });
    this.grid.addEventListener("pointermove", (ev) => {
      if (!drag) return;
      this.view.rotate(ev.clientX - drag.x, ev.clientY - drag.y);
      drag = { x: ev.clientX, y: ev.clientY };
      this.onViewChange?.();
    });
    const end = () => { drag = null; };
    this.grid.addEventListener("pointerup", end);
    this.grid.addEventListener("pointercancel", end);
    this.grid.addEventListener("wheel", (ev) => {
      if (!onTile(ev)) return;
      ev.preventDefault();
      this.view.zoomBy(ev.deltaY);
      this.onViewChange?.();
    }, { passive: false });
    this.grid.addEventListener("dblclick", (ev) => {
      if (!onTile(ev)) return;
      this.view.reset();
      this.onViewChange?.();
    });
  }
}

function statsText(m) {
  if (m.unshown) return `not shown: ${m.unshown}`;
  if (!m.tile) return "watch-only";
  const t = m.tile;
  if (t.state !== "streaming") return t.state === "avatar" ? "receiving avatar …" : t.state;
  return `${t.fps.toFixed(0)} fps (drawn ${t.drawFps.toFixed(0)}) · latency ${t.latencyText()} · ${t.framesReceived} frames, ${t.skipped} not drawn`;
}
