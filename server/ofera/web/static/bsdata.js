// LAM / OpenAvatarChat expression tracks (`bsData.json`) dropped onto the page, in the browser:
// {"names": [52 ARKit names], "metadata": {"fps": 30, ...}, "frames": [{"weights": [52], "time": s}, ...]}.
// Frames may also be bare arrays; times default to i / fps. Names are matched to ARKit by name (case and
// underscores ignored), so any order works; the result has the shape of facelog.js's parseFaceLog.

import { FaceLogError, normalizeName } from "./facelog.js";

/** True when `text` looks like a JSON object (a bsData track rather than a CSV). */
export const looksLikeJson = (text) => /^\s*\{/.test(text);

/**
 * Parse a bsData.json text into { times (s, from 0), frames (Float32Array n*52, arkit52), layout, kind, rows,
 * duration }. `table` is /static/layouts.json (its arkit52 names).
 */
export function parseBsData(text, table) {
  let doc;
  try {
    doc = JSON.parse(text);
  } catch (e) {
    throw new FaceLogError(`not JSON: ${e.message}`);
  }
  if (!doc || typeof doc !== "object" || !Array.isArray(doc.frames)) {
    throw new FaceLogError("a bsData track is an object with 'names' and 'frames' (a list)");
  }
  const meta = doc.metadata && typeof doc.metadata === "object" ? doc.metadata : {};
  const names = Array.isArray(doc.names) ? doc.names : meta.blendshape_names;
  if (!Array.isArray(names) || names.length === 0) throw new FaceLogError("the bsData track has no 'names'");
  const arkit = table.arkit52.map(normalizeName);
  const columnOf = names.map((n) => {
    const i = arkit.indexOf(normalizeName(String(n)));
    if (i < 0) throw new FaceLogError(`'${n}' is not an ARKit blendshape name`);
    return i;
  });
  columnOf.forEach((c, k) => {
    const first = columnOf.indexOf(c);
    if (first !== k) {
      throw new FaceLogError(`names '${names[first]}' and '${names[k]}' are both the ARKit shape '${table.arkit52[c]}'`);
    }
  });
  const fps = Number(meta.fps ?? doc.fps ?? 30);
  if (!(fps > 0) || !Number.isFinite(fps)) throw new FaceLogError(`fps ${meta.fps} is not a positive number`);
  const rows = doc.frames.length;
  if (rows === 0) throw new FaceLogError("the bsData track has no frames");
  const frames = new Float32Array(rows * 52);
  const times = new Float64Array(rows);
  doc.frames.forEach((f, r) => {
    const w = Array.isArray(f) ? f : f?.weights;
    if (!Array.isArray(w) || w.length !== names.length) {
      throw new FaceLogError(`frame ${r} has ${Array.isArray(w) ? w.length : "no"} weights, expected ${names.length}`);
    }
    w.forEach((v, c) => {
      const x = Number(v);
      if (!Number.isFinite(x)) throw new FaceLogError(`frame ${r}: weight ${names[c]} is not a number`);
      frames[52 * r + columnOf[c]] = Math.min(1, Math.max(0, x));
    });
    times[r] = typeof f?.time === "number" && Number.isFinite(f.time) ? f.time : r / fps;
  });
  for (let r = 1; r < rows; r++) {
    if (!(times[r] > times[r - 1])) {
      throw new FaceLogError(`frame times must increase, frame ${r} is at ${times[r]} s after ${times[r - 1]} s`);
    }
  }
  const t0 = times[0];
  for (let r = 0; r < rows; r++) times[r] -= t0;
  return { times, frames, layout: "arkit52", kind: "bsData.json", rows, duration: times[rows - 1] };
}
