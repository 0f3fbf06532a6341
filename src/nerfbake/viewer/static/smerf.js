// SMERF scenes (ours and the official export alike): submodel choice from the camera position, two GPU-resident
// submodels (ping-pong: the old one renders until the new one is uploaded), an LRU host cache of decoded
// submodels, and the deferred MLP interpolated at the camera position on the CPU every frame.
import {ViewerError, bindTextures, mat3ColumnMajor, byteArrayTexture, createProgram, drawFullscreen, fetchBytes, fetchJSON,
        setFilter, texture3D} from './gl.js';
import {mlpLayout, packMlp, smerfDirectionFragment, smerfFragment} from './smerf_shader.js';

// viewer frame <-> training frame: (x', y', z') = (-x, z, y); its own inverse
const toTrain = (p) => [-p[0], p[2], p[1]];

export class SmerfScene {
  static async open(gl, base, entry, options = {}) {
    const first = await fetchJSON(`${base}${entry}/scene_params.json`);
    checkParams(first, entry);
    const scene = new SmerfScene(gl, base, first, options);
    const mlpRaw = first.deferred_mlp || await fetchJSON(`${base}${entry}/deferred_mlp.json`);
    scene.mlp = parseMlp(mlpRaw, entry);
    // colour, features, (coarse colour, coarse features,) view direction and its sin/cos encoding
    scene.mlp.inDim = (first.merge_features_combine_op || 'coarse_sum') === 'coarse_sum' ? 41 : 34;
    if (scene.mlp.layers[0].kshape[4] < scene.mlp.inDim) {
      throw new ViewerError(`${entry}: deferred MLP's first layer takes ${scene.mlp.layers[0].kshape[4]} inputs, fewer than ${scene.mlp.inDim}`);
    }
    try {
      scene.testFrames = (await fetchJSON(`${base}${entry}/test_frames.json`)).test_frames || [];
    } catch (e) {
      scene.testFrames = [];
    }
    // Every submodel's scene_params up front (small), as the official viewer does; assets are fetched lazily.
    scene.params = await Promise.all(first.params_to_sm.map((sm) =>
      fetchJSON(`${base}${smName(sm)}/scene_params.json`).then((p) => { checkParams(p, smName(sm)); return p; })));
    return scene;
  }

  constructor(gl, base, first, options) {
    this.gl = gl;
    this.kind = 'smerf';
    this.base = base;
    this.first = first;
    this.cacheSize = options.cacheSize ?? 4;
    this.stepMult = options.stepMult ?? 1;
    this.visibilityDelay = options.visibilityDelay ?? 0.99;
    this.background = options.background ?? [0.5, 0.5, 0.5];
    this.hostCache = new Map();  // params index -> decoded payload, in least- to most-recently-used order
    this.slots = [null, null];  // GPU-resident submodels
    this.active = -1;  // slot index drawn now
    this.loading = null;  // params index being fetched/uploaded
    this.stats = {fetches: [], evictions: [], uploads: [], swaps: 0};
    this.programs = new Map();
    this.onProgress = options.onProgress || (() => {});
    this.mlpTex = gl.createTexture();
    // the deferred MLP's direction term on a grid of every directionStride-th pixel (0: per pixel)
    this.directionGrid = DirectionGrid.supported(gl, options.directionStride ?? 8);
  }

  get k() { return Math.round(Math.cbrt(this.first.num_submodels || 1)); }

  submodelForPosition(pos) {
    const p = this.first;
    if ((p.num_local_submodels || 1) <= 1) return 0;
    const k = Math.round(2 / p.submodel_voxel_size);
    const t = toTrain(pos).map((v) => Math.min(k - 1, Math.max(0, Math.floor((v + 1) / 2 * k))));
    const idx = p.sm_to_params[(t[0] * k + t[1]) * k + t[2]];
    return idx >= 0 ? idx : 0;
  }

