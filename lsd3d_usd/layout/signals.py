"""Which lanes traffic lights control: one answer for the proxy (which places the light
heads the cameras see) and the simulator (which runs their phases).

A signal group is a set of lanes one light (or the map's lights naming the same lanes)
controls, with the point where traffic must stop:

* **map lights** (``layout.traffic_lights``): the lanes each names (lights naming the same
  set are one group); a light naming no lane of the layout controls nothing known.
* **derived lights**, where the map is silent (not when it lists its lights completely,
  ``metadata.source.signalsComplete``): each group of driving lanes (same road, ends within
  12 m) entering a junction, unless a stop sign, a yield sign or a map light controls one of
  them, or a map light stands within MAP_SIGNAL_RADIUS of the group's end. Its head stands
  on the right of the group's rightmost lane, facing the approaching traffic.

The stop point of a controlled lane is its end, or its start for a junction lane a map
light names. Groups that lead into the same junction (junction lanes that cross, touch or
share a lane) share its ``junction`` key, which a signal plan cycles over.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

# A derived traffic light is left out when a map traffic light stands this close to its
# approach's end (a junction's lights, whichever lanes the map says they control).
MAP_SIGNAL_RADIUS = 50.0
GROUP_END_RADIUS = 12.0    # m: approach lanes of one road ending this close share a light
CURB_WIDTH = 0.3           # m: proxy.ground's default curb width (the proxy passes its own)


@dataclass(frozen=True)
class SignalGroup:
    """Lanes one traffic light controls. ``id``: the derived light's id (``tl_<lane id>``,
    the proxy's fixture id) or the first map light's id; ``lane_ids``: the controlled lanes;
    ``junction``: key of the junction they enter (the group's own id when none);
    ``heading``: direction of travel at the stop point (rad, CCW from +X); ``stop``: the
    stop point (x, y) of its first lane; ``light``: (x, y, yaw) of a derived head (None for
    map lights); ``map_lights``: ids of the map lights it stands for."""
    id: str
    lane_ids: tuple
    junction: str
    heading: float
    stop: tuple
    light: tuple | None = None
    map_lights: tuple = ()


def signals_complete(layout) -> bool:
    """The map lists its traffic lights completely (OpenDRIVE signals, Lanelet2 traffic-light
    rules: the importer says so in ``metadata.source.signalsComplete``)."""
    src = layout.metadata.get("source", {}) if isinstance(layout.metadata, dict) else {}
    return bool(isinstance(src, dict) and src.get("signalsComplete"))


def _heading(points: np.ndarray, at_end: bool) -> np.ndarray:
    d = points[-1, :2] - points[-2, :2] if at_end else points[1, :2] - points[0, :2]
    n = np.linalg.norm(d)
    return d / n if n > 0 else np.array([1.0, 0.0])


def _derived(layout, curb_width: float) -> list[list]:
    """[(lanes, light xy, yaw)] of the derived lights, in the proxy's order."""
    by_id = {ln.id: ln for ln in layout.lanes}
    signs = [s.lane_ids for s in layout.stop_signs] + \
        [t.lane_ids for t in layout.traffic_signs if t.kind == "yield"]
    stopped = {lid for ids in signs + [t.lane_ids for t in layout.traffic_lights] for lid in ids}
    near_pts = np.array([t.position[:2] for t in layout.traffic_lights]).reshape(-1, 2)
    approaches = [ln for ln in layout.lanes
                  if not ln.is_junction and ln.lane_type == "driving"
                  and ln.direction == "forward" and ln.id not in stopped
                  and any(by_id.get(s) is not None and by_id[s].is_junction
                          for s in ln.successors)]
    groups: list[list] = []
    for ln in sorted(approaches, key=lambda l: (l.road_id, l.id)):
        end = ln.points[-1, :2]
        for grp in groups:
            if grp[0].road_id == ln.road_id and \
                    np.linalg.norm(grp[0].points[-1, :2] - end) < GROUP_END_RADIUS:
                grp.append(ln)
                break
        else:
            groups.append([ln])
    out = []
    for grp in groups:
        if len(near_pts) and \
                np.hypot(*(near_pts - grp[0].points[-1, :2]).T).min() < MAP_SIGNAL_RADIUS:
            continue
        h = _heading(grp[0].points, True)
        right = np.array([h[1], -h[0]])
        ln = max(grp, key=lambda l: float(np.dot(l.points[-1, :2], right)))
        p = ln.points[-1, :2] + right * (ln.widths[-1] / 2 + curb_width + 1.0)
        yaw = float(np.arctan2(-h[1], -h[0]))       # facing the approaching traffic
        out.append((grp, ln, (float(p[0]), float(p[1])), yaw))
    return out


def _junctions(layout) -> dict[str, str]:
    """junction lane id -> key of its junction: junction lanes that cross or touch, or share
    a predecessor or successor, are one junction (key: the smallest lane id in it)."""
    jl = [ln for ln in layout.lanes if ln.is_junction and len(ln.points) >= 2]
    if not jl:
        return {}
    parent = list(range(len(jl)))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def union(i, j):
        a, b = find(i), find(j)
        if a != b:
            parent[max(a, b)] = min(a, b)

    by_link: dict[tuple, int] = {}
    for i, ln in enumerate(jl):
        for k in [("p", p) for p in ln.predecessors] + [("s", s) for s in ln.successors]:
            if k in by_link:
                union(i, by_link[k])
            else:
                by_link[k] = i
    lines = [shapely.LineString(np.asarray(ln.points, np.float64)[:, :2]) for ln in jl]
    a, b = shapely.STRtree(lines).query(lines, predicate="intersects")
    for i, j in zip(a.tolist(), b.tolist()):
        union(i, j)
    members: dict[int, list[str]] = {}
    for i, ln in enumerate(jl):
        members.setdefault(find(i), []).append(ln.id)
    return {lid: min(ids) for ids in members.values() for lid in ids}


def derived_lights(layout, curb_width: float = CURB_WIDTH) -> list[SignalGroup]:
    """The derived lights alone (module doc), without junction keys: what the proxy places."""
    if not layout.lanes or signals_complete(layout):
        return []
    out = []
    for grp, ln, p, yaw in _derived(layout, curb_width):
        h = _heading(grp[0].points, True)
        end = grp[0].points[-1, :2]
        out.append(SignalGroup(f"tl_{ln.id}", tuple(l.id for l in grp), "",
                               float(np.arctan2(h[1], h[0])), (float(end[0]), float(end[1])),
                               (p[0], p[1], yaw)))
    return out


def signal_groups(layout, derived: bool = True, curb_width: float = CURB_WIDTH) -> list[SignalGroup]:
    """Every signal group of the layout: the map's lights, then (``derived``: the proxy's
    ``traffic_lights`` option) the derived ones, each with its junction key."""
    by_id = {ln.id: ln for ln in layout.lanes}
    jkey = _junctions(layout)
    out: list[SignalGroup] = []
    seen: dict[tuple, int] = {}
    for tl in layout.traffic_lights:
        ids = tuple(dict.fromkeys(l for l in tl.lane_ids if l in by_id))
        if not ids:
            continue
        key = tuple(sorted(ids))
        if key in seen:
            g = out[seen[key]]
            out[seen[key]] = SignalGroup(g.id, g.lane_ids, g.junction, g.heading, g.stop, None,
                                         g.map_lights + (tl.id,))
            continue
        ln = by_id[ids[0]]
        at_end = not ln.is_junction
        h = _heading(ln.points, at_end)
        stop = ln.points[-1 if at_end else 0, :2]
        seen[key] = len(out)
        out.append(SignalGroup(tl.id, ids, _junction_of(ln, by_id, jkey, tl.id),
                               float(np.arctan2(h[1], h[0])), (float(stop[0]), float(stop[1])),
                               None, (tl.id,)))
    if derived:
        for g in derived_lights(layout, curb_width):
            j = _junction_of(by_id[g.lane_ids[0]], by_id, jkey, g.id)
            out.append(SignalGroup(g.id, g.lane_ids, j, g.heading, g.stop, g.light))
    return out


def _junction_of(ln, by_id, jkey, own: str) -> str:
    if ln.id in jkey:
        return jkey[ln.id]
    for s in ln.successors:
        if s in jkey:
            return jkey[s]
    return own


def stop_lane(cur: int, nxt: int, controlled, junction) -> int | None:
    """The controlled lane (index) whose signal governs the step from lane ``cur`` into
    ``nxt`` (-1: no lane), or None: ``cur``'s end when it is a controlled lane (not a junction
    lane), or ``nxt``'s start when it is a controlled junction lane entered from outside.
    ``controlled``: the controlled lane indices; ``junction``: per lane, is it a junction lane."""
    if cur >= 0 and not junction[cur] and cur in controlled:
        return cur
    if nxt >= 0 and junction[nxt] and nxt in controlled and (cur < 0 or not junction[cur]):
        return nxt
    return None
