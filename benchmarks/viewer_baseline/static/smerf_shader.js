// Fragment shader of the SMERF renderer. It follows docs/smerf_viewer.md step for step, in the same order as the
// Python/Warp re-implementation (src/nerfbake/kernels/smerf_march.py) that the tests compare it with.

export function smerfFragment(defs) {
  const lines = Object.entries(defs).map(([k, v]) => `#define ${k} ${v}`).join('\n');
  return `#version 300 es
precision highp float;
precision highp int;
precision highp sampler3D;
precision highp sampler2DArray;
precision highp sampler2D;
${lines}
out vec4 fragColor;

uniform vec2 uViewport;      // render-target size in pixels
uniform vec2 uPixelOffset;   // sub-pixel jitter for progressive refinement (pixels)
uniform vec3 uOrigin;        // camera centre in the submodel frame
uniform mat3 uRotation;      // camera-to-viewer rotation (three.js camera, looks down -z)
uniform mat4 uInvProjection;
uniform float uScale;        // submodel_scale
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

uniform sampler3D tBlockIndices;
uniform sampler3D tAtlasRgb;
uniform sampler3D tAtlasDensity;
uniform sampler3D tAtlasFeatures;
uniform sampler2DArray tPlaneRgb;
uniform sampler2DArray tPlaneDensity;
uniform sampler2DArray tPlaneFeatures;
uniform sampler3D tOccupancy8;
uniform sampler3D tDistance8;
uniform sampler2D tMlp;

const float INF = 1.0e25;

int majorAxis(vec3 v) {
  vec3 a = abs(v);
  if (a.x >= a.y && a.x >= a.z) return 0;
  if (a.y >= a.x && a.y >= a.z) return 1;
  return 2;
}

float maxAbs(vec3 v) { return max(abs(v.x), max(abs(v.y), abs(v.z))); }

vec3 contract(vec3 x) {
  float m = maxAbs(x);
  if (m <= 1.0) return x;
  float s = 1.0 / m;
  vec3 z = s * x;
  int a = majorAxis(x);
  z[a] = z[a] * (2.0 - s);
  return z;
}

vec3 uncontract(vec3 z) {
  float m = maxAbs(z);
  if (m <= 1.0) return z;
  float s = 1.0 / max(1.0e-6, 2.0 - m);
  vec3 x = s * z;
  int a = majorAxis(z);
  x[a] = sign(x[a]) * s;
  return x;
}

// Per axis A, the t where contract(o + t d)[A] == p[A] inside region k (0 core, 1..6 = +x,+y,+z,-x,-y,-z).
vec3 regionT(vec3 o, vec3 d, vec3 p, int k) {
  if (k == 0) return (p - o) / d;
  if (k == 1) return vec3((1.0 / (2.0 - p.x) - o.x) / d.x, (o.y - p.y * o.x) / (p.y * d.x - d.y),
                          (o.z - p.z * o.x) / (p.z * d.x - d.z));
  if (k == 2) return vec3((o.x - p.x * o.y) / (p.x * d.y - d.x), (1.0 / (2.0 - p.y) - o.y) / d.y,
                          (o.z - p.z * o.y) / (p.z * d.y - d.z));
  if (k == 3) return vec3((o.x - p.x * o.z) / (p.x * d.z - d.x), (o.y - p.y * o.z) / (p.y * d.z - d.y),
                          (1.0 / (2.0 - p.z) - o.z) / d.z);
  if (k == 4) return vec3((1.0 / (-p.x - 2.0) - o.x) / d.x, -(o.x * p.y + o.y) / (d.x * p.y + d.y),
                          -(o.x * p.z + o.z) / (d.x * p.z + d.z));
  if (k == 5) return vec3(-(o.y * p.x + o.x) / (d.y * p.x + d.x), (1.0 / (-p.y - 2.0) - o.y) / d.y,
                          -(o.y * p.z + o.z) / (d.y * p.z + d.z));
  return vec3(-(o.z * p.x + o.x) / (d.z * p.x + d.x), -(o.z * p.y + o.y) / (d.z * p.y + d.y),
              (1.0 / (-p.z - 2.0) - o.z) / d.z);
}

void regionBox(int k, out vec3 lo, out vec3 hi) {
  float c1 = 1.0 - 1.0e-5;
  float c2 = 2.0 - 1.0e-4;
  lo = vec3(-c1);
  hi = vec3(c1);
  if (k >= 1 && k <= 3) { lo[k - 1] = c1; hi[k - 1] = c2; }
  else if (k >= 4) { lo[k - 4] = -c2; hi[k - 4] = -c1; }
}

// Drop (set to -INF) per-axis solutions that do not land on the plane inside the region's box.
vec3 checkedT(vec3 o, vec3 d, vec3 t, vec3 p, vec3 lo, vec3 hi) {
  float eps = 1.0e-3;
  vec3 outT = t;
  for (int a = 0; a < 3; a++) {
    vec3 q = contract(o + t[a] * d);
    bool bad = abs(q[a] - p[a]) > eps;
    for (int b = 0; b < 3; b++) {
      if (q[b] < lo[b] - eps || q[b] > hi[b] + eps) bad = true;
    }
    if (bad) outT[a] = -INF;
  }
  return outT;
}

float regionExit(vec3 o, vec3 d, int k) {
  vec3 lo, hi;
  regionBox(k, lo, hi);
  vec3 t0 = checkedT(o, d, regionT(o, d, lo, k), lo, lo, hi);
  vec3 t1 = checkedT(o, d, regionT(o, d, hi, k), hi, lo, hi);
  return max(max(max(t0.x, t0.y), t0.z), max(max(t1.x, t1.y), t1.z));
}

vec2 slab(vec3 lo, vec3 hi, vec3 o, vec3 invD) {
  vec3 ta = (lo - o) * invD;
  vec3 tb = (hi - o) * invD;
  vec3 mn = min(ta, tb);
  vec3 mx = max(ta, tb);
  return vec2(max(max(mn.x, mn.y), mn.z), min(min(mx.x, mx.y), mx.z));
}

struct Quadrant { vec3 oc; vec3 dc; float tmin; float tmax; };

Quadrant quadrantSetup(vec3 o, vec3 d, float tp, float tq) {
  vec3 xp = o + tp * d;
  vec3 lo = vec3(-1.0);
  vec3 hi = vec3(1.0);
  if (maxAbs(xp) > 1.0) {
    int a = majorAxis(xp);
    if (xp[a] > 0.0) { lo[a] = 1.0; hi[a] = 2.0; } else { lo[a] = -2.0; hi[a] = -1.0; }
  }
  Quadrant q;
  q.oc = contract(xp);
  q.dc = normalize(contract(o + tq * d) - q.oc);
  vec2 t = slab(lo, hi, q.oc, 1.0 / q.dc);
  q.tmin = t.x;
  q.tmax = t.y;
  return q;
}

float texel8(sampler3D grid, vec3 c) {
  ivec3 i = clamp(ivec3(floor(c)), ivec3(0), ivec3(uGrid8 - 1));
  return floor(texelFetch(grid, i, 0).r * 255.0 + 0.5);
}

vec4 planeSum(sampler2DArray tex, vec3 p) {
  return texture(tex, vec3(p.y, p.z, 0.0)) + texture(tex, vec3(p.x, p.z, 1.0)) + texture(tex, vec3(p.x, p.y, 2.0));
}

float sigmoid(float x) { return 1.0 / (1.0 + exp(-x)); }
vec3 sigmoid3(vec3 x) { return 1.0 / (1.0 + exp(-x)); }
vec4 sigmoid4(vec4 x) { return 1.0 / (1.0 + exp(-x)); }

float act(float x) {
#if ACTIVATION_ELU
  return x > 0.0 ? x : exp(x) - 1.0;
#else
  return max(x, 0.0);
#endif
}

float expo(float x) {
#if USE_EXPOSURE
  float c = clamp(x, 1.0e-7, 1.0 - 1.0e-7);
  return log(c / (1.0 - c)) + log(uExposure);
#else
  return x;
#endif
}

vec4 mlpTexel(int i) { return texelFetch(tMlp, ivec2(i, 0), 0); }

// The deferred MLP (SNeRG mode): kernels and biases were interpolated at the camera position on the CPU.
vec3 deferredMlp(vec3 cIn, vec4 feat, vec3 coarseColor, vec4 coarseFeat, vec3 v) {
  float x[IN_DIM];
  int n = 0;
  for (int c = 0; c < 3; c++) x[n++] = expo(cIn[c]);
  for (int c = 0; c < 4; c++) x[n++] = expo(feat[c]);
#if COARSE_SUM
  for (int c = 0; c < 3; c++) x[n++] = expo(coarseColor[c]);
  for (int c = 0; c < 4; c++) x[n++] = expo(coarseFeat[c]);
#endif
  for (int c = 0; c < 3; c++) x[n++] = v[c];
  for (int k = 0; k < 4; k++) for (int c = 0; c < 3; c++) x[n++] = sin(v[c] * float(1 << k));
  for (int k = 0; k < 4; k++) for (int c = 0; c < 3; c++) x[n++] = cos(v[c] * float(1 << k));

  const int Q = HIDDEN / 4;
  vec4 h0[Q];
  for (int j = 0; j < Q; j++) h0[j] = mlpTexel(B0_OFF + j);
  for (int i = 0; i < IN_DIM; i++) {
    for (int j = 0; j < Q; j++) h0[j] += x[i] * mlpTexel(K0_OFF + i * Q + j);
  }
  vec4 h1[Q];
  for (int j = 0; j < Q; j++) h1[j] = mlpTexel(B1_OFF + j);
  for (int i = 0; i < HIDDEN; i++) {
    float a = act(h0[i / 4][i % 4]);
    for (int j = 0; j < Q; j++) h1[j] += a * mlpTexel(K1_OFF + i * Q + j);
  }
  vec4 o = mlpTexel(B2_OFF);
  for (int i = 0; i < HIDDEN; i++) o += act(h1[i / 4][i % 4]) * mlpTexel(K2_OFF + i);
  return sigmoid3(o.xyz);
}

void main() {
  vec2 pix = gl_FragCoord.xy + uPixelOffset;
  vec2 ndc = pix / uViewport * 2.0 - 1.0;
  vec4 q4 = uInvProjection * vec4(ndc, -1.0, 1.0);
  vec3 d = uScale * (uRotation * (q4.xyz / q4.w));  // to the near plane: the ray starts at t = 1
  vec3 viewDir = d;
  vec3 o = uOrigin;
  for (int a = 0; a < 3; a++) {
    if (abs(d[a]) < 1.0e-9) d[a] = 1.0e-9;
  }
  float nearT = 1.0;
  float exits[8];
  for (int j = 0; j < 8; j++) exits[j] = INF;
  int n = 0;
  for (int k = 0; k < 7; k++) {
    float t = regionExit(o, d, k);
    if (t >= nearT) {
      int j = n;
      while (j > 0 && exits[j - 1] > t) { exits[j] = exits[j - 1]; j--; }
      exits[j] = t;
      n++;
    }
  }
  Quadrant q = quadrantSetup(o, d, nearT, nearT + 0.5 * (exits[0] - nearT));
  float tc = 0.0;
  int qi = 1;
  float tBlock = -INF;
  float vis = 1.0;
  float ema = 1.0;
  vec3 color = vec3(0.0);
  vec4 feat = vec4(0.0);
  vec3 coarseColor = vec3(0.0);
  vec4 coarseFeat = vec4(0.0);
  int maxSteps = int(uStepMult) * int(ceil(sqrt(2.0 * uTriRes * uTriRes)));
  float origStep = uTriVoxel / uStepMult;
  vec3 minP = vec3(-2.0);
  float vsGrid = 8.0 * uTriVoxel;
  float rf = uRangeFeatures.y - uRangeFeatures.x;
  float rd = uRangeDensity.y - uRangeDensity.x;
  float b = uBlock;
  for (int i = 0; i < maxSteps; i++) {
    if (vis <= 1.0 / 255.0) break;
    ema = uVisibilityDelay * ema + (1.0 - uVisibilityDelay) * vis;
    float stepLen = origStep * (10.0 - 9.0 * sqrt(min(1.0, ema / 0.8)));
    if (tc > q.tmax) {
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
    }
    vec3 z = q.oc + tc * q.dc;
    // 1. distance grid: jump whole empty cells
    float dist = texel8(tDistance8, (z - minP) / vsGrid) * vsGrid;
    if (dist > 0.0) { tc += dist; continue; }
    // 2. bit-packed occupancy (exit of the last queried cell cached)
    if (tc > tBlock) {
      vec3 pos = (z - minP) / vsGrid;
      vec3 bmin = floor(pos);
      vec3 bmax = bmin + 1.0;
      int occ = int(texel8(tOccupancy8, bmin));
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
      tBlock = slab(bmin * vsGrid + minP, bmax * vsGrid + minP, q.oc, 1.0 / q.dc).y;
      if (empty) { tc = max(tc, tBlock) + 0.5 * stepLen; continue; }
    }
    // 3. the sparse grid's 8^3 block, then the atlas
    vec3 g = (z - minP) / uSparseVoxel - 0.5;
    vec3 blockMin = floor(g / b) * b;
    ivec3 bi = clamp(ivec3(blockMin / b), ivec3(0), ivec3(uNumBlocks - 1));
    vec3 idxRaw = texelFetch(tBlockIndices, bi, 0).rgb * 255.0;
    if (idxRaw.x > 254.5) { tc += stepLen; continue; }
    vec3 idx = floor(idxRaw + 0.5);
    vec3 s = clamp(g - blockMin, 0.0, b) + idx * (b + 1.0);
    vec3 uvw = (s + 0.5) / uAtlasSize;
    vec2 dg = texture(tAtlasDensity, uvw).rg;
    float sd = uRangeDensity.x + rd * dg.x;
    float gate = uRangeFeatures.x + rf * dg.y;
    vec3 pt = (z - minP) / (uTriVoxel * uTriRes);
    float td = 3.0 * uRangeDensity.x + rd * planeSum(tPlaneDensity, pt).r;
#if FEATURE_GATING
    float wGate = gate;
#else
    float wGate = 1.0;
#endif
    float density = exp(sd + wGate * td - 1.0);
    float tNext = min(tc + stepLen, q.tmax);
    float stepWorld = length(uncontract(q.oc + tNext * q.dc) - uncontract(z)) / uScale;
    float alpha = 1.0 - exp(-density * stepWorld);
    if (alpha > 0.25 / 255.0) {
      float w = vis * alpha;
      vec3 srgb = uRangeFeatures.x + rf * texture(tAtlasRgb, uvw).rgb;
      vec3 trgb = 3.0 * uRangeFeatures.x + rf * planeSum(tPlaneRgb, pt).rgb;
      color += w * sigmoid3(srgb + wGate * trgb);
      coarseColor += w * sigmoid3(srgb);
      vec4 sf = vec4(uRangeFeatures.x + rf * texture(tAtlasFeatures, uvw).rgb, gate);
      vec4 tf = 3.0 * uRangeFeatures.x + rf * planeSum(tPlaneFeatures, pt);
      feat += w * sigmoid4(sf + wGate * tf);
      coarseFeat += w * sigmoid4(sf);
    }
    vis *= 1.0 - alpha;
    tc += stepLen;
  }
  vec3 cIn = color + vis * uBackground;
  vec3 v = normalize(vec3(-viewDir.x, viewDir.z, viewDir.y));  // viewer frame -> training frame (W v)
  vec3 rgb = color + deferredMlp(cIn, feat, coarseColor, coarseFeat, v);
  fragColor = vec4(clamp(rgb, 0.0, 1.0), 1.0);
}
`;
}
