"""Bird's-eye views of a drive: `BirdsEye.frame` (the env's ``render()``, an RGB array centred
on the ego) and `episode_png` (a whole episode: route, ego path, agents, infractions).

The static map (drivable area, buildings, lanes) is rasterised once per scene at a fixed
scale; a frame is a crop of it around the ego with the agents drawn on top.
"""
from __future__ import annotations

import math

import numpy as np
from PIL import Image, ImageDraw

from lsd3d_usd.sim.geometry2d import box_corners

PX_PER_M = 4.0
VIEW_M = 80.0                  # the frame's side in metres
MAX_MAP_PX = 8192              # the static map's longer side at most (large scenes: coarser)
COLOURS = {"vehicle": (40, 110, 220), "cyclist": (240, 160, 20), "pedestrian": (230, 40, 160)}
SIGNAL_COLOURS = {"green": (30, 200, 60), "yellow": (250, 200, 0), "red": (160, 0, 60)}   # not the ego's red
STOP_BAR_M = (3.0, 1.2)        # a signal's stop bar across its lane: width, depth (m)


class BirdsEye:
    def __init__(self, scene, size_px: int = 320):
        self.size = int(size_px)
        (x0, y0), (x1, y1) = scene.layout.bounds()
        pad = VIEW_M
        self.x0, self.y0 = x0 - pad, y0 - pad
        span = max(x1 - x0, y1 - y0) + 2 * pad
        self.ppm = min(PX_PER_M, MAX_MAP_PX / span)
        w = int(math.ceil((x1 - x0 + 2 * pad) * self.ppm))
        h = int(math.ceil((y1 - y0 + 2 * pad) * self.ppm))
        self.h = h
        img = Image.new("RGB", (w, h), (238, 236, 228))
        d = ImageDraw.Draw(img)
        for poly in _polygons(scene.drivable):
            d.polygon([self._px(p) for p in np.asarray(poly.exterior.coords)], fill=(120, 120, 124))
            for hole in poly.interiors:
                d.polygon([self._px(p) for p in np.asarray(hole.coords)], fill=(238, 236, 228))
        for b in scene.layout.buildings:
            d.polygon([self._px(p) for p in np.asarray(b.footprint)[:, :2]], fill=(196, 180, 160))
        for g in scene.graph.geoms:
            if len(g.points) >= 2:
                d.line([self._px(p) for p in g.points[:, :2]], fill=(170, 170, 176), width=1)
        self.map = img

    def _px(self, p) -> tuple[float, float]:
        return ((float(p[0]) - self.x0) * self.ppm, self.h - (float(p[1]) - self.y0) * self.ppm)

    def frame(self, ego, limits, agents, route, signals=()) -> np.ndarray:
        """(size, size, 3) uint8: the map around the ego (north up), route, agents, ego;
        ``signals``: (x, y, heading, state) of each controlled lane's stop point, drawn as a
        bar across the lane in the state's colour."""
        cx, cy = self._px(ego.box_centre(limits))
        half = VIEW_M * self.ppm / 2
        crop = self.map.crop((int(cx - half), int(cy - half), int(cx + half), int(cy + half)))
        crop = crop.copy()
        d = ImageDraw.Draw(crop)
        off = (int(cx - half), int(cy - half))

        def px(p):
            x, y = self._px(p)
            return (x - off[0], y - off[1])
        pts, _ = route.polyline()
        d.line([px(p) for p in pts[:, :2]], fill=(40, 190, 90), width=2)
        if len(signals):
            xy = np.array([[x, y] for x, y, _, _ in signals], np.float64)
            bars = box_corners(xy, np.array([h for _, _, h, _ in signals], np.float64),
                               np.full(len(xy), STOP_BAR_M[1]), np.full(len(xy), STOP_BAR_M[0]))
            for k, (*_, state) in enumerate(signals):
                d.polygon([px(p) for p in bars[k]], fill=SIGNAL_COLOURS.get(state, (90, 90, 90)),
                          outline=(20, 20, 20))
        corners = box_corners(agents.xy, agents.yaw, agents.length, agents.width)
        for k, kind in enumerate(agents.kind):
            d.polygon([px(p) for p in corners[k]], fill=COLOURS.get(kind, (90, 90, 90)))
        ec = box_corners(ego.box_centre(limits)[None], np.array([ego.yaw]), np.array([limits.length]),
                         np.array([limits.width]))[0]
        d.polygon([px(p) for p in ec], fill=(220, 30, 30))
        d.line([px(ec[0]), px(ec[1])], fill=(255, 255, 255), width=2)     # its front edge
        return np.asarray(crop.resize((self.size, self.size), Image.BILINEAR), np.uint8)


def _polygons(geom):
    if geom is None or geom.is_empty:
        return []
    return list(getattr(geom, "geoms", [geom]))
