"""Chunk-wise GGDS: a scene of any extent optimised region by region, each region conditioned
on its neighbours (the paper's chunk-wise outpainting, p(V_e | M_e, V_{e-1}), carried through
surfels and GGDS).

A region is a set of chunks optimised together: the whole scene when it is small (mode
"auto" with at most ``max_scene_chunks`` chunks: as fast and at least as good), else one chunk.
A region trains its own surfels and renders, frozen, its neighbours' surfels within ``band_m``
of it — the neighbour's optimised surfels when the neighbour has finished in this run, its
initial ones otherwise — so views near a border see a complete scene and the new chunk
continues its finished neighbours. Its views lie on the lanes inside it (``views_per_chunk``
per chunk), its proxy G-buffers come from the 3×3 proxy neighbourhood, and image losses
compare only pixels whose proxy surface lies within the loaded surfels. So the views,
surfels and memory of a region do not depend on the size of the scene.

Regions run in phases: the chunks of one phase share no overlap band (2×2 parity classes of
the grid; two phases along a corridor), so a phase's regions run in parallel (a local process
pool or Ray, lsd3d_usd.execution) and each region runs after the neighbours it conditions on.
A region task is idempotent and resumable (its checkpoint), so a killed run resumes with
finished regions untouched. The driver holds no surfel arrays.
"""
