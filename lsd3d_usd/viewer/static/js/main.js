// The viewer page: loads the scene description, streams chunks, draws on demand, wires the panel.
// window.viewer exposes the same operations the panel uses (and the browser tests drive).
import { Renderer } from "./renderer.js";
import { Drive, FlyController, makeCamera, poseFromForward, poseFromMatrix, project, sampleIndex, sampleMatrix, norm, sub,
  sidePlanes } from "./camera.js";
import { fetchBinary, proxyStreamer, surfelStreamer } from "./chunks.js";
import { decodeEnv } from "./formats.js";

const $ = (id) => document.getElementById(id);
// Texels per surfel in the GPU pool: room for SH degree 2 (formats.js). One constant: the
// renderer exists before any configuration, and a toggled run may change the degree.
const TPS = 4;
const LINE_COLORS = {
  lane: [0, 210, 255], junction: [120, 150, 255], RoadEdge: [255, 150, 40], RoadLine: [235, 235, 235],
  Crosswalk: [255, 230, 0], StopLine: [255, 60, 60], Sidewalk: [170, 170, 170], Building: [220, 90, 220],
  ParkingSpot: [120, 220, 120], other: [150, 150, 150],
  loaded: [60, 230, 90], loading: [250, 210, 40], idle: [110, 110, 110], highlight: [255, 255, 80],
};

async function getJSON(url) {
  const r = await fetch(url);
  const body = await r.json().catch(() => ({ error: `${url}: HTTP ${r.status}` }));
  if (!r.ok) throw new Error(body.error || `${url}: HTTP ${r.status}`);
  return body;
}

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v; else if (k.startsWith("on")) e.addEventListener(k.slice(2), v); else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

class Viewer {
  constructor(canvas, gl) {
    this.canvas = canvas;
    this.gl = gl;
    this.renderer = new Renderer(gl, TPS);
    this.sorter = new Worker("/static/js/sorter.js");
    this.sorter.onmessage = (e) => this._sorted(e.data);
    this.sortId = 0; this.sortInFlight = false; this.sortKey = ""; this.sortedKey = null; this.sortMs = 0;
    this.chunkVersion = 0; this.sortedVersion = 0;
    this.surfels = surfelStreamer(this.renderer, this.sorter, TPS, () => this._chunksChanged());
    this.proxy = proxyStreamer(this.renderer, () => { this.linesDirty = true; this.dirty = true; });
    this.fly = new FlyController(canvas);
    this.fly.onInput = () => this._takeControl();
    this.fly.onSpeed = (v) => { $("fly-speed").value = v.toFixed(1); };
    this.mode = "fly"; this.sceneCam = null; this.drive = null; this.fovDeg = 60;
    this.time = 0; this.playing = false;
    // A software renderer (no GPU) draws at half resolution unless asked otherwise: frames of a
    // million surfels take seconds there, and most of that is per pixel near the camera.
    this.software = /swiftshader|llvmpipe|software/i.test(rendererName(gl));
    this.opts = { exposure: 0, tonemap: "aces", shDegree: 2, colorMode: 0, scale: this.software ? 0.5 : 1,
                  radius: 250, actors: true, lanes: false, chunks: false, proxy: false };
    this.problems = [];
    this.clientProblems = [];
    this.runs = new Set();
    this.have = { config: false, env: false, actors: false };
    this.dirty = true; this.linesDirty = true;
    this.waiters = [];
    this.frameMs = 0; this.frames = 0; this.firstIdleMs = null; this.lastDraw = 0;
    this.timeline = {}; // ms since navigation start of the load's milestones (stats())
    this.hover = null;
  }

