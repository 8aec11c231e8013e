"""Pedestrians and cyclists in a nuScenes dataset: their categories (adult / child pedestrian,
bicycle), attributes from their motion, and their lidarseg labels, read with the devkit."""
import pytest
from conftest import generate_small

pytest.importorskip("nuscenes", reason="nuscenes-devkit (pip install --no-deps "
                                       "nuscenes-devkit==1.2.0; docs/datasets.md)")


def test_people_categories_attributes_and_points(tmp_path):
    import numpy as np
    from nuscenes.nuscenes import NuScenes

    from lsd3d_usd.cli import main
    generate_small(tmp_path / "scene", steps=0, actors=True, parked=0, moving=2, pedestrians=8,
                   cyclists=3, surfels=20_000)
    assert main(["dataset", str(tmp_path / "scene"), "-o", str(tmp_path / "ds"), "--no-progress",
                 "--format", "nuscenes", "--route", "e_out", "--seconds", "1",
                 "--camera-hz", "2", "--lidar-hz", "2", "--keyframe-hz", "2",
                 "--width", "96"]) == 0
    nusc = NuScenes(version="v1.0-lsd3d", dataroot=str(tmp_path / "ds"), verbose=False)
    cat = {c["token"]: c["name"] for c in nusc.category}
    attr = {a["token"]: a["name"] for a in nusc.attribute}
    by_cat = {}
    for inst in nusc.instance:
        by_cat.setdefault(cat[inst["category_token"]], []).append(inst)
    people = [n for n in by_cat if n.startswith("human.pedestrian")]
    assert people and "vehicle.bicycle" in by_cat, sorted(by_cat)
    for ann in nusc.sample_annotation:
        name = cat[nusc.get("instance", ann["instance_token"])["category_token"]]
        names = {attr[t] for t in ann["attribute_tokens"]}
        if name.startswith("human.pedestrian"):
            assert names <= {"pedestrian.moving", "pedestrian.standing"} and names, names
        if name == "vehicle.bicycle":
            assert names == {"cycle.with_rider"}, names
    # lidarseg: every point has a label, people's points carry their categories' indices
    index = {c["name"]: c["index"] for c in nusc.category}
    seen = set()
    for ls in nusc.lidarseg:
        sd = nusc.get("sample_data", ls["sample_data_token"])
        labels = np.fromfile(tmp_path / "ds" / ls["filename"], dtype=np.uint8)
        pts = np.fromfile(tmp_path / "ds" / sd["filename"], dtype=np.float32).reshape(-1, 5)
        assert len(labels) == len(pts)
        seen |= set(np.unique(labels).tolist())
    assert seen & {index[n] for n in people + ["vehicle.bicycle"]}


def test_people_category_table():
    from lsd3d_usd.datasets.mapping import actor_category, attribute
    assert actor_category("pedestrian", "adult") == "human.pedestrian.adult"
    assert actor_category("pedestrian", "adult_broad") == "human.pedestrian.adult"
    assert actor_category("pedestrian", "child") == "human.pedestrian.child"
    assert actor_category("cyclist", "cyclist") == "vehicle.bicycle"
    assert attribute("human.pedestrian.child", "moving", 1.3) == "pedestrian.moving"
    assert attribute("human.pedestrian.adult", "moving", 0.0) == "pedestrian.standing"
    assert attribute("vehicle.bicycle", "moving", 5.0) == "cycle.with_rider"
