// WebGL2 splat drawing: one instanced quad per Gaussian, in the order given (farthest first), blended
// with premultiplied alpha. The per-splat screen-space ellipse (centre and the two scaled eigenvectors
// of the projected 2D covariance) is computed with the depth sort in splat-worker.js: the vertex shader
// only places the quad's corners, and the fragment shader applies the gaussian falloff. (Computing the
// projection per vertex costs four times the work, which a software rasteriser like SwiftShader feels.)

/** Bytes per splat in the instance buffer: centre (2 f32), axes (4 f32), RGBA8 colour and opacity. */
export const SPLAT_BYTES = 28;

const VS = `#version 300 es
precision highp float;
in vec2 aCorner;
in vec2 aCenter;
in vec4 aAxes;
in vec4 aColor;
out vec4 vColor;
out vec2 vPos;
void main() {
  vColor = aColor;
  vPos = aCorner;
  gl_Position = vec4(aCenter + aCorner.x * aAxes.xy + aCorner.y * aAxes.zw, 0.0, 1.0);
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
    const corners = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, corners);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-2, -2, 2, -2, -2, 2, 2, 2]), gl.STATIC_DRAW);
    const loc = (name) => gl.getAttribLocation(prog, name);
    gl.enableVertexAttribArray(loc("aCorner"));
    gl.vertexAttribPointer(loc("aCorner"), 2, gl.FLOAT, false, 0, 0);
    this.splats = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.splats);
    const attrs = [["aCenter", 2, gl.FLOAT, false, 0], ["aAxes", 4, gl.FLOAT, false, 8], ["aColor", 4, gl.UNSIGNED_BYTE, true, 24]];
    for (const [name, size, type, normalized, offset] of attrs) {
      gl.enableVertexAttribArray(loc(name));
      gl.vertexAttribPointer(loc(name), size, type, normalized, SPLAT_BYTES, offset);
      gl.vertexAttribDivisor(loc(name), 1);
    }
    gl.bindVertexArray(null);
    this.count = 0;
    this.capacity = 0;
  }

  /** Splats to draw, farthest first: `count` records of SPLAT_BYTES in `buffer` (an ArrayBuffer). */
  setSplats(buffer, count) {
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.splats);
    const bytes = count * SPLAT_BYTES;
    if (bytes > this.capacity) {
      this.capacity = Math.max(bytes, Math.ceil(this.capacity * 1.25));
      gl.bufferData(gl.ARRAY_BUFFER, this.capacity, gl.DYNAMIC_DRAW);
    }
    if (bytes) gl.bufferSubData(gl.ARRAY_BUFFER, 0, new Uint8Array(buffer, 0, bytes));
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
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, this.count);
    gl.bindVertexArray(null);
  }
}
