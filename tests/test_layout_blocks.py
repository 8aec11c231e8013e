"""Each block type on its own: parameter space, claims, sockets, geometry invariants; and a
new block type added by registration alone."""
import numpy as np
import pytest
import shapely
from shapely.geometry import Point, Polygon

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import blocks as B
from lsd3d_usd.layout import blocktypes as BT
from lsd3d_usd.layout import generator as G
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout import roadnet as R

NODE = np.array([50.0, 50.0])
SEC2 = B.Section(2, 3.25)
SEC1 = B.Section(1, 3.5)


def single_block(block_id, angles_deg, sections, params, style="urban", node=NODE):
    """A 100 m × 100 m description holding one block at ``node`` whose roads leave at
    ``angles_deg`` toward virtual nodes outside the extent."""
    sp = {k: (list(v) if isinstance(v, tuple) else v) for k, v in G.STYLE_PARAMS[style].items()}
    nodes = {G.node_key(0, 0): {"ij": [0, 0], "pos": [float(node[0]), float(node[1])], "real": True,
                                "block": block_id, "params": params}}
    edges = []
    for k, (ang, sec) in enumerate(zip(angles_deg, sections)):
        far = node + 120.0 * np.array([np.cos(np.radians(ang)), np.sin(np.radians(ang))])
        key = G.node_key(10 + k, 10)
        nodes[key] = {"ij": [10 + k, 10], "pos": [float(far[0]), float(far[1])], "real": False}
        edges.append({"key": f"e{k}", "a": G.node_key(0, 0), "b": key, "section": sec.to_dict()})
    return {"generator": G.GENERATOR_NAME, "version": G.GENERATOR_VERSION, "seed": 1, "style": style,
            "extent": [0.0, 0.0, 100.0, 100.0], "chunk_size": 100.0,
            "globals": {"lane_width": 3.25, "sidewalk": 3.0, "setback": 1.0}, "style_params": sp,
            "nodes": nodes, "edges": edges, "chunks": {G.node_key(0, 0): 5}}


CASES = {
    "junction4": ("junction", [0, 90, 180, 270], [SEC2, SEC1, SEC2, SEC1],
                  {"corner_radius": 8.0, "crosswalks": True, "stop_signs": True}),
    "junctionT": ("junction", [0, 100, 180], [SEC2, SEC2, SEC2],
                  {"corner_radius": 6.0, "crosswalks": False, "stop_signs": False}),
    "roundabout": ("roundabout", [10, 120, 240], [SEC1, SEC1, SEC1],
                   {"island": 9.0, "ring_width": 4.75, "corner_radius": 7.0}),
    "curve": ("curve", [0, 120], [SEC2, SEC2], {"radius": 40.0}),
    "curve_straight": ("curve", [0, 180.02], [SEC1, SEC1], {"radius": 30.0}),
    "deadend": ("deadend", [30], [SEC2], {}),
}


