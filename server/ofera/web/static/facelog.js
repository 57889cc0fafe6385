// Reading recorded blendshapes dropped onto the page, in the browser: the OFERA face-log CSV
// (protocol/FACELOG.md: `time` in seconds, `# key: value` metadata, any supported layout), MediaPipe /
// ARKit CSVs (time, time_ms, timestamp_ms, timestamp_us, or frame numbers with fps) and Live Link Face
// CSVs (`Timecode` HH:MM:SS:FF.fff at 60 fps unless `# fps:` says otherwise, `BlendshapeCount`).
// Columns are matched by name (case-insensitive, underscores ignored) and every row is converted to
// arkit52 with the layout's map from /static/layouts.json (the server's own table). Quest Pro Unity logs
// (Meta enum names beside other columns, or headerless) go to parseQuestLog below.

export class FaceLogError extends Error {}

export const normalizeName = (s) => s.trim().toLowerCase().replaceAll("_", "");

const TIME_COLUMNS = { time: 1, timems: 1e-3, timestampms: 1e-3, timestampus: 1e-6 };
const FRAME_COLUMNS = ["frame", "frameindex", "framenumber"];
const IGNORED = new Set(["confidencelower", "confidenceupper", "datasource", "blendshapecount"]);
const TIMECODE = /^(\d{1,2}):(\d{2}):(\d{2})[:;](\d+(?:\.\d*)?)$/;
const DAY = 86400;

/** `HH:MM:SS:FF.fff` (frame within the second at `fps`) -> seconds since midnight. */
export function parseTimecode(text, fps = 60) {
  const m = TIMECODE.exec(text.trim());
  if (!m) throw new FaceLogError(`timecode '${text}' is not HH:MM:SS:FF.fff`);
  const [h, mi, s] = [m[1], m[2], m[3]].map(Number);
  const frame = Number(m[4]);
  if (h >= 24 || mi >= 60 || s >= 60) throw new FaceLogError(`timecode '${text}' is out of range`);
  if (frame >= fps) throw new FaceLogError(`timecode '${text}': frame ${frame} is not below ${fps} fps (wrong fps?)`);
  return h * 3600 + mi * 60 + s + frame / fps;
}

/** Which layout the blendshape columns are: {layout, columnOf: layout index -> column}, or ARKit by name. */
function matchLayout(names, table) {
  const position = new Map(names.map((n, i) => [normalizeName(n), i]));
  let best = null;
  for (const [layout, info] of Object.entries(table.layouts)) {
    const wanted = info.names.map(normalizeName);
    const found = wanted.filter((n) => position.has(n)).length;
    if (found === wanted.length && found === position.size) return { layout, columnOf: wanted.map((n) => position.get(n)) };
    if (!best || found > best.found) best = { layout, found, missing: wanted.filter((n) => !position.has(n)) };
  }
  // Not exactly a layout: take the ARKit shapes present by name (the others stay 0) if that explains the file.
  const arkit = table.arkit52.map(normalizeName);
  const known = new Set(arkit);
  const unknown = names.filter((n) => !known.has(normalizeName(n)));
  const present = arkit.filter((n) => position.has(n)).length;
  if (present > 0 && unknown.length === 0) {
    return { layout: "arkit52", columnOf: arkit.map((n) => (position.has(n) ? position.get(n) : -1)), partial: true };
  }
  const missing = best ? best.missing.slice(0, 8).join(", ") : "";
  throw new FaceLogError(`the columns are not a known blendshape layout (closest: ${best?.layout}, missing ${missing}; `
    + `unknown: ${unknown.slice(0, 8).join(", ")})`);
}

/**
 * Parse a CSV text into { times (s, from 0), frames (Float32Array n*52, arkit52), layout, kind, rows }.
 * `table` is /static/layouts.json.
 */
