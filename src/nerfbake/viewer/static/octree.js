// PlenOctrees (raw and compressed .npz, ours and the authors'): parse the file in the browser, pack the tree into
// 2D-array textures within the device's limits (tiled over layers when one texture would be too large), and
// trace each pixel as the Python/Warp renderer does (src/nerfbake/kernels/octree.py), SH up to degree 4.
import {ViewerError, bindTextures, mat3ColumnMajor, createProgram, drawFullscreen, environmentTexture, fetchBytes,
        texture2DArray} from './gl.js';
import {asFloat, readNpz} from './npz.js';

export class OctreeScene {
  static async open(gl, url, options = {}) {
    const bytes = await fetchBytes(url, options.onBytes);
    const z = await readNpz(bytes, url);
    return new OctreeScene(gl, decodeTree(z, url), options);
  }

  constructor(gl, tree, options) {
    this.gl = gl;
    this.kind = 'octree';
    this.tree = tree;
    this.options = {
      stepSize: 1e-4, sigmaThresh: 1e-2, stopThresh: 1e-2, background: [1, 1, 1],
      bboxMin: [0, 0, 0], bboxMax: [1, 1, 1], basisMin: 0, basisMax: tree.nb, ...options.render,
    };
    const maxSize = Math.min(gl.getParameter(gl.MAX_TEXTURE_SIZE), options.maxTextureSize || 1 << 30);
    const maxLayers = gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS);
    const slots = tree.child.length;
    this.tps = Math.ceil(tree.dim / 4);  // RGBA32F texels per leaf slot
    this.childLayout = tiling(slots, maxSize, maxLayers, 'child pointers');
    this.dataLayout = tiling(slots * this.tps, maxSize, maxLayers, 'leaf data');
    const padTo = (arr, n, Arr) => { const o = new Arr(n); o.set(arr); return o; };
    const cl = this.childLayout, dl = this.dataLayout;
    this.childTex = texture2DArray(gl, cl.w, cl.h, cl.layers, 'R32I', 'RED_INTEGER', 'INT',
                                   padTo(tree.child, cl.w * cl.h * cl.layers, Int32Array), false);
    const packed = new Float32Array(dl.w * dl.h * dl.layers * 4);
    for (let s = 0; s < slots; s++) packed.set(tree.data.subarray(s * tree.dim, (s + 1) * tree.dim), s * this.tps * 4);
    this.dataTex = texture2DArray(gl, dl.w, dl.h, dl.layers, 'RGBA32F', 'RGBA', 'FLOAT', packed, false);
    // Beyond the box: the tree's environment map, or a 1x1 stand-in while the constant background is drawn.
    const env = tree.env || {width: 1, height: 1, data: new Uint8Array(3)};
    this.envTex = environmentTexture(gl, env.width, env.height, env.data);
    this.bytes = cl.w * cl.h * cl.layers * 4 + packed.byteLength + env.width * env.height * 4;
    this.program = createProgram(gl, octreeFragment(tree.nb));
  }

  // World-space bounding sphere of the tree (for the default camera).
  bounds() {
    const {offset, invradius} = this.tree;
    const center = [0, 1, 2].map((a) => (0.5 - offset[a]) / invradius[a]);
    const radius = Math.max(...invradius.map((v) => 0.5 / v)) * Math.sqrt(3);
    return {center, radius};
  }

  update() {}
  async ready() {}
  settledAt() { return true; }
  state() {
    const env = this.tree.env ? [this.tree.env.height, this.tree.env.width] : null;
    return {numLeaves: this.tree.numLeaves, nb: this.tree.nb, envMap: env, tiles: {child: this.childLayout, data: this.dataLayout}};
  }
  gpuBytes() { return this.bytes; }

  // camera: {c2w rotation rows (3x3) as `rotation`, `position`, fx, fy, cx, cy} in pixels of (width, height)
  draw(camera, target, width, height, jitter = [0, 0]) {
    const gl = this.gl;
    const o = this.options;
    const u = this.program.uniforms;
    gl.useProgram(this.program.prog);
    gl.uniform2f(u.uViewport, width, height);
    gl.uniform2f(u.uPixelOffset, jitter[0], jitter[1]);
    gl.uniform4f(u.uIntrinsics, camera.fx, camera.fy, camera.cx, camera.cy);
    gl.uniform3fv(u.uOrigin, camera.position);
    gl.uniformMatrix3fv(u.uRotation, false, mat3ColumnMajor(camera.rotation));
    gl.uniform3fv(u.uOffset, this.tree.offset);
    gl.uniform3fv(u.uInvRadius, this.tree.invradius);
    gl.uniform3fv(u.uBBoxMin, o.bboxMin);
    gl.uniform3fv(u.uBBoxMax, o.bboxMax);
    gl.uniform3fv(u.uBackground, o.background);
    gl.uniform1i(u.uHasEnv, this.tree.env ? 1 : 0);
    gl.uniform1f(u.uStepSize, o.stepSize);
    gl.uniform1f(u.uSigmaThresh, o.sigmaThresh);
    gl.uniform1f(u.uStopThresh, o.stopThresh);
    gl.uniform1i(u.uBasisMin, o.basisMin);
    gl.uniform1i(u.uBasisMax, Math.min(o.basisMax, this.tree.nb));
    gl.uniform1i(u.uDepthMode, o.depth ? 1 : 0);
    gl.uniform3i(u.uChildTile, ...this.childLayout.shift);
    gl.uniform3i(u.uDataTile, ...this.dataLayout.shift);
    bindTextures(gl, this.program, [['tChild', gl.TEXTURE_2D_ARRAY, this.childTex], ['tData', gl.TEXTURE_2D_ARRAY, this.dataTex],
                                     ['tEnv', gl.TEXTURE_2D, this.envTex]]);
    drawFullscreen(gl, target, width, height);
    return true;
  }
}