@pytest.mark.parametrize("name", CASES)
def test_block_geometry_invariants(name):
    block_id, angles, sections, params = CASES[name]
    desc = single_block(block_id, angles, sections, params)
    ctx = G.Context(desc)
    blk = ctx.block_at(G.node_key(0, 0))
    assert type(blk) is BT.BLOCKS.get(block_id)
    L = G.build(desc)

    # sockets: on each arm at its cut, inside the block's reach; road lanes start on the socket line
    sockets = blk.sockets()
    assert len(sockets) == len(angles)
    for sock, arm in zip(sockets, blk.arms):
        d = np.linalg.norm(sock.position - NODE)
        assert d == pytest.approx(arm.cut) and arm.cut <= R.MAX_BLOCK_REACH
        assert np.allclose((sock.position - NODE) / max(d, 1e-12), sock.direction) or d == 0
        for k, (lid, p, w) in enumerate(R.end_lanes(arm.edge, arm.at_a, True)):
            rel = p - sock.position
            assert abs(rel @ sock.direction) < 1e-9                       # on the socket line
            assert abs(abs(rel @ B.left_normal(sock.direction)) - sock.section.lane_offset(k)) < 1e-9
            assert L.lane_by_id(lid).widths[-1] == w

    # lanes: links resolve and meet within 1 cm; every block lane joins road lanes at both ends
    for lane in L.lanes:
        for s in lane.successors:
            gap = np.linalg.norm(L.lane_by_id(s).points[0] - lane.points[-1])
            assert gap < 0.01, (lane.id, s, gap)
            assert lane.id in L.lane_by_id(s).predecessors
    block_lanes = [ln for ln in L.lanes if ln.road_id == blk.road_id]
    road_lanes = [ln for ln in L.lanes if ln.road_id != blk.road_id and ln.lane_type == "driving"]
    if block_id != "deadend":
        assert block_lanes and all(ln.predecessors and ln.successors for ln in block_lanes)
        # from every incoming road lane some other arm is reachable
        for ln in road_lanes:
            if np.linalg.norm(ln.points[-1][:2] - NODE) < R.MAX_BLOCK_REACH:
                assert ln.successors, f"{ln.id} ends at the block without a successor"
    else:
        assert not block_lanes

    # near the block the road surface covers every lane centre; junction turn connectors (Hermite
    # curves) cut the rounded curb corner, by less than their half width in these cases
    road = shapely.union_all([Polygon(a.polygon[:, :2]) for a in L.road_areas])
    for ln in L.lanes:
        near = ln.points[np.linalg.norm(ln.points[:, :2] - NODE, axis=1) < 40.0, :2]
        if len(near) == 0:
            continue
        off = max(road.distance(Point(p)) for p in near)
        allowed = ln.widths.min() / 2 if (block_id == "junction" and ln in block_lanes) else 0.01
        assert off <= allowed, (ln.id, off)
    geo = blk.build()
    if geo is not None:
        assert geo.area.within(Point(NODE).buffer(R.MAX_BLOCK_REACH)), name

    if name == "junction4":
        assert len(L.crosswalks) == 4 and len(L.stop_lines) == 4 and len(L.stop_signs) == 4
    if name == "junctionT":
        assert not L.crosswalks and not L.stop_signs and len(L.stop_lines) == 3
    if name == "roundabout":
        assert len(L.vegetation_zones) == 1 and any(t.id.endswith("islandtree") for t in L.trees)
        ring = [ln for ln in block_lanes if "_ring" in ln.id]
        assert len(ring) == 6   # an entry and an exit mark per arm
    if name == "curve":
        radius, t, turn = blk.radius_t()
        assert abs(turn) == pytest.approx(np.radians(60.0)) and radius == pytest.approx(40.0)
        assert t == pytest.approx(40.0 * np.tan(np.radians(30.0)))
    if name == "curve_straight":
        assert np.isinf(blk.radius_t()[0]) and blk.cutbacks() == [5.0, 5.0]


def test_curve_tangent_capped_to_stay_in_its_chunk():
    desc = single_block("curve", [0, 20], [SEC1, SEC1], {"radius": 60.0})   # a 160° turn
    blk = G.Context(desc).block_at(G.node_key(0, 0))
    radius, t, _ = blk.radius_t()
    assert t == R.MAX_BLOCK_REACH - 3 and radius < 60.0


@pytest.mark.parametrize("cls", [c for _, c in BT.BLOCKS.items()])
@pytest.mark.parametrize("style", G.STYLES)
def test_parameter_space_sampling(cls, style):
    sp = G.STYLE_PARAMS[style]
    glob = {"lane_width": 3.3}
    for n_arms in (2, 3, 4):
        sections = [SEC1] * n_arms
        space = cls.parameter_space(sections, sp, glob)
        rng = np.random.default_rng(3)
        for _ in range(200):
            params = cls.sample_params(rng, sections, sp, glob)
            assert list(params) == list(space)
            for k, v in params.items():
                assert space[k].contains(v), (cls.ID, k, v, space[k])
        # the same generator state gives the same parameters
        a = cls.sample_params(np.random.default_rng(9), sections, sp, glob)
        assert a == cls.sample_params(np.random.default_rng(9), sections, sp, glob)