export function parseFaceLog(text, table, name = "file") {
  if (isQuestLog(text, table)) return parseQuestLog(text, table, name);
  const lines = text.split(/\r?\n/);
  const meta = {};
  let header = null, headerLine = 0;
  const rows = [];
  for (let i = 0; i < lines.length; i++) {
    const line = lines[i].trim();
    if (!line) continue;
    if (line.startsWith("#")) {
      const m = /^#\s*([^:]+):\s*(.*)$/.exec(line);
      if (m) meta[m[1].trim().toLowerCase()] = m[2].trim();
      continue;
    }
    if (header === null) { header = line.split(",").map((s) => s.trim()); headerLine = i + 1; continue; }
    rows.push([i + 1, line.split(",")]);
  }
  if (!header) throw new FaceLogError(`${name}: no header line`);
  if (!rows.length) throw new FaceLogError(`${name}: no data rows`);
  const norm = header.map(normalizeName);
  const tc = norm.indexOf("timecode");
  const fps = meta.fps ? Number(meta.fps) : null;
  let timeCol = -1, timeUnit = 1, frameCol = -1;
  if (tc < 0) {
    timeCol = norm.findIndex((n) => n in TIME_COLUMNS);
    if (timeCol >= 0) timeUnit = TIME_COLUMNS[norm[timeCol]];
    else {
      frameCol = norm.findIndex((n) => FRAME_COLUMNS.includes(n));
      if (frameCol < 0) throw new FaceLogError(`${name}, line ${headerLine}: no time column (time, time_ms, timestamp_ms, timestamp_us, frame or Timecode)`);
      if (!(fps > 0)) throw new FaceLogError(`${name}: a 'frame' column needs '# fps: <rate>' metadata`);
    }
  }
  const special = new Set([tc, timeCol, frameCol]);
  const shapeCols = [];
  header.forEach((h, i) => { if (!special.has(i) && !IGNORED.has(norm[i])) shapeCols.push(i); });
  let match;
  try {
    match = matchLayout(shapeCols.map((i) => header[i]), table);
  } catch (e) {
    throw new FaceLogError(`${name}, line ${headerLine}: ${e.message}`);
  }
  if (meta.layout && !match.partial && meta.layout !== match.layout) {
    throw new FaceLogError(`${name}: '# layout: ${meta.layout}' but the columns are ${match.layout}`);
  }
  const info = table.layouts[match.layout];
  const L = info.names.length;
  const n = rows.length;
  const times = new Float64Array(n);
  const frames = new Float32Array(n * 52);
  const w = new Float32Array(L);
  let day = 0;
  for (let r = 0; r < n; r++) {
    const [lineNo, cells] = rows[r];
    let t;
    if (tc >= 0) {
      try { t = parseTimecode(cells[tc] ?? "", fps ?? 60) + day; } catch (e) { throw new FaceLogError(`${name}, line ${lineNo}: ${e.message}`); }
      if (r && t < times[r - 1] - DAY / 2) { day += DAY; t += DAY; }
    } else if (timeCol >= 0) t = Number(cells[timeCol]) * timeUnit;
    else t = Number(cells[frameCol]) / fps;
    if (!Number.isFinite(t)) throw new FaceLogError(`${name}, line ${lineNo}: time '${cells[tc >= 0 ? tc : timeCol >= 0 ? timeCol : frameCol]}' is not a number`);
    if (r && t < times[r - 1]) throw new FaceLogError(`${name}, line ${lineNo}: time goes back (${t} after ${times[r - 1]})`);
    times[r] = t;
    for (let k = 0; k < L; k++) {
      const col = match.columnOf[k];
      if (col < 0) { w[k] = 0; continue; }
      const v = Number(cells[shapeCols[col]]);
      if (!Number.isFinite(v)) throw new FaceLogError(`${name}, line ${lineNo}: column '${header[shapeCols[col]]}': '${cells[shapeCols[col]]}' is not a finite number`);
      w[k] = v;
    }
    const out = frames.subarray(52 * r, 52 * r + 52);
    for (const [d, s, v] of info.to_arkit52) out[d] += v * w[s];
    for (let k = 0; k < 52; k++) out[k] = Math.min(1, Math.max(0, out[k]));
  }
  const t0 = times[0];
  for (let r = 0; r < n; r++) times[r] -= t0;
  return { times, frames, layout: match.layout, kind: tc >= 0 ? "Live Link Face CSV" : "face-log CSV", rows: n,
    duration: times[n - 1], meta };
}

