"""Build the maps that exercise what real maps hold, in code, with each format's own tools:

    python samples/maps/make_real_maps.py          # rewrites the files listed below

- ``opendrive_direct_junction``: three roads meeting through one ``type="direct"``
  junction (OpenDRIVE 1.7): a road whose two right lanes split into a through road and an
  exit ramp, and whose left lane comes back from the through road.
- ``opendrive_virtual_junction``: a main road with a driveway branching off at s = 80 and
  one merging back at s = 120 through a ``type="virtual"`` junction (road links with
  ``elementS`` / ``elementDir``, 1.7).
- ``opendrive_town``: a 160 m street with sidewalks and a georeference (UTM zone 32 with a
  header ``<offset>`` near Munich's centre) holding objects (buildings with
  outlines, trees, a hedge-like vegetation strip, poles, street lamps, a repeated guard
  rail, a wall, parking spaces, a parked car, a crosswalk, a traffic island) and signals
  (traffic lights, a stop sign, a yield sign, a speed limit, a signal reference).
- ``osm_town_of_opendrive``: the same street as OpenStreetMap XML (positions from the
  OpenDRIVE file's projection, inverted with pyproj): the georeferenced pair.
- ``lanelet2_real``: a Lanelet2 street with traffic light, yield and speed-limit rules,
  poles, a fence and a guard rail, and bad elements: a lanelet whose right bound runs
  far past its left (126 m against 24 m), a lanelet whose bounds cross (a bow tie), and a
  lane marking 50 m from any lane.
- ``osm_bounds_city``: OpenStreetMap XML whose ``<bounds>`` cover 200 m x 200 m while its
  ways run 600 m beyond, with traffic signals (at a junction and on a way, one with
  ``traffic_signals:direction``), a give-way sign, trees, a crossing, barriers (fence,
  wall, guard rail ways; bollards), street lamps, a building straddling the bounds, and
  bad ways (a self-intersecting building, a road of one repeated node).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

MUNICH = (48.137, 11.575)
# UTM zone 32 with a header offset near Munich's centre, as map tools write it
TOWN_PROJ = "+proj=utm +zone=32 +ellps=WGS84 +datum=WGS84 +units=m +no_defs"
TOWN_OFFSET = (691500.0, 5334700.0, 0.0, 0.0)     # header <offset x y z hdg>


def _header(name: str, geo: str | None = None, offset=None) -> str:
    g = f"\n    <geoReference><![CDATA[{geo}]]></geoReference>" if geo else ""
    o = ""
    if offset is not None:
        o = (f'\n    <offset x="{offset[0]:.3f}" y="{offset[1]:.3f}" z="{offset[2]:.3f}" '
             f'hdg="{offset[3]:.6f}"/>')
    return (f'<?xml version="1.0" encoding="UTF-8"?>\n<OpenDRIVE>\n  <header revMajor="1" '
            f'revMinor="7" name="{name}" version="1" date="2026-12-01" vendor="lsd3d-usd '
            f'samples">{g}{o}\n  </header>\n')


def _lane(lid: int, width: float = 3.5, typ: str = "driving", pred=None, succ=None,
          mark: str = "solid") -> str:
    link = ""
    if pred is not None or succ is not None:
        link = ("<link>" + (f'<predecessor id="{pred}"/>' if pred is not None else "")
                + (f'<successor id="{succ}"/>' if succ is not None else "") + "</link>")
    return (f'          <lane id="{lid}" type="{typ}" level="false">{link}'
            f'<width sOffset="0" a="{width}" b="0" c="0" d="0"/>'
            f'<roadMark sOffset="0" type="{mark}" weight="standard" color="standard" '
            f'width="0.12"/></lane>\n')


def _road(rid, length, geometry: str, left: list[str], right: list[str], link: str = "",
          junction: str = "-1", extra: str = "") -> str:
    ls = f"        <left>\n{''.join(left)}        </left>\n" if left else ""
    rs = f"        <right>\n{''.join(right)}        </right>\n" if right else ""
    return (f'  <road name="r{rid}" length="{length}" id="{rid}" junction="{junction}" rule="RHT">\n'
            f'    <link>{link}</link>\n'
            f'    <type s="0" type="town"><speed max="50" unit="km/h"/></type>\n'
            f'    <planView>\n{geometry}    </planView>\n'
            f'    <elevationProfile/>\n    <lateralProfile/>\n'
            f'    <lanes>\n      <laneSection s="0">\n{ls}'
            f'        <center><lane id="0" type="none" level="false"><roadMark sOffset="0" '
            f'type="broken" weight="standard" color="standard" width="0.12"/></lane></center>\n'
            f'{rs}      </laneSection>\n    </lanes>\n{extra}  </road>\n')


def _line(x, y, hdg, length, s=0.0) -> str:
    return (f'      <geometry s="{s}" x="{x}" y="{y}" hdg="{hdg}" length="{length}"><line/>'
            f'</geometry>\n')


def _arc(x, y, hdg, length, curvature, s=0.0) -> str:
    return (f'      <geometry s="{s}" x="{x}" y="{y}" hdg="{hdg}" length="{length}">'
            f'<arc curvature="{curvature}"/></geometry>\n')


def _write(path, text: str) -> Path:
    path = Path(path)
    path.write_text(text, encoding="utf-8")
    return path


# ======================================================================== OpenDRIVE

def opendrive_direct_junction(path: str | Path) -> Path:
    """Road 1 (lanes -1, -2 along s; lane 1 against) ends at direct junction 100: its lane -1
    continues as lane -1 of road 2, its lane -2 as lane -1 of the exit ramp road 3, and
    lane 1 of road 2 comes back as lane 1 of road 1."""
    r1 = _road(1, 100.0, _line(0.0, 0.0, 0.0, 100.0), [_lane(1)], [_lane(-1), _lane(-2)],
               '<successor elementType="junction" elementId="100"/>')
    r2 = _road(2, 120.0, _line(100.0, 0.0, 0.0, 120.0), [_lane(1)], [_lane(-1)],
               '<predecessor elementType="junction" elementId="100"/>')
    # the ramp leaves where lane -2 of road 1 ends (its centre at t = -5.25) and bends away
    r3 = _road(3, 80.0, _arc(100.0, -5.25 + 1.75, 0.0, 80.0, -0.01), [], [_lane(-1)],
               '<predecessor elementType="junction" elementId="100"/>')
    junction = ('  <junction id="100" name="exit" type="direct">\n'
                '    <connection id="0" incomingRoad="1" linkedRoad="2" contactPoint="start">'
                '<laneLink from="-1" to="-1"/><laneLink from="1" to="1"/></connection>\n'
                '    <connection id="1" incomingRoad="1" linkedRoad="3" contactPoint="start">'
                '<laneLink from="-2" to="-1"/></connection>\n'
                '  </junction>\n')
    return _write(path, _header("direct junction") + r1 + r2 + r3 + junction + "</OpenDRIVE>\n")


def opendrive_virtual_junction(path: str | Path) -> Path:
    """Main road 1 (200 m, lane -1 along s, lane 1 against); road 2 branches off lane -1 at
    s = 80 to the right and continues as road 4 (200 m south); road 5 (150 m north) leads
    into road 3, which merges back into lane -1 at s = 120. Roads 2 and 3 belong to virtual
    junction 555 on road 1."""
    main = _road(1, 200.0, _line(0.0, 0.0, 0.0, 200.0), [_lane(1)], [_lane(-1)])
    # road 2: starts on the right edge of lane -1 at s = 80, bends right (a quarter circle)
    r2 = _road(2, 15.7079632679, _arc(80.0, -1.75, 0.0, 15.7079632679, -0.1), [],
               [_lane(-1, 3.0, pred=-1, succ=-1)],
               '<predecessor elementType="road" elementId="1" elementS="80" elementDir="+"/>'
               '<successor elementType="road" elementId="4" contactPoint="start"/>',
               junction="555")
    r4 = _road(4, 200.0, _line(90.0, -11.75, -np.pi / 2, 200.0), [], [_lane(-1, 3.0, pred=-1)],
               '<predecessor elementType="road" elementId="2" contactPoint="end"/>')
    r5 = _road(5, 150.0, _line(110.0, -161.75, np.pi / 2, 150.0), [], [_lane(-1, 3.0, succ=-1)],
               '<successor elementType="road" elementId="3" contactPoint="start"/>')
    r3 = _road(3, 15.7079632679, _arc(110.0, -11.75, np.pi / 2, 15.7079632679, -0.1), [],
               [_lane(-1, 3.0, pred=-1, succ=-1)],
               '<predecessor elementType="road" elementId="5" contactPoint="end"/>'
               '<successor elementType="road" elementId="1" elementS="120" elementDir="+"/>',
               junction="555")
    junction = ('  <junction id="555" name="driveway" type="virtual" mainRoad="1" sStart="70" '
                'sEnd="130" orientation="+">\n'
                '    <connection id="0" incomingRoad="1" connectingRoad="2" contactPoint="start">'
                '<laneLink from="-1" to="-1"/></connection>\n'
                '    <connection id="1" incomingRoad="5" connectingRoad="3" contactPoint="start">'
                '<laneLink from="-1" to="-1"/></connection>\n'
                '  </junction>\n')
    return _write(path, _header("virtual junction") + main + r2 + r4 + r5 + r3 + junction
                  + "</OpenDRIVE>\n")


TOWN_LENGTH = 160.0
TOWN_START = (-80.0, -20.0)          # local x, y of the street's start (before the offset)


def _town_objects() -> str:
    corner = lambda u, v, h: f'<cornerLocal u="{u}" v="{v}" z="0" height="{h}"/>'  # noqa: E731
    croad = lambda s, t: f'<cornerRoad s="{s}" t="{t}" dz="0" height="0"/>'  # noqa: E731
    return (
        '    <objects>\n'
        # a building north of the street, by its outline (local corners around s=40, t=18)
        f'      <object id="b1" type="building" name="house" s="40" t="18" zOffset="0" hdg="0" '
        f'height="14" orientation="none"><outlines><outline id="0" closed="true">'
        f'{corner(-8, -5, 14)}{corner(8, -5, 14)}{corner(8, 5, 14)}{corner(-8, 5, 14)}'
        f'</outline></outlines></object>\n'
        # a building south of the street by length x width
        '      <object id="b2" type="building" name="shop" s="110" t="-20" zOffset="0" hdg="0" '
        'length="20" width="10" height="9" orientation="none"/>\n'
        # trees every 20 m along the north sidewalk (a repeat of point objects)
        '      <object id="t1" type="tree" name="lime" s="10" t="11" zOffset="0" height="9" '
        'radius="2.5" orientation="none"><repeat s="10" length="140" distance="20" tStart="11" '
        'tEnd="11" heightStart="9" heightEnd="9" zOffsetStart="0" zOffsetEnd="0"/></object>\n'
        # a vegetation strip by outline in road coordinates
        f'      <object id="v1" type="vegetation" name="hedge" s="130" t="12" zOffset="0" '
        f'height="1.2" orientation="none"><outline>{croad(125, 10.5)}{croad(155, 10.5)}'
        f'{croad(155, 13)}{croad(125, 13)}</outline></object>\n'
        '      <object id="p1" type="pole" name="post" s="60" t="-9" zOffset="0" height="3" '
        'radius="0.05" orientation="none"/>\n'
        '      <object id="p2" type="pole" subtype="bollard" name="bollard" s="150" t="-9" '
        'zOffset="0" height="1" radius="0.1" orientation="none"/>\n'
        '      <object id="l1" type="streetLamp" name="lamp" s="25" t="-9.5" zOffset="0" '
        'height="8" orientation="none"><repeat s="25" length="120" distance="40" tStart="-9.5" '
        'tEnd="-9.5" heightStart="8" heightEnd="8" zOffsetStart="0" zOffsetEnd="0"/></object>\n'
        # a continuous guard rail along the south edge (repeat with distance 0)
        '      <object id="g1" type="barrier" subtype="guardRail" name="guard rail" s="0" '
        't="-10.5" zOffset="0" height="0.8" width="0.3" orientation="none"><repeat s="0" '
        'length="50" distance="0" tStart="-10.5" tEnd="-10.5" widthStart="0.3" widthEnd="0.3" '
        'heightStart="0.8" heightEnd="0.8" zOffsetStart="0" zOffsetEnd="0"/></object>\n'
        '      <object id="w1" type="barrier" subtype="wall" name="wall" s="100" t="13.5" '
        'zOffset="0" hdg="0" length="30" width="0.3" height="2.5" orientation="none"/>\n'
        '      <object id="ps1" type="parkingSpace" name="bay" s="75" t="-5" zOffset="0" hdg="0" '
        'length="5.5" width="2.4" height="0" orientation="none"/>\n'
        '      <object id="ps2" type="parkingSpace" name="bay" s="82" t="-5" zOffset="0" hdg="0" '
        'length="5.5" width="2.4" height="0" orientation="none"/>\n'
        '      <object id="c1" type="car" name="parked car" s="82" t="-5" zOffset="0" hdg="0" '
        'length="4.5" width="1.9" height="1.5" orientation="none"/>\n'
        f'      <object id="x1" type="crosswalk" name="zebra" s="90" t="0" zOffset="0" '
        f'orientation="none"><outline>{croad(88, -7)}{croad(92, -7)}{croad(92, 7)}{croad(88, 7)}'
        f'</outline></object>\n'
        '      <object id="i1" type="trafficIsland" name="island" s="140" t="0" zOffset="0" '
        'hdg="0" length="8" width="1.5" height="0.15" orientation="none"/>\n'
        '      <object id="g2" type="gantry" name="sign gantry" s="5" t="0" zOffset="0" '
        'orientation="none"/>\n'
        '    </objects>\n')


def _town_signals() -> str:
    return (
        '    <signals>\n'
        # lights at the end of the street for both directions (German catalogue, dynamic)
        '      <signal id="s1" name="light east" s="150" t="-8" zOffset="3.2" hOffset="0" '
        'orientation="+" dynamic="yes" country="DE" type="1000001" subtype="-1" value="-1" '
        'height="1.0" width="0.4"><validity fromLane="-2" toLane="-1"/></signal>\n'
        '      <signal id="s2" name="light west" s="10" t="8" zOffset="3.2" hOffset="0" '
        'orientation="-" dynamic="yes" country="DE" type="1000001" subtype="-1" value="-1" '
        'height="1.0" width="0.4"/>\n'
        '      <signal id="s3" name="stop" s="30" t="-8.5" zOffset="1.8" orientation="+" '
        'dynamic="no" country="DE" type="206" subtype="-1" value="-1" height="0.8" '
        'width="0.8"/>\n'
        '      <signal id="s4" name="yield" s="130" t="8.5" zOffset="1.8" orientation="-" '
        'dynamic="no" country="DE" type="205" subtype="-1" value="-1" height="0.8" '
        'width="0.9"/>\n'
        '      <signal id="s5" name="speed" s="20" t="-8.5" zOffset="2.0" orientation="+" '
        'dynamic="no" country="DE" type="274" subtype="-1" value="30" unit="km/h" '
        'height="0.6" width="0.6"/>\n'
        '    </signals>\n')


def opendrive_town(path: str | Path, geo: bool = True) -> Path:
    """A 160 m east-west street (two lanes each way, 2 m sidewalks) with objects and signals;
    georeferenced (TOWN_PROJ, header offset TOWN_OFFSET) when ``geo``."""
    x0, y0 = TOWN_START
    walk = _lane(3, 2.0, "sidewalk", mark="none")
    walk_r = _lane(-3, 2.0, "sidewalk", mark="none")
    street = _road(1, TOWN_LENGTH, _line(x0, y0, 0.0, TOWN_LENGTH),
                   [_lane(1, mark="broken"), _lane(2), walk],
                   [_lane(-1, mark="broken"), _lane(-2), walk_r],
                   extra=_town_objects() + _town_signals())
    head = _header("town", TOWN_PROJ if geo else None, TOWN_OFFSET if geo else None)
    return _write(path, head + street + "</OpenDRIVE>\n")


def town_lonlat(x, y):
    """lon, lat (degrees) of local OpenDRIVE coordinates of ``opendrive_town``: the header
    offset is added, then TOWN_PROJ is inverted (pyproj)."""
    from pyproj import Transformer
    tr = Transformer.from_crs(TOWN_PROJ, "EPSG:4326", always_xy=True)
    return tr.transform(np.asarray(x) + TOWN_OFFSET[0], np.asarray(y) + TOWN_OFFSET[1])


def osm_town_of_opendrive(path: str | Path) -> Path:
    """The street of ``opendrive_town`` as OpenStreetMap: its reference line (the centre of
    the carriageway) as a two-lane-each-way primary way, the two buildings, the lights, with
    ``<bounds>`` around it. Positions come from the OpenDRIVE frame through pyproj."""
    x0, y0 = TOWN_START
    xs = np.array([x0, x0 + TOWN_LENGTH / 2, x0 + TOWN_LENGTH])
    lon, lat = town_lonlat(xs, np.full(3, y0))
    nodes = [f'  <node id="{1 + k}" version="1" lat="{la:.9f}" lon="{lo:.9f}"/>'
             for k, (lo, la) in enumerate(zip(lon, lat))]
    b = [(x0 + 32, y0 + 13), (x0 + 48, y0 + 13), (x0 + 48, y0 + 23), (x0 + 32, y0 + 23)]
    blon, blat = town_lonlat([p[0] for p in b], [p[1] for p in b])
    nodes += [f'  <node id="{10 + k}" version="1" lat="{la:.9f}" lon="{lo:.9f}"/>'
              for k, (lo, la) in enumerate(zip(blon, blat))]
    llon, llat = town_lonlat([x0 + 150], [y0 - 8])
    nodes.append(f'  <node id="20" version="1" lat="{llat[0]:.9f}" lon="{llon[0]:.9f}">'
                 '<tag k="highway" v="traffic_signals"/></node>')
    ways = ['  <way id="100" version="1">' + "".join(f'<nd ref="{1 + k}"/>' for k in range(3))
            + '<tag k="highway" v="primary"/><tag k="lanes" v="4"/><tag k="width" v="14"/>'
            '<tag k="name" v="Town Street"/></way>',
            '  <way id="101" version="1">' + "".join(f'<nd ref="{10 + k}"/>' for k in (0, 1, 2, 3, 0))
            + '<tag k="building" v="house"/><tag k="height" v="14"/></way>']
    blo, bla = town_lonlat([x0 - 20, x0 + TOWN_LENGTH + 20], [y0 - 40, y0 + 40])
    text = ('<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="lsd3d-usd '
            f'samples">\n  <bounds minlat="{bla[0]:.7f}" minlon="{blo[0]:.7f}" '
            f'maxlat="{bla[1]:.7f}" maxlon="{blo[1]:.7f}"/>\n'
            + "\n".join(nodes + ways) + "\n</osm>\n")
    return _write(path, text)


# ======================================================================== Lanelet2

def lanelet2_real(path: str | Path, origin=(49.0069, 8.4037)) -> Path:
    """A 120 m street of two lanelets each way (Lanelet2 API, written with its writer) with a
    traffic light rule, a yield sign and a 30 km/h sign, poles, a fence and a guard rail; and
    three bad elements: lanelet 9001 (right bound 126 m, left 24 m), lanelet 9002 (bounds
    that cross), line string 9003 (a dashed line 50 m from any lane)."""
    import lanelet2
    from lanelet2.core import (AttributeMap, Lanelet, LaneletMap, LineString3d, Point3d,
                               TrafficLight, TrafficSign, TrafficSignsWithType, getId)
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector

    shared: dict = {}

    def pt(x, y, z=0.0, **attrs):
        return Point3d(getId(), x, y, z, AttributeMap(attrs))

    def node(x, y, z):     # lanelets that follow each other share their bounds' end points
        key = (round(x, 6), round(y, 6), round(z, 6))
        if key not in shared:
            shared[key] = pt(x, y, z)
        return shared[key]

    def ls(xy, typ, sub=None, lid=None, z=0.0):
        attrs = {"type": typ}
        if sub:
            attrs["subtype"] = sub
        return LineString3d(lid or getId(), [node(x, y, z) for x, y in xy], AttributeMap(attrs))

    def ll(left, right, lid=None, **attrs):
        a = {"type": "lanelet", "subtype": "road", "location": "urban", "one_way": "yes"}
        a.update(attrs)
        return Lanelet(lid or getId(), left, right, AttributeMap(a))

    W = 3.5
    lmap = LaneletMap()
    centre = [ls([(0, 0), (60, 0)], "line_thin", "dashed"), ls([(60, 0), (120, 0)], "line_thin", "dashed")]
    south = [ls([(0, -W), (60, -W)], "curbstone", "high"), ls([(60, -W), (120, -W)], "curbstone", "high")]
    north = [ls([(60, W), (0, W)], "curbstone", "high"), ls([(120, W), (60, W)], "curbstone", "high")]
    east = [ll(centre[0], south[0]), ll(centre[1], south[1])]
    west = [ll(centre[1].invert(), north[1]), ll(centre[0].invert(), north[0])]
    for x in east + west:
        lmap.add(x)
    # a traffic light over the eastbound lane at x = 115 (the head 5 m up), stop line at 112
    stop = ls([(112, -W), (112, 0)], "stop_line")
    light = ls([(115, -2.0), (115, -1.5)], "traffic_light", "red_yellow_green", z=5.0)
    tl = TrafficLight(getId(), AttributeMap(), [light], stop)
    east[1].addRegulatoryElement(tl)
    lmap.add(tl)
    # a yield sign for the westbound lanelet and a speed limit for the eastbound one
    ysign = ls([(10, W + 1.0), (10, W + 1.6)], "traffic_sign", "de205")
    ys = TrafficSign(getId(), AttributeMap(), TrafficSignsWithType([ysign], "de205"),
                     TrafficSignsWithType([]), [])
    west[1].addRegulatoryElement(ys)
    lmap.add(ys)
    vsign = ls([(20, -W - 1.0), (20, -W - 1.6)], "traffic_sign", "de274-30")
    vs = TrafficSign(getId(), AttributeMap({"subtype": "speed_limit", "sign_type": "de274-30"}),
                     TrafficSignsWithType([vsign], "de274-30"), TrafficSignsWithType([]), [])
    east[0].addRegulatoryElement(vs)
    lmap.add(vs)
    # poles and furniture beside the street
    for k, x in enumerate((30.0, 70.0)):
        lmap.add(pt(x, -W - 1.5, 0.0, type="pole"))
    lmap.add(pt(50.0, W + 1.5, 0.0, type="street_lamp", height="8"))
    lmap.add(ls([(0, W + 4), (120, W + 4)], "fence"))
    lmap.add(ls([(0, -W - 3), (40, -W - 3)], "guard_rail"))
    # bad: right bound 126 m against a 24 m left bound (a spike of road)
    lmap.add(ll(ls([(150, 0), (174, 0)], "line_thin", "dashed", lid=9011),
                ls([(150, -W), (200, -W), (250, -W), (276, -W)], "curbstone", lid=9012), lid=9001))
    # bad: bounds that cross halfway (a bow tie)
    lmap.add(ll(ls([(0, 40), (30, 40)], "line_thin", "solid", lid=9013),
                ls([(0, 36.5), (30, 43.5)], "line_thin", "solid", lid=9014), lid=9002))
    # bad: a lane marking far from every lane
    lmap.add(ls([(40, -60), (80, -60)], "line_thin", "dashed", lid=9003))
    path = Path(path)
    lanelet2.io.write(str(path), lmap, LocalCartesianProjector(Origin(*origin)))
    return path


# ======================================================================== OSM

CITY = (52.5200, 13.4050)   # Berlin: origin of the bounds sample


def _ll(origin, x, y):
    lat = origin[0] + y / 111_195.0
    return lat, origin[1] + x / (111_195.0 * np.cos(np.radians(origin[0])))


def osm_bounds_city(path: str | Path, origin=CITY, half: float = 100.0, reach: float = 700.0
                    ) -> Path:
    """OSM XML: ``<bounds>`` of 2*half x 2*half m around ``origin``; an east-west primary and
    a north-south residential street cross at the centre and run ``reach`` m out each way.
    See the module doc for the features."""
    nodes, ways = [], []

    def node(nid, x, y, **tags):
        lat, lon = _ll(origin, x, y)
        body = "".join(f'<tag k="{k.replace("__", ":")}" v="{v}"/>' for k, v in tags.items())
        nodes.append(f'  <node id="{nid}" version="1" lat="{lat:.9f}" lon="{lon:.9f}">{body}</node>')

    def way(wid, refs, **tags):
        body = "".join(f'<nd ref="{r}"/>' for r in refs)
        body += "".join(f'<tag k="{k.replace("__", ":")}" v="{v}"/>' for k, v in tags.items())
        ways.append(f'  <way id="{wid}" version="1">{body}</way>')

    node(1, -reach, 0)
    node(2, -40, 0)
    node(3, 0, 0, highway="traffic_signals")          # a signalised junction
    node(4, 40, 0, highway="crossing", crossing="zebra")
    node(5, 70, 0, highway="traffic_signals", traffic_signals__direction="forward")
    node(6, reach, 0)
    node(7, 0, -reach)
    node(8, 0, -60, highway="give_way")
    node(9, 0, reach)
    way(100, [1, 2, 3, 4, 5, 6], highway="primary", lanes="2", maxspeed="50")
    way(101, [7, 8, 3, 9], highway="residential")
    # trees, lamps, bollards
    for k, x in enumerate((-80, -50, 50, 80)):
        node(20 + k, x, 12, natural="tree", height="10")
    node(30, -30, -9, highway="street_lamp")
    node(31, 30, -9, highway="street_lamp")
    node(32, 60, 9, barrier="bollard")
    # barriers: a fence, a wall, a guard rail (ways)
    for k, (a, b) in enumerate((((-90, 30), (-20, 30)), ((20, 30), (90, 30)), ((20, -20), (90, -20)))):
        node(40 + 2 * k, *a)
        node(41 + 2 * k, *b)
    way(110, [40, 41], barrier="fence")
    way(111, [42, 43], barrier="wall", height="2.5")
    way(112, [44, 45], barrier="guard_rail")
    # buildings: one inside, one straddling the north-east bounds corner
    for k, (x, y) in enumerate(((-70, -70), (-40, -70), (-40, -40), (-70, -40),
                                (80, 80), (130, 80), (130, 130), (80, 130))):
        node(50 + k, x, y)
    way(120, [50, 51, 52, 53, 50], building="yes", height="12")
    way(121, [54, 55, 56, 57, 54], building="yes", building__levels="5")
    # bad ways: a bow-tie building and a road of one repeated node
    for k, (x, y) in enumerate(((40, -80), (70, -50), (70, -80), (40, -50))):
        node(60 + k, x, y)
    way(130, [60, 61, 62, 63, 60], building="yes")
    node(70, -60, 60)
    way(131, [70, 70, 70], highway="service")
    lat0, lon0 = _ll(origin, -half, -half)
    lat1, lon1 = _ll(origin, half, half)
    text = ('<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="lsd3d-usd '
            f'samples">\n  <bounds minlat="{lat0:.7f}" minlon="{lon0:.7f}" maxlat="{lat1:.7f}" '
            f'maxlon="{lon1:.7f}"/>\n' + "\n".join(nodes + ways) + "\n</osm>\n")
    return _write(path, text)


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, fn in (("direct_junction.xodr", opendrive_direct_junction),
                     ("virtual_junction.xodr", opendrive_virtual_junction),
                     ("town_objects.xodr", opendrive_town),
                     ("town_objects.osm", osm_town_of_opendrive),
                     ("street_lanelet2.osm", lanelet2_real),
                     ("bounds_city.osm", osm_bounds_city)):
        print(fn(out / name))


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent)
