// Fragment shader of the SMERF renderer. It follows docs/smerf_viewer.md step for step, in the same order as the
// Python/Warp re-implementation (src/nerfbake/kernels/smerf_march.py) that the tests compare it with.

// The deferred MLP's weights as vec4s: biases first, then 4x4 blocks (mat4, column c = input 4g+c, row r = output
// 4j+r) of each layer; the first layer's inputs are padded to a multiple of 4. The shader is straight-line code
// with constant indices (no loops or arrays), which SwiftShader and mobile compilers run much faster than the
// per-weight texelFetch loop it replaced.
export function mlpLayout(inDim, hidden) {
  const g = Math.ceil(inDim / 4), q = hidden / 4;
  const bias = [0, q, 2 * q];  // vec4 offsets of b0, b1, b2
  const k0 = 2 * q + 1, k1 = k0 + 4 * g * q, k2 = k1 + 4 * q * q;
  return {inDim, hidden, g, q, bias, k0, k1, k2, vec4s: k2 + 4 * q};
}

// weights: [{k: Float64Array(nin*nout) row-major [in][out], b: (nout)}] x 3 -> Float32Array(vec4s * 4)
export function packMlp(layout, weights) {
  const {g, q, hidden} = layout;
  const buf = new Float32Array(layout.vec4s * 4);
  const [w0, w1, w2] = weights;
  for (let j = 0; j < hidden; j++) { buf[layout.bias[0] * 4 + j] = w0.b[j]; buf[layout.bias[1] * 4 + j] = w1.b[j]; }
  for (let j = 0; j < 3; j++) buf[layout.bias[2] * 4 + j] = w2.b[j];
  const block = (base, w, nin, nout, bi, bj, nbj) => {
    const off = (base + 4 * (bi * nbj + bj)) * 4;
    for (let c = 0; c < 4; c++) {
      for (let r = 0; r < 4; r++) {
        const i = 4 * bi + c, o = 4 * bj + r;
        if (i < nin && o < nout) buf[off + c * 4 + r] = w.k[i * nout + o];
      }
    }
  };
  for (let bi = 0; bi < g; bi++) for (let bj = 0; bj < q; bj++) block(layout.k0, w0, layout.inDim, hidden, bi, bj, q);
  for (let bi = 0; bi < q; bi++) for (let bj = 0; bj < q; bj++) block(layout.k1, w1, hidden, hidden, bi, bj, q);
  for (let bi = 0; bi < q; bi++) block(layout.k2, w2, hidden, 3, bi, 0, 1);
  return buf;
}

// The deferred MLP's inputs in the trained order, split the way its first layer is split: what the ray gathered
// (colour, features, coarse colour and features) and the view direction with its sin/cos encoding.
function mlpInputs(defs) {
  const ray = ['e0.x', 'e0.y', 'e0.z', 'e1.x', 'e1.y', 'e1.z', 'e1.w'];
  if (defs.COARSE_SUM) ray.push('e2.x', 'e2.y', 'e2.z', 'e3.x', 'e3.y', 'e3.z', 'e3.w');
  const dir = ['v.x', 'v.y', 'v.z'];
  for (const f of ['s', 'c']) for (let k = 0; k < 4; k++) dir.push(`${f}${k}.x`, `${f}${k}.y`, `${f}${k}.z`);
  return {ray, dir};
}