// ----- Quest Pro Unity logs (the port of server/ofera/sources/quest_csv.py; protocol/FACELOG.md) ----------
// Meta enum names in any spelling and order (v1 63 CamelCase, v2 70 with underscores), `Max`/`Invalid`
// ignored (left out of the header when the rows hold no value for them), tracker time `Face_Time` > a Unity
// clock > a row rate, `Face_Status` false rows and rows with `Face_Time` <= 0 dropped as invalid,
// `FaceRegionConfidence_Lower/_Upper` kept, labels ignored; repeated samples sent once (a new tracker time,
// or without one a row differing from the previous kept row; a tracker time too coarse to tell samples
// apart is not used). The page has no --layout/--fps: a headerless file's layout is taken from its width
// (63: ovr63, 70: ovr70) or `# layout:`, and a log without time is paced at `# fps:` or 30 rows per second;
// the play info says so.

const TRACKER_KEYS = ["facetime", "trackertime", "facestatetime"];
const CLOCK_KEYS = ["timesincestartup", "realtimesincestartup", "timefromstart", "time", "timestamp"];
const STATUS_KEYS = ["facestatus", "facevalid", "isvalid"];
const CONF_KEYS = [["faceregionconfidencelower", "confidencelower", "lowerfaceconfidence"],
  ["faceregionconfidenceupper", "confidenceupper", "upperfaceconfidence"]];
const SOURCE_KEYS = ["facedatasource", "datasource"];
const ENUM_EXTRA_KEYS = ["max", "invalid", "count"];
const SPECIAL_KEYS = new Set([...TRACKER_KEYS, ...CLOCK_KEYS, ...STATUS_KEYS, ...CONF_KEYS[0], ...CONF_KEYS[1],
  ...SOURCE_KEYS]);
const LONG_GAP_S = 3;
const STRICT_KEYS = new Set(["time", "timems", "timestampms", "timestampus", "frame", "frameindex", "framenumber",
  "confidencelower", "confidenceupper", "datasource"]);
const STATUS_VALUES = { true: true, 1: true, valid: true, yes: true, false: false, 0: false, invalid: false, no: false };
const MAX_MALFORMED_SHARE = 0.05;
const DEFAULT_FPS = 30;

const isNumber = (s) => s.trim() !== "" && Number.isFinite(Number(s));

/** Matching key of a column name: quotes and an enum prefix dropped, separators removed, lowercase; the
 * whole name is tried first against the time/status/confidence keys (`FaceState.Time` is the tracker time). */
