"""Sensor outputs of a rig render: the camera ground truth (depth, semantic, instance, normal),
boxes and LiDAR sweeps, checked against the geometry they came from (the proxy mesh and its
UsdSemantics labels, ray cast with trimesh/Embree) and read back by independent readers
(OpenImageIO, trimesh's PLY loader, numpy)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import generate_small

OUTPUTS = ("rgb", "depth", "semantic", "instance", "normal", "boxes")
FRAMES = 2
WIDTH = 160


@pytest.fixture(scope="module")
def sensors(tmp_path_factory):
    """A scene whose surfels lie on the proxy (no GGDS steps) with traffic, rendered through
    nuscenes6 with every camera output and the hdl32 LiDAR."""
    from lsd3d_usd.views import rig
    from lsd3d_usd.views.options import RigOptions
    root = tmp_path_factory.mktemp("sensors")
    generate_small(root / "scene", steps=0, actors=True, surfels=100_000, pedestrians=0, cyclists=0)
    # the ego creeps along a corner of the junction, looking across it (traffic passes in
    # front of it, none drives through it)
    traj = root / "poses.json"
    traj.write_text(json.dumps([{"t": 0.0, "x": -9.0, "y": -9.0, "yaw": 0.785},
                                {"t": 1.0, "x": -8.6, "y": -8.6, "yaw": 0.785}]))
    res = rig.render_rig(root / "scene", root / "out",
                         RigOptions(name="nuscenes6", trajectory=traj, seconds=1.0, fps=2.0,
                                    lidar="hdl32", video=False, overview=False),
                         width=WIDTH, outputs=OUTPUTS, progress=False, log=lambda *_: None)
    return root / "scene", root / "out", res


def _exr(path):
    import OpenImageIO as oiio
    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    px = inp.read_image("float")
    inp.close()
    return list(spec.channelnames), np.asarray(px)


def _png(path):
    import OpenImageIO as oiio
    inp = oiio.ImageInput.open(str(path))
    fmt = inp.spec().format
    px = inp.read_image(fmt)
    inp.close()
    return np.asarray(px)[..., 0], str(fmt)


def _proxy(scene):
    """The proxy mesh with each face's class, read from its UsdSemantics labels."""
    import trimesh
    from pxr import Usd, UsdGeom, UsdSemantics

    from lsd3d_usd.semantics import CLASS_ID
    stage = Usd.Stage.Open(str(Path(scene) / "scene.usda"))
    V, F, C, n = [], [], [], 0
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh) or not prim.GetPath().pathString.startswith("/World/Proxy"):
            continue
        labels = UsdSemantics.LabelsAPI(prim, "class").GetLabelsAttr().Get()
        if not labels:
            continue
        m = UsdGeom.Mesh(prim)
        pts = np.asarray(m.GetPointsAttr().Get(), np.float64)
        counts = np.asarray(m.GetFaceVertexCountsAttr().Get())
        assert np.all(counts == 3)
        faces = np.asarray(m.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        M = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(0.0), np.float64)
        V.append(pts @ M[:3, :3] + M[3, :3])
        F.append(faces + n)
        C.append(np.full(len(faces), CLASS_ID[labels[0]]))
        n += len(pts)
    assert F, "no labelled proxy meshes"
    return trimesh.Trimesh(np.concatenate(V), np.concatenate(F), process=False), np.concatenate(C)


def _cast(mesh, cls, origins, dirs):
    """(distance, face class, |cos| of the incidence) of each ray's first proxy hit."""
    loc, ray, tri = mesh.ray.intersects_location(origins, dirs, multiple_hits=False)
    t = np.full(len(dirs), np.inf)
    t[ray] = np.einsum("ij,ij->i", loc - origins[ray], dirs[ray])
    c = np.full(len(dirs), -1)
    c[ray] = cls[tri]
    cos = np.zeros(len(dirs))
    cos[ray] = np.abs(np.einsum("ij,ij->i", mesh.face_normals[tri], dirs[ray]))
    return t, c, cos


def _rig_cameras(out):
    from pxr import Usd

    from lsd3d_usd.render.camera import from_usd
    from lsd3d_usd.sensors.rigs import load_rig
    NUSCENES6 = load_rig("nuscenes6").cameras
    stage = Usd.Stage.Open(str(out / "rig.usda"))
    tcps = stage.GetTimeCodesPerSecond()
    prims = {p.GetName(): p for p in stage.Traverse() if p.GetName() in {c.name for c in NUSCENES6}}
    for k in range(FRAMES):
        boxes = json.loads((out / "boxes" / f"{k:04d}.json").read_text())
        code = round(boxes["time"] * tcps, 6)
        for spec in NUSCENES6:
            yield k, spec.name, from_usd(prims[spec.name], code, WIDTH, spec.height_for(WIDTH)), boxes