  center(paramsIdx) {
    const p = this.first;
    if ((p.num_local_submodels || 1) <= 1) return [0, 0, 0];
    const k = Math.round(2 / p.submodel_voxel_size);
    const sm = p.params_to_sm[paramsIdx];
    const ijk = [Math.floor(sm / (k * k)), Math.floor(sm / k) % k, sm % k];
    return toTrain(ijk.map((v) => (v + 0.5) * p.submodel_voxel_size - 1));
  }

  // --- streaming ----------------------------------------------------------------------------------------------

  async payload(idx) {
    if (this.hostCache.has(idx)) {
      const hit = this.hostCache.get(idx);
      this.hostCache.delete(idx);
      this.hostCache.set(idx, hit);  // most recently used
      return hit;
    }
    this.stats.fetches.push(idx);
    const data = await fetchSubmodel(this.base, smName(this.first.params_to_sm[idx]), this.params[idx], this.onProgress);
    if (this.cacheSize > 0) {
      this.hostCache.set(idx, data);
      while (this.hostCache.size > this.cacheSize) {
        const oldest = this.hostCache.keys().next().value;
        this.hostCache.delete(oldest);
        this.stats.evictions.push(oldest);
      }
    }
    return data;
  }

  // Called every frame: start loading the camera's submodel into the slot not being drawn; swap once uploaded.
  update(position) {
    const want = this.submodelForPosition(position);
    const cur = this.active >= 0 ? this.slots[this.active] : null;
    if ((cur && cur.idx === want) || this.loading !== null) return;
    const other = this.active >= 0 ? 1 - this.active : 0;
    if (this.slots[other] && this.slots[other].idx === want) {  // still resident from before: swap at once
      this.active = other;
      this.stats.swaps++;
      return;
    }
    this.loading = want;
    this.pending = this.payload(want).then((data) => {
      if (this.slots[other]) this.slots[other].dispose();
      this.slots[other] = new GpuSubmodel(this.gl, want, data);
      this.stats.uploads.push(want);
      this.active = other;
      this.stats.swaps++;
    }).finally(() => { this.loading = null; });
    this.pending.catch((e) => this.onError && this.onError(e));
  }

  // Whether what is drawn at `position` is its own submodel, with nothing left streaming.
  settledAt(position) {
    return this.loading === null && this.active >= 0 && this.slots[this.active].idx === this.submodelForPosition(position);
  }

  async ready(position) {
    this.update(position);
    while (this.loading !== null) await this.pending.catch(() => {});
    if (this.active < 0) throw new ViewerError('no submodel could be loaded');
  }

  residentSubmodels() { return this.slots.filter((s) => s).map((s) => s.idx); }

  state() {
    return {
      active: this.active >= 0 ? this.slots[this.active].idx : null, resident: this.residentSubmodels(),
      loading: this.loading, hostCache: [...this.hostCache.keys()], cacheSize: this.cacheSize,
      fetches: this.stats.fetches, evictions: this.stats.evictions, uploads: this.stats.uploads,
      numSubmodels: this.params.length,
      // the direction-grid pass as last drawn (null: the direction term per pixel)
      directionGrid: this.directionGrid && this.directionGrid.key ? {stride: this.directionGrid.stride, format: this.directionGrid.format} : null,
    };
  }

  // --- drawing ------------------------------------------------------------------------------------------------

