"""GGDS's starting point: surfels seeded on the proxy mesh (splats.init), coloured by a function
the caller gives (generate: conditioning.light.colour_by_light, the scene's light on class
albedos), so the first renders already look like the scene and GGDS refines from there.

Surfels are made chunk by chunk and written to per-chunk files as soon as a chunk is complete
(splats.chunkio), so memory follows a few chunks, not the scene: a 10 km corridor initialises
in the memory of a 100 m one. The count of a chunk is ``density`` per m² of its proxy surface
weighted by nearness to the lanes (splats.importance), at most ``max_count`` per chunk; an
explicit total ``count`` is shared between chunks in proportion to the same weighted areas.
Surfels seeded on chunk K's proxy faces belong to the chunk holding their centre (a building
may overhang its chunk), so a chunk is written once every neighbour that can contribute to it
has been seeded.
"""
from __future__ import annotations

import os
import tempfile
from collections import OrderedDict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lsd3d_usd import safepaths
from lsd3d_usd.errors import InputError
from lsd3d_usd.proxy.usdio import proxy_arrays, read_chunk_map
from lsd3d_usd.scene import parse_chunk_prim_name
from lsd3d_usd.semantics import CLASSES
from lsd3d_usd.splats import chunkio
from lsd3d_usd.splats.field import SurfelField
from lsd3d_usd.splats.importance import face_weights
from lsd3d_usd.splats.init import mesh_to_surfels, split_faces

# Faces are split to at most this area (m²) before the density weights are evaluated, so the
# density follows the distance to the lanes within large proxy faces (terrain, road).
WEIGHT_FACE_AREA = 2.0


def _weighted_mesh(vertices, faces, layout):
    """(V', F', parent, weights) of the mesh split to WEIGHT_FACE_AREA with its density weights."""
    V, F, parent = split_faces(vertices, faces, WEIGHT_FACE_AREA)
    return V, F, parent, face_weights(V, F, layout)


def _chunk_seed(seed: int, key) -> int:
    return int(np.random.SeedSequence([int(seed), int(key[0]) & 0xFFFFFFFF,
                                       int(key[1]) & 0xFFFFFFFF]).generate_state(1)[0])


def _weighted_area(V: np.ndarray, F: np.ndarray, layout) -> tuple[np.ndarray, np.ndarray]:
    """(area, density weight) per face of the mesh split to WEIGHT_FACE_AREA."""
    Vs, Fs, _, w = _weighted_mesh(V, F, layout)
    area = 0.5 * np.linalg.norm(np.cross(Vs[Fs[:, 1]] - Vs[Fs[:, 0]], Vs[Fs[:, 2]] - Vs[Fs[:, 0]]),
                                axis=1)
    return area, w


def chunk_owners(positions: np.ndarray, seed_key, chunk_size: float, tol: float = 1e-3) -> dict:
    """{chunk: indices} of surfels seeded on chunk ``seed_key``'s proxy: the chunk holding each
    centre, except that centres within ``tol`` of the seed chunk stay in it (a float32 centre
    on the chunk's edge rounds across it; a true overhang is farther)."""
    p = np.asarray(positions, np.float64)
    lo = np.asarray(seed_key, np.float64) * chunk_size
    near = np.all((p[:, :2] >= lo - tol) & (p[:, :2] <= lo + chunk_size + tol), axis=1)
    out = {}
    if near.any():
        out[tuple(seed_key)] = np.flatnonzero(near)
    far = np.flatnonzero(~near)
    for target, idx in chunkio.split_by_chunk(p[far], chunk_size).items():
        if target in out:
            out[target] = np.sort(np.concatenate([out[target], far[idx]]))
        else:
            out[target] = far[idx]
    return out


class _ProxyCache:
    """Per-chunk proxy arrays, the last few kept (a chunk and its neighbours)."""

    def __init__(self, path, keys, size: int = 16):
        self.path, self.keys, self.size = path, set(keys), size
        self._cache: OrderedDict = OrderedDict()

    def get(self, key):
        if key not in self._cache:
            self._cache[key] = proxy_arrays(self.path, [key])
            if len(self._cache) > self.size:
                self._cache.popitem(last=False)
        self._cache.move_to_end(key)
        return self._cache[key]

    def neighbourhood(self, key):
        parts = [self.get((key[0] + di, key[1] + dj)) for di in (-1, 0, 1) for dj in (-1, 0, 1)
                 if (key[0] + di, key[1] + dj) in self.keys]
        V, F, base = [], [], 0
        for v, f, _ in parts:
            V.append(v)
            F.append(f + base)
            base += len(v)
        return np.concatenate(V), np.concatenate(F)