// GLSL pieces of the deferred MLP (SNeRG mode; kernels and biases were interpolated at the camera position on the
// CPU). The first layer is bias + W_ray x_ray + W_dir x_dir; the direction part with the bias is a smooth function
// of the pixel, which the direction-grid pass (smerfDirectionFragment) evaluates on a coarse screen grid.
function mlpPieces(defs) {
  const L = mlpLayout(defs.IN_DIM, defs.HIDDEN);
  const vec = (i) => (defs.MLP_IN_UBO ? `uMlp[${i}]` : `texelFetch(tMlp, ivec2(${i % 1024}, ${Math.floor(i / 1024)}), 0)`);
  // A 4x4 block times a vec4 as the sum of its columns scaled by the inputs (no mat4 is assembled); the first layer
  // takes its inputs by name, so the padding to a multiple of 4 costs nothing.
  const mul = (i, x) => `${vec(i)} * ${x}.x + ${vec(i + 1)} * ${x}.y + ${vec(i + 2)} * ${x}.z + ${vec(i + 3)} * ${x}.w`;
  const {ray, dir} = mlpInputs(defs);
  if (ray.length + dir.length !== L.inDim) throw new Error(`MLP input layout has ${ray.length + dir.length} entries, the weights ${L.inDim}`);
  // column c of the first layer's input block (c >> 2, j) multiplies input c
  const first = (names, offset, j) => names.map((name, i) => {
    const c = offset + i;
    return `${vec(L.k0 + 4 * ((c >> 2) * L.q + j) + (c & 3))} * ${name}`;
  }).join(' + ');
  const directionTerm = (j) => `${vec(L.bias[0] + j)} + ${first(dir, ray.length, j)}`;
  // sin/cos of 2v, 4v, 8v by the double-angle rules: 2 trigonometric calls instead of 8 (|v| = 1, so the rounding
  // error grows to a few 1e-7 at 8v)
  const encoding = `  vec3 s0 = sin(v), c0 = cos(v);
  vec3 s1 = 2.0 * s0 * c0, c1 = 1.0 - 2.0 * s0 * s0;
  vec3 s2 = 2.0 * s1 * c1, c2 = 1.0 - 2.0 * s1 * s1;
  vec3 s3 = 2.0 * s2 * c2, c3 = 1.0 - 2.0 * s2 * s2;`;
  const lines = [];
  for (let j = 0; j < L.q; j++) {
    const dirPart = defs.DIR_GRID ? `texture(tDirection, vec3(dirUv, ${j}.0))` : directionTerm(j);
    lines.push(`  vec4 h${j} = act4(${dirPart} + ${first(ray, 0, j)});`);
  }
  for (let j = 0; j < L.q; j++) {
    const terms = [...Array(L.q).keys()].map((i) => mul(L.k1 + 4 * (i * L.q + j), `h${i}`));
    lines.push(`  vec4 u${j} = act4(${vec(L.bias[1] + j)} + ${terms.join(' + ')});`);
  }
  const out = [...Array(L.q).keys()].map((i) => mul(L.k2 + 4 * i, `u${i}`));
  lines.push(`  vec4 o = ${vec(L.bias[2])} + ${out.join(' + ')};`);
  const weights = defs.MLP_IN_UBO ? 'layout(std140) uniform MlpBlock { vec4 uMlp[MLP_VEC4S]; };' : 'uniform sampler2D tMlp;';
  const mlp = `// The deferred MLP; dirUv: where this pixel's first-layer direction term lies in tDirection (DIR_GRID)
vec3 deferredMlp(vec3 cIn, vec4 feat, vec3 coarseColor, vec4 coarseFeat, vec3 v, vec2 dirUv) {
  vec4 e0 = expo(vec4(cIn, 0.0)), e1 = expo(feat), e2 = expo(vec4(coarseColor, 0.0)), e3 = expo(coarseFeat);
${defs.DIR_GRID ? '' : encoding}
${lines.join('\n')}
  return sigmoid3(o.xyz);
}`;
  return {L, weights, encoding, directionTerm, mlp};
}

