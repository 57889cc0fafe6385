// WebGL2 splat drawing: one quad per Gaussian, in the order given (farthest first), blended with
// premultiplied alpha. The per-splat screen-space ellipse (the projected 2D covariance's eigenvectors
// scaled by sqrt(2 lambda)) is computed with the depth sort in splat-worker.js, which writes the quads'
// four corners; the vertex shader passes them on and the fragment shader applies the gaussian falloff
// exp(-|p|^2) over the quad's local coordinates p in [-2, 2]^2 (from gl_VertexID).
// Why not instanced quads with the projection in the vertex shader? Software rasterisers (SwiftShader,
// which headless and GPU-less browsers use) pay dearly per instance and per vertex-shader instruction:
// there a plain indexed triangle list drawn this way is an order of magnitude faster.

/** Bytes per vertex (corner): NDC x, y (2 float32), RGBA8 colour and opacity; four per splat. */
export const VERTEX_BYTES = 12;
export const SPLAT_BYTES = 4 * VERTEX_BYTES;

const VS = `#version 300 es
precision highp float;
in vec2 aPosition;
in vec4 aColor;
out vec4 vColor;
out vec2 vPos;
void main() {
  int corner = gl_VertexID & 3;
  vPos = vec2((corner & 1) == 1 ? 2.0 : -2.0, (corner & 2) == 2 ? 2.0 : -2.0);
  vColor = aColor;
  gl_Position = vec4(aPosition, 0.0, 1.0);
}`;

const FS = `#version 300 es
precision mediump float;
in vec4 vColor;
in vec2 vPos;
out vec4 fragColor;
void main() {
  float e = -dot(vPos, vPos);
  if (e < -4.0) discard;
  float alpha = min(0.99, exp(e) * vColor.a);
  if (alpha < 1.0 / 255.0) discard;
  fragColor = vec4(vColor.rgb * alpha, alpha);
}`;

function compile(gl, type, src) {
  const s = gl.createShader(type);
  gl.shaderSource(s, src);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(`shader: ${gl.getShaderInfoLog(s)}`);
  return s;
}

// ----- small matrix helpers (column-major Float32Array(16)) -------------------------------------------

export function perspective(fovy, aspect, near, far) {
  const f = 1 / Math.tan(fovy / 2);
  const m = new Float32Array(16);
  m[0] = f / aspect;
  m[5] = f;
  m[10] = (far + near) / (near - far);
  m[11] = -1;
  m[14] = (2 * far * near) / (near - far);
  return m;
}

export function lookAt(eye, target, up = [0, 1, 0]) {
  const sub = (u, v) => [u[0] - v[0], u[1] - v[1], u[2] - v[2]];
  const cross = (u, v) => [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
  const dot = (u, v) => u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
  const norm = (u) => { const l = Math.hypot(...u) || 1; return [u[0] / l, u[1] / l, u[2] / l]; };
  const z = norm(sub(eye, target));
  const x = norm(cross(up, z));
  const y = cross(z, x);
  return new Float32Array([x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0,
    -dot(x, eye), -dot(y, eye), -dot(z, eye), 1]);
}

export class SplatRenderer {
  constructor(canvas, background = [0.125, 0.137, 0.165]) {
    const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false, stencil: false,
      preserveDrawingBuffer: true, powerPreference: "high-performance" });
    if (!gl) throw new Error("this browser has no WebGL2");
    this.gl = gl;
    this.canvas = canvas;
    this.background = background;
    const prog = gl.createProgram();
    gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(`program: ${gl.getProgramInfoLog(prog)}`);
    this.prog = prog;
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    this.vertices = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.vertices);
    const aPosition = gl.getAttribLocation(prog, "aPosition"), aColor = gl.getAttribLocation(prog, "aColor");
    gl.enableVertexAttribArray(aPosition);
    gl.vertexAttribPointer(aPosition, 2, gl.FLOAT, false, VERTEX_BYTES, 0);
    gl.enableVertexAttribArray(aColor);
    gl.vertexAttribPointer(aColor, 4, gl.UNSIGNED_BYTE, true, VERTEX_BYTES, 8);
    this.indices = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.indices);
    gl.bindVertexArray(null);
    this.count = 0;
    this.capacity = 0; // bytes of the vertex buffer
    this.quads = 0; // quads the index buffer holds
  }

  /** Splats to draw, farthest first: `count` quads of SPLAT_BYTES in `buffer` (an ArrayBuffer). */
  setSplats(buffer, count) {
    const gl = this.gl;
    gl.bindVertexArray(this.vao);
    if (count > this.quads) {
      const quads = Math.max(count, Math.ceil(this.quads * 1.25));
      const idx = new Uint32Array(quads * 6);
      for (let k = 0; k < quads; k++) {
        const v = 4 * k, o = 6 * k;
        idx[o] = v; idx[o + 1] = v + 1; idx[o + 2] = v + 2; idx[o + 3] = v + 1; idx[o + 4] = v + 3; idx[o + 5] = v + 2;
      }
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, idx, gl.STATIC_DRAW);
      this.quads = quads;
    }
    gl.bindBuffer(gl.ARRAY_BUFFER, this.vertices);
    const bytes = count * SPLAT_BYTES;
    if (bytes > this.capacity) {
      this.capacity = Math.max(bytes, Math.ceil(this.capacity * 1.25));
      gl.bufferData(gl.ARRAY_BUFFER, this.capacity, gl.DYNAMIC_DRAW);
    }
    if (bytes) gl.bufferSubData(gl.ARRAY_BUFFER, 0, new Uint8Array(buffer, 0, bytes));
    gl.bindVertexArray(null);
    this.count = count;
  }

  draw() {
    const gl = this.gl;
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    const [r, g, b] = this.background;
    gl.clearColor(r, g, b, 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    if (!this.count) return;
    gl.useProgram(this.prog);
    gl.disable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.bindVertexArray(this.vao);
    gl.drawElements(gl.TRIANGLES, 6 * this.count, gl.UNSIGNED_INT, 0);
    gl.bindVertexArray(null);
  }
}
