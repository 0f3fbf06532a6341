// nerfbake viewer: one page for SMERF asset directories and PlenOctree .npz files, served by `nerfbake view`.
// URL parameters: quality=phone|low|medium|high, s=W,H (render size), mouseMode=orbit|fly, vfovy, near, up=x|y|z|-z,
// submodelCacheSize, stepMult, exposure, view=I (a test view), benchmark=1, frameMult=K, maxTextureSize,
// directionStride=N (SMERF: the deferred MLP's direction term on every N-th pixel, interpolated; 0 = every pixel).
import {RenderTarget, ViewerError, createContext, fetchJSON, finish, rendererName} from './gl.js';
import {Controls, UP_AXES, lookRotation, viewForward} from './controls.js';
import {OctreeScene} from './octree.js';
import {SmerfScene, invert4, perspective, testFrameCamera} from './smerf.js';

const params = new URLSearchParams(location.search);
const QUALITY = {phone: 300 * 450, low: 600 * 250, medium: 1200 * 640, high: Infinity};  // max pixels while moving
const $ = (id) => document.getElementById(id);

function status(text) { $('status').textContent = text; }

function fail(err) {
  console.error(err);
  $('error').textContent = err instanceof ViewerError ? err.message : `${err.name}: ${err.message}`;
  $('error').hidden = false;
  window.nerfbake.failed = String(err.message || err);
}

function numberList(text, n) {
  const v = (text || '').split(',').map(Number);
  return v.length === n && v.every(Number.isFinite) ? v : null;
}

// A camera both renderers understand: position, camera-to-world rotation rows, pinhole intrinsics or a projection.
function cameraFor(pose, width, height, vfov, near) {
  const fy = height / 2 / Math.tan((vfov * Math.PI) / 360);
  return {
    ...pose, fx: fy, fy, cx: width / 2, cy: height / 2,
    invProjection: invert4(perspective(vfov, width / height, near)),
  };
}

function toBase64(bytes) {
  let s = '';
  for (let i = 0; i < bytes.length; i += 0x8000) s += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
  return btoa(s);
}

