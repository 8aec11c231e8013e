"""Chunked proxy build: validity, seamless borders, ownership, chunk independence."""
from collections import Counter

import numpy as np
import pytest

from lsd3d_usd.proxy.chunks import ProxyBuilder, build_proxy, chunk_bounds
from lsd3d_usd.proxy.mesh import check_part
from lsd3d_usd.proxy.synthetic import grid_layout

GROUND = ("road", "curb", "sidewalk", "vegetation", "terrain")


@pytest.fixture(scope="module", params=["grid", "generated"])
def layout(request):
    if request.param == "grid":
        return grid_layout(3, 2)
    from lsd3d_usd.layout.generator import generate
    return generate(1, (300.0, 200.0), "urban")


@pytest.fixture(scope="module")
def proxy(layout):
    return build_proxy(layout)


def ground_top_triangles(parts):
    """Upward faces of the ground partition at each class's top height, with class names."""
    tris, cls = [], []
    for p in parts:
        if not p.part_id.startswith("ground/"):
            continue
        t = p.vertices[p.faces]
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        top = (n[:, 2] > 1e-12) & np.isclose(t[:, :, 2].min(1), p.vertices[:, 2].max())
        tris.append(t[top])
        cls += [p.cls] * int(top.sum())
    return np.concatenate(tris), np.array(cls)


def cover(tris, pts):
    """(P, T) bool: point p lies strictly inside triangle t (XY)."""
    a, b, c = tris[None, :, 0, :2], tris[None, :, 1, :2], tris[None, :, 2, :2]
    p = pts[:, None, :]

    def side(u, v, w):
        return (v[..., 0] - u[..., 0]) * (w[..., 1] - u[..., 1]) - (v[..., 1] - u[..., 1]) * (w[..., 0] - u[..., 0])
    return (side(a, b, p) > 0) & (side(b, c, p) > 0) & (side(c, a, p) > 0)


def test_every_part_of_every_chunk_is_valid(proxy):
    assert len(proxy) == 6
    counts = Counter()
    grid = "grid_layout" in str(proxy.get("_kind", "")) or any(
        p.part_id.startswith("tree_") for ps in proxy.values() for p in ps)
    for key, parts in proxy.items():
        for p in parts:
            assert check_part(p) == [], (key, p.part_id)
            counts[p.cls] += 1
    expected = ("road", "lane_marking", "curb", "sidewalk", "crosswalk", "building", "vegetation",
                "vehicle", "pole", "terrain", "traffic_light") + (("sign",) if grid else ())
    for cls in expected:
        assert counts[cls] > 0, cls


def test_ground_covers_each_chunk_exactly_once(proxy, layout):
    for (i, j), parts in proxy.items():
        tris, _ = ground_top_triangles(parts)
        e = tris[:, 1, :2] - tris[:, 0, :2], tris[:, 2, :2] - tris[:, 0, :2]
        area = 0.5 * np.abs(e[0][:, 0] * e[1][:, 1] - e[0][:, 1] * e[1][:, 0]).sum()
        assert area == pytest.approx(layout.chunk_size ** 2, rel=1e-9)
        x0, y0, x1, y1 = chunk_bounds(i, j, layout.chunk_size)
        rng = np.random.default_rng(i * 7 + j)
        pts = rng.uniform([x0, y0], [x1, y1], size=(3000, 2))
        hits = cover(tris, pts).sum(1)
        assert (hits == 1).mean() > 0.998      # the rest lie exactly on triangle edges
        assert (hits <= 1).all()


def test_neighbouring_chunks_meet_without_gap_or_double_cover(proxy, layout):
    """Walk every shared border: on both sides, each sample is covered once, by the same
    class (so at the same height: no step, no crack), and the border is the cut line."""
    s = layout.chunk_size
    eps = 1e-6
    n_checked = 0
    for (i, j), parts in proxy.items():
        for di, dj in ((1, 0), (0, 1)):
            nb = (i + di, j + dj)
            if nb not in proxy:
                continue
            x0, y0, x1, y1 = chunk_bounds(i, j, s)
            t = np.linspace(0.0, 1.0, 4001)[1:-1] + 1e-4    # avoid hitting vertices exactly
            if di:
                line = np.column_stack([np.full_like(t, x1), y0 + t * s])
                off = np.array([eps, 0.0])
            else:
                line = np.column_stack([x0 + t * s, np.full_like(t, y1)])
                off = np.array([0.0, eps])
            ta, ca = ground_top_triangles(parts)
            tb, cb = ground_top_triangles(proxy[nb])
            ha, hb = cover(ta, line - off), cover(tb, line + off)
            assert (ha.sum(1) == 1).all() and (hb.sum(1) == 1).all()
            cls_a = ca[ha.argmax(1)]
            cls_b = cb[hb.argmax(1)]
            assert (cls_a == cls_b).mean() > 0.999
            # nothing of the ground pokes across the border
            xy_a = np.concatenate([p.vertices[:, :2] for p in parts if p.part_id.startswith("ground/")])
            assert xy_a.max(0)[0 if di else 1] <= (x1 if di else y1) + 1e-9
            n_checked += 1
    assert n_checked == 7                      # 3x2 chunks: 4 vertical + 3 horizontal borders


def test_compact_solids_are_owned_by_one_chunk(proxy):
    owner = {}
    for key, parts in proxy.items():
        for p in parts:
            if p.cls in ("building", "vehicle", "pole", "sign", "traffic_light") or "/crown" in p.part_id:
                assert p.part_id not in owner, f"{p.part_id} in {owner.get(p.part_id)} and {key}"
                owner[p.part_id] = key


def test_a_chunk_built_alone_equals_the_same_chunk_built_with_all(layout, proxy):
    alone = build_proxy(layout, chunks=[(1, 0)])[(1, 0)]
    full = proxy[(1, 0)]
    assert [p.part_id for p in alone] == [p.part_id for p in full]
    for a, b in zip(alone, full):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)


def test_inputs_hash_changes_only_for_affected_chunks():
    import copy
    layout = grid_layout(3, 2)
    b0 = ProxyBuilder(layout)
    h0 = {k: b0.inputs(k).hash for k in b0.chunks()}
    assert len(set(h0.values())) == len(h0)
    changed = copy.deepcopy(layout)
    bd = next(b for b in changed.buildings if b.footprint[:, 0].max() < 80 and b.footprint[:, 1].max() < 80
              and b.footprint[:, 0].min() > 20 and b.footprint[:, 1].min() > 20)
    bd.height_hint += 3.0
    b1 = ProxyBuilder(changed)
    h1 = {k: b1.inputs(k).hash for k in b1.chunks()}
    assert [k for k in h0 if h0[k] != h1[k]] == [(0, 0)]