def test_files_tables_and_formats(sensors):
    from lsd3d_usd.views.labels import SKY
    _, out, res = sensors
    classes = json.loads((out / "classes.json").read_text())
    ids = {c["id"]: c["name"] for c in classes["classes"]}
    assert classes["sky"] == SKY and ids[SKY] == "sky"
    assert {"road", "sidewalk", "building", "vehicle"} <= set(ids.values())
    assert all(len(c["color"]) == 3 for c in classes["classes"])
    inst = json.loads((out / "instances.json").read_text())
    prims = [r["prim"] for r in inst["instances"]]
    assert prims == sorted(prims) and [r["id"] for r in inst["instances"]] == list(range(1, len(prims) + 1))
    for name, pngs in res.frames.items():
        assert len(pngs) == FRAMES
        for png in pngs:
            stem = str(png)[:-4]
            ch, z = _exr(stem + ".depth.exr")
            assert ch == ["Z"] and z.dtype == np.float32
            assert np.isinf(z).any() and (z[np.isfinite(z)] > 0).all()    # sky and the world
            sem, fmt = _png(stem + ".semantic.png")
            assert fmt == "uint8" and set(np.unique(sem)) <= set(ids)
            np.testing.assert_array_equal(np.isinf(z[..., 0]), sem == SKY)
            ins, fmt = _png(stem + ".instance.png")
            assert fmt == "uint16" and ins.max() <= len(prims)
            ch, nrm = _exr(stem + ".normal.exr")
            assert ch == ["X", "Y", "Z"]
            drawn = np.isfinite(z[..., 0])
            np.testing.assert_allclose(np.linalg.norm(nrm[drawn], axis=-1), 1.0, atol=1e-3)
            assert Path(stem + ".semantic_preview.png").is_file()


