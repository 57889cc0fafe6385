// Runs in a page of `ofera serve` (test_params_browser.py): a Worker of the page's own splat-worker.js fed a params
// session (avatar, rig, params frames), and an f32 session of the same avatar as the reference; for each bs the
// worker's Gaussians (its "dump") against the f32 frame's. Evaluated by playwright with [weights, layout, coords].
async ([weights, layout, coords]) => {
  const P = await import("/static/protocol.js");
  const url = `ws://${location.host}/v1/stream`;
  const open = (encoding) => new Promise((resolve, reject) => {
    const ws = new WebSocket(url);
    ws.binaryType = "arraybuffer";
    const queue = [];
    let waiter = null;
    ws.onmessage = (ev) => { if (waiter) { const w = waiter; waiter = null; w(ev.data); } else queue.push(ev.data); };
    ws.onerror = () => reject(new Error("websocket error"));
    ws.onopen = () => {
      ws.send(P.helloMessage({ layout, encoding, coords }));
      resolve({ ws, next: () => queue.length ? Promise.resolve(queue.shift()) : new Promise((r) => { waiter = r; }) });
    };
  });
  const worker = new Worker("/static/splat-worker.js", { type: "module" });
  const fromWorker = [];
  let workerWaiter = null;
  worker.onmessage = ({ data }) => {
    if (data.kind === "error") throw new Error(`worker: ${data.code}: ${data.message}`);
    if (workerWaiter) { const w = workerWaiter; workerWaiter = null; w(data); } else fromWorker.push(data);
  };
  const workerNext = () => fromWorker.length ? Promise.resolve(fromWorker.shift()) : new Promise((r) => { workerWaiter = r; });
  const p = await open("params"), f = await open("f32");
  const welcome = P.decodeServerMessage(new Uint8Array(await p.next()));
  const fw = P.decodeServerMessage(new Uint8Array(await f.next()));
  if (welcome.encoding !== "params") throw new Error(`welcome encoding ${welcome.encoding}`);
  worker.postMessage({ kind: "welcome", gen: 1, welcome });
  let rigBytes = 0, avatarBytes = 0;
  for (;;) { // avatar chunks, then rig chunks, to the worker
    const buffer = await p.next();
    const m = P.decodeServerMessage(new Uint8Array(buffer));
    if (m.type === "avatar") { avatarBytes += buffer.byteLength; worker.postMessage({ kind: "chunk", gen: 1, buffer }, [buffer]); }
    else if (m.type === "rig") { rigBytes += buffer.byteLength; worker.postMessage({ kind: "rig", gen: 1, buffer }, [buffer]); }
    else throw new Error(`unexpected ${m.type} in the handshake`);
    if (m.type === "rig" && m.chunk === m.chunks - 1) break;
  }
  while ((await workerNext()).kind !== "rig") { /* "avatar" first: the worker has the whole avatar */ }
  const n = fw.avatar.count;
  for (;;) { // the f32 session's avatar chunks
    const m = P.decodeServerMessage(new Uint8Array(await f.next()));
    if (m.type === "avatar" && m.chunk === m.chunks - 1) break;
  }
  const ref = { position: new Float32Array(3 * n), rotation: new Float32Array(4 * n), scale: new Float32Array(3 * n) };
  let maxPos = 0, maxRot = 0, maxScale = 0, deformMs = 0;
  const sizes = [];
  for (let i = 0; i < weights.length; i++) {
    p.ws.send(P.bsMessage(i, 1000 + i, weights[i]));
    f.ws.send(P.bsMessage(i, 1000 + i, weights[i]));
    const pb = await p.next(), fb = await f.next();
    sizes.push(pb.byteLength);
    const t0 = performance.now();
    worker.postMessage({ kind: "frame", gen: 1, buffer: pb }, [pb]);
    worker.postMessage({ kind: "dump", gen: 1, id: i });
    const d = await workerNext();
    deformMs += performance.now() - t0;
    const fr = P.decodeServerMessage(new Uint8Array(fb));
    P.decodeFrameArrays("f32", fr.n, fr, null, ref);
    for (let k = 0; k < 3 * n; k++) {
      maxPos = Math.max(maxPos, Math.abs(d.position[k] - ref.position[k]));
      maxScale = Math.max(maxScale, Math.abs(d.scale[k] - ref.scale[k]) / ref.scale[k]);
    }
    for (let g = 0; g < n; g++) {
      let a = 0, b = 0;
      for (let c = 0; c < 4; c++) {
        a = Math.max(a, Math.abs(d.rotation[4 * g + c] - ref.rotation[4 * g + c]));
        b = Math.max(b, Math.abs(d.rotation[4 * g + c] + ref.rotation[4 * g + c]));
      }
      maxRot = Math.max(maxRot, Math.min(a, b));
    }
  }
  p.ws.close(); f.ws.close(); worker.terminate();
  return { maxPos, maxRot, maxScale, sizes, frames: weights.length, count: n, rigBytes, avatarBytes,
    deformMs: deformMs / weights.length };
}
