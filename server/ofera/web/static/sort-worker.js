// Depth sort of the Gaussians, off the main thread: a 16-bit counting sort of view-space depths,
// farthest first (the order for back-to-front blending).
// In:  { id, positions: Float32Array (n*3), n, view: [m2, m6, m10, m14] (view matrix row giving camera z) }
// Out: { id, order: Uint32Array (n) } (transferred)
let counts = new Uint32Array(65536);
let keys = new Uint16Array(0);
let depths = new Float32Array(0);

self.onmessage = (ev) => {
  const { id, positions, n, view } = ev.data;
  const [a, b, c, d] = view;
  if (depths.length < n) {
    depths = new Float32Array(n);
    keys = new Uint16Array(n);
  }
  let lo = Infinity, hi = -Infinity;
  for (let i = 0; i < n; i++) {
    const z = a * positions[3 * i] + b * positions[3 * i + 1] + c * positions[3 * i + 2] + d; // camera z (< 0 in front)
    depths[i] = z;
    if (z < lo) lo = z;
    if (z > hi) hi = z;
  }
  const scale = hi > lo ? 65535 / (hi - lo) : 0;
  counts.fill(0);
  for (let i = 0; i < n; i++) {
    const k = ((depths[i] - lo) * scale) | 0; // most negative z (farthest) -> smallest key -> drawn first
    keys[i] = k;
    counts[k]++;
  }
  let sum = 0;
  for (let k = 0; k < 65536; k++) {
    const c0 = counts[k];
    counts[k] = sum;
    sum += c0;
  }
  const order = new Uint32Array(n);
  for (let i = 0; i < n; i++) order[counts[keys[i]]++] = i;
  self.postMessage({ id, order }, [order.buffer]);
};
