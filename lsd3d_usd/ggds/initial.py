"""GGDS's starting point: surfels seeded on the proxy mesh (splats.init) and coloured by the
scene's light — class albedo times sky irradiance plus the sun where the proxy does not shadow
it — so the first renders already look like the scene and GGDS refines from there."""
from __future__ import annotations

import numpy as np

from lsd3d_usd.splats.field import SurfelField

# Faces are split to at most this area (m²) before the density weights are evaluated, so the
# density follows the distance to the lanes within large proxy faces (terrain, road).
WEIGHT_FACE_AREA = 2.0


def _weighted_mesh(vertices, faces, layout):
    """(V', F', parent, weights) of the mesh split to WEIGHT_FACE_AREA with its density weights."""
    from lsd3d_usd.splats.importance import face_weights
    from lsd3d_usd.splats.init import split_faces
    V, F, parent = split_faces(vertices, faces, WEIGHT_FACE_AREA)
    return V, F, parent, face_weights(V, F, layout)


def surfel_count(vertices: np.ndarray, faces: np.ndarray, layout, *, density: float,
                 max_count: int, minimum: int = 1000, weighted_mesh=None) -> tuple[int, dict]:
    """Default count: ``density`` per m² of proxy surface weighted by nearness to the lanes
    (splats.importance), clamped to [minimum, max_count]. Returns (count, areas)."""
    V, F, _, w = weighted_mesh or _weighted_mesh(vertices, faces, layout)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    weighted = float((area * w).sum())
    count = int(min(max_count, max(minimum, density * weighted)))
    return count, {"proxyArea_m2": round(float(area.sum()), 1),
                   "viewWeightedArea_m2": round(weighted, 1)}


def initial_surfels(proxy, layout, light, *, count: int | None, density: float, max_count: int,
                    sh_degree: int = 1, seed: int = 0) -> tuple[SurfelField, np.ndarray, dict]:
    """(field, seed face index per surfel, info) for proxy arrays (V, F, face class ids)."""
    from lsd3d_usd.ggds.conditioning import shadow_map
    from lsd3d_usd.semantics import CLASS_COLORS, CLASSES
    from lsd3d_usd.splats.field import rgb_to_sh_dc
    from lsd3d_usd.splats.init import mesh_to_surfels
    V, F, ids = proxy
    wm = _weighted_mesh(V, F, layout)
    default, info = surfel_count(V, F, layout, density=density, max_count=max_count,
                                 weighted_mesh=wm)
    n = int(count or default)
    Vs, Fs, parent, w = wm
    field, face = mesh_to_surfels(Vs, Fs, np.asarray(ids)[parent], count=n, seed=seed,
                                  sh_degree=sh_degree, semantic_classes=CLASSES,
                                  return_face_index=True, face_weights=w)
    face = parent[face]
    shadow = shadow_map(V, F, light.sun_direction)
    vis = shadow.visibility(field.positions.astype(np.float64) + 0.05 * field.normals()) \
        if shadow is not None else None
    albedo = CLASS_COLORS[np.clip(field.semantic_ids, 0, None)]
    rgb = np.clip(albedo * light.irradiance(field.normals(), vis), 0.0, 4.0)
    field.sh[:, 0, :] = rgb_to_sh_dc(rgb)
    return field, face, {"count": n, **info}