class App {
  async start() {
    this.canvas = $('canvas');
    const size = numberList(params.get('s'), 2);
    this.size = size || [Math.min(window.innerWidth, 1920), Math.min(window.innerHeight, 1080)];
    this.canvas.width = this.size[0];
    this.canvas.height = this.size[1];
    this.gl = createContext(this.canvas);
    if (!this.gl.getExtension('EXT_color_buffer_float')) console.warn('EXT_color_buffer_float missing (not needed here)');
    this.quality = params.get('quality') || 'high';
    if (!(this.quality in QUALITY)) throw new ViewerError(`quality must be phone, low, medium or high, not ${this.quality}`);
    this.vfov = Number(params.get('vfovy') || 40);
    this.near = Number(params.get('near') || 0.2);
    const info = await fetchJSON('/scene.json');
    document.title = `nerfbake · ${info.name}`;
    status(`loading ${info.kind} scene ${info.name}…`);
    const onProgress = (sm, file) => status(`loading ${sm}/${file}`);
    if (info.kind === 'smerf') {
      this.scene = await SmerfScene.open(this.gl, info.base, info.entry, {
        cacheSize: params.has('submodelCacheSize') ? Number(params.get('submodelCacheSize')) : (this.quality === 'phone' ? 0 : 4),
        stepMult: Number(params.get('stepMult') || 1),
        directionStride: params.has('directionStride') ? Number(params.get('directionStride')) : undefined,
        visibilityDelay: {high: 0.99, medium: 0.95, low: 0.8, phone: 0.8}[this.quality],
        onProgress,
      });
      this.scene.onError = fail;
      if (params.get('exposure')) this.scene.exposureOverride = Number(params.get('exposure'));
      const first = this.scene.testFrames.length ? this.scene.testCamera(Number(params.get('view') || 0)) : null;
      const forward = first ? viewForward(first.rotation) : [0, 0, -1];
      const position = first ? first.position : [0, 0, 0];
      // orbit the scene's centre, or a point ahead where the camera stands at the centre itself
      const target = Math.hypot(...position) > 0.1 ? [0, 0, 0] : position.map((v, a) => v + forward[a]);
      this.controls = new Controls(this.canvas, {
        mode: params.get('mouseMode') || 'fly', up: UP_AXES[params.get('up') || 'y'], position, forward, target, speed: 0.3,
      });
    } else {
      let loaded = 0;
      this.scene = await OctreeScene.open(this.gl, `${info.base}${info.entry}`, {
        onBytes: (n) => { loaded += n; status(`loading ${info.entry}: ${(loaded / 1e6).toFixed(1)} MB`); },
        maxTextureSize: Number(params.get('maxTextureSize') || 0) || undefined,
        render: {stepSize: {phone: 2e-3, low: 2e-3, medium: 1e-3, high: 1e-4}[this.quality],
                 sigmaThresh: {phone: 0.1, low: 0.1, medium: 0.02, high: 0.01}[this.quality],
                 stopThresh: {phone: 0.1, low: 0.1, medium: 0.02, high: 0.01}[this.quality]},
      });
      const {center, radius} = this.scene.bounds();
      this.controls = new Controls(this.canvas, {
        mode: params.get('mouseMode') || 'orbit', up: UP_AXES[params.get('up') || 'z'], target: center,
        distance: 2.2 * radius, speed: radius,
      });
      this.buildOctreePanel();
    }
    const pose = numberList(params.get('pose'), 6);
    if (pose) this.controls.setPose(pose.slice(0, 3), pose.slice(3));
    await this.scene.ready(this.controls.camera().position);
    this.frames = 0;
    this.frameLog = [];
    this.lastTime = performance.now();
    this.fpsEma = null;
    this.resting = 0;
    $('screenshot').onclick = () => this.screenshot();
    status('');
    this.running = true;
    requestAnimationFrame((t) => this.loop(t));
  }

  currentCamera(width, height) {
    return cameraFor(this.controls.camera(), width, height, this.vfov, this.near);
  }

