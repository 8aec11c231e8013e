"""Pedestrian and cyclist assets, `actors add --pedestrians/--cyclists`, what plain usd-core and
the sensors' label tables see of them."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from pxr import Usd, UsdGeom, UsdSemantics

from lsd3d_usd.actors import assets as A
from lsd3d_usd.actors import people as P
from lsd3d_usd.scene import ACTORS_PATH, Scene

SAMPLE = Path(__file__).resolve().parents[1] / "samples" / "layouts" / "hand_crossing.usda"


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    return P.write_people_library(tmp_path_factory.mktemp("people"))


def test_people_asset_conventions(library):
    assert set(library) == set(P.PEDESTRIAN_KINDS + P.CYCLIST_KINDS)
    for kind, path in library.items():
        stage = Usd.Stage.Open(str(path))
        root = stage.GetDefaultPrim()
        assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
        cls = "cyclist" if kind == "cyclist" else "pedestrian"
        assert list(UsdSemantics.LabelsAPI(root, "class").GetLabelsAttr().Get()) == [cls]
        assert root.GetAttribute(A.KIND_ATTR).Get() == kind
        info = A.read_asset(path)
        assert info.label == cls and info.kind == kind
        # over the whole motion cycle: feet never below the ground, standing on it, inside
        # the extentsHint and the dimensions (footprint centred on the origin)
        hint = np.array(UsdGeom.ModelAPI(root).GetExtentsHint())
        cache_lo, cache_hi = np.full(3, np.inf), np.full(3, -np.inf)
        for code in np.linspace(0, P.CYCLE_CODES, 13):
            cache = UsdGeom.XformCache(Usd.TimeCode(float(code)))
            for prim in Usd.PrimRange(root):
                if prim.IsA(UsdGeom.Mesh):
                    M = np.array(cache.GetLocalToWorldTransform(prim)).T
                    v = A.mesh_data_from_prim(prim, M).vertices
                    cache_lo, cache_hi = np.minimum(cache_lo, v.min(0)), np.maximum(cache_hi, v.max(0))
        assert cache_lo[2] > -1e-6 and cache_lo[2] < 0.02
        assert np.all(cache_lo >= hint[0] - 1e-5) and np.all(cache_hi <= hint[1] + 1e-5)
        L, W, H = info.dimensions
        assert np.all(np.abs(cache_lo[:2]) <= np.array([L, W]) / 2 + 1e-5)
        assert np.all(cache_hi[:2] <= np.array([L, W]) / 2 + 1e-5) and abs(cache_hi[2] - H) < 1e-5
        # the limbs / wheels are time-sampled xform ops (one cycle), rest pose by default
        joints = [stage.GetPrimAtPath(f"{root.GetPath()}/{j}") for j in P.joint_names(kind)]
        for j in joints:
            rot = j.GetAttribute("xformOp:rotateY")
            assert rot.GetNumTimeSamples() > 10 and rot.Get() == 0.0
    dims = {k: A.read_asset(p).dimensions for k, p in library.items()}
    assert dims["child"][2] < 1.4 < dims["adult"][2] <= dims["adult_broad"][2]
    assert dims["adult"][1] < dims["adult_broad"][1]
    assert 1.5 < dims["cyclist"][0] < 2.0 and 1.6 < dims["cyclist"][2] < 1.9


def test_gait_and_wheels_follow_the_distance():
    b = P.BODIES["adult"]
    d = np.linspace(0, 3 * b.stride, 200)
    g = P.gait_angles(d, np.full_like(d, P.REFERENCE_WALK), b)
    assert np.allclose(g["LeftLeg"], -g["RightLeg"])
    assert np.allclose(g["LeftArm"], -g["LeftLeg"] * b.arm_swing / b.leg_swing)
    assert abs(np.abs(g["LeftLeg"]).max() - b.leg_swing) < 0.1
    # one cycle per stride, and standing still is the rest pose
    assert np.allclose(P.gait_angles(d + b.stride, 1.3, b)["LeftLeg"], g["LeftLeg"])
    assert np.all(P.gait_angles(d, 0.0, b)["LeftLeg"] == 0)
    c = P.cyclist_angles(np.array([0.0, 2 * np.pi * P.WHEEL_R]))
    assert np.allclose(c["FrontWheel"], [0.0, 360.0]) and np.allclose(c["Crank"], [0.0, 360.0 / P.GEAR])


def test_wheel_spin_rolls_forward():
    """A positive rotateY of the wheel moves its bottom point backwards (-X) relative to the hub:
    rolling forward along +X without slipping."""
    a = np.radians(10.0)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    bottom = R @ np.array([0.0, 0.0, -P.WHEEL_R])
    assert bottom[0] < 0


@pytest.fixture()
def scene(tmp_path):
    from lsd3d_usd.layout.usdio import layout_to_stage, read_layout
    sc = Scene.create(tmp_path / "scene")
    sc.write_layer("layout", layout_to_stage(read_layout(SAMPLE)))
    return sc


def test_actors_add_people_cli_and_plain_usd(scene, capsys):
    from lsd3d_usd.cli import main
    assert main(["actors", "add", str(scene.root), "--parked", "0", "--moving", "3", "--pedestrians",
                 "6", "--cyclists", "2", "--seconds", "2", "--seed", "4"]) == 0
    out = capsys.readouterr().out
    assert "3 moving actors, 6 pedestrians, 2 cyclists" in out
    assert (scene.root / "assets" / "adult.usda").is_file() and (scene.root / "assets" / "cyclist.usda").is_file()
    # plain usd-core (no lsd3d_usd import, no plugin) sees the references and time samples
    code = textwrap.dedent(f"""
        import json
        from pxr import Usd, UsdGeom, UsdSemantics
        st = Usd.Stage.Open({str(scene.root_layer_path)!r})
        out = {{}}
        for group in ("Pedestrians", "Cyclists"):
            g = st.GetPrimAtPath("{ACTORS_PATH}/" + group)
            rows = []
            for p in g.GetChildren():
                refs = p.GetPrimStack()[0].referenceList.prependedItems
                leg = st.GetPrimAtPath(str(p.GetPath()) + "/LeftLeg")
                lab = UsdSemantics.LabelsAPI(p, "class").GetLabelsAttr().Get()
                rows.append([refs[0].assetPath, UsdGeom.Xformable(p).GetTimeSamples()[-1],
                             leg.GetAttribute("xformOp:rotateY").GetNumTimeSamples(), list(lab)])
            out[group] = rows
        print(json.dumps(out))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                       env={"PATH": "/usr/bin:/bin"})
    seen = json.loads(r.stdout)
    assert len(seen["Pedestrians"]) == 6 and len(seen["Cyclists"]) == 2
    for ref, last, n_leg, label in seen["Pedestrians"] + seen["Cyclists"]:
        assert ref.startswith("../assets/") and last == pytest.approx(2.0 * 24.0) and n_leg == 21
        assert label[0] in ("pedestrian", "cyclist")
    # the sensors' instance table labels them by class; limbs move within the walkers
    from lsd3d_usd.actors.usdio import ActorSet
    from lsd3d_usd.views.labels import Instances
    stage = Usd.Stage.Open(str(scene.root_layer_path))
    aset = ActorSet(stage)
    rows = Instances.of(aset).rows
    assert sorted(r["class"] for r in rows) == ["cyclist"] * 2 + ["pedestrian"] * 6 + ["vehicle"] * 3
    assert {r["class_id"] for r in rows if r["class"] == "pedestrian"} == {12}
    walkers = [q for q, a in enumerate(aset.actors) if a.label == "pedestrian"
               and stage.GetPrimAtPath(a.path).GetAttribute("lsd3d:actor:behaviour").Get() == "walking"]
    moved = 0
    for q in walkers:
        a = aset.actors[q]
        assert len(a.animated) == 4                     # two legs, two arms
        feet = []
        for code in (0.0, 6.0, 12.0):
            M = np.linalg.inv(aset.transforms(code)[q]) @ aset.part_transforms(q, code)[0]
            local = a.animated[0][2]                    # the left leg in its own frame
            v = local @ M[:3, :3].T + M[:3, 3]          # in the walker's frame
            feet.append(v[np.argmin(v[:, 2])])
            assert v[:, 2].min() > -1e-6                # never below the ground
        moved += max(abs(f[0] - feet[0][0]) for f in feet) > 0.05   # the foot swings along x
    assert moved > 0
    # re-run with the same seed: the same layer
    first = scene.layer_path("actors").read_text()
    assert main(["actors", "add", str(scene.root), "--parked", "0", "--moving", "3", "--pedestrians",
                 "6", "--cyclists", "2", "--seconds", "2", "--seed", "4"]) == 0

    def body(t):
            skip = ("timestamp", "created =", "double seconds =")
            return [ln for ln in t.splitlines() if not any(k in ln for k in skip)]
    assert body(scene.layer_path("actors").read_text()) == body(first)