  program(sm) {
    const p = sm.params;
    const gl = this.gl;
    const layout = mlpLayout(this.mlp.inDim, this.mlp.hidden);
    const grid = this.directionGrid && layout.q <= gl.getParameter(gl.MAX_DRAW_BUFFERS) ? this.directionGrid : null;
    const defs = {
      IN_DIM: layout.inDim, HIDDEN: layout.hidden, COARSE_SUM: (p.merge_features_combine_op || 'coarse_sum') === 'coarse_sum' ? 1 : 0,
      FEATURE_GATING: p.feature_gating === false ? 0 : 1, ACTIVATION_ELU: (p.activation || 'elu') === 'elu' ? 1 : 0,
      USE_EXPOSURE: this.exposure(p) ? 1 : 0, MLP_VEC4S: layout.vec4s,
      // the weights as a uniform block where it fits (every WebGL2 device allows 16 KiB: hidden widths up to 32)
      MLP_IN_UBO: layout.vec4s * 16 <= gl.getParameter(gl.MAX_UNIFORM_BLOCK_SIZE) ? 1 : 0,
      DIR_GRID: grid ? 1 : 0, DIR_STRIDE: grid ? grid.stride : 0,
    };
    const key = JSON.stringify(defs);
    if (!this.programs.has(key)) {
      const withMlp = (source) => {
        const prog = createProgram(gl, source);
        if (defs.MLP_IN_UBO) gl.uniformBlockBinding(prog.prog, gl.getUniformBlockIndex(prog.prog, 'MlpBlock'), 0);
        return prog;
      };
      this.programs.set(key, {
        prog: withMlp(smerfFragment(defs)), layout, ubo: defs.MLP_IN_UBO,
        direction: grid ? withMlp(smerfDirectionFragment(defs)) : null,
      });
    }
    return this.programs.get(key);
  }

  exposure(p) { return p.default_exposure || this.exposureOverride || null; }

