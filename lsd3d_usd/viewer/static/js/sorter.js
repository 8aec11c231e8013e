// Depth-sort worker. Holds the centre and reach of every loaded surfel by global index (a
// surfel's slot in the GPU pool) and answers "sort for this camera" with the indices of the
// surfels that can show: centre depth in [near, far] (the CPU renderer's culling) and not
// wholly outside one of the four side planes of the view, farthest first (back-to-front "over"
// compositing gives the same image as the CPU renderer's front-to-back pass in centre-depth
// order). Outside a side plane means beyond the surfel's reach (where its alpha < 1/255) plus
// 4 pixels at its distance, the reach of its low-pass footprint.
// Exact order: an LSD radix sort on the float32 bit patterns of the depths (positive floats
// order like their bits), 3 passes of 11/11/10 bits, stable, so ties keep index order.

let spheres = new Float32Array(0); // x, y, z, reach per surfel
let ranges = new Map(); // start -> count

function ensure(capacity) {
  if (spheres.length >= capacity * 4) return;
  const grown = new Float32Array(Math.max(capacity * 4, spheres.length * 2));
  grown.set(spheres);
  spheres = grown;
}

let keys = new Uint32Array(0), keys2 = new Uint32Array(0), vals = new Uint32Array(0), vals2 = new Uint32Array(0);
const depthF = new Float32Array(1), depthU = new Uint32Array(depthF.buffer);
const counts = new Uint32Array(2048);

function sort(msg) {
  const t0 = performance.now();
  const [cx, cy, cz] = msg.centre, [fx, fy, fz] = msg.forward;
  const P = msg.planes.flat(), margin = msg.pixelAngle * 4;
  let total = 0;
  for (const count of ranges.values()) total += count;
  if (keys.length < total) {
    keys = new Uint32Array(total); keys2 = new Uint32Array(total);
    vals = new Uint32Array(total); vals2 = new Uint32Array(total);
  }
  let n = 0;
  const starts = [...ranges.keys()].sort((a, b) => a - b);
  for (const start of starts) {
    const end = start + ranges.get(start);
    for (let s = start; s < end; s++) {
      const o = 4 * s;
      const vx = spheres[o] - cx, vy = spheres[o + 1] - cy, vz = spheres[o + 2] - cz;
      const d = vx * fx + vy * fy + vz * fz;
      if (!(d >= msg.near && d <= msg.far)) continue;
      const out = -(spheres[o + 3] + Math.sqrt(vx * vx + vy * vy + vz * vz) * margin);
      if (vx * P[0] + vy * P[1] + vz * P[2] < out || vx * P[3] + vy * P[4] + vz * P[5] < out
          || vx * P[6] + vy * P[7] + vz * P[8] < out || vx * P[9] + vy * P[10] + vz * P[11] < out) continue;
      depthF[0] = d;
      keys[n] = depthU[0];
      vals[n] = s;
      n++;
    }
  }
  let kIn = keys, kOut = keys2, vIn = vals, vOut = vals2;
  for (const [shift, bits] of [[0, 11], [11, 11], [22, 10]]) {
    const mask = (1 << bits) - 1;
    counts.fill(0);
    for (let k = 0; k < n; k++) counts[(kIn[k] >>> shift) & mask]++;
    let sum = 0;
    for (let b = 0; b <= mask; b++) { const c = counts[b]; counts[b] = sum; sum += c; }
    for (let k = 0; k < n; k++) {
      const b = (kIn[k] >>> shift) & mask;
      const at = counts[b]++;
      kOut[at] = kIn[k]; vOut[at] = vIn[k];
    }
    [kIn, kOut] = [kOut, kIn];
    [vIn, vOut] = [vOut, vIn];
  }
  const order = new Uint32Array(n);
  for (let k = 0; k < n; k++) order[k] = vIn[n - 1 - k];
  postMessage({ type: "sorted", id: msg.id, order, count: n, ms: performance.now() - t0 }, [order.buffer]);
}

onmessage = (e) => {
  const msg = e.data;
  if (msg.type === "add") {
    ensure(msg.start + msg.count);
    spheres.set(msg.spheres, msg.start * 4);
    ranges.set(msg.start, msg.count);
  } else if (msg.type === "remove") {
    ranges.delete(msg.start);
  } else if (msg.type === "reset") {
    ranges = new Map();
  } else if (msg.type === "sort") {
    sort(msg);
  }
};