def test_pixels_depth_and_class_match_the_proxy(sensors):
    """Surfels lie on the proxy here, so each static-world pixel's depth is the proxy's along
    the pixel's ray and its class the UsdSemantics label of the face the ray meets. The depth
    may come from anywhere within the rasteriser's screen-space filter (about a pixel) of the
    pixel centre: the tolerance is 1.5 pixels of the surface's depth gradient there (large
    where the ray grazes it; the LiDAR, which has no such filter, is exact)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    from lsd3d_usd.views.labels import SKY
    scene, out, res = sensors
    mesh, cls = _proxy(scene)
    agree, rel = [], []
    for k, name, cam, _ in _rig_cameras(out):
        stem = str(res.frames[name][k])[:-4]
        z = _exr(stem + ".depth.exr")[1][..., 0]
        sem = _png(stem + ".semantic.png")[0]
        ins = _png(stem + ".instance.png")[0]
        # static-world pixels away from silhouettes: one class in the 3x3 around, no actor
        inner = (minimum_filter(sem, 3) == maximum_filter(sem, 3)) & (maximum_filter(ins, 3) == 0)
        v, u = np.nonzero(inner & (sem != SKY))
        pc = np.stack([u + 0.5, v + 0.5, np.ones_like(u, float)], 1) @ np.linalg.inv(cam.K).T
        c2w = np.linalg.inv(cam.viewmat)
        d = pc @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.tile(c2w[:3, 3], (len(d), 1))
        t, c, cos = _cast(mesh, cls, o, d)
        ok = np.isfinite(t)
        agree.append(c[ok] == sem[v[ok], u[ok]])
        ok &= cos >= 0.1
        zp = t[ok] * (pc[ok, 2] / np.linalg.norm(pc[ok], axis=1))      # ray distance -> z
        tan = np.sqrt(1.0 - cos[ok] ** 2) / cos[ok]
        tol = 1.5 * zp * tan / cam.K[0, 0] + 1e-3
        rel.append(np.abs(z[v[ok], u[ok]] - zp) / tol)                # in tolerances
    rel, agree = np.concatenate(rel), np.concatenate(agree)
    assert len(rel) > 20_000
    # (the rest: same-class occlusion edges, e.g. a building in front of another)
    assert np.median(rel) < 1e-3 and np.mean(rel <= 1.0) > 0.9, np.mean(rel <= 1.0)
    assert agree.mean() > 0.95, agree.mean()       # the rest: pixels on class boundaries


def test_instances_are_stable_and_boxes_enclose_them(sensors):
    """An actor keeps its id in every frame and camera (ids by prim path), its pixels carry
    its class, and its projected 3D box encloses the tight box of its pixels."""
    _, out, res = sensors
    inst = {r["id"]: r for r in json.loads((out / "instances.json").read_text())["instances"]}
    seen_boxes = 0
    for k, name, cam, boxes in _rig_cameras(out):
        stem = str(res.frames[name][k])[:-4]
        ins = _png(stem + ".instance.png")[0]
        sem = _png(stem + ".semantic.png")[0]
        by_id = {b["instance_id"]: b for b in boxes["boxes"]}
        for i in np.unique(ins[ins > 0]):
            assert np.all(sem[ins == i] == inst[i]["class_id"])
            if inst[i]["role"] == "ego":
                continue
            b = by_id[i]
            assert b["prim"] == inst[i]["prim"]
            entry = b["cameras"][name]
            ys, xs = np.nonzero(ins == i)
            assert entry["box_2d"] == [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]
            x0, y0, x1, y1 = entry["box_3d_projected"]
            bx0, by0, bx1, by1 = entry["box_2d"]
            assert x0 <= bx0 + 1 and y0 <= by0 + 1 and x1 >= bx1 - 1 and y1 >= by1 - 1
            assert 0 < entry["visible_fraction"] <= 1.0 + 1e-9
            seen_boxes += 1
    assert seen_boxes >= 2
    # the same prims get the same ids in another render of the scene (a different rig)
    from lsd3d_usd.views import rig
    from lsd3d_usd.views.options import RigOptions
    other = rig.render_rig(sensors[0], out.parent / "other",
                           RigOptions(name="waymo5", seconds=0.5, fps=2.0, video=False,
                                      overview=False, lidar="none"),
                           width=64, outputs=("instance",), progress=False, log=lambda *_: None)
    assert json.loads((other.rig_layer.parent / "instances.json").read_text()) == \
        json.loads((out / "instances.json").read_text())


def test_boxes_carry_pose_size_and_velocity(sensors, tmp_path):
    """Box centres and velocities against the actor prims' transforms as USD composes them
    (the box centre moved by the prim's motion over ±10 ms); the file read back as typed
    boxes (views.boxes.read_boxes) writes the same bytes again."""
    from pxr import Usd, UsdGeom

    from lsd3d_usd.views.boxes import read_boxes, write_boxes
    _, out, _ = sensors
    stage = Usd.Stage.Open(str(out / "rig.usda"))
    tcps = stage.GetTimeCodesPerSecond()

    def world(prim, seconds):
        M = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(seconds * tcps)
        return np.asarray(M, np.float64).T            # column-vector convention

    moving = 0
    for k in range(FRAMES):
        path = out / "boxes" / f"{k:04d}.json"
        frame, time, boxes = read_boxes(path)
        assert frame == k and boxes
        again = write_boxes(tmp_path / f"{k:04d}.json", frame, time, boxes)
        assert again.read_bytes() == path.read_bytes()
        for b in boxes:
            assert len(b.size) == 3 and all(s > 0.1 for s in b.size)
            assert len(b.rotation_xyzw) == 4 and b.instance_id > 0
            prim = stage.GetPrimAtPath(b.prim)
            M0 = world(prim, time)
            c = np.append(b.center, 1.0)
            yaw = np.arctan2(M0[1, 0], M0[0, 0])
            assert abs(np.angle(np.exp(1j * (yaw - b.yaw)))) < 1e-6
            h = 0.01
            ahead = world(prim, time + h) @ np.linalg.solve(M0, c)
            behind = world(prim, time - h) @ np.linalg.solve(M0, c)
            v = (ahead - behind)[:3] / (2 * h)
            np.testing.assert_allclose(b.velocity_world, v, atol=1e-3)
            R_ego = world(stage.GetPrimAtPath("/World/Cameras/Ego"), time)[:3, :3]
            np.testing.assert_allclose(b.velocity_ego, R_ego.T @ v, atol=1e-3)
            moving += int(np.linalg.norm(v) > 0.5)
    assert moving >= 1


def test_lidar_sweeps(sensors):
    """Keys and types; classes against the proxy's labels; points of an actor inside its
    box at the point's own time; the PLY opens in trimesh; the LiDAR prim is in rig.usda."""
    import trimesh
    from pxr import Usd

    from lsd3d_usd.views.boxes import local_boxes
    from lsd3d_usd.views.stage_data import SceneReader
    scene, out, res = sensors
    assert len(res.sweeps) == FRAMES
    mesh, cls = _proxy(scene)
    stage = Usd.Stage.Open(str(out / "rig.usda"))
    tcps = stage.GetTimeCodesPerSecond()
    actors = SceneReader(stage, use_env=False).actors
    lboxes = local_boxes(actors)
    inst = {r["id"]: r for r in json.loads((out / "instances.json").read_text())["instances"]}
    index = {a.path: q for q, a in enumerate(actors.actors)}
    agree, inside, actor_points = [], [], 0
    for k, path in enumerate(res.sweeps):
        z = np.load(path)
        keys = {"xyz", "xyz_world", "origin_world", "range", "intensity", "ring", "column", "t",
                "class_id", "instance_id"}
        assert keys <= set(z.files)
        n = len(z["range"])
        assert n > 5000 and all(len(z[key]) == n for key in keys)
        assert z["ring"].max() < 32 and z["column"].max() < 1086
        assert (z["t"] >= 0).all() and (z["t"] <= 0.05).all()
        assert (z["intensity"] >= 0).all() and (z["intensity"] <= 1).all()
        d = z["xyz_world"] - z["origin_world"]
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), z["range"], rtol=1e-5)
        # sensor frame: the world points through the sweep-start pose
        M = z["world_from_sensor"]
        np.testing.assert_allclose(z["xyz"] @ M[:3, :3].T + M[:3, 3], z["xyz_world"], atol=1e-3)
        stuff = z["instance_id"] == 0
        t, c, _ = _cast(mesh, cls, z["origin_world"][stuff], (d / np.linalg.norm(d, axis=1)[:, None])[stuff])
        ok = np.isfinite(t)
        agree.append(c[ok] == z["class_id"][stuff][ok])
        t0 = json.loads((out / "boxes" / f"{k:04d}.json").read_text())["time"]
        for i in np.unique(z["instance_id"][~stuff]):
            q = index[inst[int(i)]["prim"]]
            lo, hi = lboxes[q]
            rows = np.flatnonzero(z["instance_id"] == i)
            assert np.all(z["class_id"][rows] == inst[int(i)]["class_id"])
            for tp in np.unique(z["t"][rows]):            # each column at its own time
                Mq = actors.transforms(round((t0 + float(tp)) * tcps, 6))[q]
                pts = z["xyz_world"][rows[z["t"][rows] == tp]]
                p = (pts - Mq[:3, 3]) @ Mq[:3, :3]            # actor frame (rigid)
                inside.extend(np.all((p >= lo - 0.05) & (p <= hi + 0.05), axis=1))
            actor_points += len(rows)
        cloud = trimesh.load(str(path.with_suffix(".ply")))
        assert len(cloud.vertices) == n
        np.testing.assert_allclose(cloud.vertices, z["xyz"], atol=1e-4)
        assert (out / "LIDAR_TOP" / f"{k:04d}_bev.png").is_file()
    agree = np.concatenate(agree)
    assert agree.mean() > 0.95, agree.mean()
    assert actor_points > 20 and all(inside)
    lidar = [p for p in stage.Traverse() if p.GetName() == "LIDAR_TOP"]
    assert len(lidar) == 1 and "/Ego" in lidar[0].GetPath().pathString
    assert lidar[0].GetAttribute("lsd3d:lidar:columns").Get() == 1086
    assert len(lidar[0].GetAttribute("lsd3d:lidar:elevationsDeg").Get()) == 32


