// Decoders of the server's binary buffers (lsd3d_usd/viewer/pack.py, docs/viewer.md).
// Surfel chunks become the GPU layout of renderer.js: per surfel TPS texels of RGBA32UI,
//   texel 0: float bits of x, y, z (world), packed quaternion
//   texel 1: f16 scales, f16 dc r|g, f16 dc b|u8 opacity|u8 semantic, sh1 word 0
//   texel 2: sh1 words 1..3, 0 (SH degree >= 1; with degree 2, f16 m2 in word 2 bits 24-31
//            and word 3 bits 0-7, the first 3 band-2 i8 in word 3 bits 8-31)
//   texel 3: sh2 words 0..3 (SH degree 2: the other 12 band-2 i8, then 0)
// (TPS = 4; texels of a lower degree stay 0). The sh1/sh2 words are the wire's as they are,
// so the quantised wire format is expanded only for the positions, which the sorter needs too,
// with each surfel's reach: the radius around its centre outside which its alpha < 1/255.

const CHUNK_HEADER = 96;

function magic(view, text) {
  for (let k = 0; k < 4; k++) if (view.getUint8(k) !== text.charCodeAt(k)) return false;
  return true;
}

const HALF = new Float32Array(65536).map((_, b) => {
  const e = (b >> 10) & 31, m = b & 1023, sign = b >> 15 ? -1 : 1;
  if (e === 0) return sign * m * 2 ** -24;
  if (e === 31) return m ? NaN : sign * Infinity;
  return sign * (1 + m / 1024) * 2 ** (e - 15);
});
const half = (bits) => HALF[bits];

export function decodeChunk(buffer, tps) {
  const view = new DataView(buffer);
  const version = magic(view, "LSDV") ? view.getUint16(4, true) : 0;
  if (version !== 1 && version !== 2) throw new Error("not an LSDV v2 chunk");
  const deg = view.getUint8(6);
  if (deg > (version === 1 ? 1 : 2)) throw new Error(`LSDV v${version} chunk with SH degree ${deg}`);
  const n = view.getUint32(8, true);
  const i = view.getInt32(12, true), j = view.getInt32(16, true);
  const lo = [0, 1, 2].map((k) => view.getFloat64(24 + 8 * k, true));
  const hi = [0, 1, 2].map((k) => view.getFloat64(48 + 8 * k, true));
  const step = lo.map((l, k) => (hi[k] > l ? (hi[k] - l) / 65535 : 0));
  const q = new Uint16Array(buffer, CHUNK_HEADER, n * 3);
  let off = CHUNK_HEADER + n * 6;
  off += (4 - (off % 4)) % 4;
  const rec = new Uint32Array(buffer, off, n * 4);
  off += n * 16;
  const sh = deg >= 1 ? new Uint32Array(buffer, off, n * 4) : null;
  off += sh ? n * 16 : 0;
  const sh2 = deg >= 2 ? new Uint32Array(buffer, off, n * 4) : null;

  const spheres = new Float32Array(n * 4);
  const gpu = new Uint32Array(n * tps * 4);
  const gpuF = new Float32Array(gpu.buffer);
  for (let s = 0; s < n; s++) {
    const x = lo[0] + q[3 * s] * step[0], y = lo[1] + q[3 * s + 1] * step[1], z = lo[2] + q[3 * s + 2] * step[2];
    const scale = Math.max(half(rec[4 * s + 1] & 0xffff), half(rec[4 * s + 1] >>> 16));
    const opacity = ((rec[4 * s + 3] >>> 16) & 255) / 255;
    spheres[4 * s] = x; spheres[4 * s + 1] = y; spheres[4 * s + 2] = z;
    spheres[4 * s + 3] = Math.sqrt(Math.max(0, 2 * Math.log(255 * opacity))) * scale * 1.001;
    const g = s * tps * 4;
    gpuF[g] = x; gpuF[g + 1] = y; gpuF[g + 2] = z;
    gpu[g + 3] = rec[4 * s];
    gpu[g + 4] = rec[4 * s + 1]; gpu[g + 5] = rec[4 * s + 2]; gpu[g + 6] = rec[4 * s + 3];
    if (sh && tps >= 3) {
      gpu[g + 7] = sh[4 * s]; gpu[g + 8] = sh[4 * s + 1]; gpu[g + 9] = sh[4 * s + 2]; gpu[g + 10] = sh[4 * s + 3];
    }
    if (sh2 && tps >= 4) {
      gpu[g + 12] = sh2[4 * s]; gpu[g + 13] = sh2[4 * s + 1]; gpu[g + 14] = sh2[4 * s + 2]; gpu[g + 15] = sh2[4 * s + 3];
    }
  }
  return { i, j, n, deg, lo, hi, spheres, gpu };
}

// Latlong env map: RGBA half floats, top row first.
export function decodeEnv(buffer) {
  const view = new DataView(buffer);
  if (!magic(view, "LSDE")) throw new Error("not an LSDE env map");
  const width = view.getUint32(8, true), height = view.getUint32(12, true);
  return { width, height, texels: new Uint16Array(buffer, 16, width * height * 4) };
}

// Triangle mesh: f32 positions, u8 RGBA colours, u32 indices.
export function decodeMesh(buffer) {
  const view = new DataView(buffer);
  if (!magic(view, "LSDM")) throw new Error("not an LSDM mesh");
  const nv = view.getUint32(8, true), nt = view.getUint32(12, true);
  let off = 16;
  const positions = new Float32Array(buffer.slice(off, off + nv * 12)); off += nv * 12;
  const colors = new Uint8Array(buffer.slice(off, off + nv * 4)); off += nv * 4;
  const indices = new Uint32Array(buffer.slice(off, off + nt * 12));
  return { positions, colors, indices };
}