  uploadMlp(idx, position, program) {
    const w = interpolateMlp(this.mlp, this.first, idx, position, this.center(idx));
    const buf = packMlp(program.layout, w);
    const gl = this.gl;
    if (program.ubo) {
      if (!this.mlpBuffer) this.mlpBuffer = gl.createBuffer();
      gl.bindBuffer(gl.UNIFORM_BUFFER, this.mlpBuffer);
      gl.bufferData(gl.UNIFORM_BUFFER, buf, gl.DYNAMIC_DRAW);
      gl.bindBufferBase(gl.UNIFORM_BUFFER, 0, this.mlpBuffer);
      return;
    }
    const n = program.layout.vec4s, width = Math.min(n, 1024), rows = Math.ceil(n / 1024);
    const padded = new Float32Array(width * rows * 4);
    padded.set(buf);
    gl.bindTexture(gl.TEXTURE_2D, this.mlpTex);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, width, rows, 0, gl.RGBA, gl.FLOAT, padded);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  }

  // The camera uniforms both passes share (smerf_shader.js: CAMERA_GLSL).
  setCamera(u, camera, sm, width, height, jitter) {
    const gl = this.gl;
    const scale = sm.params.submodel_scale;
    const c = this.center(sm.idx);
    gl.uniform2f(u.uViewport, width, height);
    gl.uniform2f(u.uPixelOffset, jitter[0], jitter[1]);
    gl.uniform3f(u.uOrigin, scale * (camera.position[0] - c[0]), scale * (camera.position[1] - c[1]), scale * (camera.position[2] - c[2]));
    gl.uniformMatrix3fv(u.uRotation, false, mat3ColumnMajor(camera.rotation));
    gl.uniformMatrix4fv(u.uInvProjection, false, camera.invProjection);
    gl.uniform1f(u.uScale, scale);
  }

  // camera: {position, rotation (3x3 row-major array of rows), invProjection (16, column-major)}
  draw(camera, target, width, height, jitter = [0, 0]) {
    if (this.active < 0) return false;
    const gl = this.gl;
    const sm = this.slots[this.active];
    const p = sm.params;
    const program = this.program(sm);
    this.uploadMlp(sm.idx, camera.position, program);
    if (program.direction) {
      // pass 1: the deferred MLP's direction term on the coarse pixel grid
      const grid = this.directionGrid.resize(width, height, program.layout.q);
      gl.useProgram(program.direction.prog);
      this.setCamera(program.direction.uniforms, camera, sm, width, height, jitter);
      bindTextures(gl, program.direction, [['tMlp', gl.TEXTURE_2D, this.mlpTex]]);
      drawFullscreen(gl, grid, grid.width, grid.height);
    }
    const prog = program.prog;
    gl.useProgram(prog.prog);
    const u = prog.uniforms;
    this.setCamera(u, camera, sm, width, height, jitter);
    if (program.direction) gl.uniform2f(u.uDirectionGrid, this.directionGrid.width, this.directionGrid.height);
    gl.uniform1f(u.uStepMult, this.stepMult);
    gl.uniform1f(u.uVisibilityDelay, this.visibilityDelay);
    gl.uniform3fv(u.uBackground, this.background);
    gl.uniform1f(u.uExposure, this.exposure(p) || 1);
    gl.uniform1f(u.uTriRes, p.triplane_resolution);
    gl.uniform1f(u.uTriVoxel, p.triplane_voxel_size);
    gl.uniform1f(u.uSparseVoxel, p.sparse_grid_voxel_size);
    gl.uniform1f(u.uBlock, p.data_block_size);
    gl.uniform2fv(u.uRangeFeatures, p.range_features);
    gl.uniform2fv(u.uRangeDensity, p.range_density);
    gl.uniform3f(u.uAtlasSize, p.atlas_width, p.atlas_height, p.atlas_depth);
    gl.uniform1i(u.uNumBlocks, sm.numBlocks);
    gl.uniform1i(u.uGrid8, sm.grid8);
    gl.uniform3fv(u.uOccLo, sm.occupied[0]);
    gl.uniform3fv(u.uOccHi, sm.occupied[1]);
    const T3 = gl.TEXTURE_3D, TA = gl.TEXTURE_2D_ARRAY;
    bindTextures(gl, prog, [
      ['tBlockIndices', T3, sm.tex.blockIndices], ['tAtlasA', T3, sm.tex.atlasA], ['tAtlasB', T3, sm.tex.atlasB],
      ['tPlaneA', TA, sm.tex.planeA], ['tPlaneB', TA, sm.tex.planeB], ['tGrid8', T3, sm.tex.grid8],
      ['tMlp', gl.TEXTURE_2D, this.mlpTex], ['tDirection', TA, this.directionGrid ? this.directionGrid.tex : null],
    ]);
    drawFullscreen(gl, target, width, height);
    return true;
  }

  // A test_frames.json view as a camera for draw().
  testCamera(i) {
    const f = this.testFrames[i];
    if (!f) throw new ViewerError(`test_frames.json has no view ${i}`);
    return testFrameCamera(f);
  }

  // bytes of the resident submodels' textures as allocated (RGBA8 where repacked)
  gpuBytes() { return this.slots.filter((s) => s).reduce((a, s) => a + s.textureBytes, 0); }
}

// The direction-grid pass's target (smerf_shader.js: smerfDirectionFragment): one float texel per stride x stride
// pixels and one more at the far edges, so that every pixel lies between texel centres; one layer per vec4 of the
// first layer's hidden units, each a colour attachment of one draw. It needs float render targets; where the
// browser has none, supported() returns null and the shader evaluates the direction term per pixel.
class DirectionGrid {
  static supported(gl, stride) {
    if (!stride) return null;
    const floatTargets = gl.getExtension('EXT_color_buffer_float');
    // 32-bit floats where they can also be filtered; 16-bit floats (always filterable) otherwise
    const format = floatTargets && gl.getExtension('OES_texture_float_linear') ? 'RGBA32F'
      : (floatTargets || gl.getExtension('EXT_color_buffer_half_float')) ? 'RGBA16F' : null;
    return format ? new DirectionGrid(gl, stride, format) : null;
  }

  constructor(gl, stride, format) {
    this.gl = gl;
    this.stride = stride;
    this.format = format;
    this.tex = null;
    this.fbo = gl.createFramebuffer();
    this.key = '';
  }

