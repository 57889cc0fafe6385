// Reading recorded blendshapes dropped onto the page, in the browser: the OFERA face-log CSV
// (protocol/FACELOG.md: `time` in seconds, `# key: value` metadata, any supported layout), MediaPipe /
// ARKit CSVs (time, time_ms, timestamp_ms, timestamp_us, or frame numbers with fps) and Live Link Face
// CSVs (`Timecode` HH:MM:SS:FF.fff at 60 fps unless `# fps:` says otherwise, `BlendshapeCount`).
// Columns are matched by name (case-insensitive, underscores ignored) and every row is converted to
// arkit52 with the layout's map from /static/layouts.json (the server's own table).

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
