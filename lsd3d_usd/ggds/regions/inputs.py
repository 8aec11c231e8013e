"""What a region task reads of the scene: the proxy of its 3×3 neighbourhood, its initial
surfels with their seed faces, and the frozen band of its neighbours' surfels."""
from __future__ import annotations

import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.regions.plan import Region
from lsd3d_usd.ggds.run.store import run_layer_path
from lsd3d_usd.proxy.usdio import proxy_arrays, read_chunk_map
from lsd3d_usd.splats import chunkio
from lsd3d_usd.splats.field import SurfelField


def proxy_neighbourhood(proxy_path, keys):
    """Proxy arrays of ``keys`` (those that exist) concatenated, and each chunk's face offset."""
    have = {S.parse_chunk_prim_name(n) for n in read_chunk_map(proxy_path)}
    V, F, ids, offsets, vb, fb = [], [], [], {}, 0, 0
    for key in sorted(k for k in keys if k in have):
        v, f, c = proxy_arrays(proxy_path, [key])
        offsets[key] = fb
        V.append(v)
        F.append(f + vb)
        ids.append(c)
        vb += len(v)
        fb += len(f)
    if not F:
        raise InputError(f"{proxy_path}: no proxy geometry around chunks {sorted(keys)}")
    return (np.concatenate(V), np.concatenate(F), np.concatenate(ids)), offsets


def region_surfels(sc: S.Scene, region: Region, offsets: dict):
    """The region's initial surfels (chunks in order), their owner ranges, and their seed
    faces as indices into the neighbourhood's proxy arrays (-1 where unknown)."""
    root = sc.layer_path("surfels")
    have = chunkio.read_chunk_map(root)
    fields, owners, faces, n = [], [], [], 0
    for key in region.keys:
        if key not in have:
            continue
        f = chunkio.read_chunk(root, key)
        seed = chunkio.read_seed_faces(root, key)
        if seed is None:
            face = np.full(f.n, -1, np.int64)
        else:
            chunks, local = seed
            base = np.array([offsets.get((int(a), int(b)), -1) for a, b in chunks], np.int64)
            face = np.where(base >= 0, base + local, -1)
        fields.append(f)
        faces.append(face)
        owners.append((key, n, n + f.n))
        n += f.n
    if not fields:
        return None, [], None
    return SurfelField.concat(fields), owners, np.concatenate(faces)


def region_context(sc: S.Scene, run: str, region: Region, finished: set, band_m: float,
                   chunk_size: float):
    """(frozen surfels of the neighbours within ``band_m`` of the region: this run's result
    for finished neighbours, the initial surfels otherwise; (n,) bool: which rows are
    initial), or None when there are none."""
    if band_m <= 0:
        return None
    root = sc.layer_path("surfels")
    have = chunkio.read_chunk_map(root)
    x0, y0, x1, y1 = region.bounds(chunk_size)
    parts, initial = [], []
    for key in sorted(region.neighbourhood() - set(region.keys)):
        if key not in have:
            continue
        runs = [run_layer_path(sc, run)] if key in finished else []
        f = chunkio.read_chunk(root, key, runs)
        p = f.positions
        near = ((p[:, 0] >= x0 - band_m) & (p[:, 0] <= x1 + band_m) &
                (p[:, 1] >= y0 - band_m) & (p[:, 1] <= y1 + band_m))
        if near.any():
            parts.append(f.subset(np.flatnonzero(near)))
            initial.append(np.full(parts[-1].n, key not in finished))
    if not parts:
        return None
    return SurfelField.concat(parts, drop_mismatched_semantics=True), np.concatenate(initial)