class Stash:
    """Surfel parts parked in a temporary folder inside ``parent`` (the scene's chunk
    folder), read back once and deleted."""

    NAMES = ("positions", "orientations", "scales", "opacities", "sh", "semantic_ids")

    def __init__(self, parent):
        Path(parent).mkdir(parents=True, exist_ok=True)
        self._dir = tempfile.TemporaryDirectory(prefix=".pending-", dir=parent)
        self._n = 0
        self._classes: dict = {}

    def put(self, field: SurfelField, src: np.ndarray, face: np.ndarray) -> str:
        self._n += 1
        path = os.path.join(self._dir.name, f"{self._n}.npz")
        np.savez(path, src=src, face=face, **{k: getattr(field, k) for k in self.NAMES
                                              if getattr(field, k) is not None})
        self._classes[path] = field.semantic_classes
        return path

    def take(self, path: str):
        with np.load(path, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        os.unlink(path)
        field = SurfelField(*(a.get(k) for k in self.NAMES), self._classes.pop(path))
        return field, a["src"], a["face"]

    def close(self) -> None:
        self._dir.cleanup()


def _counts(keys, cache, layout, count, density, max_count) -> tuple[dict, dict]:
    """Surfels per chunk, and the areas (for provenance)."""
    wareas, total_area = {}, 0.0
    for key in keys:
        V, F, _ = cache.get(key)
        area, w = _weighted_area(V, F, layout)
        wareas[key] = float((area * w).sum())
        total_area += float(area.sum())
    if count is None:
        counts = {k: int(min(max_count, round(density * a))) for k, a in wareas.items()}
    else:  # an explicit total, shared by weighted area (largest remainders)
        total = sum(wareas.values()) or 1.0
        exact = {k: count * a / total for k, a in wareas.items()}
        counts = {k: int(np.floor(v)) for k, v in exact.items()}
        rest = count - sum(counts.values())
        for k in sorted(exact, key=lambda k: exact[k] - counts[k], reverse=True)[:rest]:
            counts[k] += 1
        over = [k for k, c in counts.items() if c > max_count]
        if over:
            raise InputError(f"--surfels {count}: chunk {over[0]} would get {counts[over[0]]:,} "
                             f"surfels, above the per-chunk limit {max_count:,}")
    return counts, {"proxyArea_m2": round(total_area, 1),
                    "viewWeightedArea_m2": round(sum(wareas.values()), 1)}


def write_initial_surfels(proxy_path, layout, out_root, *, colour, count: int | None,
                          density: float, max_count: int, sh_degree: int = 1, seed: int = 0,
                          inputs_hash: str, provenance: dict | None = None,
                          progress: bool = False, preview_fraction: float = 0.0) -> dict:
    """Seed, colour and write the initial surfels of every proxy chunk to a new chunk folder
    named by ``inputs_hash``, then the surfel root layer ``out_root`` (splats.chunkio), then
    remove the folders of earlier versions. ``colour(field, vertices, faces)`` sets a chunk's
    surfel colours in place, given the proxy of its 3×3 neighbourhood (what can shadow it).
    ``preview_fraction`` > 0: each chunk file also holds a Points preview of that fraction of
    its surfels (splats.preview). Returns a summary."""

    # Chunk folders are written and pruned below: never through a planted link.
    safepaths.check_tree(chunkio.chunks_base(out_root), Path(out_root).absolute().parent,
                         "surfel chunk folder")
    keys = sorted(parse_chunk_prim_name(n) for n in read_chunk_map(proxy_path))
    cache = _ProxyCache(proxy_path, keys)
    counts, areas = _counts(keys, cache, layout, count, density, max_count)
    chunk_size = float(layout.chunk_size)
    folder = chunkio.chunks_base(out_root) / inputs_hash[:16]
    # Surfels waiting for a neighbour wait on disk: a grid sweeps a row of chunks (and more)
    # before the first is complete, and holding them cost ~0.1 GB per chunk in memory.
    stash = Stash(chunkio.chunks_base(out_root))
    pending: dict = {}           # target chunk -> [stashed (field, seed chunks, seed faces)]
    done_sources: set = set()
    infos: dict = {}
    written_total = 0

    def complete(target) -> bool:
        return all((target[0] + di, target[1] + dj) in done_sources or
                   (target[0] + di, target[1] + dj) not in counts
                   for di in (-1, 0, 1) for dj in (-1, 0, 1))

    def flush(target):
        nonlocal written_total
        parts = [stash.take(k) for k in pending.pop(target)]
        field = SurfelField.concat([p[0] for p in parts])
        chunks = np.concatenate([p[1] for p in parts])
        faces = np.concatenate([p[2] for p in parts])
        chunkio.write_chunk(folder, target, field, seed_faces=(chunks, faces),
                            preview_fraction=preview_fraction)
        infos[target] = chunkio.chunk_info(target, field, preview_fraction=preview_fraction)
        written_total += field.n

    try:
        for key in tqdm(keys, desc="surfels", unit="chunk", disable=not progress):
            V, F, ids = cache.get(key)
            n = counts[key]
            if n > 0:
                Vs, Fs, parent, weights = _weighted_mesh(V, F, layout)
                field, face = mesh_to_surfels(Vs, Fs, np.asarray(ids)[parent], count=n,
                                              seed=_chunk_seed(seed, key), sh_degree=sh_degree,
                                              semantic_classes=CLASSES, return_face_index=True,
                                              face_weights=weights, max_count=max_count)
                face = parent[face]
                NV, NF = cache.neighbourhood(key)
                colour(field, NV, NF)
                for target, idx in chunk_owners(field.positions, key, chunk_size).items():
                    src = np.tile(np.asarray(key, np.int32), (len(idx), 1))
                    pending.setdefault(target, []).append(
                        stash.put(field.subset(idx), src, face[idx]))
                del field, face
            done_sources.add(key)
            for target in [t for t in pending if complete(t)]:
                flush(target)
        for target in list(pending):
            flush(target)
    finally:
        stash.close()   # also after an error: nothing parked is left behind
    chunkio.write_root(out_root, folder, infos, {**(provenance or {}), "inputsHash": inputs_hash,
                                                 "previewFraction": float(preview_fraction)})
    chunkio.prune_chunk_folders(out_root)
    return {"count": int(written_total), "chunks": len(infos), **areas,
            "preview": int(sum(v.get("preview", 0) for v in infos.values()))}