  // (Re)allocate for a frame of width x height and `layers` vec4s; returns this (a target for drawFullscreen).
  resize(width, height, layers) {
    const gl = this.gl;
    const w = Math.floor((width - 1) / this.stride) + 2, h = Math.floor((height - 1) / this.stride) + 2;
    const key = `${w}x${h}x${layers}`;
    if (key === this.key) return this;
    if (this.tex) gl.deleteTexture(this.tex);
    this.tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.tex);
    gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl[this.format], w, h, layers);
    setFilter(gl, gl.TEXTURE_2D_ARRAY, true);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
    const attachments = [];
    for (let j = 0; j < layers; j++) {
      gl.framebufferTextureLayer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + j, this.tex, 0, j);
      attachments.push(gl.COLOR_ATTACHMENT0 + j);
    }
    gl.drawBuffers(attachments);
    const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (status !== gl.FRAMEBUFFER_COMPLETE) throw new ViewerError(`direction grid: ${this.format} framebuffer incomplete (0x${status.toString(16)}); open the viewer with directionStride=0`);
    this.width = w;
    this.height = h;
    this.key = key;
    return this;
  }
}

// One submodel's textures. The baked arrays are repacked so that a ray step's fetches come together: the atlas as
// (density, gate, r, g) + (b, features), the triplanes as (density, rgb) + features, the factor-8 grids as
// (distance, occupancy). Interleaving bytes changes no value the shader reads.
class GpuSubmodel {
  constructor(gl, idx, data) {
    this.gl = gl;
    this.idx = idx;
    this.params = data.params;
    const p = data.params;
    const nb = p.sparse_grid_resolution / p.data_block_size;
    const t = p.triplane_resolution;
    this.numBlocks = nb;
    this.grid8 = Math.ceil(t / 8);
    const [aw, ah, ad] = [p.atlas_width, p.atlas_height, p.atlas_depth];
    const [atlasA, atlasB] = interleave([[concat(data.atlas.density), 2], [concat(data.atlas.rgb), 3], [concat(data.atlas.features), 3]]);
    const [planeA] = interleave([[concat(data.planes.density), 1], [concat(data.planes.rgb), 3]]);
    const [grid8] = interleave([[data.distance8, 1], [data.occupancy8, 1]], 2);
    const g8 = this.grid8;
    this.occupied = occupiedBox(data.occupancy8, g8, 8 * p.triplane_voxel_size);
    this.tex = {
      blockIndices: texture3D(gl, nb, nb, nb, 3, false, data.blockIndices),
      atlasA: texture3D(gl, aw, ah, ad, 4, true, atlasA),
      atlasB: texture3D(gl, aw, ah, ad, 4, true, atlasB),
      planeA: byteArrayTexture(gl, t, t, 3, 4, planeA, true),
      planeB: byteArrayTexture(gl, t, t, 3, 4, concat(data.planes.features), true),
      grid8: texture3D(gl, g8, g8, g8, 2, false, grid8),
    };
    this.bytes = data.bytes;
    this.textureBytes = nb ** 3 * 4 + 2 * aw * ah * ad * 4 + 2 * 3 * t * t * 4 + g8 ** 3 * 2;
  }
  dispose() { for (const t of Object.values(this.tex)) this.gl.deleteTexture(t); }
}

// [lo, hi] in contracted coordinates around every occupied factor-8 cell (a non-zero byte of the bit-packed
// grid; the distance grid's zeros include their neighbours), as kernels/smerf_march.py: occupied_box computes
// it; an empty grid gives an empty box (lo > hi).
function occupiedBox(occupancy8, n, voxel) {
  const lo = [n, n, n], hi = [-1, -1, -1];
  for (let f = 0; f < occupancy8.length; f++) {
    if (occupancy8[f] === 0) continue;
    const c = [f % n, Math.floor(f / n) % n, Math.floor(f / (n * n))];  // texel (x, y, z) as the 3D texture holds it
    for (let a = 0; a < 3; a++) { lo[a] = Math.min(lo[a], c[a]); hi[a] = Math.max(hi[a], c[a] + 1); }
  }
  if (hi[0] < 0) return [[1, 1, 1], [-1, -1, -1]];
  return [lo.map((v) => -2 + v * voxel), hi.map((v) => -2 + v * voxel)];
}

