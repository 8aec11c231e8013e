"""A small deterministic Manhattan-grid layout for tests and benchmarks of the proxy.

Not the procedural generator (that lives in layout/): just enough of every
feature kind — two-lane roads with junction lanes, lines, edges, crosswalks,
stop lines, a stop sign, buildings with all roof shapes, trees, hedges,
parking, vegetation — to exercise the proxy builder on any number of chunks.
"""
from __future__ import annotations

import numpy as np

from lsd3d_usd.layout import model as m


def grid_layout(nx: int = 2, ny: int = 2, block: float = 100.0, offset: float = 30.0,
                seed: int = 0) -> m.Layout:
    """Roads along x at y = offset + k*block and along y at x = offset + k*block,
    over an area of nx*block by ny*block starting at the origin."""
    rng = np.random.default_rng(seed)
    W, H = nx * block, ny * block
    L = m.Layout(extent=((0.0, 0.0), (W, H)), chunk_size=100.0)
    xs = offset + block * np.arange(nx)
    ys = offset + block * np.arange(ny)
    hw, jz = 3.5, 10.0                  # lane width, junction half size

    def road(axis: str, c: float, crossings: np.ndarray, length: float, rid: str):
        # breakpoints along the road: junction entries/exits
        cuts = [0.0]
        for q in crossings:
            cuts += [q - jz, q + jz]
        cuts.append(length)

        def P(s, off):
            s = np.asarray(s, dtype=float)
            return (np.column_stack([s, np.full_like(s, c + off)]) if axis == "x"
                    else np.column_stack([np.full_like(s, c - off), s]))
        ids_fwd, ids_bwd = [], []
        for k in range(len(cuts) - 1):
            a, b = cuts[k], cuts[k + 1]
            junction = k % 2 == 1
            n = max(2, int((b - a) // 10) + 1)
            s = np.linspace(a, b, n)
            f = L.add(m.LaneCenter(f"{rid}_f{k}", P(s, -hw / 2), np.full(n, hw),
                                   road_id=rid, is_junction=junction))
            r = L.add(m.LaneCenter(f"{rid}_b{k}", P(s[::-1], hw / 2), np.full(n, hw),
                                   road_id=rid, is_junction=junction))
            f.left_neighbors, r.left_neighbors = [r.id], [f.id]
            ids_fwd.append(f)
            ids_bwd.append(r)
            if not junction:
                L.add(m.RoadLine(f"{rid}_c{k}", P(s, 0.0), "solid", "yellow", double=True))
                L.add(m.RoadEdge(f"{rid}_er{k}", P(s, -hw), "boundary"))
                L.add(m.RoadEdge(f"{rid}_el{k}", P(s[::-1], hw), "boundary"))
        for k in range(len(ids_fwd) - 1):
            ids_fwd[k].successors.append(ids_fwd[k + 1].id)
            ids_fwd[k + 1].predecessors.append(ids_fwd[k].id)
            ids_bwd[k + 1].successors.append(ids_bwd[k].id)
            ids_bwd[k].predecessors.append(ids_bwd[k + 1].id)
        for q in crossings:
            for sgn in (-1, 1):                      # crosswalk + stop line at each mouth
                s0 = q + sgn * (jz - 1.0)
                cw = P([s0 - 1.5, s0 + 1.5], 0.0)
                d = cw[1] - cw[0]
                nrm = np.array([-d[1], d[0]]) / np.linalg.norm(d) * hw
                L.add(m.Crosswalk(f"{rid}_cw{int(q)}_{sgn}",
                                  np.array([cw[0] - nrm, cw[1] - nrm, cw[1] + nrm, cw[0] + nrm])))
                sl = q + sgn * (jz + 0.5)             # across the lane entering here
                L.add(m.StopLine(f"{rid}_sl{int(q)}_{sgn}",
                                 np.vstack([P([sl], 0.0), P([sl], -hw if sgn < 0 else hw)])))

    for k, y in enumerate(ys):
        road("x", y, xs, W, f"rx{k}")
    for k, x in enumerate(xs):
        road("y", x, ys, H, f"ry{k}")
    L.add(m.StopSign("stop0", (xs[0] - jz - 0.5, ys[0] - hw - 1.5), [f"rx0_f0"]))

    # blocks between roads: buildings set back 8 m, trees, parking, hedges, a park
    edges_x = np.concatenate([[-block + offset], xs, [W + offset]])
    edges_y = np.concatenate([[-block + offset], ys, [H + offset]])
    roofs = 0
    for bi in range(len(edges_x) - 1):
        for bj in range(len(edges_y) - 1):
            x0, x1 = max(edges_x[bi] + hw + 8, 2.0), min(edges_x[bi + 1] - hw - 8, W - 2.0)
            y0, y1 = max(edges_y[bj] + hw + 8, 2.0), min(edges_y[bj + 1] - hw - 8, H - 2.0)
            if x1 - x0 < 12 or y1 - y0 < 12:
                continue
            bid = f"blk{bi}_{bj}"
            if (bi + bj) % 5 == 3:                   # a park
                L.add(m.VegetationZone(f"{bid}_park", np.array(
                    [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]), kind="park"))
                L.add(m.Hedge(f"{bid}_hedge", np.array([[x0, y0 - 1], [x1, y0 - 1]])))
                continue
            north = min(14.0, (y1 - y0) / 2 - 1)     # the north building's depth
            x = x0
            while x1 - x >= 10:                      # a row of buildings along the block's south side
                w = min(rng.uniform(10, 24), x1 - x)
                d = min(rng.uniform(10, 18), (y1 - y0) - north - 2)
                fp = np.array([[x, y0], [x + w, y0], [x + w, y0 + d], [x, y0 + d]])
                if roofs % 4 == 3:                   # an L-shaped one now and then
                    fp = np.array([[x, y0], [x + w, y0], [x + w, y0 + d / 2], [x + w / 2, y0 + d / 2],
                                   [x + w / 2, y0 + d], [x, y0 + d]])
                roofs += 1
                L.add(m.Building(f"{bid}_b{roofs}", fp, height_hint=float(rng.uniform(6, 30))))
                x += w + rng.uniform(1, 4)
            # a big building on the north side crossing whatever chunk border is there
            L.add(m.Building(f"{bid}_n", np.array([[x0, y1 - north], [x1, y1 - north], [x1, y1], [x0, y1]]),
                             height_hint=float(rng.uniform(8, 20)), floors_hint=3))
    for k, x in enumerate(xs):                        # trees and parking along the y roads
        for n, y in enumerate(np.arange(5.0, H, 15.0)):
            if any(abs(y - q) < jz + 4 for q in ys):
                continue
            L.add(m.Tree(f"tree_{k}_{n}", (x + hw + 2.3, y), height_hint=7 + (n % 3),
                         crown_radius_hint=2.0 + 0.3 * (n % 2)))
            if n % 2 == 0:
                L.add(m.ParkingSpot(f"park_{k}_{n}", (x - hw - 1.6, y), heading=np.pi / 2,
                                    length=5.5 if n % 4 else 9.0, width=2.4))
    return L
