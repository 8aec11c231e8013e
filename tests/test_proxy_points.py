"""Point-cloud proxy: readers, ground fit, reconstruction accuracy (Chamfer), labels, CLI."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

import lsd3d_usd  # noqa: F401
from lsd3d_usd.errors import InputError
from lsd3d_usd.proxy.chunks import build_proxy
from lsd3d_usd.proxy.pointcloud import (PointProxyParams, fit_ground_plane, points_to_parts,
                                        read_cloud)
from lsd3d_usd.proxy.synthetic import grid_layout
from lsd3d_usd.semantics import CLASS_ID

CROP = (35.0, 20.0, 70.0, 55.0)     # road, curb, sidewalk, a building, trees, parked car


def sample_faces(v, f, n, rng):
    t = v[f]
    area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    k = rng.choice(len(f), n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    return (1 - s)[:, None] * t[k, 0] + (s * (1 - r2))[:, None] * t[k, 1] + (s * r2)[:, None] * t[k, 2]


@pytest.fixture(scope="module")
def scene_points():
    """Points sampled from our own proxy meshes in CROP, with labels; plus clean GT points."""
    rng = np.random.default_rng(0)
    parts = build_proxy(grid_layout(1, 1))[(0, 0)]
    x0, y0, x1, y1 = CROP
    pts, labs = [], []
    for p in parts:
        c = p.vertices[p.faces].mean(1)
        keep = (c[:, 0] > x0) & (c[:, 0] < x1) & (c[:, 1] > y0) & (c[:, 1] < y1)
        if not keep.any():
            continue
        t = p.vertices[p.faces[keep]]
        area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
        n = max(int(area * 60), 10)            # ~60 points / m^2
        pts.append(sample_faces(p.vertices, p.faces[keep], n, rng))
        labs.append(np.full(n, CLASS_ID[p.cls], np.int32))
    gt = np.concatenate(pts)
    labels = np.concatenate(labs)
    noisy = gt + rng.normal(scale=0.02, size=gt.shape)
    return gt, noisy, labels


def chamfer(parts, gt, rng):
    rec = np.concatenate([sample_faces(p.vertices, p.faces, 60000 * p.n_faces //
                                       sum(q.n_faces for q in parts) + 1, rng) for p in parts])
    d_rec = cKDTree(gt).query(rec)[0]
    d_gt = cKDTree(rec).query(gt)[0]
    return d_rec.mean(), d_gt.mean()


def test_reconstruction_is_within_two_voxels(scene_points):
    gt, noisy, _ = scene_points
    prm = PointProxyParams(voxel=0.2)
    out = points_to_parts(noisy, None, prm)
    parts = [p for ps in out.values() for p in ps]
    assert parts
    a, b = chamfer(parts, gt, np.random.default_rng(1))
    assert a < 2 * prm.voxel and b < 2 * prm.voxel, (a, b)
    classes = {p.cls for p in parts}
    assert {"road", "building"} <= classes          # height rule without labels
    for p in parts:
        assert np.isfinite(p.vertices).all()
        t = p.vertices[p.faces]
        assert (np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1) > 0).all()


def test_labels_come_from_the_points(scene_points):
    gt, noisy, labels = scene_points
    out = points_to_parts(noisy, labels, PointProxyParams(voxel=0.25))
    parts = [p for ps in out.values() for p in ps]
    by = {p.cls: p for p in parts}
    assert {"road", "building", "sidewalk", "curb", "vegetation"} <= set(by)
    # faces labelled building lie near building points
    tree = cKDTree(gt[labels == CLASS_ID["building"]])
    c = by["building"].vertices[by["building"].faces].mean(1)
    assert np.median(tree.query(c)[0]) < 0.3


def test_ground_plane_fit_recovers_a_tilted_plane_with_clutter():
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 60, size=(20000, 2))
    z = 0.05 * xy[:, 0] - 0.02 * xy[:, 1] + 1.5 + rng.normal(scale=0.01, size=len(xy))
    clutter = np.column_stack([rng.uniform(10, 30, (5000, 2)), rng.uniform(2, 12, 5000)])
    plane = fit_ground_plane(np.vstack([np.column_stack([xy, z]), clutter]))
    np.testing.assert_allclose(plane, [0.05, -0.02, 1.5], atol=0.01)


def write_ply(path, pts, labels=None, binary=True):
    props = ["x", "y", "z"] + (["label"] if labels is not None else [])
    head = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment test",
            f"element vertex {len(pts)}"]
    head += [f"property float {p}" for p in props[:3]]
    if labels is not None:
        head.append("property int label")
    head += ["element face 0", "property list uchar int vertex_indices", "end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode())
        if binary:
            dt = [(p, "<f4") for p in props[:3]] + ([("label", "<i4")] if labels is not None else [])
            a = np.zeros(len(pts), dtype=dt)
            for k, p in enumerate("xyz"):
                a[p] = pts[:, k]
            if labels is not None:
                a["label"] = labels
            f.write(a.tobytes())
        else:
            for k, p in enumerate(pts):
                f.write((" ".join(f"{v:.6f}" for v in p)
                         + (f" {labels[k]}" if labels is not None else "") + "\n").encode())


@pytest.mark.parametrize("binary", [True, False])
def test_ply_reader_round_trip(tmp_path, binary):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (50, 3)).astype(np.float32).astype(np.float64)
    lab = rng.integers(-1, 5, 50).astype(np.int32)
    write_ply(tmp_path / "c.ply", pts, lab, binary)
    p, l = read_cloud(tmp_path / "c.ply")
    np.testing.assert_allclose(p, pts, atol=1e-5)
    np.testing.assert_array_equal(l, lab)


def test_bad_clouds_give_clear_errors(tmp_path):
    (tmp_path / "x.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n"
                                     b"property float x\nproperty float y\nproperty float z\nend_header\n" + b"\0" * 12)
    with pytest.raises(InputError, match="truncated"):
        read_cloud(tmp_path / "x.ply")
    np.savez(tmp_path / "a.npz", xyz=np.zeros((5, 2)))
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        read_cloud(tmp_path / "a.npz")
    np.savez(tmp_path / "b.npz", points=np.zeros((5, 3)), labels=np.full(5, 99))
    with pytest.raises(InputError, match="not a class id"):
        read_cloud(tmp_path / "b.npz")
    np.savez(tmp_path / "c.npz", points=np.zeros((3, 3)), labels=np.array([0, 1, 0]),
             classes=np.array(["car", "road"]))
    with pytest.raises(InputError, match="'car'"):
        read_cloud(tmp_path / "c.npz")
    with pytest.raises(InputError, match="must be .ply or .npz"):
        read_cloud(tmp_path / "a.npz".replace(".npz", ".xyz")) if False else read_cloud(_touch(tmp_path / "p.xyz"))


def _touch(p):
    p.write_text("")
    return p


def test_npz_class_names_are_mapped(tmp_path):
    np.savez(tmp_path / "c.npz", points=np.zeros((3, 3)), labels=np.array([0, 1, -1]),
             classes=np.array(["building", "road"]))
    _, lab = read_cloud(tmp_path / "c.npz")
    np.testing.assert_array_equal(lab, [CLASS_ID["building"], CLASS_ID["road"], -1])


def test_cli_from_points_writes_a_valid_proxy_layer(tmp_path, scene_points, capsys):
    from lsd3d_usd import validation
    from lsd3d_usd.cli import main
    from lsd3d_usd.proxy.usdio import read_proxy

    _, noisy, labels = scene_points
    np.savez(tmp_path / "cloud.npz", points=noisy[::3], labels=labels[::3])
    out = tmp_path / "pc.usdc"
    assert main(["proxy", "from-points", str(tmp_path / "cloud.npz"), "-o", str(out),
                 "--voxel", "0.3"]) == 0
    assert "per-point labels" in capsys.readouterr().out
    data = read_proxy(out)
    assert list(data) == [(0, 0)] and "building" in data[(0, 0)]
    assert [p for p in validation.validate(str(out)) if p.severity == "error"] == []
    assert main(["proxy", "from-points", str(tmp_path / "none.ply"), "-o", str(out)]) == 1
