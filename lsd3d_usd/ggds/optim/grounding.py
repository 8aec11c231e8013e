"""Geometry grounding of flat classes: surfels whose class is the map's ground (road, lane
marking, crosswalk, sidewalk, curb by default; ``GGDSConfig.ground_classes``) are held on
the plane of the proxy face they were seeded on, facing its normal.

The proxy of those classes is the map itself — a road is where the layout says, flat — so
GGDS has nothing to learn about their geometry, while its image terms, seen at grazing
angles, move them a few millimetres and tilt them by a degree or two; a LiDAR beam or a
depth pixel at a grazing angle turns that into centimetres. After each update the moved
rows are projected back: the position onto its plane along the normal (the in-plane
position stays free, so the MCMC noise and relocation still spread surfels over the face),
the orientation by the smallest rotation that brings its normal back onto the plane's
(the in-plane rotation and the scales stay free). Relocation copies a source's plane with
its parameters.
"""
from __future__ import annotations

import numpy as np
import torch

from lsd3d_usd.render.projection import quat_to_rotmat


def _quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of (N,4) xyzw quaternions, a ⊗ b (rotation b, then a)."""
    ax, ay, az, aw = a.unbind(1)
    bx, by, bz, bw = b.unbind(1)
    return torch.stack([aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw,
                        aw * bw - ax * bx - ay * by - az * bz], dim=1)


def class_mask(semantic_ids, semantic_classes, names: str) -> np.ndarray:
    """(N,) bool: rows whose class (a name of ``semantic_classes`` indexed by the row's id)
    is one of the comma-separated ``names``."""
    wanted = {n for n in names.split(",") if n}
    if semantic_ids is None or not wanted:
        return np.zeros(0 if semantic_ids is None else len(semantic_ids), bool)
    table = np.array([str(c) in wanted for c in semantic_classes] + [False])
    ids = np.asarray(semantic_ids, np.int64)
    return table[np.where((ids >= 0) & (ids < len(table) - 1), ids, len(table) - 1)]


class Grounding:
    """The planes of the grounded rows: ``rows`` (M,) int64 indices into the run's surfels,
    ``point`` / ``normal`` (M,3) float32 (the surfel's initial centre and unit normal: it
    was seeded on its face, facing it). ``slot`` maps a surfel row to its plane (-1: free)."""

    def __init__(self, means: torch.Tensor, quats: torch.Tensor, mask: np.ndarray):
        self.slot = torch.full((len(means),), -1, dtype=torch.int64)
        rows = torch.from_numpy(np.flatnonzero(mask).astype(np.int64))
        self.slot[rows] = torch.arange(len(rows))
        with torch.no_grad():
            self.point = means[rows].detach().clone()
            self.normal = quat_to_rotmat(quats[rows].detach())[..., 2].contiguous()

    @classmethod
    def of(cls, params: dict, semantic_ids, semantic_classes, names: str):
        """A grounding of ``params``' rows of the classes ``names``; None when none is."""
        mask = class_mask(semantic_ids, semantic_classes, names)
        if not mask.any():
            return None
        return cls(params["means"], params["quats"], mask)

    @property
    def count(self) -> int:
        return int((self.slot >= 0).sum())

    @torch.no_grad()
    def project(self, params: dict, rows: torch.Tensor | None = None) -> int:
        """Put ``rows`` (default: all) of the grounded surfels back on their planes, in
        place; returns how many were grounded."""
        rows = torch.arange(len(self.slot)) if rows is None else rows.to(torch.int64)
        slot = self.slot[rows]
        keep = slot >= 0
        r, s = rows[keep], slot[keep]
        if r.numel() == 0:
            return 0
        n = self.normal[s]
        m = params["means"][r]
        params["means"][r] = m - ((m - self.point[s]) * n).sum(1, keepdim=True) * n
        q = params["quats"][r]
        norm = q.norm(dim=1, keepdim=True).clamp_min(1e-12)
        cur = quat_to_rotmat(q)[..., 2]
        # the plane's normal on the surfel's side (a disk has two faces: keep the one it shows)
        tgt = torch.where(((cur * n).sum(1, keepdim=True) < 0), -n, n)
        dot = (cur * tgt).sum(1, keepdim=True)
        align = torch.cat([torch.linalg.cross(cur, tgt), 1.0 + dot], dim=1)
        ok = dot[:, 0] > -0.999999   # antiparallel cannot happen after the side choice
        align = align / align.norm(dim=1, keepdim=True).clamp_min(1e-12)
        new = _quat_mul(align, q / norm)
        params["quats"][r] = torch.where(ok[:, None], new / new.norm(dim=1, keepdim=True), q / norm) * norm
        return int(r.numel())

    def relocated(self, dead: torch.Tensor, src: torch.Tensor) -> None:
        """Relocated rows take their source's plane (or become free with a free source)."""
        dead, src = dead.to(torch.int64), src.to(torch.int64)
        s = self.slot[src]
        # a dead row that had a plane keeps its slot (overwritten with the source's plane);
        # a row that had none and lands on a grounded source gets a new slot
        need = (self.slot[dead] < 0) & (s >= 0)
        if need.any():
            k = int(need.sum())
            base = len(self.point)
            self.point = torch.cat([self.point, torch.zeros(k, 3)])
            self.normal = torch.cat([self.normal, torch.zeros(k, 3)])
            self.slot[dead[need]] = torch.arange(base, base + k)
        has = s >= 0
        d_slot = self.slot[dead[has]]
        self.point[d_slot] = self.point[s[has]]
        self.normal[d_slot] = self.normal[s[has]]
        self.slot[dead[~has]] = -1

    def state_tensors(self) -> dict:
        return {"ground.slot": self.slot.contiguous(), "ground.point": self.point.contiguous(),
                "ground.normal": self.normal.contiguous()}

    def load_state_tensors(self, tensors: dict) -> None:
        if "ground.slot" in tensors:
            self.slot = tensors["ground.slot"].clone()
            self.point = tensors["ground.point"].clone()
            self.normal = tensors["ground.normal"].clone()