  // One displayed frame: low resolution while the camera moves (quality preset), full resolution once it rests.
  loop(now) {
    if (!this.running) return;
    const dt = Math.min(0.1, (now - this.lastTime) / 1000);
    this.lastTime = now;
    this.controls.update(dt);
    const moving = this.controls.moved;
    this.controls.moved = false;
    this.resting = moving ? 0 : this.resting + 1;
    const cam = this.controls.camera();
    this.scene.update(cam.position);
    const [w, h] = this.size;
    const budget = QUALITY[this.quality];
    const factor = this.resting > 2 ? 1 : Math.max(1, Math.sqrt((w * h) / budget));
    const t0 = performance.now();
    let drawn;
    if (factor > 1) {
      const lw = Math.max(1, Math.round(w / factor)), lh = Math.max(1, Math.round(h / factor));
      if (!this.lowRes || this.lowRes.width !== lw || this.lowRes.height !== lh) {
        if (this.lowRes) this.lowRes.dispose();
        this.lowRes = new RenderTarget(this.gl, lw, lh);
      }
      drawn = this.scene.draw(this.currentCamera(lw, lh), this.lowRes, lw, lh);
      const gl = this.gl;
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, this.lowRes.fbo);
      gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, null);
      gl.blitFramebuffer(0, 0, lw, lh, 0, 0, w, h, gl.COLOR_BUFFER_BIT, gl.LINEAR);
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, null);
    } else if (moving || this.resting <= 3 || this.scene.kind === 'smerf') {
      drawn = this.scene.draw(this.currentCamera(w, h), null, w, h);
    }
    const ms = performance.now() - t0;
    this.fpsEma = this.fpsEma === null ? dt : 0.9 * this.fpsEma + 0.1 * dt;
    this.frames++;
    if (params.has('frameLog')) this.logFrame(drawn);
    if (drawn) this.lastDrawMs = ms;
    if (!(now - this.lastHud < 500)) { this.lastHud = now; this.updateHud(this.lastDrawMs || 0); }
    requestAnimationFrame((t) => this.loop(t));
  }

  logFrame(drawn) {
    // Mean brightness of the displayed frame (tests check that a streaming switch never shows a black frame).
    const gl = this.gl;
    const [w, h] = this.size;
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    const s = this.scene.state();
    this.frameLog.push({frame: this.frames, drawn: !!drawn, mean: meanBrightness(px), active: s.active ?? null,
                        resident: s.resident || [], loading: s.loading ?? null});
  }

  updateHud(ms) {
    const fps = this.fpsEma ? 1 / this.fpsEma : 0;
    const s = this.scene.state();
    const sm = this.scene.kind === 'smerf' ? ` · submodel ${s.active} (resident ${s.resident.join(',')})` : ` · ${s.numLeaves} leaves`;
    $('fps').textContent = `${fps.toFixed(1)} fps · ${ms.toFixed(1)} ms/draw (cpu) · ${(this.scene.gpuBytes() / 1e6).toFixed(0)} MB GPU${sm}`;
    const cam = this.controls.camera();
    const f = this.controls.forward();
    const pose = [...cam.position, ...f].map((v) => v.toFixed(4)).join(',');
    $('pose').textContent = `pose=${pose}`;
    const url = new URL(location.href);
    url.searchParams.set('pose', pose);
    $('pose').href = url.toString();
  }

  screenshot() {
    const a = document.createElement('a');
    a.download = `nerfbake-${Date.now()}.png`;
    a.href = this.canvas.toDataURL('image/png');
    a.click();
  }

  buildOctreePanel() {
    const o = this.scene.options;
    const panel = $('panel');
    panel.hidden = false;
    const row = (label, input) => { const l = document.createElement('label'); l.textContent = label; l.append(input); panel.append(l); };
    const slider = (label, min, max, step, value, set) => {
      const i = document.createElement('input');
      Object.assign(i, {type: 'range', min, max, step, value});
      i.oninput = () => { set(Number(i.value)); this.controls.moved = true; };
      row(label, i);
    };
    for (const [a, name] of [[0, 'x'], [1, 'y'], [2, 'z']]) {
      slider(`slice ${name} min`, 0, 1, 0.01, o.bboxMin[a], (v) => { o.bboxMin[a] = v; });
      slider(`slice ${name} max`, 0, 1, 0.01, o.bboxMax[a], (v) => { o.bboxMax[a] = v; });
    }
    slider('SH from', 0, this.scene.tree.nb - 1, 1, 0, (v) => { o.basisMin = v; });
    slider('SH to', 1, this.scene.tree.nb, 1, this.scene.tree.nb, (v) => { o.basisMax = v; });
    slider('background', 0, 1, 0.01, 1, (v) => { o.background = [v, v, v]; });
    const depth = document.createElement('input');
    depth.type = 'checkbox';
    depth.onchange = () => { o.depth = depth.checked; this.controls.moved = true; };
    row('depth', depth);
  }

  // --- for tests and benchmarks -------------------------------------------------------------------------------

  async renderOffscreen(camera, width, height) {
    await this.scene.ready(camera.position);
    const target = new RenderTarget(this.gl, width, height);
    this.scene.draw(camera, target, width, height);
    const px = target.read();
    target.dispose();
    return toBase64(px);
  }

  // A walkthrough's cameras: the benchmark views in order, or a path of test_frames.json entries (position, rotation
  // and projection as 16 column-major numbers each) or of {position, forward} poses seen with the viewer's lens.
  pathCameras(path, width, height) {
    if (!path) return this.benchmarkViews(width, height);
    return path.map((p, i) => {
      if (!Array.isArray(p.position) || p.position.length !== 3) throw new ViewerError(`walkthrough camera ${i}: needs a position [x, y, z]`);
      if (p.rotation && p.projection) return testFrameCamera(p);
      if (!Array.isArray(p.forward) || p.forward.length !== 3) throw new ViewerError(`walkthrough camera ${i}: needs forward [x, y, z] or rotation and projection`);
      return cameraFor({position: p.position.slice(), rotation: lookRotation(p.forward, this.controls.up)}, width, height, this.vfov, this.near);
    });
  }

  benchmarkViews(width, height) {
    if (this.scene.kind === 'smerf') {
      return this.scene.testFrames.map((_, i) => this.scene.testCamera(i));
    }
    const {center, radius} = this.scene.bounds();
    const up = this.controls.up;
    return [...Array(8).keys()].map((i) => {
      const c = new Controls(document.createElement('div'), {mode: 'orbit', up, target: center, distance: 2.2 * radius});
      c.yaw += (i * Math.PI) / 4;
      return cameraFor(c.camera(), width, height, this.vfov, this.near);
    });
  }

  // Fly the camera along a path (cameras as benchmarkViews gives them), `between` frames interpolated between
  // consecutive ones, as the interactive loop does: the scene streams the submodel of each position while the one
  // resident keeps drawing. Per frame: draw time, whether anything was drawn and its mean brightness (a blank
  // frame is 0), the submodel drawn and the one loading, the resident submodels and the host cache.
  async walkthrough(path, width, height, between = 3) {
    this.running = false;
    const gl = this.gl;
    const target = new RenderTarget(gl, width, height);
    const frames = [];
    const lerp = (a, b, t) => a.map((v, i) => v + (b[i] - v) * t);
    const up = this.controls.up;
    const last = path[path.length - 1];
    const cameras = [];  // every frame's camera along the path
    for (let i = 0; i < path.length; i++) {
      for (let k = 0; k <= (i + 1 < path.length ? between : 0); k++) {
        const t = k / (between + 1);
        const a = path[i], b = path[Math.min(i + 1, path.length - 1)];
        cameras.push(k === 0 ? a : {...a, position: lerp(a.position, b.position, t),
                                     rotation: lookRotation(lerp(viewForward(a.rotation), viewForward(b.rotation), t), up)});
      }
    }
    // A user who stops at the path's end sees its own submodel once it has streamed in: the walk holds the last
    // camera until then (at most `holdMs`), so how long the arrival took is measured rather than cut off.
    // Settled is judged on what the last frame drew (its state is read right after drawing it): a submodel that
    // swaps in while the page waits between frames has not been seen yet, so one more frame draws it.
    const holdMs = 20000;
    let holdStart = null;
    let drewSettled = false;
    for (let n = 0; ; n++) {
      const holding = n >= cameras.length;
      if (holding) {
        if (drewSettled) break;
        holdStart = holdStart ?? performance.now();
        if (performance.now() - holdStart > holdMs) break;
      }
      const cam = holding ? last : cameras[n];
      this.scene.update(cam.position);
      const t0 = performance.now();
      const drawn = this.scene.draw(cam, target, width, height);
      finish(gl);
      const ms = performance.now() - t0;
      const s = this.scene.state();
      drewSettled = n >= cameras.length - 1 && this.scene.settledAt(last.position);
      frames.push({ms, drawn: !!drawn, mean: meanBrightness(target.read()), active: s.active ?? null, held: holding,
                   loading: s.loading ?? null, resident: s.resident || [], host_cache: (s.hostCache || []).length});
      await new Promise(requestAnimationFrame);  // let fetches and uploads go on between frames, as on screen
    }
    const settled = drewSettled;
    target.dispose();
    this.running = true;
    requestAnimationFrame((t) => this.loop(t));
    const times = frames.map((f) => f.ms);
    return {
      width, height, frames: frames.length, path_cameras: path.length, between,
      held_frames: frames.filter((f) => f.held).length, settled,
      p50_ms: percentile(times, 50), p95_ms: percentile(times, 95), max_ms: Math.max(...times),
      frames_while_loading: frames.filter((f) => f.loading !== null).length,
      blank_frames: frames.filter((f) => !f.drawn || f.mean < 1.0).length,
      max_resident: Math.max(...frames.map((f) => f.resident.length)),
      max_host_cache: Math.max(...frames.map((f) => f.host_cache)),
      submodels_drawn: [...new Set(frames.map((f) => f.active))],
      uploads: this.scene.state().uploads || [], per_frame: frames, renderer: rendererName(gl),
    };
  }

  // Each view is drawn `frameMult` times per animation frame so the display refresh does not cap the figure;
  // warm-up frames are discarded; the result is the mean frame time per view. With `gpuTimer` and a browser that
  // offers EXT_disjoint_timer_query_webgl2, every timed frame is also measured on the GPU itself (a TIME_ELAPSED
  // query around its draws), so figures on a real GPU are GPU time, not requestAnimationFrame jitter.
  async benchmark(width, height, frameMult = 1, framesPerView = 6, warmup = 2, maxViews = 0, gpuTimer = false) {
    this.running = false;
    const gl = this.gl;
    const target = new RenderTarget(gl, width, height);
    let views = this.benchmarkViews(width, height);
    if (maxViews > 0) views = views.slice(0, maxViews);
    if (!views.length) throw new ViewerError('the scene has no test_frames.json views to benchmark');
    const timer = gpuTimer ? gl.getExtension('EXT_disjoint_timer_query_webgl2') : null;
    const perView = [];
    let disjoint = false;
    for (const [i, cam] of views.entries()) {
      await this.scene.ready(cam.position);
      const times = [];
      const queries = [];
      await new Promise((resolve) => {
        let frame = 0;
        const tick = () => {
          const timed = frame >= warmup;
          const query = timer && timed ? gl.createQuery() : null;
          if (query) gl.beginQuery(timer.TIME_ELAPSED_EXT, query);
          const t0 = performance.now();
          for (let k = 0; k < frameMult; k++) this.scene.draw(cam, target, width, height);
          if (query) { gl.endQuery(timer.TIME_ELAPSED_EXT); queries.push(query); }
          finish(gl);
          if (timed) times.push((performance.now() - t0) / frameMult);
          frame++;
          if (frame < warmup + framesPerView) requestAnimationFrame(tick); else resolve();
        };
        requestAnimationFrame(tick);
      });
      const entry = {view: i, ms_per_frame: times.reduce((a, b) => a + b, 0) / times.length};
      if (timer) {
        const ns = await queryResults(gl, timer, queries);
        disjoint = disjoint || ns === null;
        if (ns) entry.gpu_ms_per_frame = ns.reduce((a, b) => a + b, 0) / ns.length / 1e6 / frameMult;
      }
      perView.push(entry);
      status(`benchmark ${width}x${height}: view ${i + 1}/${views.length}`);
    }
    target.dispose();
    this.running = true;
    requestAnimationFrame((t) => this.loop(t));
    const mean = perView.reduce((a, v) => a + v.ms_per_frame, 0) / perView.length;
    const out = {width, height, frame_mult: frameMult, frames_per_view: framesPerView, warmup_frames: warmup,
                 mean_ms_per_frame: mean, fps: 1000 / mean, views: perView, kind: this.scene.kind,
                 renderer: rendererName(gl),
                 gpu_bytes: this.scene.gpuBytes(), timer: 'cpu'};
    if (gpuTimer && !timer) out.timer_note = 'EXT_disjoint_timer_query_webgl2 is not offered: CPU wall time after finish()';
    else if (disjoint) out.timer_note = 'the GPU timer reported a disjoint operation: CPU wall time after finish()';
    else if (timer) {
      out.timer = 'gpu';
      out.gpu_mean_ms_per_frame = perView.reduce((a, v) => a + v.gpu_ms_per_frame, 0) / perView.length;
    }
    return out;
  }
}

