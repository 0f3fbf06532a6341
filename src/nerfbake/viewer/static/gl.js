// WebGL2 helpers shared by the SMERF and PlenOctree renderers: shader programs, textures, render targets.

export class ViewerError extends Error {}

export function createContext(canvas) {
  const gl = canvas.getContext('webgl2', {
    antialias: false, alpha: false, depth: false, preserveDrawingBuffer: true, powerPreference: 'high-performance',
  });
  if (!gl) {
    throw new ViewerError('This browser has no WebGL2. Use a current Chrome, Firefox, Safari or Edge with hardware ' +
                          'acceleration enabled (chrome://gpu shows whether WebGL2 is available).');
  }
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  gl.pixelStorei(gl.PACK_ALIGNMENT, 1);
  return gl;
}

const VERTEX = `#version 300 es
// One triangle covering the viewport; the fragment shader builds each pixel's ray from gl_FragCoord.
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;

export function createProgram(gl, fragmentSource) {
  const compile = (type, src) => {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) {
      const log = gl.getShaderInfoLog(s);
      const numbered = src.split('\n').map((l, i) => `${i + 1}: ${l}`).join('\n');
      throw new ViewerError(`shader compile failed: ${log}\n${numbered}`);
    }
    return s;
  };
  const prog = gl.createProgram();
  gl.attachShader(prog, compile(gl.VERTEX_SHADER, VERTEX));
  gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, fragmentSource));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) {
    throw new ViewerError(`shader link failed: ${gl.getProgramInfoLog(prog)}`);
  }
  const uniforms = {};
  const n = gl.getProgramParameter(prog, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) {
    const info = gl.getActiveUniform(prog, i);
    uniforms[info.name.replace(/\[0\]$/, '')] = gl.getUniformLocation(prog, info.name);
  }
  return {prog, uniforms};
}

// Texture formats by channel count: unsigned-normalised bytes (sampled as value / 255).
const BYTE_FORMATS = {1: ['R8', 'RED'], 2: ['RG8', 'RG'], 3: ['RGB8', 'RGB'], 4: ['RGBA8', 'RGBA']};

export function texture3D(gl, width, height, depth, channels, linear, slices) {
  // `slices`: one Uint8Array with the whole volume (x fastest), or a list of per-depth-slice arrays.
  const [internal, format] = BYTE_FORMATS[channels];
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_3D, tex);
  gl.texStorage3D(gl.TEXTURE_3D, 1, gl[internal], width, height, depth);
  if (Array.isArray(slices)) {
    slices.forEach((s, z) => gl.texSubImage3D(gl.TEXTURE_3D, 0, 0, 0, z, width, height, 1, gl[format], gl.UNSIGNED_BYTE, s));
  } else {
    gl.texSubImage3D(gl.TEXTURE_3D, 0, 0, 0, 0, width, height, depth, gl[format], gl.UNSIGNED_BYTE, slices);
  }
  setFilter(gl, gl.TEXTURE_3D, linear);
  return tex;
}

export function texture2DArray(gl, width, height, layers, internal, format, type, data, linear) {
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D_ARRAY, tex);
  gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl[internal], width, height, layers);
  if (Array.isArray(data)) {
    data.forEach((d, z) => gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, z, width, height, 1, gl[format], gl[type], d));
  } else {
    gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, 0, width, height, layers, gl[format], gl[type], data);
  }
  setFilter(gl, gl.TEXTURE_2D_ARRAY, linear);
  return tex;
}

export function byteArrayTexture(gl, width, height, layers, channels, data, linear) {
  const [internal, format] = BYTE_FORMATS[channels];
  return texture2DArray(gl, width, height, layers, internal, format, 'UNSIGNED_BYTE', data, linear);
}

// An equirectangular environment map (src/nerfbake/render/envmap.py): RGB bytes, bilinear, wrapping around in
// longitude (s) and clamped at the poles (t), as the Python renderers sample it.
export function environmentTexture(gl, width, height, data) {
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGB8, width, height);
  gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, width, height, gl.RGB, gl.UNSIGNED_BYTE, data);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.REPEAT);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  return tex;
}

// Linear or nearest filtering, clamped to the edge on every axis.
export function setFilter(gl, target, linear) {
  const f = linear ? gl.LINEAR : gl.NEAREST;
  gl.texParameteri(target, gl.TEXTURE_MIN_FILTER, f);
  gl.texParameteri(target, gl.TEXTURE_MAG_FILTER, f);
  for (const w of [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T, gl.TEXTURE_WRAP_R]) gl.texParameteri(target, w, gl.CLAMP_TO_EDGE);
}

// A 3x3 given as rows (r[i][j]) in the column-major order uniformMatrix3fv takes.
export function mat3ColumnMajor(r) {
  return [r[0][0], r[1][0], r[2][0], r[0][1], r[1][1], r[2][1], r[0][2], r[1][2], r[2][2]];
}

export function bindTextures(gl, program, bindings) {
  // bindings: [[uniformName, target, texture], ...] -> consecutive texture units
  bindings.forEach(([name, target, tex], unit) => {
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(target, tex);
    if (program.uniforms[name] !== undefined) gl.uniform1i(program.uniforms[name], unit);
  });
}

// An RGBA8 render target of a given size (tests, screenshots and benchmark frames read it back).
export class RenderTarget {
  constructor(gl, width, height) {
    this.gl = gl; this.width = width; this.height = height;
    this.tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.tex);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA8, width, height);
    this.fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.tex, 0);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  }
  // Rows top to bottom, RGBA bytes.
  read() {
    const {gl, width, height} = this;
    const px = new Uint8Array(width * height * 4);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
    gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, px);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    const out = new Uint8Array(px.length);
    const row = width * 4;
    for (let y = 0; y < height; y++) out.set(px.subarray((height - 1 - y) * row, (height - y) * row), y * row);
    return out;
  }
  dispose() {
    this.gl.deleteFramebuffer(this.fbo);
    this.gl.deleteTexture(this.tex);
  }
}

export function drawFullscreen(gl, target, width, height) {
  gl.bindFramebuffer(gl.FRAMEBUFFER, target ? target.fbo : null);
  gl.viewport(0, 0, width, height);
  gl.drawArrays(gl.TRIANGLES, 0, 3);
}

// The GPU's name as the driver reports it (the unmasked renderer string where the browser gives it).
export function rendererName(gl) {
  const dbg = gl.getExtension('WEBGL_debug_renderer_info');
  return dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
}

// Wait for the GPU: a one-pixel read back forces every queued draw to finish.
export function finish(gl) {
  const px = new Uint8Array(4);
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
}

export async function fetchBytes(url, onBytes) {
  const res = await fetch(url);
  if (!res.ok) throw new ViewerError(`${url}: HTTP ${res.status} (the scene folder is incomplete; re-run the bake)`);
  if (!onBytes || !res.body) return new Uint8Array(await res.arrayBuffer());
  const reader = res.body.getReader();
  const parts = [];
  let total = 0;
  for (;;) {
    const {done, value} = await reader.read();
    if (done) break;
    parts.push(value);
    total += value.length;
    onBytes(value.length);
  }
  const out = new Uint8Array(total);
  let o = 0;
  for (const p of parts) { out.set(p, o); o += p.length; }
  return out;
}

export async function fetchJSON(url) {
  const res = await fetch(url);
  if (!res.ok) throw new ViewerError(`${url}: HTTP ${res.status}`);
  return res.json();
}