// Power-of-two widths (and heights, once there is more than one layer), so that the shader finds texel i with
// shifts and masks: integer division is slow on the GPU and slower still in SwiftShader.
function tiling(texels, maxSize, maxLayers, what) {
  const log2 = (v) => Math.round(Math.log2(v));
  const cap = 2 ** Math.floor(Math.log2(maxSize));
  const w = Math.min(cap, 2 ** Math.ceil(Math.log2(Math.max(1, texels))));
  const oneLayer = Math.ceil(texels / w) <= cap;
  const h = oneLayer ? Math.ceil(texels / w) : cap;
  const layers = Math.ceil(texels / (w * h));
  if (layers > maxLayers) {
    throw new ViewerError(`the tree's ${what} need ${layers} texture layers of ${w}x${h}; this device allows ${maxLayers}. ` +
                          'Build a smaller tree (lower --grid) or open it on a device with larger texture limits.');
  }
  // x = i & (w - 1); y = (i >> log2 w) & yMask; layer = i >> layerShift (31: always 0 with one layer)
  const shift = [log2(w), oneLayer ? 0x7fffffff : h - 1, oneLayer ? 31 : log2(w) + log2(h)];
  return {w, h, layers, shift};
}

function decodeTree(z, name) {
  const need = (k) => { if (!z[k]) throw new ViewerError(`${name}: missing key '${k}'; not a PlenOctree file`); return z[k]; };
  const child = need('child');
  if (child.descr !== '<i4') throw new ViewerError(`${name}: 'child' is ${child.descr}; svox stores int32 pointers`);
  if (child.shape.length !== 4 || child.shape.slice(1).some((v) => v !== 2)) {
    throw new ViewerError(`${name}: 'child' has shape (${child.shape}); the viewer needs an N=2 tree`);
  }
  const n = child.shape[0];
  const dim = Number(need('data_dim').data[0]);
  const fmt = z.data_format ? z.data_format.value : (dim === 4 ? 'RGBA' : `SH${(dim - 1) / 3}`);
  const m = /^SH(\d+)$/.exec(fmt);
  if (!m) throw new ViewerError(`${name}: data_format ${fmt}; the viewer renders SH trees (SH1..SH25)`);
  const nb = Number(m[1]);
  if (![1, 4, 9, 16, 25].includes(nb) || 3 * nb + 1 !== dim) throw new ViewerError(`${name}: data_format ${fmt} does not fit data_dim ${dim}`);
  const invradius = z.invradius3 ? Array.from(asFloat(z.invradius3)) : Array(3).fill(Number(asFloat(need('invradius'))[0]));
  const offset = Array.from(asFloat(need('offset')));
  const slots = n * 8;
  let data;
  if (z.quant_colors) {
    const colors = need('quant_colors'), qmap = need('quant_map'), sigma = asFloat(need('sigma'));
    const retained = z.data_retained ? asFloat(z.data_retained) : null;
    const r = z.data_retained ? z.data_retained.shape[0] : 0;
    const book = asFloat(colors);
    const k = colors.shape[1];
    data = new Float32Array(slots * dim);
    for (let s = 0; s < slots; s++) {
      for (let b = 0; b < nb; b++) {
        for (let ch = 0; ch < 3; ch++) {
          const v = b < r ? retained[(b * slots + s) * 3 + ch] : book[((b - r) * k + qmap.data[(b - r) * slots + s]) * 3 + ch];
          data[s * dim + ch * nb + b] = v;
        }
      }
      data[s * dim + 3 * nb] = sigma[s];
    }
  } else {
    const d = need('data');
    if (d.kind !== 'f16') throw new ViewerError(`${name}: 'data' is ${d.descr}; volrend requires float16`);
    data = asFloat(d);
    if (data.length !== slots * dim) throw new ViewerError(`${name}: 'data' size does not match 'child' and 'data_dim'`);
  }
  let env = null;
  if (z.env_map) {
    const e = z.env_map;
    if (e.data.BYTES_PER_ELEMENT !== 1 || e.shape.length !== 3 || e.shape[2] !== 3) {
      throw new ViewerError(`${name}: 'env_map' is ${e.descr} (${e.shape}); nerfbake writes uint8 (H, W, 3)`);
    }
    env = {height: e.shape[0], width: e.shape[1], data: e.data};
  }
  let leaves = 0;
  for (let i = 0; i < child.data.length; i++) if (child.data[i] === 0) leaves++;
  return {child: child.data, data, dim, nb, offset, invradius, env, numNodes: n, numLeaves: leaves, format: fmt};
}

