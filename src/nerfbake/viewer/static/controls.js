// Camera controls: orbit (drag to rotate, wheel or pinch to zoom, right-drag or two fingers to pan) and fly
// (drag to look, WASD to move, Q/E down/up, Shift for speed). The camera is a position and a camera-to-world
// rotation (rows), OpenGL convention: it looks down its -z axis with +y up.

const sub = (a, b) => a.map((v, i) => v - b[i]);
const add = (a, b) => a.map((v, i) => v + b[i]);
const mul = (a, s) => a.map((v) => v * s);
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => mul(a, 1 / Math.hypot(...a));

export const UP_AXES = {x: [1, 0, 0], y: [0, 1, 0], z: [0, 0, 1], '-x': [-1, 0, 0], '-y': [0, -1, 0], '-z': [0, 0, -1]};

export function lookRotation(forward, up) {
  const f = norm(forward);
  let r = cross(f, up);
  if (Math.hypot(...r) < 1e-8) r = cross(f, [up[1], up[2], up[0]]);
  r = norm(r);
  const u = cross(r, f);
  return [[r[0], u[0], -f[0]], [r[1], u[1], -f[1]], [r[2], u[2], -f[2]]];
}

// The viewing direction (the camera's -z axis) of a camera-to-world rotation given as rows.
export function viewForward(rotation) { return [-rotation[0][2], -rotation[1][2], -rotation[2][2]]; }

export class Controls {
  constructor(element, {mode = 'orbit', up = [0, 1, 0], target = [0, 0, 0], distance = 1, position = null,
    forward = null, speed = 1} = {}) {
    this.mode = mode;
    this.up = norm(up);
    this.target = target.slice();
    this.speed = speed;
    this.keys = new Set();
    this.moved = true;
    if (position && forward) this.setPose(position, forward);
    else {
      const off = mul(norm(this.defaultOffset()), distance);
      this.setPose(add(target, off), mul(off, -1));
    }
    this.attach(element);
  }

  defaultOffset() {
    const [a, b] = this.basis();
    return add(add(mul(a, 0.8), mul(b, 0.6)), mul(this.up, 0.5));
  }

  basis() {  // two unit vectors orthogonal to up
    let a = cross(this.up, [0, 0, 1]);
    if (Math.hypot(...a) < 1e-6) a = cross(this.up, [1, 0, 0]);
    a = norm(a);
    return [a, cross(this.up, a)];
  }

  // Pose from a position and a viewing direction: yaw/pitch about the up axis.
  setPose(position, forward) {
    const f = norm(forward);
    const [a, b] = this.basis();
    this.yaw = Math.atan2(dot(f, b), dot(f, a));
    this.pitch = Math.asin(Math.max(-1, Math.min(1, dot(f, this.up))));
    this.position = position.slice();
    if (this.mode === 'orbit') this.distance = Math.max(1e-3, Math.hypot(...sub(this.target, position)));
    this.moved = true;
  }

  forward() {
    const [a, b] = this.basis();
    const c = Math.cos(this.pitch);
    return add(add(mul(a, c * Math.cos(this.yaw)), mul(b, c * Math.sin(this.yaw))), mul(this.up, Math.sin(this.pitch)));
  }

  camera() {
    const f = this.forward();
    if (this.mode === 'orbit') this.position = sub(this.target, mul(f, this.distance));
    return {position: this.position.slice(), rotation: lookRotation(f, this.up)};
  }

  rotate(dx, dy) {
    const s = this.mode === 'orbit' ? -1 : 1;
    this.yaw += s * dx * 0.005;
    this.pitch = Math.max(-1.55, Math.min(1.55, this.pitch - s * dy * 0.005));
    this.moved = true;
  }

  zoom(factor) {
    if (this.mode === 'orbit') this.distance *= factor;
    else this.position = add(this.position, mul(this.forward(), (1 - factor) * this.speed));
    this.moved = true;
  }

  pan(dx, dy) {
    const rot = lookRotation(this.forward(), this.up);
    const right = [rot[0][0], rot[1][0], rot[2][0]];
    const upv = [rot[0][1], rot[1][1], rot[2][1]];
    const s = (this.mode === 'orbit' ? this.distance : this.speed) * 0.002;
    const move = add(mul(right, -dx * s), mul(upv, dy * s));
    this.target = add(this.target, move);
    this.position = add(this.position, move);
    this.moved = true;
  }

  update(dt) {
    if (!this.keys.size) return;
    const rot = lookRotation(this.forward(), this.up);
    const right = [rot[0][0], rot[1][0], rot[2][0]];
    let v = [0, 0, 0];
    const f = this.forward();
    if (this.keys.has('w')) v = add(v, f);
    if (this.keys.has('s')) v = sub(v, f);
    if (this.keys.has('d')) v = add(v, right);
    if (this.keys.has('a')) v = sub(v, right);
    if (this.keys.has('e')) v = add(v, this.up);
    if (this.keys.has('q')) v = sub(v, this.up);
    if (!dot(v, v)) return;
    const step = mul(norm(v), this.speed * dt * (this.keys.has('shift') ? 4 : 1));
    if (this.mode === 'orbit') this.target = add(this.target, step);
    else this.position = add(this.position, step);
    this.moved = true;
  }

  attach(el) {
    let last = null;
    let button = 0;
    const touches = new Map();
    el.addEventListener('contextmenu', (e) => e.preventDefault());
    el.addEventListener('pointerdown', (e) => {
      el.setPointerCapture(e.pointerId);
      touches.set(e.pointerId, [e.clientX, e.clientY]);
      last = [e.clientX, e.clientY];
      button = e.button;
    });
    el.addEventListener('pointermove', (e) => {
      if (!touches.has(e.pointerId)) return;
      const prev = touches.get(e.pointerId);
      touches.set(e.pointerId, [e.clientX, e.clientY]);
      if (touches.size === 2) {  // pinch to zoom, two-finger drag to pan
        const [p, q] = [...touches.values()];
        const other = [...touches.entries()].find(([id]) => id !== e.pointerId)[1];
        const before = Math.hypot(prev[0] - other[0], prev[1] - other[1]);
        const after = Math.hypot(p[0] - q[0], p[1] - q[1]);
        if (before > 0 && after > 0) this.zoom(before / after);
        this.pan((e.clientX - prev[0]) / 2, (e.clientY - prev[1]) / 2);
        return;
      }
      const dx = e.clientX - last[0], dy = e.clientY - last[1];
      last = [e.clientX, e.clientY];
      if (button === 2 || e.shiftKey) this.pan(dx, dy);
      else this.rotate(dx, dy);
    });
    const up = (e) => {
      touches.delete(e.pointerId);
      if (touches.size === 1) last = [...touches.values()][0];  // the finger left down goes on from where it is
    };
    el.addEventListener('pointerup', up);
    el.addEventListener('pointercancel', up);
    el.addEventListener('wheel', (e) => { e.preventDefault(); this.zoom(Math.exp(e.deltaY * 0.001)); }, {passive: false});
    window.addEventListener('keydown', (e) => {
      if (e.target && e.target.tagName === 'INPUT') return;
      const k = e.key.toLowerCase();
      if ('wasdqe'.includes(k) && k.length === 1) this.keys.add(k);
      if (k === 'shift') this.keys.add('shift');
    });
    window.addEventListener('keyup', (e) => {
      this.keys.delete(e.key.toLowerCase());
    });
    window.addEventListener('blur', () => this.keys.clear());
  }
}
