"""The drivable area of a layout as a nuScenes map mask: a PNG at 0.1 m per pixel (nuScenes'
native mask resolution), 255 on the drivable surface, 0 elsewhere, its bottom-left pixel
corner at the global frame's origin (the devkit's MapMask maps global (x, y) to column x / 0.1,
row height - y / 0.1). The drivable surface is the proxy's road area (proxy.ground: lane
ribbons and road areas, the union the proxy builds its road mesh from), so the mask and the
road in the images agree.

The dataset's global frame is the scene's world shifted so the layout's south-west corner,
less MARGIN_M, is the origin (nuScenes' global coordinates are positive over the map).
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from lsd3d_usd import scene as S

RESOLUTION = 0.1
MARGIN_M = 20.0
MAX_PIXELS = 400_000_000     # 40 km^2 at 0.1 m; larger layouts get a coarser mask


def map_frame(layout) -> tuple[np.ndarray, tuple[float, float]]:
    """(world position of the global origin (3,), (width m, height m) of the map)."""
    (x0, y0), (x1, y1) = layout.area_box()
    return (np.array([x0 - MARGIN_M, y0 - MARGIN_M, 0.0]),
            (x1 - x0 + 2 * MARGIN_M, y1 - y0 + 2 * MARGIN_M))


def drivable_area(layout):
    """The road area of the layout (a shapely geometry, world XY)."""
    from lsd3d_usd.proxy.ground import ground_areas
    from lsd3d_usd.proxy.mesh import ROAD
    (x0, y0), (x1, y1) = layout.area_box()
    areas = ground_areas((x0, y0, x1, y1), 0.0,
                         lanes=[(ln.points, ln.widths, ln.lane_type) for ln in layout.lanes],
                         road_areas=[r.polygon for r in layout.road_areas])
    return areas[ROAD]


def mask_image(layout) -> tuple[np.ndarray, np.ndarray]:
    """((H, W) uint8 mask, world position of the global origin)."""
    from PIL import Image, ImageDraw

    from lsd3d_usd.proxy.planar import polygons_of
    origin, (w_m, h_m) = map_frame(layout)
    W, H = int(np.ceil(w_m / RESOLUTION)), int(np.ceil(h_m / RESOLUTION))
    if W * H > MAX_PIXELS:
        raise ValueError(f"map of {w_m:.0f} x {h_m:.0f} m exceeds {MAX_PIXELS} pixels")
    img = Image.new("L", (W, H), 0)
    draw = ImageDraw.Draw(img)

    def px(coords):
        c = np.asarray(coords, np.float64)[:, :2] - origin[:2]
        return [(float(x / RESOLUTION), float(H - y / RESOLUTION)) for x, y in c]

    for poly in polygons_of(drivable_area(layout)):
        draw.polygon(px(poly.exterior.coords), fill=255)
        for hole in poly.interiors:
            draw.polygon(px(hole.coords), fill=0)
    return np.asarray(img), origin


def write_mask(path: Path, mask: np.ndarray) -> Path:
    from PIL import Image
    buf = io.BytesIO()
    Image.fromarray(mask).save(buf, format="PNG", optimize=False)
    return S.atomic_write_bytes(path, buf.getvalue())