// The leaf colour as straight-line code for this tree's SH count: texel t of a slot holds data[4t..4t+3], the
// layout is [r_0..r_nb-1, g_0.., b_0.., sigma] (svox), so every coefficient's texel and component are constants.
function shColourSource(nb) {
  const tps = Math.ceil((3 * nb + 1) / 4);
  const lines = [...Array(tps).keys()].map((t) => `  vec4 t${t} = ${t === (3 * nb >> 2) ? 'last' : `dataAt(slot, ${t})`};`);
  const comp = 'xyzw';
  for (let ch = 0; ch < 3; ch++) {
    const terms = [...Array(nb).keys()].map((k) => { const i = ch * nb + k; return `basis[${k}] * t${i >> 2}.${comp[i & 3]}`; });
    lines.push(`  s.${'xyz'[ch]} = ${terms.join(' + ')};`);
  }
  return lines.join('\n');
}

// Real SH basis up to degree 4 in svox's order and signs.
const SH_BASIS = `void shBasis(vec3 d, out float b[25]) {
  float x = d.x, y = d.y, z = d.z;
  float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  b[0] = 0.28209479177387814;
  b[1] = -0.4886025119029199 * y;
  b[2] = 0.4886025119029199 * z;
  b[3] = -0.4886025119029199 * x;
  b[4] = 1.0925484305920792 * xy;
  b[5] = -1.0925484305920792 * yz;
  b[6] = 0.31539156525252005 * (2.0 * zz - xx - yy);
  b[7] = -1.0925484305920792 * xz;
  b[8] = 0.5462742152960396 * (xx - yy);
  b[9] = -0.5900435899266435 * y * (3.0 * xx - yy);
  b[10] = 2.890611442640554 * xy * z;
  b[11] = -0.4570457994644658 * y * (4.0 * zz - xx - yy);
  b[12] = 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
  b[13] = -0.4570457994644658 * x * (4.0 * zz - xx - yy);
  b[14] = 1.445305721320277 * z * (xx - yy);
  b[15] = -0.5900435899266435 * x * (xx - 3.0 * yy);
  b[16] = 2.5033429417967046 * xy * (xx - yy);
  b[17] = -1.7701307697799304 * yz * (3.0 * xx - yy);
  b[18] = 0.9461746957575601 * xy * (7.0 * zz - 1.0);
  b[19] = -0.6690465435572892 * yz * (7.0 * zz - 3.0);
  b[20] = 0.10578554691520431 * (zz * (35.0 * zz - 30.0) + 3.0);
  b[21] = -0.6690465435572892 * xz * (7.0 * zz - 3.0);
  b[22] = 0.47308734787878004 * (xx - yy) * (7.0 * zz - 1.0);
  b[23] = -1.7701307697799304 * xz * (xx - 3.0 * yy);
  b[24] = 0.6258357354491761 * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy));
}`;