// Mean of the R, G and B bytes of RGBA pixels (a blank, black frame is 0).
function meanBrightness(px) {
  let sum = 0;
  for (let i = 0; i < px.length; i += 4) sum += px[i] + px[i + 1] + px[i + 2];
  return sum / (px.length / 4 * 3);
}

// Percentile (0..100) of a list of numbers, linear between ranks.
function percentile(values, q) {
  const v = [...values].sort((a, b) => a - b);
  const r = (q / 100) * (v.length - 1);
  const lo = Math.floor(r);
  return v[lo] + (v[Math.min(lo + 1, v.length - 1)] - v[lo]) * (r - lo);
}

// Nanoseconds of each finished TIME_ELAPSED query, or null when the GPU reported a disjoint operation (the
// figures would be meaningless then); polls once per animation frame as the extension requires.
async function queryResults(gl, timer, queries) {
  const pending = (q) => !gl.getQueryParameter(q, gl.QUERY_RESULT_AVAILABLE);
  for (let tries = 0; queries.some(pending) && tries < 600; tries++) await new Promise(requestAnimationFrame);
  const bad = gl.getParameter(timer.GPU_DISJOINT_EXT) || queries.some(pending);
  const ns = bad ? null : queries.map((q) => gl.getQueryParameter(q, gl.QUERY_RESULT));
  for (const q of queries) gl.deleteQuery(q);
  return ns;
}