def test_lidar_sweep_is_seeded(sensors, tmp_path):
    """Noise is seeded: the same sweep twice is the same, another seed another."""
    from pxr import Usd

    from lsd3d_usd.views.ego import EgoTrack
    from lsd3d_usd.views.labels import Instances
    from lsd3d_usd.views.lidar_sweep import sweep
    from lsd3d_usd.sensors.lidar import model_from_table
    from lsd3d_usd.views.stage_data import SceneReader
    _, out, _ = sensors
    stage = Usd.Stage.Open(str(out / "rig.usda"))
    reader = SceneReader(stage, use_env=False, actors=False)
    model = model_from_table({"beams": 16, "elevation_min": -20, "elevation_max": 0,
                              "columns": 360, "range_sigma": 0.05, "drop_prob": 0.2}, "n.toml")
    track = EgoTrack(np.array([0.0, 1.0]), np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]]),
                     np.tile(np.eye(3), (2, 1, 1)))
    args = (reader, model, track.at, 0.0, stage.GetTimeCodesPerSecond(), Instances.of(None))
    a, b, c = sweep(*args, seed=1), sweep(*args, seed=1), sweep(*args, seed=2)
    np.testing.assert_array_equal(a.range, b.range)
    assert len(a.range) != len(c.range) or not np.array_equal(a.range, c.range)
    quiet = model_from_table({"beams": 16, "elevation_min": -20, "elevation_max": 0,
                              "columns": 360}, "q.toml")
    clean = sweep(reader, quiet, track.at, 0.0, stage.GetTimeCodesPerSecond(), Instances.of(None))
    assert 0.7 < len(a.range) / len(clean.range) < 0.9          # 20 % dropped