function concat(parts) {
  if (!Array.isArray(parts)) return parts;
  const out = new Uint8Array(parts.reduce((a, p) => a + p.length, 0));
  let o = 0;
  for (const part of parts) { out.set(part, o); o += part.length; }
  return out;
}

// [[bytes, channels], ...] of equally many texels -> texels of `width` channels, in order, as many as needed.
function interleave(sources, width = 4) {
  const n = sources[0][0].length / sources[0][1];
  const total = sources.reduce((a, [, c]) => a + c, 0);
  const outs = [...Array(Math.ceil(total / width))].map(() => new Uint8Array(n * width));
  let ch = 0;
  for (const [bytes, c] of sources) {
    if (bytes.length !== n * c) throw new ViewerError(`asset arrays disagree in size (${bytes.length} vs ${n * c} bytes)`);
    for (let k = 0; k < c; k++, ch++) {
      const out = outs[Math.floor(ch / width)], oc = ch % width;
      for (let i = 0; i < n; i++) out[i * width + oc] = bytes[i * c + k];
    }
  }
  return outs;
}

// A test_frames.json entry ({position, rotation, projection}, both matrices 16 numbers column-major) as a camera
// for draw(): rotation rows and the inverse projection.
export function testFrameCamera(f) {
  const m = f.rotation;
  const rotation = [[m[0], m[4], m[8]], [m[1], m[5], m[9]], [m[2], m[6], m[10]]];
  return {position: f.position.slice(), rotation, invProjection: invert4(f.projection)};
}

function smName(sm) { return `sm_${String(sm).padStart(3, '0')}`; }

function checkParams(p, where) {
  if ((p.export_array_format || 'png') !== 'raw.gz') {
    throw new ViewerError(`${where}: export_array_format ${p.export_array_format}; this viewer reads raw.gz assets`);
  }
  if (!p.export_store_rgb_and_density_separately) {
    throw new ViewerError(`${where}: the legacy merged rgb+density layout is not supported`);
  }
  if ((p.deferred_rendering_mode || 'snerg') !== 'snerg') {
    throw new ViewerError(`${where}: deferred_rendering_mode ${p.deferred_rendering_mode} (only snerg is supported)`);
  }
}

async function fetchSubmodel(base, name, params, onProgress) {
  const meta = new Map(params.asset_metadata.map((m) => [m.filename, m]));
  const url = (file) => `${base}${name}/${file.replace(/\.gz$/, '')}`;  // the server answers X.raw from X.raw.gz
  let bytes = 0;
  const get = async (file) => {
    const m = meta.get(file);
    if (!m) throw new ViewerError(`${name}/scene_params.json: asset_metadata has no entry for ${file}`);
    const data = await fetchBytes(url(file));
    const want = m.shape.reduce((a, b) => a * b, 1);
    if (data.length !== want) {
      throw new ViewerError(`${name}/${file}: ${data.length} bytes, expected ${want}; the file is truncated or from another export`);
    }
    bytes += data.length;
    onProgress(name, file);
    return data;
  };
  const slices = (kind) => Promise.all([...Array(params.num_slices).keys()].map(
    (k) => get(`sparse_grid_${kind}_${String(k).padStart(3, '0')}.raw.gz`)));
  const planes = (kind) => Promise.all([0, 1, 2].map((k) => get(`plane_${kind}_${k}.raw.gz`)));
  const grid8 = async (kind) => {
    const first = meta.get(`${kind}_grid_8_000.raw.gz`);
    if (!first) throw new ViewerError(`${name}: needs ${kind}_grid_8 (the factor-8 grid the renderer uses)`);
    return concat(await Promise.all([...Array(first.slice_count || 1).keys()].map(
      (i) => get(`${kind}_grid_8_${String(i).padStart(3, '0')}.raw.gz`))));
  };
  const [blockIndices, rgb, density, features, prgb, pdensity, pfeatures, occupancy8, distance8] = await Promise.all([
    get('sparse_grid_block_indices.raw.gz'), slices('rgb'), slices('density'), slices('features'),
    planes('rgb'), planes('density'), planes('features'), grid8('occupancy'), grid8('distance')]);
  return {params, blockIndices, atlas: {rgb, density, features}, planes: {rgb: prgb, density: pdensity, features: pfeatures},
          occupancy8, distance8, bytes};
}