def test_parameter_kinds():
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert BT.Chance(1.0, active=False).sample(rng) is False
    assert rng.bit_generator.state == state      # an inactive chance draws nothing
    assert BT.Chance(1.0).sample(rng) is True and BT.Chance(0.0).sample(rng) is False
    vals = [BT.Uniform(5.0, 9.0).sample(rng) for _ in range(500)]
    assert min(vals) >= 5.0 and max(vals) <= 9.0 and max(vals) - min(vals) > 3.5
    assert all(round(v, 2) == v for v in vals)
    assert not BT.Uniform(5.0, 9.0).contains(9.5) and not BT.Chance(0.5, False).contains(True)
    assert BT.Fixed(4.75).contains(4.75) and not BT.Fixed(4.75).contains(4.8)


def test_claims_by_degree_and_sections():
    sp = dict(G.STYLE_PARAMS["urban"], p_roundabout=1.0)
    rng = np.random.default_rng(0)
    assert BT.choose(rng, [], sp) is BT.NoBlock
    assert BT.choose(rng, [SEC1], sp) is BT.DeadEnd
    assert BT.choose(rng, [SEC1, SEC1], sp) is BT.Curve
    assert BT.choose(rng, [SEC1, SEC2], sp) is BT.Junction          # unequal roads: no curve
    assert BT.choose(rng, [SEC1] * 3, sp) is BT.Roundabout
    wide = B.Section(3, 3.5, median=4.0)                            # half width 12.5 m
    assert BT.choose(rng, [wide] * 4, sp) is BT.Junction
    assert BT.choose(rng, [SEC1] * 4, dict(sp, p_roundabout=0.0)) is BT.Junction
    assert BT.BLOCKS.ordered()[-1] == "junction"


def test_new_block_type_by_registration_only():
    """A block type added with register() is chosen by plan() and built by build()."""
    class Plaza(BT.Junction):
        """A junction of four single-lane roads with crosswalks on every approach."""
        ID = "plaza"

        @classmethod
        def claims(cls, rng, sections, sp):
            return len(sections) == 4 and all(s.lanes == 1 for s in sections)

        @classmethod
        def parameter_space(cls, sections, sp, glob):
            return {"corner_radius": BT.Uniform(4.0, 5.0), "crosswalks": BT.Chance(1.0),
                    "stop_signs": BT.Chance(0.0)}

    BT.register(Plaza)                       # before the catch-all junction
    try:
        assert BT.BLOCKS.ordered()[-2:] == ["plaza", "junction"]
        with pytest.raises(InputError, match="already registered"):
            BT.register(Plaza)
        n_plazas = 0
        for seed in range(12):
            desc = G.plan(seed, (300.0, 300.0), "suburban")
            plazas = [k for k, n in desc["nodes"].items() if n.get("block") == "plaza"]
            n_plazas += len(plazas)
            L = G.build(desc)
            for k in plazas:
                assert 4.0 <= desc["nodes"][k]["params"]["corner_radius"] <= 5.0
                assert sum(cw.id.startswith(("h", "v")) for cw in L.crosswalks) >= 4
                assert any(ln.road_id == f"n{k}" for ln in L.lanes)
        assert n_plazas > 0
    finally:
        BT.BLOCKS.unregister("plaza")


def test_unknown_block_in_description_is_an_input_error():
    desc = single_block("ziggurat", [0, 90], [SEC1, SEC1], {})
    with pytest.raises(Exception, match="node 0_0: unknown block type 'ziggurat'"):
        G.build(desc)


def test_block_lane_ids_and_road_ids_are_unique_per_node():
    desc = single_block(*CASES["junction4"])
    L = G.build(desc)
    ids = [f.id for f in L.features()]
    assert len(ids) == len(set(ids))
    assert all(isinstance(f, m.LaneCenter) for f in L.lanes)
