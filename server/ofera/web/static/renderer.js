// WebGL2 Gaussian splatting: one instanced quad per Gaussian, drawn in a depth-sorted order.
// Per-Gaussian data lives in float textures (position RGB32F, rotation RGBA32F, scale RGB32F, colour and
// opacity RGBA8) fetched by index; the only instance attribute is the sorted index. The vertex shader
// projects the 3D covariance R S S^T R^T to a 2D one (EWA splatting: J W Sigma W^T J^T, plus a 0.3 px^2
// low-pass), and spans the quad along its eigenvectors out to about 2.8 sigma; the fragment shader
// applies the gaussian falloff. Blending is premultiplied alpha, back to front.

export const TEX_WIDTH = 1024;

/** Texels needed for n Gaussians (whole texture rows). */
export function textureCapacity(n) {
  return TEX_WIDTH * Math.max(1, Math.ceil(n / TEX_WIDTH));
}

const VS = `#version 300 es
precision highp float;
precision highp int;
uniform highp sampler2D uPos;
uniform highp sampler2D uRot;
uniform highp sampler2D uScale;
uniform mediump sampler2D uColor;
uniform mat4 uView;
uniform mat4 uProj;
uniform vec2 uFocal;
uniform vec2 uViewport;
uniform float uScaleMul;
in uint aIndex;
in vec2 aCorner;
out vec4 vColor;
out vec2 vPos;

void main() {
  int i = int(aIndex);
  ivec2 tc = ivec2(i % ${TEX_WIDTH}, i / ${TEX_WIDTH});
  vec3 p = texelFetch(uPos, tc, 0).xyz;
  vec4 cam = uView * vec4(p, 1.0);
  vec4 clip = uProj * cam;
  float lim = 1.2 * clip.w;
  if (cam.z > -1e-3 || abs(clip.x) > lim || abs(clip.y) > lim) {
    gl_Position = vec4(0.0, 0.0, 2.0, 1.0);  // behind the camera or well off screen: clipped
    return;
  }
  vec4 q = texelFetch(uRot, tc, 0);
  q = q / max(length(q), 1e-12);
  vec3 s = texelFetch(uScale, tc, 0).xyz * uScaleMul;
  float x = q.x, y = q.y, z = q.z, w = q.w;
  mat3 R = mat3(
    1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),
    2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),
    2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
  mat3 M = mat3(uView) * R * mat3(s.x, 0.0, 0.0, 0.0, s.y, 0.0, 0.0, 0.0, s.z);
  mat3 Sc = M * transpose(M);  // covariance in camera space
  float tz = -cam.z;
  vec3 j0 = vec3(uFocal.x / tz, 0.0, uFocal.x * cam.x / (tz * tz));
  vec3 j1 = vec3(0.0, uFocal.y / tz, uFocal.y * cam.y / (tz * tz));
  float a = dot(j0, Sc * j0) + 0.3;
  float b = dot(j0, Sc * j1);
  float c = dot(j1, Sc * j1) + 0.3;
  float mid = 0.5 * (a + c);
  float rad = length(vec2(0.5 * (a - c), b));
  float l1 = mid + rad;
  float l2 = max(mid - rad, 0.1);
  vec2 d = vec2(b, l1 - a);
  d = dot(d, d) < 1e-12 ? vec2(1.0, 0.0) : normalize(d);
  vec2 major = min(sqrt(2.0 * l1), 1024.0) * d;
  vec2 minor = min(sqrt(2.0 * l2), 1024.0) * vec2(d.y, -d.x);
  vColor = texelFetch(uColor, tc, 0);
  vPos = aCorner;
  vec2 ndc = clip.xy / clip.w + (aCorner.x * major + aCorner.y * minor) * 2.0 / uViewport;
  gl_Position = vec4(ndc, 0.0, 1.0);
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
    const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false, preserveDrawingBuffer: true,
      powerPreference: "high-performance" });
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
    this.u = {};
    for (const name of ["uPos", "uRot", "uScale", "uColor", "uView", "uProj", "uFocal", "uViewport", "uScaleMul"]) {
      this.u[name] = gl.getUniformLocation(prog, name);
    }
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const corners = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, corners);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-2, -2, 2, -2, -2, 2, 2, 2]), gl.STATIC_DRAW);
    const aCorner = gl.getAttribLocation(prog, "aCorner");
    gl.enableVertexAttribArray(aCorner);
    gl.vertexAttribPointer(aCorner, 2, gl.FLOAT, false, 0, 0);
    this.indexBuffer = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
    const aIndex = gl.getAttribLocation(prog, "aIndex");
    gl.enableVertexAttribArray(aIndex);
    gl.vertexAttribIPointer(aIndex, 1, gl.UNSIGNED_INT, 0, 0);
    gl.vertexAttribDivisor(aIndex, 1);
    gl.bindVertexArray(null);
    this.textures = {};
    this.count = 0;
    this.rows = 0;
  }

  _texture(name, unit, internal, format, type, data) {
    const gl = this.gl;
    let t = this.textures[name];
    gl.activeTexture(gl.TEXTURE0 + unit);
    if (!t || t.rows !== this.rows) {
      if (t) gl.deleteTexture(t.tex);
      const tex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
      gl.texStorage2D(gl.TEXTURE_2D, 1, internal, TEX_WIDTH, this.rows);
      t = this.textures[name] = { tex, rows: this.rows };
    }
    gl.bindTexture(gl.TEXTURE_2D, t.tex);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TEX_WIDTH, this.rows, format, type, data);
  }

  /** A new set of Gaussians (an AvatarState whose arrays are textureCapacity(count) long). */
  setGaussians(state) {
    const gl = this.gl;
    this.count = state.count;
    this.rows = textureCapacity(state.count) / TEX_WIDTH;
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    this._texture("color", 3, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, state.color);
    this.updateDynamic(state);
    const identity = new Uint32Array(state.count);
    for (let i = 0; i < identity.length; i++) identity[i] = i;
    this.setOrder(identity);
  }

  /** Upload the newest positions, rotations and scales. */
  updateDynamic(state) {
    const gl = this.gl;
    this._texture("pos", 0, gl.RGB32F, gl.RGB, gl.FLOAT, state.position);
    this._texture("rot", 1, gl.RGBA32F, gl.RGBA, gl.FLOAT, state.rotation);
    this._texture("scale", 2, gl.RGB32F, gl.RGB, gl.FLOAT, state.scale);
  }

  /** Draw order (indices, farthest first). */
  setOrder(order) {
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, order, gl.DYNAMIC_DRAW);
    this.drawCount = order.length;
  }

  draw(view, proj, scaleMul = 1) {
    const gl = this.gl;
    const w = this.canvas.width, h = this.canvas.height;
    gl.viewport(0, 0, w, h);
    const [r, g, b] = this.background;
    gl.clearColor(r, g, b, 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    if (!this.count) return;
    gl.useProgram(this.prog);
    gl.disable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    const units = { uPos: ["pos", 0], uRot: ["rot", 1], uScale: ["scale", 2], uColor: ["color", 3] };
    for (const [u, [name, unit]] of Object.entries(units)) {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_2D, this.textures[name].tex);
      gl.uniform1i(this.u[u], unit);
    }
    gl.uniformMatrix4fv(this.u.uView, false, view);
    gl.uniformMatrix4fv(this.u.uProj, false, proj);
    gl.uniform2f(this.u.uFocal, (proj[0] * w) / 2, (proj[5] * h) / 2);
    gl.uniform2f(this.u.uViewport, w, h);
    gl.uniform1f(this.u.uScaleMul, scaleMul);
    gl.bindVertexArray(this.vao);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, Math.min(this.drawCount, this.count));
    gl.bindVertexArray(null);
  }
}