@pytest.mark.parametrize("extra,needles", [
    (["--outputs", "rgb,depthz"], ["--outputs", "'depthz'"]),
    (["--lidar", "velodyne_nope"], ["--lidar", "velodyne_nope"]),
])
def test_rig_bad_outputs_and_lidar_write_nothing(small_scene, tmp_path, cli_error, extra, needles):
    out = tmp_path / "out"
    cli_error(["render", small_scene, "-o", out, "--rig", "nuscenes6", *extra], *needles)
    assert not out.exists()


@pytest.mark.parametrize("body,key", [
    ("beams = 0\nelevation_min = -10\nelevation_max = 10\ncolumns = 100\n", "beams"),
    ("beams = 8\nelevation_min = -100\nelevation_max = 10\ncolumns = 100\n", "elevation_min: -100 deg"),
    ("beams = 8\nelevation_min = -10\nelevation_max = 10\ncolumns = 100\nmin_range = 3.0\n"
     "max_range = 2.0\n", "max_range"),
    ("beams = 8\nelevation_min = -10\nelevation_max = 10\ncolumns = 1000000000\n", "columns"),
    ("beams = 8\nelevation_min = -10\nelevation_max = 10\ncolumns = 100\nspin = 3\n", "spin"),
    ("beams = [\n", "toml"),
])
def test_bad_lidar_toml_is_one_line_and_writes_nothing(small_scene, tmp_path, cli_error, body, key):
    f = tmp_path / "my_lidar.toml"
    f.write_text("[lidar]\n" + body)
    out = tmp_path / "out"
    line = cli_error(["render", small_scene, "-o", out, "--rig", "waymo5", "--lidar", f])
    assert "my_lidar.toml" in line and key in line.lower()
    assert not out.exists()


def test_camera_render_outputs_and_bad_output(small_scene, tmp_path, cli_error):
    from pxr import Usd, UsdGeom

    from lsd3d_usd.cli import main
    stage = Usd.Stage.Open(str(small_scene / "scene.usda"))
    cam = next(p.GetPath().pathString for p in stage.Traverse() if p.IsA(UsdGeom.Camera))
    out = tmp_path / "cam"
    assert main(["render", str(small_scene), "-o", str(out), "--camera", cam, "--resolution",
                 "64x48", "--outputs", "rgb,depth,semantic,instance,normal", "--no-progress"]) == 0
    name = cam.rsplit("/", 1)[-1]
    for suffix in (".png", ".depth.exr", ".semantic.png", ".instance.png", ".normal.exr"):
        assert (out / f"{name}{suffix}").is_file(), suffix
    assert (out / "classes.json").is_file()
    bad = tmp_path / "bad"
    cli_error(["render", small_scene, "-o", bad, "--camera", cam, "--outputs", "lidar"],
              "'lidar'")
    assert not bad.exists()


def test_rig_lidar_default_and_none(small_scene, tmp_path):
    """nuscenes6 carries its LIDAR_TOP unless --lidar none; waymo5 carries none unless asked."""
    from pxr import Usd

    from lsd3d_usd.cli import main
    common = ["--seconds", "0.1", "--resolution", "32", "--no-video", "--no-overview",
              "--no-progress"]
    for rig_name, flag, has in (("nuscenes6", [], True), ("nuscenes6", ["--lidar", "none"], False),
                                ("waymo5", [], False), ("waymo5", ["--lidar", "hdl32"], True)):
        out = tmp_path / f"{rig_name}{len(flag)}"
        assert main(["render", str(small_scene), "-o", str(out), "--rig", rig_name, *common,
                     *flag]) == 0
        assert (out / "LIDAR_TOP").is_dir() == has, (rig_name, flag)
        stage = Usd.Stage.Open(str(out / "rig.usda"))
        assert any(p.GetName() == "LIDAR_TOP" for p in stage.Traverse()) == has
