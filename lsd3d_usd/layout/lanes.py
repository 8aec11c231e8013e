"""`layout lanes`: the drivable lane graph of a layout (`routes.LaneGraph`) as a listing and
as a top view with lane ids. Routes along it live in `routes`.
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from lsd3d_usd.layout.model import DRIVABLE_TYPES, Layout
from lsd3d_usd.layout.routes import LaneGraph
from lsd3d_usd.scene import atomic_write_bytes


@dataclass
class LaneRow:
    """One drivable lane: its links restricted to drivable lanes."""
    id: str
    lane_type: str
    length_m: float
    speed_limit_mps: float
    junction: bool
    road_id: str
    successors: list[str]
    predecessors: list[str]

    def to_json(self) -> dict:
        return {"id": self.id, "type": self.lane_type, "length_m": round(self.length_m, 2),
                "speed_limit_mps": round(self.speed_limit_mps, 2), "junction": self.junction,
                "road": self.road_id, "successors": self.successors,
                "predecessors": self.predecessors}


def lane_graph(layout: Layout) -> list[LaneRow]:
    """The drivable lanes in layout order, with their drivable successors / predecessors
    (the rows of `routes.LaneGraph`)."""
    g = LaneGraph(layout)
    return [LaneRow(ln.id, ln.lane_type, float(g.length[i]), ln.speed_limit_mps, ln.is_junction,
                    ln.road_id, [g.ids[j] for j in g.succ[i]], [g.ids[j] for j in g.pred[i]])
            for i, ln in enumerate(g.lanes)]


def format_lanes(rows: list[LaneRow], route: tuple[list[str], float], where: str) -> str:
    links = sum(len(r.successors) for r in rows)
    out = [f"{where}: {len(rows)} drivable lanes (type {', '.join(DRIVABLE_TYPES)}), "
           f"{links} successor links"]
    if rows:
        w = max(8, *(len(r.id) for r in rows))
        out.append(f"  {'id':{w}s}  {'type':8s} {'length':>8s}  {'limit':>8s}  junction  successors")
        for r in rows:
            out.append(f"  {r.id:{w}s}  {r.lane_type:8s} {r.length_m:7.1f}m  {r.speed_limit_mps * 3.6:4.0f}km/h"
                       f"  {'yes' if r.junction else 'no ':8s}  {', '.join(r.successors) or '-'}")
    if route[0]:
        out.append(f"longest route ({route[1]:.1f} m): --route {','.join(route[0])}")
    return "\n".join(out)


def draw_lanes(layout: Layout, path, title: str = "", max_px: int = 2400) -> Path:
    """Top view PNG: drivable lanes coloured with an arrow at their end and their id at the
    middle (junction lanes dashed), other lanes grey, road edges and buildings faint."""
    matplotlib.use("Agg")

    (x0, y0), (x1, y1) = layout.bounds()
    span = max(x1 - x0, y1 - y0, 1.0)
    # ~8 px per metre, so ids of neighbouring lanes stay apart; at most max_px on a side
    size_in = min(max_px / 100.0, max(6.0, span * 8 / 100.0))
    aspect = max(y1 - y0, 1.0) / max(x1 - x0, 1.0)
    fig, ax = plt.subplots(figsize=(size_in, max(3.0, min(size_in * aspect, max_px / 100.0))), dpi=100)
    for e in layout.road_edges:
        ax.plot(e.points[:, 0], e.points[:, 1], color="0.75", lw=0.6, zorder=1)
    for b in layout.buildings:
        fp = np.vstack([b.footprint, b.footprint[:1]])
        ax.fill(fp[:, 0], fp[:, 1], color="0.92", zorder=0)
    drivable = {ln.id for ln in layout.drivable_lanes()}
    cmap = plt.get_cmap("tab10")
    font = float(np.clip(size_in * 100.0 / max(span, 1.0), 3.0, 8.0))   # ~1 m high
    for k, ln in enumerate(layout.lanes):
        pts = np.asarray(ln.points)
        if ln.direction == "backward":
            pts = pts[::-1]
        if ln.id not in drivable:
            ax.plot(pts[:, 0], pts[:, 1], color="0.6", lw=0.6, zorder=2)
            continue
        c = cmap(k % 10)
        ax.plot(pts[:, 0], pts[:, 1], color=c, lw=1.4, ls="--" if ln.is_junction else "-", zorder=3)
        a, b = pts[-2, :2], pts[-1, :2]
        ax.annotate("", xy=b, xytext=a + 0.6 * (b - a) if np.linalg.norm(b - a) > 4 else a,
                    arrowprops=dict(arrowstyle="-|>", color=c, lw=1.2), zorder=4)
        # the id along the lane, beside it on the right of travel: the two directions of a
        # road put their labels on opposite sides; junction lanes at 40 %, away from the middle
        seg = np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        s = cum[-1] * (0.4 if ln.is_junction else 0.5)
        mid = np.array([np.interp(s, cum, pts[:, i]) for i in (0, 1)])
        j = int(np.clip(np.searchsorted(cum, s) - 1, 0, len(seg) - 1))
        t = (pts[j + 1, :2] - pts[j, :2]) / max(seg[j], 1e-9)
        angle = float(np.degrees(np.arctan2(t[1], t[0])))
        angle = angle - 180 if angle > 90 else angle + 180 if angle < -90 else angle
        right = np.array([t[1], -t[0]]) * font * 0.9
        ax.annotate(ln.id, mid, xytext=tuple(right), textcoords="offset points", fontsize=font,
                    color=c, ha="center", va="center", rotation=angle, rotation_mode="anchor",
                    zorder=5, bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.7))
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or "drivable lanes (arrow: direction of travel; dashed: junction)", fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())