# the counts' bounds are the configuration tree's (actors.config), shared with generate
@pytest.mark.parametrize("argv,needle", [
    (["--pedestrians", "-1"], "--pedestrians"),
    (["--cyclists", "100000"], "--cyclists"),
    (["--pedestrians", "99999999", "--cyclists", "-3"], "--pedestrians"),
])
def test_bad_counts_one_error_line(scene, cli_error, argv, needle):
    before = sorted(p.name for p in (scene.root / "layers").iterdir())
    cli_error(["actors", "add", str(scene.root), *argv], needle, "must be in [0, ")
    assert sorted(p.name for p in (scene.root / "layers").iterdir()) == before   # nothing written


def test_layout_without_sidewalks_notes_how_many(tmp_path, capsys):
    from lsd3d_usd.cli import main
    from lsd3d_usd.layout.model import LaneCenter, Layout
    from lsd3d_usd.layout.usdio import layout_to_stage
    # a 60 m road whose sidewalk band lies outside the layout's extent: no sidewalk at all
    L = Layout(lanes=[LaneCenter("a", points=[[0, 0, 0], [60, 0, 0]])], extent=((0.0, -1.7), (60.0, 1.7)))
    sc = Scene.create(tmp_path / "s")
    sc.write_layer("layout", layout_to_stage(L))
    assert main(["actors", "add", str(sc.root), "--parked", "0", "--moving", "0", "--pedestrians", "5",
                 "--cyclists", "1", "--seconds", "1"]) == 0
    out = capsys.readouterr().out
    notes = [ln for ln in out.splitlines() if ln.startswith("note:")]
    assert notes == ["note: no pedestrians: the layout has no sidewalk area (no sidewalk polygons or "
                     "lanes, and none derived along its roads within its extent)"], out
    assert "0 pedestrians, 1 cyclists" in out