export function columnKey(name) {
  const s = name.trim().replace(/^["']+|["']+$/g, "");
  const full = s.replace(/[\s_\-.]+/g, "").toLowerCase();
  if (SPECIAL_KEYS.has(full) || !s.includes(".") || isNumber(s)) return full;
  return s.slice(s.lastIndexOf(".") + 1).replace(/[\s_\-.]+/g, "").toLowerCase();
}

/** The most common number of cells in a row. */
function usualWidth(rows) {
  const count = new Map();
  for (const [, c] of rows) count.set(c.length, (count.get(c.length) ?? 0) + 1);
  let best = -1, most = 0;
  for (const [w, n] of count) if (n > most) { best = w; most = n; }
  return best;
}

function ovrKeys(table) {
  return new Map(table.layouts.ovr70.names.map((n, i) => [n.replaceAll("_", "").toLowerCase(), i]));
}

function splitLines(text) {
  const meta = {};
  let magic = false;
  const kept = [];
  const lines = text.replace(/^\ufeff/, "").split(/\r?\n/);
  for (let i = 0; i < lines.length; i++) {
    const line = lines[i].trim();
    if (!line) continue;
    if (line.startsWith("#")) {
      const body = line.slice(1).trim();
      if (!kept.length && body.toLowerCase().startsWith("ofera facelog")) magic = true;
      const m = /^([^:]+):\s*(.*)$/.exec(body);
      if (m) meta[m[1].trim().toLowerCase()] = m[2].trim();
      continue;
    }
    kept.push([i + 1, line]);
  }
  return { meta, magic, kept };
}

function delimiterOf(line) {
  let best = ",", count = (line.match(/,/g) || []).length;
  for (const d of [";", "\t"]) {
    const c = line.split(d).length - 1;
    if (c > count) { best = d; count = c; }
  }
  return best;
}

const cellsOf = (line, d) => line.split(d).map((c) => c.trim().replace(/^"(.*)"$/, "$1"));
const headerless = (cells) => {
  const v = cells.filter((c) => c);
  return v.length > 0 && v.every((c) => isNumber(c.replace(",", ".")) || c.toLowerCase() in STATUS_VALUES);
};

/** True if the page should read `text` as a Quest Pro log (same rule as quest_csv.sniff_quest_log). */
export function isQuestLog(text, table) {
  const { magic, kept } = splitLines(text.slice(0, 1 << 16));
  if (!kept.length) return false;
  const cells = cellsOf(kept[0][1], delimiterOf(kept[0][1]));
  if (headerless(cells)) return true;
  const ovr = ovrKeys(table);
  const keys = cells.map(columnKey);
  if (keys.filter((k) => ovr.has(k)).length < 31) return false;
  const strict = keys.every((k) => ovr.has(k) || STRICT_KEYS.has(k));
  return !(magic && strict);
}

/**
 * Parse a Quest Pro Unity log into the same shape as parseFaceLog, plus `conf` (Float32Array 2n,
 * [lower, upper] per sample, or null) and `report` {rows, samples, duplicates, invalid, malformed,
 * timeSource, ignored, labels, problems}.
 */
export function parseQuestLog(text, table, name = "file") {
  const { meta, kept } = splitLines(text);
  if (!kept.length) throw new FaceLogError(`${name}: no data lines`);
  const d = delimiterOf(kept[0][1]);
  const comma = d !== ",";
  let rows = kept.map(([n, line]) => [n, cellsOf(line, d)]);
  const ovr = ovrKeys(table);
  const problems = [];
  let header = null, headerLine = 0, layout, shapeCols, format;
  const col = { tracker: -1, clock: -1, status: -1, lower: -1, upper: -1, source: -1 };
  const ignored = [], ignoredIdx = [];
  let width;
  if (headerless(rows[0][1])) {
    width = rows[0][1].length;
    while (width && rows.slice(0, 50).every(([, c]) => c.length >= width && !c[width - 1])) width--;
    layout = meta.layout || (width === 70 ? "ovr70" : width === 63 ? "ovr63" : null);
    if (!layout || !(layout in table.layouts) || table.layouts[layout].names.length !== width || !layout.startsWith("ovr")) {
      throw new FaceLogError(`${name}, line ${rows[0][0]}: headerless rows of ${width} values are not ovr63 (63) or ovr70 (70)`);
    }
    problems.push(`headerless: ${layout} taken from the row width`);
    shapeCols = Array.from({ length: width }, (_, i) => i);
    format = "quest-headerless";
  } else {
    [headerLine, header] = rows[0];
    rows = rows.slice(1);
    let keys = header.map(columnKey);
    width = keys.length;
    while (width && !keys[width - 1] && rows.slice(0, 50).every(([, c]) => c.length < width || !c[width - 1])) width--;
    header = header.slice(0, width);
    keys = keys.slice(0, width);
    const extras = keys.map((k, i) => (ENUM_EXTRA_KEYS.includes(k) ? i : -1)).filter((i) => i >= 0);
    if (extras.length && rows.length && usualWidth(rows) === width - extras.length) {
      // `Enum.GetNames` in the header (`...,UpperLipRaiserR,Max`), no value for `Max` in the rows
      const dropped = extras.map((i) => header[i]);
      header = header.filter((_, i) => !extras.includes(i));
      keys = keys.filter((_, i) => !extras.includes(i));
      width -= extras.length;
      ignored.push(...dropped);
      problems.push(`header column${dropped.length > 1 ? "s" : ""} ${dropped.join(", ")} (from Enum.GetNames, not `
        + `expressions) ha${dropped.length > 1 ? "ve" : "s"} no value in the rows: left out of the header`);
    }
    const shapes = new Map();
    const take = (k, list, slot) => list.includes(k) && col[slot] < 0;
    for (let i = 0; i < width; i++) {
      const k = keys[i];
      if (ovr.has(k)) {
        if (shapes.has(ovr.get(k))) throw new FaceLogError(`${name}, line ${headerLine}: duplicate column '${header[i]}'`);
        shapes.set(ovr.get(k), i);
      } else if (take(k, TRACKER_KEYS, "tracker")) col.tracker = i;
      else if (CLOCK_KEYS.includes(k) && (col.clock < 0 || CLOCK_KEYS.indexOf(k) < CLOCK_KEYS.indexOf(keys[col.clock]))) {
        if (col.clock >= 0) { ignored.push(header[col.clock]); ignoredIdx.push(col.clock); }
        col.clock = i;
      } else if (take(k, STATUS_KEYS, "status")) col.status = i;
      else if (take(k, CONF_KEYS[0], "lower")) col.lower = i;
      else if (take(k, CONF_KEYS[1], "upper")) col.upper = i;
      else if (take(k, SOURCE_KEYS, "source")) col.source = i;
      else { ignored.push(header[i] || `(column ${i + 1}, unnamed)`); ignoredIdx.push(i); }
    }
    if ((col.lower < 0) !== (col.upper < 0)) {
      const lone = Math.max(col.lower, col.upper);
      ignored.push(header[lone]); ignoredIdx.push(lone);
      col.lower = col.upper = -1;
    }
    const tongue = [...shapes.keys()].some((j) => j >= 63);
    layout = tongue || meta.layout === "ovr70" ? "ovr70" : "ovr63";
    const names = table.layouts[layout].names;
    const missing = names.filter((_, j) => !shapes.has(j));
    if (missing.length) {
      throw new FaceLogError(`${name}, line ${headerLine}: not a complete Meta ${layout} log: missing `
        + `${missing.slice(0, 8).join(", ")}${missing.length > 8 ? ` and ${missing.length - 8} more` : ""}`
        + (ignored.length ? `; columns not understood: ${ignored.slice(0, 8).join(", ")}` : ""));
    }
    shapeCols = names.map((_, j) => shapes.get(j));
    format = layout === "ovr70" ? "quest-v2" : "quest-v1";
  }
  const info = table.layouts[layout];
  const L = info.names.length;
  const num = (c) => Number(comma ? c.replace(",", ".") : c);
  const colName = (i) => (header ? header[i] : `value ${i + 1}`);
  const good = []; // {w, tracker, clock, conf, ok, pos, line}
  let malformed = 0, firstProblem = null;
  for (let r = 0; r < rows.length; r++) {
    const [lineNo, cells] = rows[r];
    let problem = null;
    const w = new Float64Array(L);
    let tracker = NaN, clock = NaN, ok = true;
    let conf = null;
    if (cells.length < width || cells.slice(width).some((c) => c)) problem = `${cells.length} fields, the header has ${width}`;
    else {
      const read = (i) => {
        const v = num(cells[i]);
        if (!isNumber(comma ? cells[i].replace(",", ".") : cells[i])) problem ??= `column '${colName(i)}': '${cells[i]}' is not a number`;
        return v;
      };
      for (let k = 0; k < L; k++) w[k] = read(shapeCols[k]);
      if (col.tracker >= 0) tracker = read(col.tracker);
      if (col.clock >= 0) clock = read(col.clock);
      if (col.lower >= 0) conf = [read(col.lower), read(col.upper)];
      if (!problem && col.status >= 0) {
        const s = STATUS_VALUES[cells[col.status].toLowerCase()];
        if (s === undefined) problem = `column '${colName(col.status)}': '${cells[col.status]}' is not true or false`;
        ok = !!s;
      }
    }
    if (problem) {
      malformed++;
      firstProblem ??= [lineNo, problem];
      if (problems.length < 5) problems.push(`line ${lineNo}: ${problem} (row dropped)`);
      continue;
    }
    good.push({ w, tracker, clock, conf, ok, pos: r, line: lineNo });
  }
  if (malformed && (!good.length || malformed > MAX_MALFORMED_SHARE * rows.length)) {
    throw new FaceLogError(`${name}, line ${firstProblem[0]}: ${firstProblem[1]} (${malformed} of ${rows.length} rows malformed)`);
  }
  let valid = good.filter((g) => g.ok);
  let invalid = good.length - valid.length;
  if (!valid.length) throw new FaceLogError(`${name}: no valid face rows (${invalid} have status false)`);
  let useTracker = col.tracker >= 0;
  const fps = meta.fps ? Number(meta.fps) : DEFAULT_FPS;
  if (useTracker) {
    // Face_Time 0 (or below): no tracker sample (rows before tracking started): invalid, unless it never rises
    const timed = valid.filter((g) => g.tracker > 0);
    const distinct = new Set(timed.map((g) => g.tracker)).size;
    if (distinct === 0 || (distinct === 1 && valid.length > 1)) {
      problems.push(`${header[col.tracker]} never changes${distinct === 0 ? " (never above 0)" : ""}: not used as the time source`);
      useTracker = false;
    } else if (timed.length < valid.length) {
      const untimed = valid.length - timed.length;
      invalid += untimed;
      problems.push(`${untimed} rows with ${header[col.tracker]} <= 0 (no tracker sample: before tracking started, `
        + "or while lost) dropped as invalid");
      valid = timed;
    }
  }
  if (useTracker) {
    let clashes = 0, firstLine = 0;
    for (let i = 1; i < valid.length; i++) {
      const [a, b] = [valid[i - 1], valid[i]];
      if (b.tracker === a.tracker && b.w.some((v, k) => v !== a.w[k])) { clashes++; firstLine ||= b.line; }
    }
    if (clashes) { // one tracker time, two faces: too coarse to tell samples apart
      const instead = col.clock >= 0 ? `the Unity clock (${header[col.clock]})` : `${fps} rows/s`;
      problems.push(`${header[col.tracker]} is too coarse to tell samples apart: ${clashes} rows have the tracker time `
        + `of the row before but a different face (first at line ${firstLine}); samples found by weight changes and `
        + `timed by ${instead} instead`);
      useTracker = false;
    }
  }
  let timeSource;
  const samples = [];
  for (const g of valid) {
    const prev = samples[samples.length - 1];
    const fresh = !prev || (useTracker ? g.tracker !== prev.tracker : g.w.some((v, k) => v !== prev.w[k]));
    if (fresh) samples.push(g);
  }
  const timeOf = useTracker ? (g) => g.tracker : col.clock >= 0 ? (g) => g.clock : (g) => g.pos / fps;
  if (useTracker) timeSource = `tracker (${header[col.tracker]})`;
  else if (col.clock >= 0) timeSource = `unity clock (${header[col.clock]})`;
  else timeSource = `no time column: ${fps} rows/s${meta.fps ? " (# fps)" : " (assumed)"}`;
  const n = samples.length;
  const times = new Float64Array(n);
  const frames = new Float32Array(n * 52);
  const conf = col.lower >= 0 ? new Float32Array(2 * n) : null;
  for (let r = 0; r < n; r++) {
    const g = samples[r];
    times[r] = timeOf(g);
    if (r && times[r] < times[r - 1]) throw new FaceLogError(`${name}, line ${g.line}: time goes back (${times[r]} after ${times[r - 1]})`);
    const out = frames.subarray(52 * r, 52 * r + 52);
    for (const [dst, src, v] of info.to_arkit52) out[dst] += v * g.w[src];
    for (let k = 0; k < 52; k++) out[k] = Math.min(1, Math.max(0, out[k]));
    if (conf) { conf[2 * r] = Math.min(1, Math.max(0, g.conf[0])); conf[2 * r + 1] = Math.min(1, Math.max(0, g.conf[1])); }
  }
  if (useTracker || col.clock >= 0) {
    let long = 0, longest = 0, at = 0;
    for (let r = 1; r < n; r++) {
      const step = times[r] - times[r - 1];
      if (step > LONG_GAP_S) { long++; if (step > longest) { longest = step; at = samples[r].line; } }
    }
    if (long) {
      problems.push(`${long} step(s) over ${LONG_GAP_S} s in the time (tracking lost or the app paused?); the longest, `
        + `${longest.toFixed(3)} s, ends at line ${at}: kept, the replay waits through it`);
    }
  }
  const t0 = times[0];
  for (let r = 0; r < n; r++) times[r] -= t0;
  const labels = header ? ignoredIdx.filter((i) => rows.slice(0, 200).some(([, c]) => c[i] && !isNumber(c[i]))).map((i) => header[i]) : [];
  const report = { format, rows: rows.length, samples: n, duplicates: valid.length - n, invalid, malformed, timeSource,
    ignored, labels, problems };
  const kind = `Quest Pro log (${format}, ${n} samples of ${rows.length} rows, ${report.duplicates} repeats and `
    + `${invalid + malformed} invalid dropped, time: ${timeSource}${conf ? ", confidence" : ""})`;
  return { times, frames, conf, layout, kind, rows: n, duration: times[n - 1], meta, report };
}
