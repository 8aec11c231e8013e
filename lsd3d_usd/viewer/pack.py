"""Compact binary buffers the browser viewer downloads: surfel chunks, env maps, proxy meshes.

docs/viewer.md documents every byte; the browser decodes them in static/js/formats.js, and
`decode_chunk` here is the same decoding in numpy (the tests hold the two together through
rendered images). All little-endian.

Surfel chunk (``LSDV`` version 2): a 96-byte header, then per surfel 6 + 16 (+ 16 with SH
degree 1, + 32 with degree 2) bytes:

    header   magic "LSDV", u16 version, u8 shDegree (0|1|2), u8 flags (bit 0: semantic ids),
             u32 n, i32 i, i32 j, u32 0, f64[3] lo, f64[3] hi, 24 bytes 0
    pos      n x u16[3]: lo + q / 65535 * (hi - lo)   (padded to 4 bytes)
    rec      n x u32[4]: quaternion (smallest three: 2-bit index + 3 x 10 bits, 511 = 0), f16 scale u | f16 scale v,
             f16 dc r | f16 dc g, f16 dc b | u8 opacity * 255 | u8 semantic id + 1 (0 = none)
    sh1      (shDegree >= 1) n x u32[4]: f16 m1 | 9 x i8 (c / m1 * 127, order band-1 coefficient
             then RGB) | f16 m2 | first 3 band-2 i8 (shDegree 2; else 5 bytes 0)
    sh2      (shDegree 2) n x u32[4]: the other 12 band-2 i8 (c / m2 * 127, order band-2
             coefficient then RGB) | 4 bytes 0

m1, m2 are the largest |coefficient| of band 1, 2, rounded up to f16. Coefficients of bands
above 2 are not sent: the viewer shades with SH degree 0, 1 or 2. Version 1 was the same
layout restricted to degree 0/1 (its 5 spare bytes 0); decode_chunk reads both.
"""
from __future__ import annotations

import struct

import numpy as np

CHUNK_MAGIC = b"LSDV"
CHUNK_VERSION = 2
CHUNK_VERSIONS_READ = (1, 2)      # version 1: degree 0/1 only, same layout
MAX_SH_DEGREE = 2                 # bands above are not sent
CHUNK_HEADER = struct.Struct("<4sHBBIiiI3d3d24x")
assert CHUNK_HEADER.size == 96
ENV_MAGIC = b"LSDE"
ENV_HEADER = struct.Struct("<4sHHII")        # magic, version, 0, width, height (16 bytes)
MESH_MAGIC = b"LSDM"
MESH_HEADER = struct.Struct("<4sHHII")       # magic, version, 0, vertices, triangles
MAX_ENV_WIDTH = 2048
_SQRT2 = np.sqrt(2.0)


# ----------------------------------------------------------------------------- binning
def chunk_keys(positions: np.ndarray, size: float) -> np.ndarray:
    """(N,2) int64 chunk indices (i, j) = floor(x / size), floor(y / size): the scene's grid."""
    return np.floor(np.asarray(positions, np.float64)[:, :2] / size).astype(np.int64)


def bin_by_chunk(positions: np.ndarray, size: float) -> dict[tuple[int, int], np.ndarray]:
    """Chunk key -> indices (ascending) of the surfels whose centre lies in it."""
    keys = chunk_keys(positions, size)
    if not len(keys):
        return {}
    lo = keys.min(0)
    flat = (keys[:, 0] - lo[0]) * (int(keys[:, 1].max() - lo[1]) + 1) + (keys[:, 1] - lo[1])
    order = np.argsort(flat, kind="stable")
    starts = np.flatnonzero(np.diff(flat[order])) + 1
    return {(int(keys[g[0], 0]), int(keys[g[0], 1])): g
            for g in np.split(order, starts)}


# ------------------------------------------------------------------------------ quats
def encode_quats(q: np.ndarray) -> np.ndarray:
    """(N,4) xyzw -> (N,) u32: index of the largest |component| in bits 0-1, the other three in
    xyzw order (signs flipped so the largest is positive; each then lies in [-1/sqrt2, 1/sqrt2])
    in bits 2-11, 12-21, 22-31 as k = 511 + round(511 sqrt2 c), so 0 is exact."""
    q = np.asarray(q, np.float64).reshape(-1, 4)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    rows = np.arange(len(q))
    big = np.argmax(np.abs(q), axis=1)
    q = q * np.where(q[rows, big] < 0, -1.0, 1.0)[:, None]
    keep = np.ones(q.shape, bool)
    keep[rows, big] = False
    others = q[keep].reshape(-1, 3)
    v = (np.clip(np.round(others * _SQRT2 * 511.0), -511, 511) + 511).astype(np.uint32)
    return big.astype(np.uint32) | (v[:, 0] << 2) | (v[:, 1] << 12) | (v[:, 2] << 22)