def test_sensor_class_table_has_the_new_classes():
    from lsd3d_usd import semantics
    from lsd3d_usd.views.labels import class_table
    assert semantics.CLASSES[:12][-1] == "traffic_light"          # appended, never reordered
    assert semantics.CLASSES[12:14] == ("pedestrian", "cyclist")
    assert len(semantics.CLASS_COLORS) == len(semantics.CLASSES)
    rows = {r["name"]: r for r in class_table()}
    assert rows["pedestrian"]["id"] == 12 and rows["cyclist"]["id"] == 13
    assert rows["pedestrian"]["color"] == [220, 20, 60]


def test_user_people_assets_by_class(scene, tmp_path, capsys):
    """--assets DIR: an asset of class pedestrian is a pedestrian whatever its file name; a
    folder without one refuses --pedestrians with one line naming the folder."""
    from lsd3d_usd.cli import main
    lib = tmp_path / "lib"
    A.write_vehicle_asset("car", lib / "car.usda")
    P.write_person_asset("child", lib / "kid.usda")
    assert main(["actors", "add", str(scene.root), "--parked", "0", "--moving", "2", "--pedestrians", "3",
                 "--seconds", "1", "--assets", str(lib)]) == 0
    stage = Usd.Stage.Open(str(scene.root_layer_path))
    kids = stage.GetPrimAtPath(f"{ACTORS_PATH}/Pedestrians").GetChildren()
    assert len(kids) == 3 and all(k.GetName().startswith("Kid_") for k in kids)
    cars = stage.GetPrimAtPath(f"{ACTORS_PATH}/Moving").GetChildren()
    assert len(cars) == 2 and all(c.GetName().startswith("Car_") for c in cars)
    (lib / "kid.usda").unlink()
    capsys.readouterr()
    assert main(["actors", "add", str(scene.root), "--pedestrians", "2", "--assets", str(lib)]) == 1
    err = capsys.readouterr().err
    assert "--pedestrians 2" in err and str(lib) in err and "pedestrian" in err


def test_generate_configuration_keys():
    from lsd3d_usd.config import generate_config
    from lsd3d_usd.errors import InputError
    assert generate_config(pedestrians=3, cyclists=1).actors.pedestrians == 3
    assert generate_config(actors={"cyclists": 2}).actors.cyclists == 2
    with pytest.raises(InputError, match="--pedestrians: must be in"):
        generate_config(pedestrians=-1)
    with pytest.raises(InputError, match="--cyclists: must be in"):
        generate_config(cyclists=10_000)