  // ----------------------------------------------------------------------- loading
  async start() {
    const q = new URLSearchParams(location.search);
    this.scene = await getJSON("/api/scene");
    this._mark("scene");
    this.chunkSize = this.scene.chunkSize;
    $("scene-name").textContent = this.scene.name;
    document.title = `${this.scene.name} - lsd3d-usd viewer`;
    for (const k of Object.keys(this.opts)) {
      if (!q.has(k)) continue;
      const v = q.get(k);
      this.opts[k] = typeof this.opts[k] === "boolean" ? v !== "0" && v !== "false" : typeof this.opts[k] === "number" ? Number(v) : v;
    }
    this.runs = new Set(q.has("runs") ? q.get("runs").split(",").filter(Boolean) : this.scene.defaultRuns);
    const t = this.scene.time;
    this.time = q.has("time") ? Number(q.get("time")) : t.start;
    this._setProblems(this.scene.problems, this.scene.validating);
    this._buildPanel();
    this._resize();
    const variant = q.get("variant") || this.scene.env.selected;
    await Promise.all([this.loadConfig(), this.loadEnv(variant), this.loadActors(), this.loadLayout()]);
    this._syncProxy();
    this._initialView(q);
    this._loop();
  }

  async loadConfig() {
    this.have.config = false;
    const runs = [...this.runs].join(",");
    const seq = (this.configSeq = (this.configSeq || 0) + 1);
    let cfg;
    try {
      cfg = await getJSON(`/api/config?runs=${encodeURIComponent(runs)}`);
    } catch (err) {
      cfg = { chunks: [], surfels: 0, shDegree: 0, semanticClasses: [], semanticColors: [] };
      this._clientProblem("surfels", err.message);
    }
    if (seq !== this.configSeq) return;  // a later toggle won
    this.cfg = cfg;
    const colors = new Float32Array(48);
    (this.cfg.semanticColors || []).slice(0, 16).forEach((c, k) => colors.set(c, 3 * k));
    this.classColors = colors;
    this._mark("config");
    this.surfels.setEntries(this.cfg.chunks.map((c) => ({ ...c, key: c.url })));
    this.have.config = true;
    this._stats();
    this.dirty = true;
  }

  async loadEnv(variant) {
    this.have.env = false;
    const seq = (this.envSeq = (this.envSeq || 0) + 1);
    let info, map = null;
    try {
      info = await getJSON("/api/env" + (variant ? `?variant=${encodeURIComponent(variant)}` : ""));
      if (info.map) map = decodeEnv(await fetchBinary(info.map.url));
    } catch (err) {
      info = { lighting: null, map: null };
      this._clientProblem("environment", err.message);
    }
    if (seq !== this.envSeq) return;     // a later choice won
    this.envInfo = info;
    this.renderer.setEnv(map, info.map);
    this._mark("env");
    this.have.env = true;
    this.dirty = true;
  }

  async loadActors() {
    try {
      this.actorData = await getJSON("/api/actors");
    } catch (err) {
      this.actorData = { times: [], meshes: [], actors: [] };
      this._clientProblem("actors", err.message);
    }
    this.renderer.setActorMeshes(this.actorData.meshes);
    this.have.actors = true;
    this.dirty = true;
  }

  async loadLayout() {
    try {
      this.layout = await getJSON("/api/layout");
    } catch (err) {
      this.layout = { lanes: [], lines: [] };
      this._clientProblem("layout", err.message);
    }
    this.lanes = new Map();
    for (const lane of this.layout.lanes) {
      const p = lane.points, pts = [];
      for (let k = 0; k < p.length; k += 3) pts.push([p[k], p[k + 1], p[k + 2]]);
      this.lanes.set(lane.id, { ...lane, pts });
    }
    this.linesDirty = true;
  }

  // ------------------------------------------------------------------------ camera
  _initialView(q) {
    if (q.has("camera") && this.lookThrough(q.get("camera"))) return;
    if (q.has("eye")) {
      const eye = q.get("eye").split(",").map(Number);
      const target = (q.get("target") || "0,0,0").split(",").map(Number);
      return this.setPose(eye, target);
    }
    const b = this._bounds();
    const ext = Math.max(b.hi[0] - b.lo[0], b.hi[1] - b.lo[1], 20);
    const c = [(b.lo[0] + b.hi[0]) / 2, (b.lo[1] + b.hi[1]) / 2, b.lo[2]];
    const lane = this.lanes.values().next().value;
    if (ext > 400 && lane) {
      const p = lane.pts[0], n = lane.pts[Math.min(1, lane.pts.length - 1)];
      return this.setPose([p[0], p[1], p[2] + 2], [n[0], n[1], p[2] + 2]);
    }
    this.setPose([c[0] - 0.45 * ext, c[1] - 0.6 * ext, c[2] + 0.4 * ext], c);
  }

