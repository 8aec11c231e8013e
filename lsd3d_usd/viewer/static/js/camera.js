// Cameras: the CPU renderer's pinhole model (render/camera.py): a world-from-camera pose with
// OpenCV axes (columns right, down, forward, centre) and pixel intrinsics for the canvas size.

export const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
export const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
export const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
export const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
export const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
export const norm = (a) => Math.hypot(a[0], a[1], a[2]);
export const unit = (a) => { const n = norm(a) || 1; return [a[0] / n, a[1] / n, a[2] / n]; };

// Pose from a forward direction (Z up), like render.camera.look_at.
export function poseFromForward(eye, forward) {
  const f = unit(forward);
  let right = cross(f, [0, 0, 1]);
  if (norm(right) < 1e-9) right = [1, 0, 0];
  right = unit(right);
  const down = cross(f, right);
  return { eye: [...eye], right, down, forward: f };
}

// Pose from a 4x4 column-major world-from-camera matrix (OpenCV axes).
export function poseFromMatrix(m) {
  return { eye: [m[12], m[13], m[14]], right: [m[0], m[1], m[2]], down: [m[4], m[5], m[6]], forward: [m[8], m[9], m[10]] };
}

// Interpolated 4x4 column-major matrix at time t from samples (times ascending): translation
// linear, rotation part linear then re-orthonormalised (time samples are dense).
export function sampleMatrix(times, mats, t) {
  if (!times.length || mats.length === 1) return mats[0];
  if (t <= times[0]) return mats[0];
  if (t >= times[times.length - 1]) return mats[mats.length - 1];
  let lo = 0, hi = times.length - 1;
  while (hi - lo > 1) { const mid = (lo + hi) >> 1; if (times[mid] <= t) lo = mid; else hi = mid; }
  const w = (t - times[lo]) / (times[hi] - times[lo]);
  const a = mats[lo], b = mats[hi];
  const m = a.map((v, k) => v + (b[k] - v) * w);
  const c0 = [m[0], m[1], m[2]], c1 = [m[4], m[5], m[6]];
  const s0 = norm(c0), s1 = norm(c1), s2 = norm([m[8], m[9], m[10]]);
  const x = unit(c0);
  const y = unit(sub(c1, scale(x, dot(x, c1))));
  const z = cross(x, y);
  const det = Math.sign(dot(cross([a[0], a[1], a[2]], [a[4], a[5], a[6]]), [a[8], a[9], a[10]])) || 1;
  const out = m.slice();
  [out[0], out[1], out[2]] = scale(x, s0);
  [out[4], out[5], out[6]] = scale(y, s1);
  [out[8], out[9], out[10]] = scale(z, s2 * det);
  return out;
}

export function sampleIndex(times, t) {
  if (!times.length || t <= times[0]) return 0;
  let lo = 0, hi = times.length - 1;
  if (t >= times[hi]) return hi;
  while (hi - lo > 1) { const mid = (lo + hi) >> 1; if (times[mid] <= t) lo = mid; else hi = mid; }
  return lo;
}

// The camera as the shaders take it; intrinsics either from a horizontal field of view or,
// when looking through a scene camera, from its USD filmback exactly as render.camera.from_usd
// computes them for this image size (conform "horizontal": square pixels).
export function makeCamera(pose, width, height, lens) {
  let fx, fy, cx, cy, near, far;
  if (lens.usd) {
    const u = lens.usd;
    fx = (u.focalLength * width) / u.hAperture;
    fy = fx;
    cx = width / 2 - (u.hOffset * fx) / u.focalLength;
    cy = height / 2 + (u.vOffset * fy) / u.focalLength;
    near = u.near; far = u.far;
  } else {
    fx = (0.5 * width) / Math.tan((lens.fovDeg * Math.PI) / 360);
    fy = fx; cx = width / 2; cy = height / 2;
    near = lens.near; far = lens.far;
  }
  const { right: r, down: d, forward: f } = pose;
  // world -> camera rotation R (rows right, down, forward) as column-major mat3 data
  const rotColumns = new Float32Array([r[0], d[0], f[0], r[1], d[1], f[1], r[2], d[2], f[2]]);
  return { eye: new Float32Array(pose.eye), eye64: pose.eye, right: r, down: d, forward: f, rotColumns,
           fx, fy, cx, cy, width, height, near, far };
}

// Inward unit normals (world) of the planes through the camera centre and the image's left,
// right, top and bottom edges: a point p is in view when n . (p - eye) >= 0 for all four.
export function sidePlanes(cam) {
  const { fx, fy, cx, cy, width: w, height: h } = cam;
  return [[fx, 0, cx], [-fx, 0, w - cx], [0, fy, cy], [0, -fy, h - cy]].map(([a, b, c]) =>
    unit(add(add(scale(cam.right, a), scale(cam.down, b)), scale(cam.forward, c))));
}

