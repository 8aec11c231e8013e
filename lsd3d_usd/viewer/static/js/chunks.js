// Chunk streaming: chunks whose square lies within the view distance of the camera (farther
// when behind it) are fetched, nearest first, two at a time; chunks beyond it plus one chunk of
// hysteresis are dropped. Surfel chunks go to the GPU pool and the sorter; proxy chunks (when
// the overlay is on) to the overlay meshes.
import { decodeChunk, decodeMesh } from "./formats.js";

function distance(cam, i, j, size) {
  const x0 = i * size, y0 = j * size;
  const ex = cam.eye64[0], ey = cam.eye64[1];
  const dx = Math.max(x0 - ex, 0, ex - (x0 + size));
  const dy = Math.max(y0 - ey, 0, ey - (y0 + size));
  const d = Math.hypot(dx, dy);
  const cx = x0 + size / 2 - ex, cy = y0 + size / 2 - ey;
  const behind = cx * cam.forward[0] + cy * cam.forward[1] < 0;
  return behind ? 2 * d : d;
}

export class Streamer {
  constructor({ load, unload, onChange, maxInFlight = 2 }) {
    this.load = load;        // async (entry) -> handle
    this.unload = unload;    // (entry, handle) -> void
    this.onChange = onChange;
    this.maxInFlight = maxInFlight;
    this.entries = new Map();   // key -> entry {key, i, j, ...}
    this.loaded = new Map();    // key -> handle
    this.inFlight = new Map();  // key -> generation
    this.generation = 0;
    this.wanted = 0;
    this.failed = new Set();
  }

  setEntries(list) {
    this.generation++;
    for (const [key, handle] of this.loaded) this.unload(this.entries.get(key), handle);
    this.loaded.clear();
    this.inFlight.clear();
    this.failed.clear();
    this.entries = new Map(list.map((e) => [e.key, e]));
    this.onChange();
  }

  clear() { this.setEntries([]); }

  // Returns the number of wanted chunks not loaded yet.
  update(cam, size, radius, enabled = true) {
    const want = [];
    for (const e of this.entries.values()) {
      const d = enabled ? distance(cam, e.i, e.j, size) : Infinity;
      e.distance = d;
      if (this.loaded.has(e.key) && d > radius + size) {
        this.unload(e, this.loaded.get(e.key));
        this.loaded.delete(e.key);
        this.onChange();
      } else if (d <= radius && !this.loaded.has(e.key) && !this.failed.has(e.key)) {
        want.push(e);
      }
    }
    want.sort((a, b) => a.distance - b.distance);
    this.wanted = want.length;
    for (const e of want) {
      if (this.inFlight.size >= this.maxInFlight) break;
      if (this.inFlight.has(e.key)) continue;
      const gen = this.generation;
      this.inFlight.set(e.key, gen);
      this.load(e).then((handle) => {
        if (this.inFlight.get(e.key) !== gen || gen !== this.generation) {
          if (handle !== undefined) this.unload(e, handle);
          return;
        }
        this.inFlight.delete(e.key);
        this.loaded.set(e.key, handle);
        this.onChange();
      }, (err) => {
        if (gen !== this.generation) return;
        this.inFlight.delete(e.key);
        this.failed.add(e.key);
        console.warn(`chunk ${e.key}: ${err.message}`);
        this.onChange();
      });
    }
    return this.wanted;
  }

  state(key) {
    if (this.loaded.has(key)) return "loaded";
    if (this.inFlight.has(key)) return "loading";
    return "idle";
  }
}

export async function fetchBinary(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return r.arrayBuffer();
}

let tokens = 0; // unique GPU-side names: a stale load never collides with a newer one

export function surfelStreamer(renderer, sorter, tps, onChange) {
  let surfels = 0;
  const s = new Streamer({
    onChange,
    load: async (e) => {
      const chunk = decodeChunk(await fetchBinary(e.url), tps);
      const token = `${e.key}#${++tokens}`;
      const start = renderer.addChunk(token, chunk.gpu, chunk.n);
      sorter.postMessage({ type: "add", start, count: chunk.n, spheres: chunk.spheres }, [chunk.spheres.buffer]);
      surfels += chunk.n;
      return { token, start, n: chunk.n };
    },
    unload: (e, h) => {
      renderer.removeChunk(h.token);
      sorter.postMessage({ type: "remove", start: h.start });
      surfels -= h.n;
    },
  });
  s.surfels = () => surfels;
  return s;
}

export function proxyStreamer(renderer, onChange) {
  return new Streamer({
    onChange,
    load: async (e) => {
      const token = `${e.key}#${++tokens}`;
      renderer.addProxy(token, decodeMesh(await fetchBinary(e.url)));
      return { token };
    },
    unload: (e, h) => renderer.removeProxy(h.token),
  });
}