// The camera uniforms and the pixel -> ray map, shared by the march and the direction-grid pass.
const CAMERA_GLSL = `uniform vec2 uViewport;      // render-target size in pixels
uniform vec2 uPixelOffset;   // sub-pixel jitter for progressive refinement (pixels)
uniform vec3 uOrigin;        // camera centre in the submodel frame
uniform mat3 uRotation;      // camera-to-viewer rotation (three.js camera, looks down -z)
uniform mat4 uInvProjection;
uniform float uScale;        // submodel_scale

// The ray through pixel position pix, scaled to reach the near plane at t = 1 (submodel frame).
vec3 pixelRay(vec2 pix) {
  vec2 ndc = pix / uViewport * 2.0 - 1.0;
  vec4 q4 = uInvProjection * vec4(ndc, -1.0, 1.0);
  return uScale * (uRotation * (q4.xyz / q4.w));
}

// A ray's unit direction in the training frame, which the deferred MLP was trained on (viewer -> training: W v).
vec3 trainingDirection(vec3 ray) { return normalize(vec3(-ray.x, ray.z, ray.y)); }`;

function header(defs) {
  const lines = Object.entries(defs).map(([k, v]) => `#define ${k} ${v}`).join('\n');
  return `#version 300 es
precision highp float;
precision highp int;
precision highp sampler3D;
precision highp sampler2DArray;
precision highp sampler2D;
${lines}`;
}

// The direction-grid pass: the deferred MLP's first-layer direction term (with its bias) at every DIR_STRIDE-th
// pixel of the frame, one vec4 of hidden units per layer of the target array (smerf.js: DirectionGrid). The march
// pass interpolates it bilinearly instead of evaluating 27 of the layer's 34 inputs and 6 sin/cos per pixel; across
// DIR_STRIDE pixels the direction turns by well under a degree, so the interpolation error is far below a colour
// level (the browser-vs-Python test holds it to its threshold).
export function smerfDirectionFragment(defs) {
  const m = mlpPieces(defs);
  const outs = [...Array(m.L.q).keys()].map((j) => `layout(location = ${j}) out vec4 dir${j};`).join('\n');
  const writes = [...Array(m.L.q).keys()].map((j) => `  dir${j} = ${m.directionTerm(j)};`).join('\n');
  return `${header(defs)}
${outs}
${CAMERA_GLSL}
${m.weights}

void main() {
  vec2 pix = (gl_FragCoord.xy - 0.5) * float(DIR_STRIDE) + 0.5 + uPixelOffset;
  vec3 v = trainingDirection(pixelRay(pix));
${m.encoding}
${writes}
}
`;
}

