"""Build the small example maps in samples/maps/ in code, with each format's own tools.

    python samples/maps/make_maps.py            # rewrites crossing_lanelet2.osm, town.osm, ...

The tests import the same builders (no downloaded data anywhere):

- ``lanelet2_crossing``: a 4-way crossing of two-lane roads made with the lanelet2 API and
  written with lanelet2's writer (lanelets with shared points, junction lanelets for every
  movement, curbstones, dashed centre lines, a traffic light with its stop line, a stop sign,
  a crosswalk, a building, a parking area and a vegetation area).
- ``osm_town``: OpenStreetMap XML written as text: a grid of highways of several classes
  (lanes, oneway, sidewalk tags), a crossing node, a stop node, buildings with height and
  levels, trees, a tree row and a park.
- ``opendrive_from_layout``: the README crossing exported with ``layout export``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

KARLSRUHE = (49.0069, 8.4037)    # origin of the Lanelet2 sample
LANE = 3.5
ARM = 40.0                        # length of each approach road
BOX = 7.0                         # half size of the junction box


def _rot(pts, quarter: int) -> np.ndarray:
    a = quarter * np.pi / 2
    c, s = np.cos(a), np.sin(a)
    p = np.asarray(pts, dtype=np.float64)
    return np.round(np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], axis=1), 9)


def _arc(center, r, a0, a1, n=12) -> np.ndarray:
    t = np.linspace(a0, a1, n)
    return np.stack([center[0] + r * np.cos(t), center[1] + r * np.sin(t)], axis=1)


def lanelet2_crossing(path: str | Path, origin=KARLSRUHE) -> Path:
    """Write the Lanelet2 sample crossing (local metres around ``origin``) to ``path``."""
    import lanelet2
    from lanelet2.core import (AttributeMap, Area, Lanelet, LaneletMap, LineString3d, Point3d,
                               TrafficLight, TrafficSign, TrafficSignsWithType, getId)
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector

    points: dict = {}

    def pt(x, y):
        key = (round(float(x), 6), round(float(y), 6))
        if key not in points:
            points[key] = Point3d(getId(), key[0], key[1], 0.0)
        return points[key]

    lines: dict = {}

    def line(xy, typ, sub=None):
        xy = np.asarray(xy)
        key = tuple(map(tuple, np.round(xy, 6)))
        rev = key[::-1]
        if rev in lines:
            return lines[rev].invert()
        if key not in lines:
            attrs = {"type": typ}
            if sub:
                attrs["subtype"] = sub
            lines[key] = LineString3d(getId(), [pt(x, y) for x, y in xy], AttributeMap(attrs))
        return lines[key]

    def lanelet(left, right, sub="road"):
        return Lanelet(getId(), left, right, AttributeMap(
            {"type": "lanelet", "subtype": sub, "location": "urban", "one_way": "yes",
             "speed_limit": "50"}))

    lmap = LaneletMap()
    approach = {}
    for q in range(4):
        # the arm west of the box, rotated by q quarter turns; inbound lane travels +x
        x0, x1 = -BOX - ARM, -BOX
        centre = line(_rot([(x0, 0), (x1, 0)], q), "line_thin", "dashed")
        south = line(_rot([(x0, -LANE), (x1, -LANE)], q), "curbstone", "high")
        north = line(_rot([(x1, LANE), (x0, LANE)], q), "curbstone", "high")
        inbound = lanelet(centre, south)
        outbound = lanelet(centre.invert(), north)
        lmap.add(inbound)
        lmap.add(outbound)
        approach[q] = inbound
    for q in range(4):
        # movements from the arm at quarter q: straight, right, left (virtual bounds)
        straight = lanelet(line(_rot([(-BOX, 0), (BOX, 0)], q), "virtual"),
                           line(_rot([(-BOX, -LANE), (BOX, -LANE)], q), "virtual"))
        right = lanelet(line(_rot(_arc((-BOX, -BOX), BOX, np.pi / 2, 0), q), "virtual"),
                        line(_rot(_arc((-BOX, -BOX), BOX - LANE, np.pi / 2, 0), q), "virtual"))
        left = lanelet(line(_rot(_arc((-BOX, BOX), BOX, -np.pi / 2, 0), q), "virtual"),
                       line(_rot(_arc((-BOX, BOX), BOX + LANE, -np.pi / 2, 0), q), "virtual"))
        for ll in (straight, right, left):
            lmap.add(ll)

    # traffic light with its stop line on the west approach; a stop sign on the south approach
    stop = line([(-BOX - 1.0, -LANE), (-BOX - 1.0, 0.0)], "stop_line")
    light = line([(-BOX - 1.5, -LANE - 1.0), (-BOX - 1.5, -LANE - 1.3)], "traffic_light", "red_yellow_green")
    tl = TrafficLight(getId(), AttributeMap(), [light], stop)
    approach[0].addRegulatoryElement(tl)
    lmap.add(tl)   # the lanelet joined the map before it had the rule
    stop_s = line(_rot([(-BOX - 1.0, -LANE), (-BOX - 1.0, 0.0)], 1), "stop_line")
    sign = line(_rot([(-BOX - 1.2, -LANE - 1.0), (-BOX - 1.2, -LANE - 1.6)], 1), "traffic_sign", "de206")
    ts = TrafficSign(getId(), AttributeMap(), TrafficSignsWithType([sign], "de206"),
                     TrafficSignsWithType([]), [stop_s])
    approach[1].addRegulatoryElement(ts)
    lmap.add(ts)
    # a crosswalk over the east arm
    lmap.add(Lanelet(getId(), line([(BOX + 6, LANE), (BOX + 6, -LANE)], "zebra_marking"),
                     line([(BOX + 3, LANE), (BOX + 3, -LANE)], "zebra_marking"),
                     AttributeMap({"type": "lanelet", "subtype": "crosswalk", "one_way": "no"})))

    def area(ring, sub, **extra):
        ring = list(ring) + [ring[0]]
        ls = line(ring, "virtual")
        return Area(getId(), [ls], [], AttributeMap({"type": "multipolygon", "subtype": sub, **extra}))

    lmap.add(area([(-40, 12), (-15, 12), (-15, 30), (-40, 30)], "building", height="15"))
    lmap.add(area([(15, 15), (35, 15), (35, 22), (15, 22)], "parking"))
    lmap.add(area([(12, -40), (40, -40), (40, -12), (12, -12)], "vegetation"))
    path = Path(path)
    lanelet2.io.write(str(path), lmap, LocalCartesianProjector(Origin(*origin)))
    return path


MUNICH = (48.137, 11.575)        # origin of the OSM sample


def _latlon(origin, x, y) -> tuple[float, float]:
    """Local metres → degrees on a sphere (plenty for a sample; the importer projects exactly)."""
    lat = origin[0] + y / 111_195.0
    return lat, origin[1] + x / (111_195.0 * np.cos(np.radians(origin[0])))


def osm_town(path: str | Path, origin=MUNICH, bounds: bool = True) -> Path:
    """Write the OSM sample (OSM XML 0.6 as text): a main street with two side streets, a
    one-way street, a service road, a zebra crossing, a stop sign, buildings, trees, a park."""
    nodes: list[str] = []
    ways: list[str] = []
    ids: dict = {}

    def node(x, y, **tags):
        key = (x, y) if not tags else None
        if key in ids:
            return ids[key]
        nid = 1000 + len(nodes)
        lat, lon = _latlon(origin, x, y)
        body = "".join(f'<tag k="{k.replace("__", ":")}" v="{v}"/>' for k, v in tags.items())
        nodes.append(f'  <node id="{nid}" version="1" lat="{lat:.9f}" lon="{lon:.9f}">{body}</node>'
                     if body else f'  <node id="{nid}" version="1" lat="{lat:.9f}" lon="{lon:.9f}"/>')
        if key is not None:
            ids[key] = nid
        return nid

    def way(refs, **tags):
        wid = 5000 + len(ways)
        nds = "".join(f'<nd ref="{r}"/>' for r in refs)
        tg = "".join(f'<tag k="{k.replace("__", ":")}" v="{v}"/>' for k, v in tags.items())
        ways.append(f'  <way id="{wid}" version="1">{nds}{tg}</way>')
        return wid

    def ring(pts, **tags):
        refs = [node(x, y) for x, y in pts]
        return way(refs + refs[:1], **tags)

    crossing = node(0.0, 0.0, highway="crossing", crossing="zebra")
    ids[(0.0, 0.0)] = crossing
    stop = node(-50.0, -12.0, highway="stop")
    ids[(-50.0, -12.0)] = stop
    way([node(x, 0.0) for x in (-150.0, -50.0, 0.0, 50.0, 150.0)], highway="primary", lanes="4",
        sidewalk="both", maxspeed="50", name="Hauptstrasse")
    way([node(-50.0, y) for y in (-120.0, -12.0, 0.0, 120.0)], highway="residential", sidewalk="both")
    way([node(50.0, y) for y in (120.0, 60.0, 0.0, -120.0)], highway="residential", oneway="yes",
        lanes="1", width="4")
    way([node(50.0, 60.0), node(95.0, 70.0), node(140.0, 60.0)], highway="service")
    way([node(-150.0, 30.0), node(-60.0, 30.0)], highway="footway")        # not a road
    ring([(-40.0, 12.0), (-10.0, 12.0), (-10.0, 35.0), (-40.0, 35.0)], building="apartments", height="18")
    ring([(5.0, 12.0), (40.0, 12.0), (40.0, 30.0), (5.0, 30.0)], building="yes", building__levels="4")
    ring([(-140.0, -15.0), (-65.0, -15.0), (-65.0, -40.0), (-140.0, -40.0)], building="retail")
    ring([(65.0, -20.0), (140.0, -20.0), (140.0, -110.0), (65.0, -110.0)], leisure="park")
    for x in (-130.0, -100.0, -70.0, 70.0, 100.0, 130.0):
        node(x, 9.0, natural="tree", height="11", diameter_crown="6")
    way([node(-35.0, -30.0), node(-35.0, -110.0)], natural="tree_row")
    lat0, lon0 = _latlon(origin, -160.0, -130.0)
    lat1, lon1 = _latlon(origin, 160.0, 130.0)
    head = (f'  <bounds minlat="{lat0:.9f}" minlon="{lon0:.9f}" maxlat="{lat1:.9f}" maxlon="{lon1:.9f}"/>\n'
            if bounds else "")
    text = ('<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="lsd3d-usd samples">\n'
            + head + "\n".join(nodes + ways) + "\n</osm>\n")
    path = Path(path)
    path.write_text(text)
    return path


def opendrive_from_layout(path: str | Path, layout_path: str | Path) -> Path:
    """The README crossing exported with ``layout export``."""
    from lsd3d_usd.layout import opendrive_export, usdio
    opendrive_export.write_opendrive(usdio.read_layout(layout_path), path)
    return Path(path)


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    print(lanelet2_crossing(out / "crossing_lanelet2.osm"))
    print(osm_town(out / "town.osm"))
    here = Path(__file__).resolve().parent
    print(opendrive_from_layout(out / "hand_crossing.xodr", here.parent / "layouts" / "hand_crossing.usda"))


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent)