// Pixel position (x right, y down) and depth of a world point.
export function project(cam, p) {
  const v = sub(p, cam.eye64);
  const z = dot(v, cam.forward);
  return [cam.fx * dot(v, cam.right) / z + cam.cx, cam.fy * dot(v, cam.down) / z + cam.cy, z];
}

// Free fly: position + yaw/pitch, WASD/QE/arrows, mouse drag to look, wheel for speed.
export class FlyController {
  constructor(element) {
    this.eye = [0, 0, 2];
    this.yaw = 0; this.pitch = 0;
    this.speed = 10;
    this.keys = new Set();
    this.changed = false;
    this.onInput = () => {};
    let drag = null;
    element.addEventListener("keydown", (e) => {
      if (e.target.tagName === "INPUT" || e.target.tagName === "SELECT") return;
      const k = e.key.toLowerCase();
      if (["w", "a", "s", "d", "q", "e", "arrowup", "arrowdown", "arrowleft", "arrowright", "shift"].includes(k)) {
        this.keys.add(k); this.onInput(); e.preventDefault();
      }
    });
    element.addEventListener("keyup", (e) => this.keys.delete(e.key.toLowerCase()));
    window.addEventListener("blur", () => this.keys.clear());
    element.addEventListener("mousedown", (e) => { if (e.button === 0) drag = [e.clientX, e.clientY]; });
    window.addEventListener("mouseup", () => { drag = null; });
    window.addEventListener("mousemove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag[0], dy = e.clientY - drag[1];
      drag = [e.clientX, e.clientY];
      if (dx || dy) {
        this.onInput();
        this.yaw -= dx * 0.004;
        this.pitch = Math.max(-1.55, Math.min(1.55, this.pitch - dy * 0.004));
        this.changed = true;
      }
    });
    element.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.speed = Math.max(0.5, Math.min(500, this.speed * (e.deltaY > 0 ? 0.8 : 1.25)));
      this.onSpeed?.(this.speed);
    }, { passive: false });
  }

  setPose(pose) {
    this.eye = [...pose.eye];
    const f = pose.forward;
    this.yaw = Math.atan2(f[1], f[0]);
    this.pitch = Math.asin(Math.max(-1, Math.min(1, f[2])));
  }

  pose() {
    const cp = Math.cos(this.pitch);
    return poseFromForward(this.eye, [cp * Math.cos(this.yaw), cp * Math.sin(this.yaw), Math.sin(this.pitch)]);
  }

  // Advance by dt seconds; returns true when the camera moved.
  update(dt) {
    const k = this.keys;
    if (!k.size) { const c = this.changed; this.changed = false; return c; }
    const fast = k.has("shift") ? 4 : 1;
    const step = this.speed * fast * dt;
    const cp = Math.cos(this.pitch);
    const fwd = [cp * Math.cos(this.yaw), cp * Math.sin(this.yaw), Math.sin(this.pitch)];
    const right = [Math.sin(this.yaw), -Math.cos(this.yaw), 0];
    let m = [0, 0, 0];
    if (k.has("w") || k.has("arrowup")) m = add(m, fwd);
    if (k.has("s") || k.has("arrowdown")) m = sub(m, fwd);
    if (k.has("d") || k.has("arrowright")) m = add(m, right);
    if (k.has("a") || k.has("arrowleft")) m = sub(m, right);
    if (k.has("e")) m = add(m, [0, 0, 1]);
    if (k.has("q")) m = sub(m, [0, 0, 1]);
    this.changed = false;
    if (norm(m) === 0) return false;
    this.eye = add(this.eye, scale(unit(m), step));
    return true;
  }
}

// Drive: along a route of lanes (concatenated centre lines) at a set speed, eye at a set height
// above the lane, looking at a point a few metres ahead.
export class Drive {
  constructor(points, speed, height = 1.6) {
    this.pts = points;
    this.cum = [0];
    for (let k = 1; k < points.length; k++) this.cum.push(this.cum[k - 1] + norm(sub(points[k], points[k - 1])));
    this.length = this.cum[this.cum.length - 1];
    this.s = 0;
    this.speed = speed;
    this.height = height;
  }
  at(s) {
    s = Math.max(0, Math.min(this.length, s));
    let k = 1;
    while (k < this.cum.length - 1 && this.cum[k] < s) k++;
    const seg = this.cum[k] - this.cum[k - 1] || 1;
    const w = (s - this.cum[k - 1]) / seg;
    return add(this.pts[k - 1], scale(sub(this.pts[k], this.pts[k - 1]), w));
  }
  update(dt) { this.s = Math.min(this.length, this.s + this.speed * dt); return this.s < this.length; }
  pose() {
    const p = this.at(this.s);
    const ahead = this.at(this.s + 6);
    let f = sub(ahead, p);
    if (norm(f) < 1e-6) f = sub(p, this.at(this.s - 6));
    f[2] = 0;
    return poseFromForward(add(p, [0, 0, this.height]), f);
  }
}