const app = new App();
let resolveReady, rejectReady;
window.nerfbake = {
  ready: new Promise((res, rej) => { resolveReady = res; rejectReady = rej; }),
  app,
  state: () => ({...app.scene.state(), frames: app.frames, gpuBytes: app.scene.gpuBytes()}),
  frameLog: () => app.frameLog,
  clearFrameLog: () => { app.frameLog = []; },
  // A test_frames.json view (SMERF) as RGBA rows top to bottom, base64.
  renderTestView: (i, w, h) => app.renderOffscreen(app.scene.testCamera(i), w, h),
  // An arbitrary camera: {position, rotation (rows of the camera-to-world 3x3)} plus fx, fy, cx, cy (octree) or
  // projection (16, column-major, SMERF).
  renderCamera: (cam, w, h) => app.renderOffscreen(
    cam.projection ? {...cam, invProjection: invert4(cam.projection)} : cam, w, h),
  setPose: (position, forward) => app.controls.setPose(position, forward),
  lookRotation,
  benchmark: (w, h, k, n, warm, views, gpuTimer) => app.benchmark(w, h, k, n, warm, views, gpuTimer),
  // path: null for the scene's test cameras in order, or [{position, forward} | {position, rotation, projection}]
  walkthrough: (path, w, h, between) => app.walkthrough(app.pathCameras(path, w, h), w, h, between),
  // The camera controls' state (tests drive them with touch events and read this).
  controls: () => ({...app.controls.camera(), target: app.controls.target.slice(), distance: app.controls.distance,
                    yaw: app.controls.yaw, pitch: app.controls.pitch}),
};
app.start().then(() => resolveReady(true), (e) => { fail(e); rejectReady(e); });
if (params.get('benchmark') === '1') {
  window.nerfbake.ready.then(async () => {
    const k = Number(params.get('frameMult') || 1);
    const sizes = [[512, 512], [1280, 720]];
    const results = [];
    for (const [w, h] of sizes) results.push(await app.benchmark(w, h, k));
    window.nerfbake.benchmarkResult = results;
    status(results.map((r) => `${r.width}x${r.height}: ${r.mean_ms_per_frame.toFixed(2)} ms/frame`).join(' · '));
  }).catch(fail);
}