function parseMlp(raw, where) {
  const layers = [0, 1, 2].map((i) => {
    const k = raw[`ResampleDense_${i}/kernel`];
    const b = raw[`ResampleDense_${i}/bias`];
    if (!k || !b) throw new ViewerError(`${where}: deferred MLP lacks ResampleDense_${i}; exactly 3 grid layers are needed`);
    return {kernel: Float32Array.from(k.data), kshape: k.shape, bias: Float32Array.from(b.data), bshape: b.shape};
  });
  const hidden = layers[0].kshape[5];
  if (hidden % 4 !== 0 || layers[2].kshape[5] !== 3) throw new ViewerError(`${where}: unexpected deferred MLP widths`);
  return {layers, hidden, inDim: 0};
}

// Kernels and biases of the 3 layers trilinearly interpolated on the P^3 lattice at the camera position (lattice
// axes in the training frame, arrays [submodel, z, y, x, ...]); as smerf/baked_render.py:deferred_mlp_weights.
function interpolateMlp(mlp, first, idx, position, center) {
  const k = Math.round(Math.cbrt(first.num_submodels || 1));
  const p = toTrain([0, 1, 2].map((a) => (position[a] - center[a]) * k));
  return mlp.layers.map((layer) => {
    const [, g, , , nin, nout] = layer.kshape;
    const x = p.map((v) => (v + 1) / 2 * g - 0.5);
    const lo = x.map(Math.floor);
    const f = x.map((v, a) => v - lo[a]);
    const kw = new Float64Array(nin * nout);
    const bw = new Float64Array(nout);
    for (let c = 0; c < 8; c++) {
      const off = [(c >> 2) & 1, (c >> 1) & 1, c & 1];
      const ii = off.map((o, a) => Math.min(g - 1, Math.max(0, lo[a] + o)));
      const w = off.reduce((acc, o, a) => acc * (o ? f[a] : 1 - f[a]), 1);
      const cell = ((idx * g + ii[2]) * g + ii[1]) * g + ii[0];
      const kb = cell * nin * nout;
      for (let j = 0; j < nin * nout; j++) kw[j] += w * layer.kernel[kb + j];
      for (let j = 0; j < nout; j++) bw[j] += w * layer.bias[cell * nout + j];
    }
    return {k: kw, b: bw, nin, nout};
  });
}

