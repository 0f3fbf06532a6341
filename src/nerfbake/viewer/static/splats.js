// Splat files (a .ply in the 3DGS layout or a .splat), drawn by gsplat.js (npm gsplat, which `nerfbake view` serves
// under /gsplat/) with its orbit controls: drag to orbit, right-drag to pan, wheel or pinch to zoom.
// URL parameters: s=W,H (canvas size, else the window), up=z|y|-y (the scene's up axis: z for nerfbake's
// object-centric frame, the default; -y for the 3DGS reference code's COLMAP frame).
// window.nerfbake.renderCamera(cam, w, h) draws one camera (OpenCV axes: {position, rotation (x, y, z, w), fx, fy})
// in the file's own frame and returns its RGBA pixels, rows bottom-up (the tests' and benchmarks' entry point).
import * as SPLAT from '/gsplat/index.es.js';

const params = new URLSearchParams(location.search);
const $ = (id) => document.getElementById(id);
// gsplat.js orbits about its -y axis; this turns the scene's up axis onto it
const UP = {z: new SPLAT.Vector3(Math.PI / 2, 0, 0), y: new SPLAT.Vector3(Math.PI, 0, 0), '-y': new SPLAT.Vector3(0, 0, 0)};

async function start() {
  const info = await (await fetch('/scene.json')).json();
  document.title = `nerfbake · ${info.name}`;
  const canvas = $('canvas');
  const given = (params.get('s') || '').split(',').map(Number);
  const size = given.length === 2 && given.every((v) => v > 0) ? given : [window.innerWidth, window.innerHeight];
  [canvas.width, canvas.height] = size;
  canvas.style.width = `${size[0]}px`;
  canvas.style.height = `${size[1]}px`;
  const renderer = new SPLAT.WebGLRenderer(canvas);
  renderer.setSize(size[0], size[1]);
  const scene = new SPLAT.Scene();
  const camera = new SPLAT.Camera();
  const url = `${info.base}${info.entry}`;
  const onProgress = (p) => { $('status').textContent = `loading ${info.name}: ${Math.round(p * 100)} %`; };
  const loader = info.entry.toLowerCase().endsWith('.ply') ? SPLAT.PLYLoader : SPLAT.Loader;
  const splat = await loader.LoadAsync(url, scene, onProgress);
  const up = UP[params.get('up') || 'z'];
  if (!up) throw new Error(`up must be z, y or -y, not ${params.get('up')}`);
  splat.rotation = SPLAT.Quaternion.FromEuler(up);
  $('status').textContent = `${info.name}: ${splat.data.vertexCount.toLocaleString()} splats (gsplat.js)`;
  const controls = new SPLAT.OrbitControls(camera, canvas);
  const app = {renderer, scene, camera, controls, splat, interactive: true, up};
  const frame = () => {
    if (app.interactive) {
      controls.update();
      renderer.render(scene, camera);
    }
    requestAnimationFrame(frame);
  };
  requestAnimationFrame(frame);
  return app;
}

async function renderCamera(cam, w, h) {
  const app = await window.nerfbake.ready;
  app.interactive = false;  // the orbit controls would move the camera between frames
  const {renderer, scene, splat} = app;
  splat.rotation = new SPLAT.Quaternion();  // the file's own frame for the shot (no up-axis turn)
  renderer.setSize(w, h);
  const camera = new SPLAT.Camera();  // not the interactive one, which the orbit controls own
  camera.data.fx = cam.fx;
  camera.data.fy = cam.fy;
  camera.data.setSize(w, h);
  camera.position = new SPLAT.Vector3(...cam.position);
  camera.rotation = new SPLAT.Quaternion(...cam.rotation);
  const gl = renderer.gl;
  const pixels = new Uint8Array(w * h * 4);
  let last = null;
  for (let i = 0; i < 200; i++) {  // the depth sort runs in a worker: draw until the picture stops changing
    renderer.render(scene, camera);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
    const now = pixels.join(',');
    if (i > 3 && now === last && pixels.some((v) => v > 0)) break;
    last = now;
    await new Promise((r) => setTimeout(r, 100));
  }
  splat.rotation = SPLAT.Quaternion.FromEuler(app.up);
  app.interactive = true;
  return Array.from(pixels);
}

window.nerfbake = {renderCamera};
window.nerfbake.ready = start();
window.nerfbake.ready.catch((err) => {
  console.error(err);
  $('error').textContent = String(err && err.message || err);
  $('error').hidden = false;
});