  _bounds() {
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (const c of this.cfg.chunks) for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], c.lo[k]); hi[k] = Math.max(hi[k], c.hi[k]); }
    for (const lane of this.lanes.values()) for (const p of lane.pts) for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], p[k]); hi[k] = Math.max(hi[k], p[k]); }
    if (!isFinite(lo[0])) return { lo: [-50, -50, 0], hi: [50, 50, 10] };
    return { lo, hi };
  }

  setPose(eye, target) {
    this.mode = "fly";
    this.fly.setPose(poseFromForward(eye, sub(target, eye)));
    $("camera").value = "";
    this.dirty = true;
  }

  lookThrough(path) {
    const cam = this.scene.cameras.find((c) => c.path === path);
    if (!cam) { this._clientProblem("camera", `no camera ${path} in the scene`); return false; }
    this.mode = "camera";
    this.sceneCam = cam;
    $("camera").value = path;
    this.dirty = true;
    return true;
  }

  _takeControl() {
    if (this.mode === "fly") return;
    const cam = this.cam;
    if (cam) {
      this.fly.setPose(cam);
      this.fovDeg = (2 * Math.atan(cam.width / (2 * cam.fx)) * 180) / Math.PI;
    }
    this.mode = "fly";
    $("camera").value = "";
    for (const r of document.querySelectorAll("input[name=mode]")) r.checked = r.value === "fly";
    $("drive-box").hidden = true;
  }

  _pose() {
    if (this.mode === "camera" && this.sceneCam) {
      const c = this.sceneCam;
      return poseFromMatrix(c.poses.length > 1 ? sampleMatrix(c.times, c.poses, this.time) : c.poses[0]);
    }
    if (this.mode === "drive" && this.drive) return this.drive.pose();
    return this.fly.pose();
  }

  _camera() {
    const w = this.canvas.width, h = this.canvas.height;
    const lens = this.mode === "camera" && this.sceneCam ? { usd: this.sceneCam }
      : { fovDeg: this.fovDeg, near: 0.1, far: 20000 };
    return makeCamera(this._pose(), w, h, lens);
  }

  // ---------------------------------------------------------------------- drive mode
  startDrive() {
    let ids = $("route").value.split(/[\s,]+/).filter(Boolean);
    const unknown = ids.filter((id) => !this.lanes.has(id));
    if (unknown.length) { $("drive-info").textContent = `unknown lane ${unknown[0]}`; return false; }
    if (!ids.length) {
      const near = this._nearestLane(this.cam.eye64);
      if (!near) { $("drive-info").textContent = "no lanes in this scene"; return false; }
      ids = [near];
    }
    // follow first successors until the route is 3 km long or ends
    const seen = new Map();
    let length = 0;
    const lanes = ids.map((id) => this.lanes.get(id));
    for (const l of lanes) length += this._laneLength(l);
    let last = lanes[lanes.length - 1];
    while (length < 3000 && last.successors.length) {
      const next = this.lanes.get(last.successors[0]);
      if (!next || (seen.get(next.id) || 0) >= 1) break;
      seen.set(next.id, 1);
      lanes.push(next); length += this._laneLength(next); last = next;
    }
    const pts = [];
    for (const l of lanes) for (const p of l.pts) if (!pts.length || norm(sub(p, pts[pts.length - 1])) > 1e-3) pts.push(p);
    if (pts.length < 2) { $("drive-info").textContent = "route too short"; return false; }
    this.drive = new Drive(pts, Number($("drive-speed").value) || 10);
    this.mode = "drive";
    $("camera").value = "";
    $("drive-info").textContent = `${lanes.length} lanes, ${Math.round(this.drive.length)} m`;
    this.dirty = true;
    return true;
  }

  _laneLength(l) { let s = 0; for (let k = 1; k < l.pts.length; k++) s += norm(sub(l.pts[k], l.pts[k - 1])); return s; }

  _nearestLane(p) {
    let best = null, bd = Infinity;
    for (const l of this.lanes.values()) for (const q of l.pts) { const d = norm(sub(q, p)); if (d < bd) { bd = d; best = l.id; } }
    return best;
  }

  // ------------------------------------------------------------------- state setters
  setTime(t) {
    const tr = this.scene.time;
    this.time = Math.max(tr.start, Math.min(tr.end, Number(t)));
    $("time").value = this.time;
    this._timeLabel();
    this.dirty = true;
  }

  async setRun(name, on) {
    if (on) this.runs.add(name); else this.runs.delete(name);
    const box = document.querySelector(`input[data-run="${CSS.escape(name)}"]`);
    if (box) box.checked = on;
    await this.loadConfig();
  }

  async setVariant(name) { $("env-variant").value = name; await this.loadEnv(name); }

  setOption(key, value) {
    this.opts[key] = value;
    if (["lanes", "chunks", "proxy"].includes(key)) this.linesDirty = true;
    if (key === "scale") this._resize();
    if (key === "proxy") this._syncProxy();
    this.dirty = true;
  }

  _syncProxy() {
    if (!this.opts.proxy) this.proxy.clear();
    else if (!this.proxy.entries.size) {
      this.proxy.setEntries((this.scene.proxyChunks || []).map(([i, j]) => ({ key: `${i}_${j}`, i, j, url: `/api/proxy/${i}_${j}` })));
    }
  }

  // ------------------------------------------------------------------------- frames
  _resize() {
    const dpr = Math.min(window.devicePixelRatio || 1, 2) * this.opts.scale;
    const w = Math.max(1, Math.round(this.canvas.clientWidth * dpr)), h = Math.max(1, Math.round(this.canvas.clientHeight * dpr));
    if (w !== this.canvas.width || h !== this.canvas.height) { this.canvas.width = w; this.canvas.height = h; }
    this.dirty = true;
  }

  _chunksChanged() { this.chunkVersion++; this.linesDirty = true; this.dirty = true; this._stats(); }

  _requestSort(cam, key) {
    this.sortInFlight = true;
    this.pendingKey = key;
    this.pendingVersion = this.chunkVersion;
    this.sorter.postMessage({ type: "sort", id: ++this.sortId, centre: cam.eye64, forward: cam.forward, near: cam.near,
                              far: cam.far, planes: sidePlanes(cam), pixelAngle: 1 / Math.min(cam.fx, cam.fy) });
  }

  _sorted(msg) {
    if (msg.id !== this.sortId) return;
    this.sortInFlight = false;
    this.sortedKey = this.pendingKey;
    this.sortedVersion = this.pendingVersion;
    this.sortMs = msg.ms;
    if (!this.surfels.wanted && !this.surfels.inFlight.size && this.surfels.loaded.size) this._mark("sorted");
    this.renderer.setOrder(msg.order, msg.count);
    this.dirty = true;
  }

  _actorsAt(t) {
    if (!this.opts.actors || !this.actorData) return [];
    const A = this.actorData, out = [];
    for (const a of A.actors) {
      const k = sampleIndex(A.times, t);
      if (a.visible.length && !a.visible[k]) continue;
      out.push({ mesh: a.mesh, model: new Float32Array(a.transforms.length > 1 ? sampleMatrix(A.times, a.transforms, t) : a.transforms[0]) });
    }
    return out;
  }

  draw() {
    const cam = this.cam;
    const t0 = performance.now();
    this.renderer.render({
      camera: cam, actors: this._actorsAt(this.time), lighting: this.envInfo?.lighting || DEFAULT_LIGHT,
      exposure: this.opts.exposure, tonemap: this.opts.tonemap, shDegree: Math.min(this.opts.shDegree, this.cfg.shDegree || 0),
      colorMode: this.opts.colorMode, classColors: this.classColors, proxy: this.opts.proxy, proxyAlpha: 0.45,
    });
    const px = new Uint8Array(4);
    this.gl.readPixels(0, 0, 1, 1, this.gl.RGBA, this.gl.UNSIGNED_BYTE, px); // waits for the frame
    this.frameMs = performance.now() - t0;
    this.frames++;
    if (this.frames <= 8) (this.timeline.frames ??= []).push([Math.round(t0), Math.round(this.frameMs), this.renderer.count]);
    this.dirty = false;
  }

  _idle() {
    const s = this.surfels;
    return this.have.config && this.have.env && this.have.actors && s.wanted === 0 && s.inFlight.size === 0
      && (!this.opts.proxy || (this.proxy.wanted === 0 && this.proxy.inFlight.size === 0))
      && !this.sortInFlight && this.sortedKey === this.sortKey && !this.dirty;
  }

  _mark(name) { if (!(name in this.timeline)) this.timeline[name] = Math.round(performance.now()); }

  whenIdle() { return new Promise((resolve) => this.waiters.push(resolve)); }

  screenshot() {
    this.cam = this._camera();
    this.draw();
    return this.canvas.toDataURL("image/png");
  }

  stats() {
    return { frameMs: this.frameMs, sortMs: this.sortMs, frames: this.frames, drawn: this.renderer.count,
             loadedSurfels: this.surfels.surfels(), loadedChunks: [...this.surfels.loaded.keys()].map((u) => u.split("/").pop()),
             chunks: this.cfg?.chunks.length || 0, firstIdleMs: this.firstIdleMs, mode: this.mode, time: this.time,
             size: [this.canvas.width, this.canvas.height], runs: [...this.runs], configId: this.cfg?.id,
             renderer: this.renderer.note || "", timeline: this.timeline };
  }

  _loop() {
    let last = performance.now();
    const tick = (now) => {
      const dt = Math.min(0.25, (now - last) / 1000);   // slow frames still move, without jumps
      last = now;
      if (this.fly.update(dt) && this.mode === "fly") this.dirty = true;
      if (this.mode === "drive" && this.drive) { this.drive.update(dt); this.dirty = true; }
      if (this.playing) {
        const tr = this.scene.time;
        let t = this.time + dt * tr.codesPerSecond;
        if (t > tr.end) t = tr.start;
        this.setTime(t);
      }
      const cam = this._camera();
      this.cam = cam;
      this.surfels.update(cam, this.chunkSize, this.opts.radius);
      if (this.opts.proxy) this.proxy.update(cam, this.chunkSize, this.opts.radius);
      this.sortKey = `${this.chunkVersion}|${cam.eye64.join(",")}|${cam.forward.join(",")}|${cam.near}|${cam.far}`;
      if (this.sortKey !== this.sortedKey && !this.sortInFlight) this._requestSort(cam, this.sortKey);
      if (this.linesDirty) this._rebuildLines();
      const key = this._viewKey(cam);
      if (key !== this.lastViewKey) { this.lastViewKey = key; this.dirty = true; }
      // Frames wait while chunks stream in (one frame of 1 M surfels takes seconds in a software
      // renderer): the first load draws the background, then the complete set; later streaming
      // redraws at most every 3 frame times. After the chunk set changed, a frame waits for its
      // sort (milliseconds) rather than draw a stale order.
      const loading = this.surfels.inFlight.size > 0 || this.surfels.wanted > 0;
      const stale = this.sortedVersion !== this.chunkVersion && this.frames > 0;
      const due = !stale && (!loading || !this.frames
        || (this.firstIdleMs !== null && now - this.lastDraw >= Math.max(300, 3 * this.frameMs)));
      if (this.dirty && due) { this.draw(); this.lastDraw = performance.now(); this._status(); }
      else if (loading) this._status();
      if (this._idle()) {
        if (this.firstIdleMs === null) { this.firstIdleMs = performance.now(); this._mark("idle"); }
        for (const w of this.waiters.splice(0)) w();
      }
      requestAnimationFrame(tick);
    };
    requestAnimationFrame(tick);
  }

  _viewKey(cam) {
    return `${cam.eye64.join(",")}|${cam.forward.join(",")}|${cam.width}x${cam.height}|${cam.fx}|${this.time}`;
  }

  // ------------------------------------------------------------------------ overlays
  _rebuildLines() {
    this.linesDirty = false;
    const pos = [], col = [];
    const seg = (a, b, c) => { pos.push(a[0], a[1], a[2] + 0.05, b[0], b[1], b[2] + 0.05); col.push(...c, 255, ...c, 255); };
    if (this.opts.lanes && this.layout) {
      for (const l of this.lanes.values()) {
        const c = l.junction ? LINE_COLORS.junction : LINE_COLORS.lane;
        for (let k = 1; k < l.pts.length; k++) seg(l.pts[k - 1], l.pts[k], c);
      }
      for (const f of this.layout.lines) {
        const c = LINE_COLORS[f.kind] || LINE_COLORS.other, p = f.points, n = p.length / 3;
        for (let k = 1; k < n + (f.closed ? 1 : 0); k++) {
          const a = (k - 1) % n, b = k % n;
          seg([p[3 * a], p[3 * a + 1], p[3 * a + 2]], [p[3 * b], p[3 * b + 1], p[3 * b + 2]], c);
        }
      }
    }
    if (this.opts.chunks && this.cfg) {
      const S = this.chunkSize;
      for (const c of this.cfg.chunks) {
        const z = c.lo[2], x0 = c.i * S, y0 = c.j * S, x1 = x0 + S, y1 = y0 + S;
        const colr = LINE_COLORS[this.surfels.state(c.url)];
        seg([x0, y0, z], [x1, y0, z], colr); seg([x1, y0, z], [x1, y1, z], colr);
        seg([x1, y1, z], [x0, y1, z], colr); seg([x0, y1, z], [x0, y0, z], colr);
      }
    }
    this.renderer.setLines(new Float32Array(pos), new Uint8Array(col));
    this.dirty = true;
  }

  _hoverLane(mx, my) {
    if (!this.opts.lanes || !this.cam) return this._setHover(null);
    const cam = this.cam, sx = this.canvas.width / this.canvas.clientWidth, sy = this.canvas.height / this.canvas.clientHeight;
    const x = mx * sx, y = my * sy;
    let best = null, bd = 8 * sx;
    for (const l of this.lanes.values()) {
      let prev = null;
      for (const p of l.pts) {
        const q = project(cam, p);
        if (prev && prev[2] > cam.near && q[2] > cam.near) {
          const dx = q[0] - prev[0], dy = q[1] - prev[1];
          const len2 = dx * dx + dy * dy || 1;
          const w = Math.max(0, Math.min(1, ((x - prev[0]) * dx + (y - prev[1]) * dy) / len2));
          const d = Math.hypot(prev[0] + w * dx - x, prev[1] + w * dy - y);
          if (d < bd) { bd = d; best = l; }
        }
        prev = q;
      }
    }
    this._setHover(best, mx, my);
  }

  _setHover(lane, mx, my) {
    const tip = $("tooltip");
    if (!lane) {
      tip.hidden = true;
      if (this.hover) { this.hover = null; this.renderer.setHighlight(null); this.dirty = true; }
      return;
    }
    tip.hidden = false;
    tip.textContent = `lane ${lane.id}` + (lane.successors.length ? ` → ${lane.successors.join(", ")}` : "");
    tip.style.left = `${mx + 14}px`; tip.style.top = `${my + 10}px`;
    if (this.hover !== lane.id) {
      this.hover = lane.id;
      const pos = [], col = [];
      for (let k = 1; k < lane.pts.length; k++) {
        const a = lane.pts[k - 1], b = lane.pts[k];
        pos.push(a[0], a[1], a[2] + 0.1, b[0], b[1], b[2] + 0.1);
        col.push(...LINE_COLORS.highlight, 255, ...LINE_COLORS.highlight, 255);
      }
      this.renderer.setHighlight(new Float32Array(pos), new Uint8Array(col));
      this.dirty = true;
    }
  }

  // --------------------------------------------------------------------------- panel
  _setProblems(list, validating) {
    this.problems = list;
    const all = [...this.problems, ...this.clientProblems];
    const box = $("problems-box"), ul = $("problems");
    ul.replaceChildren(...all.map((p) => el("li", { class: p.severity }, `${p.severity === "warning" ? "warning: " : ""}${p.where}: ${p.message}`)));
    box.hidden = !all.length;
    const errors = all.filter((p) => p.severity === "error").length;
    $("problem-count").textContent = `(${errors} error(s), ${all.length - errors} warning(s))` + (validating ? " validating…" : "");
    if (errors) box.open = true;
    this.validating = validating;
    this._stats();
    if (validating) setTimeout(() => getJSON("/api/problems").then((r) => this._setProblems(r.problems, r.validating), () => {}), 1000);
  }

  _clientProblem(where, message) {
    this.clientProblems.push({ severity: "error", where, message });
    this._setProblems(this.problems, false);
  }

  _buildPanel() {
    const sc = this.scene;
    // layers
    $("layers").replaceChildren(...sc.layers.map((L) => {
      const prov = L.provenance || {};
      const bits = [prov.step, prov.created, prov.stepsDone !== undefined ? `${prov.stepsDone} steps` : null].filter(Boolean).join(", ");
      const links = (L.files || []).map((f) => el("a", { href: `/files/${f.split("/").map(encodeURIComponent).join("/")}`, target: "_blank" }, f.split("/").pop()));
      if (L.kind === "ggds") {
        const box = el("input", { type: "checkbox", "data-run": L.name });
        box.checked = this.runs.has(L.name);
        box.disabled = !L.exists;
        box.addEventListener("change", () => this.setRun(L.name, box.checked));
        return el("li", { title: bits }, el("label", {}, box, ` ${L.name}`, L.active ? "" : " (muted in the scene)"), ...links);
      }
      return el("li", { class: L.active ? "" : "muted", title: bits }, `· ${L.name}`, L.active ? "" : " (muted in the scene)", L.exists ? "" : " (file missing)");
    }));
    // environment
    const vs = $("env-variant");
    vs.replaceChildren(...(sc.env.variants.length ? sc.env.variants : ["(none)"]).map((v) => el("option", {}, v)));
    if (sc.env.selected) vs.value = sc.env.selected;
    vs.disabled = !sc.env.variants.length;
    vs.addEventListener("change", () => this.loadEnv(vs.value));
    const ex = $("exposure");
    ex.value = this.opts.exposure;
    ex.addEventListener("input", () => { this.setOption("exposure", Number(ex.value)); $("exposure-value").textContent = ex.value; });
    $("tonemap").value = this.opts.tonemap;
    $("tonemap").addEventListener("change", (e) => this.setOption("tonemap", e.target.value));
    // time
    const ts = $("time");
    ts.min = sc.time.start; ts.max = sc.time.end; ts.value = this.time;
    ts.disabled = sc.time.end <= sc.time.start;
    ts.addEventListener("input", () => this.setTime(ts.value));
    $("play").addEventListener("click", () => this.togglePlay());
    this._timeLabel();
    // cameras and modes
    const cs = $("camera");
    for (const c of sc.cameras) cs.append(el("option", { value: c.path }, c.path));
    cs.addEventListener("change", () => { if (cs.value) this.lookThrough(cs.value); else this._takeControl(); });
    for (const r of document.querySelectorAll("input[name=mode]")) {
      r.addEventListener("change", () => {
        $("drive-box").hidden = r.value !== "drive";
        if (r.value === "fly") this._takeControl();
      });
    }
    $("fly-speed").addEventListener("change", (e) => { this.fly.speed = Number(e.target.value) || 10; });
    $("drive-start").addEventListener("click", () => this.startDrive());
    this.canvas.addEventListener("click", () => {
      if (!$("pick-route").checked || !this.hover) return;
      const r = $("route");
      r.value = (r.value ? r.value.replace(/[\s,]+$/, "") + ", " : "") + this.hover;
    });
    // display
    for (const [id, key] of [["show-actors", "actors"], ["show-lanes", "lanes"], ["show-chunks", "chunks"], ["show-proxy", "proxy"]]) {
      $(id).checked = this.opts[key];
      $(id).addEventListener("change", (e) => this.setOption(key, e.target.checked));
    }
    $("color-mode").value = String(this.opts.colorMode);
    $("color-mode").addEventListener("change", (e) => this.setOption("colorMode", Number(e.target.value)));
    $("sh-degree").value = String(this.opts.shDegree);
    $("sh-degree").addEventListener("change", (e) => this.setOption("shDegree", Number(e.target.value)));
    $("scale").value = String(this.opts.scale);
    $("scale").addEventListener("change", (e) => this.setOption("scale", Number(e.target.value)));
    $("radius").value = String(this.opts.radius);
    $("radius").addEventListener("change", (e) => this.setOption("radius", Math.max(50, Number(e.target.value) || 250)));
    $("screenshot").addEventListener("click", () => {
      const a = el("a", { href: this.screenshot(), download: `${sc.name}.png` });
      a.click();
    });
    const togglePanel = () => { $("panel").classList.toggle("hidden"); document.body.classList.toggle("panel-hidden"); };
    $("toggle-panel").addEventListener("click", togglePanel);
    window.addEventListener("keydown", (e) => {
      if (e.target.tagName === "INPUT" || e.target.tagName === "SELECT") return;
      if (e.key === "h" || e.key === "H") togglePanel();
      if (e.key === " ") { e.preventDefault(); this.togglePlay(); }
    });
    window.addEventListener("resize", () => this._resize());
    this.canvas.addEventListener("mousemove", (e) => { if (!e.buttons) this._hoverLane(e.offsetX, e.offsetY); });
    this.canvas.addEventListener("mouseleave", () => this._setHover(null));
  }

  togglePlay() {
    this.playing = !this.playing && this.scene.time.end > this.scene.time.start;
    $("play").textContent = this.playing ? "⏸" : "▶";
  }

  _timeLabel() {
    const tr = this.scene.time;
    $("time-value").textContent = `time code ${this.time.toFixed(1)} (${((this.time - tr.start) / tr.codesPerSecond).toFixed(2)} s of ${((tr.end - tr.start) / tr.codesPerSecond).toFixed(2)} s)`;
  }

  _stats() {
    if (!this.cfg) return;
    const mb = (this.cfg.bytes / 1e6).toFixed(1);
    $("scene-stats").textContent = `${this.cfg.surfels.toLocaleString("en")} surfels in ${this.cfg.chunks.length} chunks · ${mb} MB (${this.cfg.bytesPerSurfel} B/surfel)`
      + (this.validating ? " · validating…" : "");
  }

  _status() {
    const loaded = this.surfels.loaded.size;
    const pending = this.surfels.wanted + this.surfels.inFlight.size;
    $("status").textContent = (pending ? `loading ${pending} chunk(s) · ` : "") + `frame ${this.frameMs.toFixed(0)} ms · sort ${this.sortMs.toFixed(0)} ms · ${this.renderer.count.toLocaleString("en")} surfels drawn · chunks ${loaded}/${this.cfg?.chunks.length || 0}` +
      ` · ${this.canvas.width}×${this.canvas.height}${this.software ? " (software renderer)" : ""} · ${this.mode}`
      + (this.renderer.note ? ` · ${this.renderer.note}` : "");
  }
}