export function invert4(m) {
  // column-major 4x4 inverse (general)
  const inv = new Float64Array(16);
  inv[0] = m[5] * m[10] * m[15] - m[5] * m[11] * m[14] - m[9] * m[6] * m[15] + m[9] * m[7] * m[14] + m[13] * m[6] * m[11] - m[13] * m[7] * m[10];
  inv[4] = -m[4] * m[10] * m[15] + m[4] * m[11] * m[14] + m[8] * m[6] * m[15] - m[8] * m[7] * m[14] - m[12] * m[6] * m[11] + m[12] * m[7] * m[10];
  inv[8] = m[4] * m[9] * m[15] - m[4] * m[11] * m[13] - m[8] * m[5] * m[15] + m[8] * m[7] * m[13] + m[12] * m[5] * m[11] - m[12] * m[7] * m[9];
  inv[12] = -m[4] * m[9] * m[14] + m[4] * m[10] * m[13] + m[8] * m[5] * m[14] - m[8] * m[6] * m[13] - m[12] * m[5] * m[10] + m[12] * m[6] * m[9];
  inv[1] = -m[1] * m[10] * m[15] + m[1] * m[11] * m[14] + m[9] * m[2] * m[15] - m[9] * m[3] * m[14] - m[13] * m[2] * m[11] + m[13] * m[3] * m[10];
  inv[5] = m[0] * m[10] * m[15] - m[0] * m[11] * m[14] - m[8] * m[2] * m[15] + m[8] * m[3] * m[14] + m[12] * m[2] * m[11] - m[12] * m[3] * m[10];
  inv[9] = -m[0] * m[9] * m[15] + m[0] * m[11] * m[13] + m[8] * m[1] * m[15] - m[8] * m[3] * m[13] - m[12] * m[1] * m[11] + m[12] * m[3] * m[9];
  inv[13] = m[0] * m[9] * m[14] - m[0] * m[10] * m[13] - m[8] * m[1] * m[14] + m[8] * m[2] * m[13] + m[12] * m[1] * m[10] - m[12] * m[2] * m[9];
  inv[2] = m[1] * m[6] * m[15] - m[1] * m[7] * m[14] - m[5] * m[2] * m[15] + m[5] * m[3] * m[14] + m[13] * m[2] * m[7] - m[13] * m[3] * m[6];
  inv[6] = -m[0] * m[6] * m[15] + m[0] * m[7] * m[14] + m[4] * m[2] * m[15] - m[4] * m[3] * m[14] - m[12] * m[2] * m[7] + m[12] * m[3] * m[6];
  inv[10] = m[0] * m[5] * m[15] - m[0] * m[7] * m[13] - m[4] * m[1] * m[15] + m[4] * m[3] * m[13] + m[12] * m[1] * m[7] - m[12] * m[3] * m[5];
  inv[14] = -m[0] * m[5] * m[14] + m[0] * m[6] * m[13] + m[4] * m[1] * m[14] - m[4] * m[2] * m[13] - m[12] * m[1] * m[6] + m[12] * m[2] * m[5];
  inv[3] = -m[1] * m[6] * m[11] + m[1] * m[7] * m[10] + m[5] * m[2] * m[11] - m[5] * m[3] * m[10] - m[9] * m[2] * m[7] + m[9] * m[3] * m[6];
  inv[7] = m[0] * m[6] * m[11] - m[0] * m[7] * m[10] - m[4] * m[2] * m[11] + m[4] * m[3] * m[10] + m[8] * m[2] * m[7] - m[8] * m[3] * m[6];
  inv[11] = -m[0] * m[5] * m[11] + m[0] * m[7] * m[9] + m[4] * m[1] * m[11] - m[4] * m[3] * m[9] - m[8] * m[1] * m[7] + m[8] * m[3] * m[5];
  inv[15] = m[0] * m[5] * m[10] - m[0] * m[6] * m[9] - m[4] * m[1] * m[10] + m[4] * m[2] * m[9] + m[8] * m[1] * m[6] - m[8] * m[2] * m[5];
  const det = m[0] * inv[0] + m[1] * inv[4] + m[2] * inv[8] + m[3] * inv[12];
  if (!det) throw new ViewerError('singular projection matrix');
  return Array.from(inv, (v) => v / det);
}

// three.js-style perspective projection (column-major) for the interactive camera.
export function perspective(vfovDeg, aspect, near = 0.2, far = 100) {
  const f = 1 / Math.tan((vfovDeg * Math.PI) / 360);
  return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, (2 * far * near) / (near - far), 0];
}
