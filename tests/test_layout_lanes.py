"""The drivable lane graph: one definition of drivable, `layout lanes`, routes, and route
errors that name valid ids."""
from pathlib import Path

import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import lanes as LN
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout import routes as R
from lsd3d_usd.layout.usdio import read_layout

SAMPLES = Path(__file__).resolve().parents[1] / "samples" / "layouts"


def _lane(lid, pts, **kw):
    return m.LaneCenter(lid, points=np.array(pts, float), **kw)


def test_drivable_is_one_definition():
    L = m.Layout()
    for t in m.LANE_TYPES:
        L.add(_lane(f"{t}_lane", [[0, 0], [10, 0]], lane_type=t))
    L.add(_lane("stopped", [[0, 5], [10, 5]], speed_limit_mps=0.0))
    L.add(_lane("dot", [[1, 1], [1, 1]]))
    assert [ln.id for ln in L.drivable_lanes()] == [f"{t}_lane" for t in m.DRIVABLE_TYPES]
    # every consumer sees the same lanes: traffic, GGDS cameras, surfel density
    from lsd3d_usd.layout.routes import LaneGraph
    from lsd3d_usd.conditioning.view_sampling import sample_views
    from lsd3d_usd.splats.importance import lane_samples
    assert LaneGraph(L).ids == [ln.id for ln in L.drivable_lanes()]
    assert {v.lane_id for v in sample_views(L, 40, 32, 24, seed=3)} <= set(LaneGraph(L).ids)
    assert np.allclose(lane_samples(L)[:, 1], 0.0)   # only the y=0 lanes (the drivable ones)


def test_longest_route_on_the_crossing():
    L = read_layout(SAMPLES / "hand_crossing.usda")
    ids, length = R.longest_route(L)
    assert length == pytest.approx(120.0) and len(ids) == 3
    assert all(b in L.lane_by_id(a).successors for a, b in zip(ids, ids[1:]))
    assert R.longest_route(L) == (ids, length)                         # deterministic
    short, s_len = R.longest_route(L, max_length=60.0)
    assert 60.0 <= s_len < 120.0 and len(short) == 2
    assert R.longest_route(m.Layout()) == ([], 0.0)


def test_longest_route_survives_loops_and_budget():
    L = m.Layout()   # a ring of 4 lanes: no entry lane, every lane starts a search
    corners = [(0, 0), (10, 0), (10, 10), (0, 10)]
    for k in range(4):
        L.add(_lane(f"r{k}", [corners[k], corners[(k + 1) % 4]], successors=[f"r{(k + 1) % 4}"]))
    ids, length = R.longest_route(L)
    assert ids == ["r0", "r1", "r2", "r3"] and length == pytest.approx(40.0)   # no lane twice
    assert len(R.longest_route(L, budget=2)[0]) == 2


def test_route_errors_name_valid_ids():
    from lsd3d_usd.layout.routes import LaneGraph
    L = read_layout(SAMPLES / "hand_crossing.usda")
    L.add(_lane("park_1", [[-40, -5.5], [-20, -5.5]], lane_type="parking", speed_limit_mps=0.0))
    g = LaneGraph(L)
    with pytest.raises(InputError, match=r"'w_inn' is not a lane of the layout; drivable lanes "
                                         r"nearby: w_in.*layout lanes"):
        g.route_indices(["w_inn"])
    with pytest.raises(InputError) as e:
        g.route_indices(["park_1"])
    assert "is a parking lane" in str(e.value) and "nearby: w_in," in str(e.value)
    with pytest.raises(InputError, match="nearby: "):
        g.route_indices(["zzzzzz"])     # nothing similar: still some valid ids


def test_layout_lanes_command(tmp_path, capsys):
    import json

    from lsd3d_usd.cli import main
    from lsd3d_usd.views.images import read_image
    png = tmp_path / "lanes.png"
    assert main(["layout", "lanes", str(SAMPLES / "hand_crossing.usda"), "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "13 drivable lanes" in out and "longest route (120.0 m): --route " in out
    row = next(line for line in out.splitlines() if line.split()[:1] == ["w_in"])
    assert row.split()[1:3] == ["driving", "50.0m"] and row.endswith("j_we, j_ws")
    im = read_image(png)
    assert im.shape[0] > 400 and im.shape[1] > 400 and im[..., :3].std() > 0.05
    assert main(["layout", "lanes", str(SAMPLES / "hand_crossing.usda"), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    w_in = next(r for r in data["lanes"] if r["id"] == "w_in")
    assert w_in["successors"] == ["j_we", "j_ws"] and w_in["length_m"] == 50.0
    assert data["longest_route"]["length_m"] == 120.0
    assert main(["layout", "info", str(SAMPLES / "hand_crossing.usda")]) == 0
    assert "lane graph: 13 drivable lanes, 10 successor links" in capsys.readouterr().out
    assert main(["layout", "lanes", str(SAMPLES / "hand_crossing.usda"), "--png", str(tmp_path)]) == 1
    assert "--png" in capsys.readouterr().err