export function smerfFragment(defs) {
  const m = mlpPieces(defs);
  return `${header(defs)}
out vec4 fragColor;

${CAMERA_GLSL}
uniform float uStepMult;
uniform float uVisibilityDelay;
uniform vec3 uBackground;
uniform float uExposure;
uniform float uTriRes;
uniform float uTriVoxel;
uniform float uSparseVoxel;
uniform float uBlock;
uniform vec2 uRangeFeatures;
uniform vec2 uRangeDensity;
uniform vec3 uAtlasSize;
uniform int uNumBlocks;
uniform int uGrid8;
uniform vec3 uOccLo;         // contracted box around every occupied factor-8 cell (smerf.js: occupiedBox)
uniform vec3 uOccHi;

// The baked arrays repacked at upload so that one fetch serves what a step needs together (smerf.js: GpuSubmodel):
uniform sampler3D tBlockIndices;
uniform sampler3D tAtlasA;         // sparse density, gate, r, g
uniform sampler3D tAtlasB;         // b, features 0..2
uniform sampler2DArray tPlaneA;    // triplane density, r, g, b
uniform sampler2DArray tPlaneB;    // triplane features 0..3
uniform sampler3D tGrid8;          // factor-8 distance (cells) and occupancy bits
${m.weights}
${defs.DIR_GRID ? 'uniform sampler2DArray tDirection;  // the direction-grid pass\'s output\nuniform vec2 uDirectionGrid;       // its size in texels' : ''}

const float INF = 1.0e25;

// One-hot mask of the largest |component| (ties to the first): selects instead of dynamic vector indexing, which
// SwiftShader and many mobile compilers turn into memory accesses.
bvec3 majorMask(vec3 a) {
  bool x = a.x >= a.y && a.x >= a.z;
  bool y = !x && a.y >= a.z;
  return bvec3(x, y, !x && !y);
}

float maxAbs(vec3 v) { return max(abs(v.x), max(abs(v.y), abs(v.z))); }

vec3 contract(vec3 x) {
  vec3 a = abs(x);
  float m = max(a.x, max(a.y, a.z));
  if (m <= 1.0) return x;
  float s = 1.0 / m;
  vec3 z = s * x;
  return mix(z, z * (2.0 - s), majorMask(a));
}

vec3 uncontract(vec3 z) {
  vec3 a = abs(z);
  float m = max(a.x, max(a.y, a.z));
  if (m <= 1.0) return z;
  float s = 1.0 / max(1.0e-6, 2.0 - m);
  vec3 x = s * z;
  return mix(x, sign(x) * s, majorMask(a));
}

vec2 slab(vec3 lo, vec3 hi, vec3 o, vec3 invD) {
  vec3 ta = (lo - o) * invD;
  vec3 tb = (hi - o) * invD;
  vec3 mn = min(ta, tb);
  vec3 mx = max(ta, tb);
  return vec2(max(max(mn.x, mn.y), mn.z), min(min(mx.x, mx.y), mx.z));
}

// [t in, t out] of the ray in the core box |x| <= 1 - 1e-5 (empty when t in > t out).
vec2 coreSpan(vec3 o, vec3 invD) { return slab(vec3(-1.0 + 1.0e-5), vec3(1.0 - 1.0e-5), o, invD); }

// Intersect the interval iv of t with the half-line where n.(o + t d) >= c, given no = n.o and nd = n.d.
vec2 halfSpace(vec2 iv, float no, float nd, float c) {
  if (nd > 0.0) return vec2(max(iv.x, (c - no) / nd), iv.y);
  if (nd < 0.0) return vec2(iv.x, min(iv.y, (c - no) / nd));
  return no >= c ? iv : vec2(INF, -INF);
}

// The t where the ray leaves region k (0 core, 1..6 = +x,+y,+z,-x,-y,-z), or -INF where it never is in it. A region
// is convex in world space, so its stretch of the ray is one interval, cut out by closed-form half-spaces: the core
// is the box |x| <= c1; outer region (axis a, sign s) is s x_a >= 1, s x_a <= 1e4 (contracted 2 - 1e-4) and
// s x_a >= |x_b| for the two other axes. This replaces testing contract() at 12 candidate crossings per region
// with a few divisions; the exits agree to float precision.
float regionExit(vec3 o, vec3 d, vec3 invD, int k) {
  if (k == 0) {
    vec2 t = coreSpan(o, invD);
    return t.x <= t.y ? t.y : -INF;
  }
  int a = (k - 1) % 3;
  float sg = k <= 3 ? 1.0 : -1.0;
  vec3 ea = vec3(equal(ivec3(a), ivec3(0, 1, 2)));
  vec3 eb = vec3(equal(ivec3((a + 1) % 3), ivec3(0, 1, 2)));
  vec3 ec = vec3(equal(ivec3((a + 2) % 3), ivec3(0, 1, 2)));
  float oa = sg * dot(o, ea), da = sg * dot(d, ea);
  float ob = dot(o, eb), db = dot(d, eb), oc = dot(o, ec), dc = dot(d, ec);
  vec2 iv = vec2(-INF, INF);
  iv = halfSpace(iv, oa, da, 1.0);
  iv = halfSpace(iv, -oa, -da, -1.0e4);
  iv = halfSpace(iv, oa - ob, da - db, 0.0);
  iv = halfSpace(iv, oa + ob, da + db, 0.0);
  iv = halfSpace(iv, oa - oc, da - dc, 0.0);
  iv = halfSpace(iv, oa + oc, da + dc, 0.0);
  return iv.x <= iv.y ? iv.y : -INF;
}

// core: the quadrant is the unit box, where contraction is the identity (world steps are contracted steps).
// tEnd: where the quadrant's straight contracted ray leaves the occupied box for good (-INF if it never meets it);
// no step after it can land in an occupied cell, so the march moves on to the next quadrant there.
struct Quadrant { vec3 oc; vec3 dc; vec3 invDc; float tmin; float tmax; float tEnd; bool core; };

Quadrant quadrantSetup(vec3 o, vec3 d, float tp, float tq) {
  vec3 xp = o + tp * d;
  vec3 lo = vec3(-1.0);
  vec3 hi = vec3(1.0);
  Quadrant q;
  q.core = maxAbs(xp) <= 1.0;
  if (!q.core) {
    bvec3 m = majorMask(abs(xp));
    bool pos = dot(xp, vec3(m)) > 0.0;
    lo = mix(lo, vec3(pos ? 1.0 : -2.0), m);
    hi = mix(hi, vec3(pos ? 2.0 : -1.0), m);
  }
  q.oc = contract(xp);
  q.dc = normalize(contract(o + tq * d) - q.oc);
  q.invDc = 1.0 / q.dc;
  vec2 t = slab(lo, hi, q.oc, q.invDc);
  q.tmin = t.x;
  q.tmax = t.y;
  vec2 occ = slab(uOccLo, uOccHi, q.oc, q.invDc);
  q.tEnd = occ.x <= occ.y ? min(q.tmax, occ.y) : -INF;
  return q;
}

// (distance in cells, occupancy bits) of the factor-8 cell holding grid position c
vec2 grid8(vec3 c) {
  ivec3 i = clamp(ivec3(floor(c)), ivec3(0), ivec3(uGrid8 - 1));
  return floor(texelFetch(tGrid8, i, 0).rg * 255.0 + 0.5);
}

vec4 planeSum(sampler2DArray tex, vec3 p) {
  return texture(tex, vec3(p.y, p.z, 0.0)) + texture(tex, vec3(p.x, p.z, 1.0)) + texture(tex, vec3(p.x, p.y, 2.0));
}

float sigmoid(float x) { return 1.0 / (1.0 + exp(-x)); }
vec3 sigmoid3(vec3 x) { return 1.0 / (1.0 + exp(-x)); }
vec4 sigmoid4(vec4 x) { return 1.0 / (1.0 + exp(-x)); }

vec4 act4(vec4 x) {
#if ACTIVATION_ELU
  return mix(exp(min(x, 0.0)) - 1.0, x, greaterThan(x, vec4(0.0)));
#else
  return max(x, 0.0);
#endif
}

vec4 expo(vec4 x) {
#if USE_EXPOSURE
  vec4 c = clamp(x, 1.0e-7, 1.0 - 1.0e-7);
  return log(c / (1.0 - c)) + log(uExposure);
#else
  return x;
#endif
}

${m.mlp}

void main() {
  vec3 d = pixelRay(gl_FragCoord.xy + uPixelOffset);  // to the near plane: the ray starts at t = 1
  vec3 viewDir = d;
  vec3 o = uOrigin;
  d = mix(d, vec3(1.0e-9), lessThan(abs(d), vec3(1.0e-9)));
  float nearT = 1.0;
  float exits[8];
  for (int j = 0; j < 8; j++) exits[j] = INF;
  int n = 0;
  // Where the occupied box lies in the core (contracted = world there), a ray that misses it in world space can
  // meet no occupied cell: it skips the regions and the march and keeps only the deferred MLP's background.
  bool occInCore = maxAbs(uOccLo) <= 1.0 && maxAbs(uOccHi) <= 1.0;
  vec3 invD = 1.0 / d;
  vec2 occWorld = slab(uOccLo, uOccHi, o, invD);
  bool misses = occInCore && (occWorld.x > occWorld.y || occWorld.y < nearT);
  for (int k = 0; k < (misses ? 0 : 7); k++) {
    float t = regionExit(o, d, invD, k);
    if (t >= nearT) {
      int j = n;
      while (j > 0 && exits[j - 1] > t) { exits[j] = exits[j - 1]; j--; }
      exits[j] = t;
      n++;
    }
  }
  Quadrant q = quadrantSetup(o, d, nearT, nearT + 0.5 * (exits[0] - nearT));
  float tc = 0.0;
  float origStep = uTriVoxel / uStepMult;
  if (occInCore && !misses && !q.core) {
    // A camera outside the core meets the occupied box only in the core: the march starts where the ray enters it,
    // as a quadrant change there would (visibility is still 1, so the step is origStep).
    vec2 core = coreSpan(o, invD);
    q = quadrantSetup(o, d, core.x + 0.1 * (core.y - core.x), core.x + 0.9 * (core.y - core.x));
    tc = q.tmin + 0.5 * origStep;
  }
  int qi = 1;
  float tBlock = -INF;
  float vis = 1.0;
  float ema = 1.0;
  vec3 color = vec3(0.0);
  vec4 feat = vec4(0.0);
  vec3 coarseColor = vec3(0.0);
  vec4 coarseFeat = vec4(0.0);
  int maxSteps = misses ? 0 : int(uStepMult) * int(ceil(sqrt(2.0 * uTriRes * uTriRes)));
  vec3 minP = vec3(-2.0);
  float vsGrid = 8.0 * uTriVoxel;
  float rf = uRangeFeatures.y - uRangeFeatures.x;
  float rd = uRangeDensity.y - uRangeDensity.x;
  float b = uBlock;
  ivec3 lastBlock = ivec3(-1);
  vec3 blockAtlas = vec3(255.0);
  float tWorld = -INF;  // uncontract(q.oc + tWorld q.dc) of the last step's end, reused as the next step's start
  vec3 world = vec3(0.0);
  for (int i = 0; i < maxSteps; i++) {
    if (vis <= 1.0 / 255.0) break;
    ema = uVisibilityDelay * ema + (1.0 - uVisibilityDelay) * vis;
    float stepLen = origStep * (10.0 - 9.0 * sqrt(min(1.0, ema / 0.8)));
    if (tc > q.tEnd) {
      // past the occupied box in the core, which holds it all: a line leaves a convex box once, so nothing is left
      if (q.core && occInCore) break;
      if (maxAbs(q.oc + q.tmax * q.dc) >= 2.0 - 1.0e-3) break;
      if (qi >= 7) break;
      if (exits[qi - 1] >= exits[qi] - 16.0 * stepLen) {
        qi++;
        if (qi >= 7) break;
      }
      float loT = exits[qi - 1];
      float hiT = exits[qi];
      q = quadrantSetup(o, d, loT + 0.1 * (hiT - loT), loT + 0.9 * (hiT - loT));
      tc = q.tmin + 0.5 * stepLen;
      qi++;
      tBlock = -INF;
      tWorld = -INF;
    }
    vec3 z = q.oc + tc * q.dc;
    // Until tc passes tBlock the ray is inside the occupied half-cell found last, whose factor-8 cell has
    // distance 0: both grid queries are skipped there (the same answers, one texture fetch less per step).
    if (tc > tBlock) {
      // 1. distance grid: jump whole empty cells (one fetch also brings the cell's occupancy bits)
      vec3 pos = (z - minP) / vsGrid;
      vec2 cell = grid8(pos);
      if (cell.x > 0.0) { tc += cell.x * vsGrid; continue; }
      // 2. bit-packed occupancy (exit of the last queried cell cached)
      vec3 bmin = floor(pos);
      vec3 bmax = bmin + 1.0;
      int occ = int(cell.y);
      bool empty = occ == 0;
      if (!empty) {
        vec3 rel = pos - bmin;
        int bit = 1;
        if (rel.z > 0.5) { bit *= 2; bmin.z += 0.5; }
        if (rel.y > 0.5) { bit *= 4; bmin.y += 0.5; }
        if (rel.x > 0.5) { bit *= 16; bmin.x += 0.5; }
        bmax = bmin + 0.5;
        empty = (occ / bit) % 2 == 0;
      }
      tBlock = slab(bmin * vsGrid + minP, bmax * vsGrid + minP, q.oc, q.invDc).y;
      if (empty) { tc = max(tc, tBlock) + 0.5 * stepLen; continue; }
    }
    // 3. the sparse grid's 8^3 block (its atlas index cached while the ray stays in it), then the atlas
    vec3 g = (z - minP) / uSparseVoxel - 0.5;
    vec3 blockMin = floor(g / b) * b;
    ivec3 bi = clamp(ivec3(blockMin / b), ivec3(0), ivec3(uNumBlocks - 1));
    if (bi != lastBlock) {
      lastBlock = bi;
      blockAtlas = texelFetch(tBlockIndices, bi, 0).rgb * 255.0;
    }
    if (blockAtlas.x > 254.5) { tc += stepLen; continue; }
    vec3 idx = floor(blockAtlas + 0.5);
    vec3 s = clamp(g - blockMin, 0.0, b) + idx * (b + 1.0);
    vec3 uvw = (s + 0.5) / uAtlasSize;
    vec4 atlasA = texture(tAtlasA, uvw);
    float sd = uRangeDensity.x + rd * atlasA.x;
    float gate = uRangeFeatures.x + rf * atlasA.y;
    vec3 pt = (z - minP) / (uTriVoxel * uTriRes);
    vec4 planeA = planeSum(tPlaneA, pt);
    float td = 3.0 * uRangeDensity.x + rd * planeA.x;
#if FEATURE_GATING
    float wGate = gate;
#else
    float wGate = 1.0;
#endif
    float density = exp(sd + wGate * td - 1.0);
    float tNext = min(tc + stepLen, q.tmax);
    float stepWorld;
    if (q.core) {
      stepWorld = (tNext - tc) / uScale;  // |dc| = 1 and no contraction inside the unit box
    } else {
      vec3 wz = tc == tWorld ? world : uncontract(z);
      world = uncontract(q.oc + tNext * q.dc);
      tWorld = tNext;
      stepWorld = length(world - wz) / uScale;
    }
    float alpha = 1.0 - exp(-density * stepWorld);
    if (alpha > 0.25 / 255.0) {
      float w = vis * alpha;
      vec4 atlasB = texture(tAtlasB, uvw);
      vec3 srgb = uRangeFeatures.x + rf * vec3(atlasA.zw, atlasB.x);
      vec3 trgb = 3.0 * uRangeFeatures.x + rf * planeA.yzw;
      color += w * sigmoid3(srgb + wGate * trgb);
      coarseColor += w * sigmoid3(srgb);
      vec4 sf = vec4(uRangeFeatures.x + rf * atlasB.yzw, gate);
      vec4 tf = 3.0 * uRangeFeatures.x + rf * planeSum(tPlaneB, pt);
      feat += w * sigmoid4(sf + wGate * tf);
      coarseFeat += w * sigmoid4(sf);
    }
    vis *= 1.0 - alpha;
    tc += stepLen;
  }
  vec3 cIn = color + vis * uBackground;
  vec3 v = trainingDirection(viewDir);
${defs.DIR_GRID ? '  vec2 dirUv = ((gl_FragCoord.xy - 0.5) / float(DIR_STRIDE) + 0.5) / uDirectionGrid;' : '  vec2 dirUv = vec2(0.0);'}
  vec3 rgb = color + deferredMlp(cIn, feat, coarseColor, coarseFeat, v, dirUv);
  fragColor = vec4(clamp(rgb, 0.0, 1.0), 1.0);
}
`;
}