function rendererName(gl) {
  const info = gl.getExtension("WEBGL_debug_renderer_info");
  return String(gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER));
}

// Lighting when the scene has no env layer (actors/relight.py default_lighting).
const DEFAULT_LIGHT = (() => {
  const s = [Math.cos((50 * Math.PI) / 180) * 0.6, Math.cos((50 * Math.PI) / 180) * 0.8, Math.sin((50 * Math.PI) / 180)];
  const n = Math.hypot(...s);
  const sh = Array.from({ length: 9 }, (_, k) => (k === 0 ? [1 / 0.28209479177387814, 1 / 0.28209479177387814, 1 / 0.28209479177387814] : [0, 0, 0]));
  return { sh, sunDir: s.map((v) => v / n), sunResidual: [2.5, 2.5, 2.5], reference: 1 + 2.5 * (s[2] / n) };
})();

async function main() {
  const canvas = $("view");
  const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: true, preserveDrawingBuffer: false });
  if (!gl) {
    $("panel").hidden = true;
    $("toggle-panel").hidden = true;
    const m = $("message");
    m.textContent = "This viewer needs WebGL2, which this browser does not provide.";
    m.hidden = false;
    window.viewer = { error: m.textContent };
    return;
  }
  let viewer;
  try {
    viewer = new Viewer(canvas, gl);
  } catch (err) {
    const m = $("message");
    m.textContent = `The viewer could not start: ${err.message}`;
    m.hidden = false;
    throw err;
  }
  window.viewer = viewer;
  viewer.ready = viewer.start();
  viewer.ready.catch((err) => {
    const m = $("message");
    m.textContent = `The scene could not be loaded: ${err.message}`;
    m.hidden = false;
  });
}

main();