function octreeFragment(nb) {
  const sigIndex = 3 * nb;
  return `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2DArray;
precision highp isampler2DArray;
#define TPS ${Math.ceil((3 * nb + 1) / 4)}
#define NB ${nb}
out vec4 fragColor;
uniform vec2 uViewport;
uniform vec2 uPixelOffset;
uniform vec4 uIntrinsics;  // fx, fy, cx, cy (pixels, rows counted from the top)
uniform vec3 uOrigin;
uniform mat3 uRotation;    // camera-to-world (OpenGL: looks down -z)
uniform vec3 uOffset;
uniform vec3 uInvRadius;
uniform vec3 uBBoxMin;
uniform vec3 uBBoxMax;
uniform vec3 uBackground;
uniform int uHasEnv;        // 1: colour beyond the box from tEnv (equirectangular, render/envmap.py), else uBackground
uniform sampler2D tEnv;
uniform float uStepSize;
uniform float uSigmaThresh;
uniform float uStopThresh;
uniform int uBasisMin;
uniform int uBasisMax;
uniform int uDepthMode;
uniform ivec3 uChildTile;   // (log2 width, row mask, layer shift) of the tiling in octree.js
uniform ivec3 uDataTile;
uniform isampler2DArray tChild;
uniform sampler2DArray tData;

ivec3 tileAddress(int i, ivec3 tile) { return ivec3(i & ((1 << tile.x) - 1), (i >> tile.x) & tile.y, i >> tile.z); }
int childAt(int slot) { return texelFetch(tChild, tileAddress(slot, uChildTile), 0).r; }
vec4 dataAt(int slot, int t) { return texelFetch(tData, tileAddress(slot * TPS + t, uDataTile), 0); }

${SH_BASIS}

vec3 background(vec3 d) {
  if (uHasEnv == 0) return uBackground;
  float s = atan(d.y, d.x) * 0.15915494309189535 + 0.5;
  float t = acos(clamp(d.z, -1.0, 1.0)) * 0.3183098861837907;
  return textureLod(tEnv, vec2(s, t), 0.0).rgb;
}

const int MAX_LEVELS = 24;

// findMSB (GLSL ES 3.1) for 0 <= v < 2^24: the exponent of float(v), which is exact there; -127 for 0.
int highestBit(int v) { return (floatBitsToInt(float(v)) >> 23) - 127; }
const float CELLS = 16777216.0;  // 2^MAX_LEVELS: a point in [0, 1)^3 as integer cell coordinates at the finest level

void main() {
  vec2 pix = vec2(gl_FragCoord.x, uViewport.y - gl_FragCoord.y) + uPixelOffset;  // +0.5 centres, rows from the top
  vec3 dc = vec3((pix.x - uIntrinsics.z) / uIntrinsics.x, -(pix.y - uIntrinsics.w) / uIntrinsics.y, -1.0);
  vec3 d = uRotation * normalize(dc);
  // tree space
  vec3 ot = uOffset + uInvRadius * uOrigin;
  vec3 ds = uInvRadius * d;
  float scale = length(ds);
  vec3 dt = ds / scale;
  float toWorld = 1.0 / scale;
  float t = 0.0;
  float tEnd = 1.0e9;
  for (int a = 0; a < 3; a++) {
    if (dt[a] != 0.0) {
      float inv = 1.0 / dt[a];
      float ta = (uBBoxMin[a] - ot[a]) * inv;
      float tb = (uBBoxMax[a] - ot[a]) * inv;
      t = max(t, min(ta, tb));
      tEnd = min(tEnd, max(ta, tb));
    } else if (ot[a] < uBBoxMin[a] || ot[a] > uBBoxMax[a]) {
      tEnd = -1.0;
    }
  }
  float basis[25];
  shBasis(d, basis);
  for (int k = 0; k < NB; k++) if (k < uBasisMin || k >= uBasisMax) basis[k] = 0.0;
  vec3 acc = vec3(0.0);
  float dep = 0.0;
  float T = 1.0;
  bool stopped = false;
  // The path of the last descent: the node at each level and the leaf's integer coordinates; the next point
  // resumes from the deepest node whose cell still holds it (usually one or two levels up, not the root).
  int path[MAX_LEVELS + 1];
  path[0] = 0;
  ivec3 leafCell = ivec3(-1);
  int leafLevel = 0;
  for (int iter = 0; iter < 100000; iter++) {
    if (t >= tEnd) break;
    vec3 q = clamp(ot + t * dt, 0.0, 0.9999999);
    ivec3 cell = ivec3(q * CELLS);  // exact: q < 1 has at most 24 significant bits below 1
    ivec3 diff = cell ^ leafCell;
    int level = leafCell.x < 0 ? 0 : min(leafLevel, MAX_LEVELS - 1 - highestBit(diff.x | diff.y | diff.z));
    int node = path[level];
    int slot = 0;
    for (; level < MAX_LEVELS; ) {
      ivec3 ii = (cell >> (MAX_LEVELS - 1 - level)) & 1;
      slot = node * 8 + ii.x * 4 + ii.y * 2 + ii.z;
      level++;
      int skip = childAt(slot);
      if (skip == 0) break;
      node += skip;
      path[level] = node;
    }
    leafCell = cell;
    leafLevel = level - 1;
    float cube = float(1 << level);
    vec3 ql = fract(q * cube);  // the point inside its leaf, in units of the leaf
    float delta = 1.0e9;
    for (int a = 0; a < 3; a++) {
      if (dt[a] > 0.0) delta = min(delta, (1.0 - ql[a]) / dt[a]);
      else if (dt[a] < 0.0) delta = min(delta, -ql[a] / dt[a]);
    }
    delta /= cube;
    vec4 last = dataAt(slot, ${sigIndex >> 2});
    float sigma = last.${'xyzw'[sigIndex & 3]};
    if (sigma > uSigmaThresh) {
      float att = exp(-delta * toWorld * sigma);
      float w = T * (1.0 - att);
      vec3 s;
${shColourSource(nb)}
      acc += w / (1.0 + exp(-s));
      dep += w * (t + 0.5 * delta) * toWorld;
      T *= att;
      if (T < uStopThresh) { stopped = true; break; }
    }
    t += delta + uStepSize;
  }
  vec3 rgb = stopped ? acc / (1.0 - T) : acc + T * background(d);
  if (uDepthMode == 1) rgb = vec3(clamp(dep * 0.3, 0.0, 1.0));
  fragColor = vec4(clamp(rgb, 0.0, 1.0), 1.0);
}
`;
}