def decode_quats(word: np.ndarray) -> np.ndarray:
    word = np.asarray(word, np.uint32).reshape(-1)
    rows = np.arange(len(word))
    big = (word & 3).astype(np.int64)
    vals = np.stack([((word >> np.uint32(s)) & 1023).astype(np.float64) for s in (2, 12, 22)], 1)
    vals = (vals - 511.0) / 511.0 / _SQRT2
    q = np.zeros((len(word), 4))
    keep = np.ones(q.shape, bool)
    keep[rows, big] = False
    q[keep] = vals.reshape(-1)
    q[rows, big] = np.sqrt(np.clip(1.0 - (vals * vals).sum(1), 0.0, None))
    return q


# ------------------------------------------------------------------------------ chunks
def _quantise_band(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One SH band (N,K,3) as (N,) little-endian f16 m = max |c| rounded up and (N,3K) i8
    round(127 c / m), coefficient then RGB (all 0 where m = 0)."""
    n, k = c.shape[0], c.shape[1] * c.shape[2]
    c = c.reshape(n, k).astype(np.float64)
    m = np.abs(c).max(1) if n else np.zeros(0)
    m16 = m.astype(np.float16)
    m16 = np.where(m16.astype(np.float64) < m, np.nextafter(m16, np.float16(np.inf)), m16)
    mf = m16.astype(np.float64)
    q = np.where(mf[:, None] > 0, np.round(c / np.where(mf > 0, mf, 1.0)[:, None] * 127.0), 0)
    return m16.astype("<f2"), np.clip(q, -127, 127).astype(np.int8)


def pack_chunk(key: tuple[int, int], positions, orientations, scales, opacities, sh,
               semantic_ids=None) -> bytes:
    """One chunk's surfels (world space) as an ``LSDV`` buffer (see the module doc)."""
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    n = len(p)
    sh = np.asarray(sh, np.float32)
    sh = sh.reshape(n, sh.shape[1] if sh.ndim == 3 else sh.size // max(3 * n, 1), 3)
    deg = 2 if sh.shape[1] >= 9 else 1 if sh.shape[1] >= 4 else 0   # bands above 2 not sent
    lo = p.min(0) if n else np.zeros(3)
    hi = p.max(0) if n else np.zeros(3)
    span = np.where(hi > lo, hi - lo, 1.0)
    qpos = np.clip(np.round((p - lo) / span * 65535.0), 0, 65535).astype("<u2")
    pos_bytes = qpos.tobytes()
    pos_bytes += b"\0" * (-len(pos_bytes) % 4)

    rec = np.zeros((n, 4), "<u4")
    rec[:, 0] = encode_quats(np.asarray(orientations).reshape(n, 4))
    s16 = np.clip(np.asarray(scales, np.float64).reshape(n, 2), 0.0, 65504.0).astype("<f2").view("<u2")
    rec[:, 1] = s16[:, 0].astype(np.uint32) | (s16[:, 1].astype(np.uint32) << 16)
    dc = np.clip(sh[:, 0, :].astype(np.float64), -65504.0, 65504.0).astype("<f2").view("<u2").astype(np.uint32)
    rec[:, 2] = dc[:, 0] | (dc[:, 1] << 16)
    op = np.clip(np.round(np.clip(np.asarray(opacities, np.float64).reshape(n), 0.0, 1.0) * 255.0), 0, 255)
    sem = np.zeros(n, np.uint32)
    flags = 0
    if semantic_ids is not None:
        ids = np.asarray(semantic_ids).reshape(n)
        sem = np.where((ids >= 0) & (ids < 255), ids + 1, 0).astype(np.uint32)
        flags |= 1
    rec[:, 3] = dc[:, 2] | (op.astype(np.uint32) << 16) | (sem << 24)
    body = [pos_bytes, rec.tobytes()]
    if deg >= 1:
        m1, q1 = _quantise_band(sh[:, 1:4])
        b = np.zeros((n, 16), np.uint8)
        b[:, 0:2] = m1.view(np.uint8).reshape(n, 2)
        b[:, 2:11] = q1.view(np.uint8)
        body.append(b)
    if deg >= 2:
        m2, q2 = _quantise_band(sh[:, 4:9])
        b[:, 11:13] = m2.view(np.uint8).reshape(n, 2)     # the sh1 block's spare bytes
        b[:, 13:16] = q2[:, :3].view(np.uint8)
        b2 = np.zeros((n, 16), np.uint8)
        b2[:, 0:12] = q2[:, 3:].view(np.uint8)
        body.append(b2)
    head = CHUNK_HEADER.pack(CHUNK_MAGIC, CHUNK_VERSION, deg, flags, n, int(key[0]), int(key[1]), 0,
                             *lo.tolist(), *hi.tolist())
    return head + b"".join(x if isinstance(x, bytes) else x.tobytes() for x in body)


def decode_chunk(buf: bytes) -> dict:
    """An ``LSDV`` buffer back to arrays: positions (N,3) f64, orientations (N,4) xyzw, scales
    (N,2), opacities (N,), sh (N,1|4|9,3), semantic_ids (N,) (-1 none), key, sh_degree."""
    magic, ver, deg, flags, n, i, j, _, *box = CHUNK_HEADER.unpack_from(buf, 0)
    if magic != CHUNK_MAGIC or ver not in CHUNK_VERSIONS_READ:
        raise ValueError(f"not an LSDV v{CHUNK_VERSION} chunk buffer")
    if deg > (1 if ver == 1 else 2):
        raise ValueError(f"LSDV v{ver} chunk buffer with SH degree {deg}")
    lo, hi = np.array(box[:3]), np.array(box[3:])
    off = CHUNK_HEADER.size
    q = np.frombuffer(buf, "<u2", n * 3, off).reshape(n, 3).astype(np.float64)
    off += n * 6 + (-(n * 6) % 4)
    span = np.where(hi > lo, hi - lo, 1.0)
    pos = lo + q / 65535.0 * span
    rec = np.frombuffer(buf, "<u4", n * 4, off).reshape(n, 4)
    off += n * 16

    def half(words, shift):
        return ((words >> shift) & 0xFFFF).astype("<u2").view("<f2").astype(np.float64)

    quats = decode_quats(rec[:, 0])
    scales = np.stack([half(rec[:, 1], 0), half(rec[:, 1], 16)], 1)
    dc = np.stack([half(rec[:, 2], 0), half(rec[:, 2], 16), half(rec[:, 3], 0)], 1)
    opac = ((rec[:, 3] >> 16) & 255).astype(np.float64) / 255.0
    sem = ((rec[:, 3] >> 24) & 255).astype(np.int64) - 1
    sh = dc[:, None, :]
    if deg >= 1:
        b = np.frombuffer(buf, np.uint8, n * 16, off).reshape(n, 16)
        off += n * 16
        m = b[:, 0:2].copy().view("<f2").astype(np.float64).reshape(n)
        c = b[:, 2:11].copy().view(np.int8).astype(np.float64) / 127.0 * m[:, None]
        sh = np.concatenate([sh, c.reshape(n, 3, 3)], axis=1)
    if deg >= 2:
        b2 = np.frombuffer(buf, np.uint8, n * 16, off).reshape(n, 16)
        m = b[:, 11:13].copy().view("<f2").astype(np.float64).reshape(n)
        q = np.concatenate([b[:, 13:16], b2[:, 0:12]], axis=1).view(np.int8)
        c = q.astype(np.float64) / 127.0 * m[:, None]
        sh = np.concatenate([sh, c.reshape(n, 5, 3)], axis=1)
    return dict(key=(i, j), sh_degree=deg, positions=pos, orientations=quats, scales=scales,
                opacities=opac, sh=sh, semantic_ids=sem if flags & 1 else None)


# -------------------------------------------------------------------------------- env
def pack_env(image: np.ndarray) -> bytes:
    """A latlong map (h, w, 3) scene-linear as ``LSDE``: 16-byte header, then RGBA float16
    rows top (zenith) first. Maps wider than MAX_ENV_WIDTH are box-filtered down by 2x steps."""
    img = np.asarray(image, np.float64)
    while img.shape[1] > MAX_ENV_WIDTH and img.shape[0] % 2 == 0 and img.shape[1] % 2 == 0:
        img = 0.25 * (img[0::2, 0::2] + img[1::2, 0::2] + img[0::2, 1::2] + img[1::2, 1::2])
    h, w = img.shape[:2]
    rgba = np.ones((h, w, 4), np.float64)
    rgba[..., :3] = np.clip(np.nan_to_num(img[..., :3], nan=0.0, posinf=65504.0), 0.0, 65504.0)
    return ENV_HEADER.pack(ENV_MAGIC, 1, 0, w, h) + rgba.astype("<f2").tobytes()


# ------------------------------------------------------------------------------- mesh
def pack_mesh(parts) -> bytes:
    """Triangle meshes [(vertices (V,3), faces (F,3), rgb (3,) or (V,3))] as one ``LSDM``:
    16-byte header, f32 positions (V,3), u8 RGBA colours (V,4, linear x 255), u32 indices."""
    vs, cs, fs = [], [], []
    base = 0
    for v, f, rgb in parts:
        v = np.asarray(v, np.float64).reshape(-1, 3)
        f = np.asarray(f, np.int64).reshape(-1, 3)
        c = np.broadcast_to(np.asarray(rgb, np.float64).reshape(-1, 3), (len(v), 3))
        vs.append(v)
        cs.append(c)
        fs.append(f + base)
        base += len(v)
    V = np.concatenate(vs) if vs else np.zeros((0, 3))
    C = np.concatenate(cs) if cs else np.zeros((0, 3))
    F = np.concatenate(fs) if fs else np.zeros((0, 3), np.int64)
    col = np.ones((len(V), 4), np.uint8) * 255
    col[:, :3] = np.clip(np.round(C * 255.0), 0, 255).astype(np.uint8)
    return (MESH_HEADER.pack(MESH_MAGIC, 1, 0, len(V), len(F)) + V.astype("<f4").tobytes()
            + col.tobytes() + F.astype("<u4").tobytes())
