"""Geometry grounding (ggds/optim/grounding.py): surfels of the flat classes stay on their seed
face's plane, facing its normal, through the steps, relocation and a checkpoint; a relocated
surfel takes its source's class."""
import numpy as np
import pytest
import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.optim import params as P
from lsd3d_usd.ggds.optim.grounding import Grounding, class_mask
from lsd3d_usd.ggds.settings import GGDSConfig, check_ground_classes
from lsd3d_usd.render.projection import quat_to_rotmat
from lsd3d_usd.semantics import CLASS_ID, CLASSES
from lsd3d_usd.splats.field import SurfelField

from test_ggds_run import make_run


def _rot64(q):
    """float64 rotation matrices of xyzw quaternions, written out (the plain reference)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def _random_field(n, rng):
    q = rng.normal(size=(n, 4))
    return SurfelField(rng.normal(size=(n, 3)) * 5, q / np.linalg.norm(q, axis=1, keepdims=True),
                       np.full((n, 2), 0.1), np.full(n, 0.5), np.zeros((n, 1, 3)))


def test_projection_puts_rows_back_on_their_planes_by_the_smallest_move():
    rng = np.random.default_rng(0)
    n = 400
    params = P.to_params(_random_field(n, rng))
    mask = rng.random(n) < 0.5
    g = Grounding(params["means"], params["quats"], mask)
    p0 = params["means"].double().numpy().copy()
    n0 = _rot64(params["quats"].numpy())[..., 2]
    # perturb every row: positions by centimetres, orientations by a few degrees, norms vary
    with torch.no_grad():
        params["means"] += torch.from_numpy(rng.normal(size=(n, 3)) * 0.03).float()
        params["quats"] += torch.from_numpy(rng.normal(size=(n, 4)) * 0.05).float()
        params["quats"] *= torch.from_numpy(rng.uniform(0.5, 2.0, (n, 1))).float()
    m1 = params["means"].double().numpy().copy()
    q1 = params["quats"].numpy().copy()
    assert g.project(params) == mask.sum()
    m2 = params["means"].double().numpy()
    q2 = params["quats"].numpy()
    R1, R2 = _rot64(q1), _rot64(q2)
    # grounded rows: on the plane, normal the plane's, the in-plane displacement kept
    d = np.einsum("ij,ij->i", m2 - p0, n0)
    assert np.abs(d[mask]).max() < 2e-6
    assert np.abs(np.abs(np.einsum("ij,ij->i", R2[..., 2], n0)) - 1)[mask].max() < 1e-6
    inplane = (m1 - p0) - np.einsum("ij,ij->i", m1 - p0, n0)[:, None] * n0
    np.testing.assert_allclose((m2 - p0)[mask], inplane[mask], atol=2e-6)
    # the smallest rotation: the old tangent's in-plane direction is where the new one points
    t_old = R1[..., 0] - np.einsum("ij,ij->i", R1[..., 0], n0)[:, None] * n0
    t_old /= np.linalg.norm(t_old, axis=1, keepdims=True)
    assert (np.einsum("ij,ij->i", R2[..., 0], t_old)[mask] > 0.99).all()
    # the raw quaternion's norm (its Adam scale) is kept
    np.testing.assert_allclose(np.linalg.norm(q2, axis=1), np.linalg.norm(q1, axis=1), rtol=1e-5)
    # free rows untouched
    np.testing.assert_array_equal(m2[~mask], m1[~mask])
    np.testing.assert_array_equal(q2[~mask], q1[~mask])


def test_projection_keeps_the_side_a_disk_shows():
    # a disk flipped to face the other way is put back on the plane facing that way
    params = P.to_params(SurfelField(np.zeros((2, 3)), np.array([[0, 0, 0, 1.0], [0, 0, 0, 1.0]]),
                                     np.full((2, 2), 0.1), np.full(2, 0.5), np.zeros((2, 1, 3))))
    g = Grounding(params["means"], params["quats"], np.array([True, True]))
    with torch.no_grad():
        params["quats"][1] = torch.tensor([0.999, 0.02, 0.0, 0.03])   # ~180° about x
    g.project(params)
    normals = quat_to_rotmat(params["quats"])[..., 2]
    torch.testing.assert_close(normals[0], torch.tensor([0.0, 0.0, 1.0]))
    torch.testing.assert_close(normals[1], torch.tensor([0.0, 0.0, -1.0]), atol=1e-6, rtol=0)


def test_relocated_rows_take_their_sources_plane_or_become_free():
    rng = np.random.default_rng(1)
    params = P.to_params(_random_field(6, rng))
    mask = np.array([True, True, False, False, True, False])
    g = Grounding(params["means"], params["quats"], mask)
    point, normal = g.point.clone(), g.normal.clone()
    # 0 (grounded) <- 4 (grounded); 2 (free) <- 1 (grounded); 4 (grounded) <- 3 (free)
    g.relocated(torch.tensor([0, 2, 4]), torch.tensor([4, 1, 3]))
    assert g.slot[4] == -1 and g.slot[3] == -1 and g.slot[5] == -1
    torch.testing.assert_close(g.point[g.slot[0]], point[2])      # 4's old plane (slot 2)
    torch.testing.assert_close(g.point[g.slot[2]], point[1])
    torch.testing.assert_close(g.normal[g.slot[2]], normal[1])
    assert g.count == 3


def test_class_mask_and_the_option_check():
    ids = np.array([CLASS_ID["road"], CLASS_ID["building"], -1, CLASS_ID["sidewalk"], 99])
    np.testing.assert_array_equal(class_mask(ids, CLASSES, "road,sidewalk"),
                                  [True, False, False, True, False])
    assert not class_mask(ids, CLASSES, "").any()
    assert check_ground_classes(" road , curb", "ggds.ground_classes") == "road,curb"
    with pytest.raises(InputError, match="ggds.ground_classes: unknown class 'roads'"):
        check_ground_classes("roads", "ggds.ground_classes")


def _road_off_plane(run):
    ids = run.state.semantics[0]
    m = run.params["means"].detach().double().numpy()
    road = ids == CLASS_ID["road"]
    nz = quat_to_rotmat(run.params["quats"].detach())[..., 2].numpy()
    return np.abs(m[road, 2]).max(), np.abs(np.abs(nz[road, 2]) - 1).max()


def test_a_run_keeps_road_surfels_on_the_road_and_moves_them_without_grounding():
    grounded = make_run(steps=30)
    free = make_run(steps=30, ground_classes="")
    assert grounded.state.grounding.count == int((grounded.state.semantics[0]
                                                  == CLASS_ID["road"]).sum()) > 0
    assert free.state.grounding is None
    for _ in range(30):
        grounded.step()
        free.step()
    dz, tilt = _road_off_plane(grounded)
    assert dz < 1e-5 and tilt < 1e-5
    dz_free, tilt_free = _road_off_plane(free)
    assert dz_free > 1e-4 or tilt_free > 1e-4          # without it the steps move them
    # the walls (not a ground class) still move
    ids = grounded.state.semantics[0]
    wall = ids == CLASS_ID["building"]
    m = grounded.params["means"].detach().numpy()
    assert np.abs(m[wall, 1] - 5.0).max() > 1e-4


def test_relocation_carries_the_class_and_a_checkpoint_keeps_both():
    run = make_run(steps=20)
    ids0 = run.state.semantics[0].copy()
    with torch.no_grad():   # kill a handful of walls: relocation draws sources by opacity
        run.params["opacities"][np.flatnonzero(ids0 == CLASS_ID["building"])[:50]] = -20.0
    for _ in range(10):
        run.step()
    dead, src = run.state.strategy.last_relocation
    assert dead.numel() >= 50
    ids = run.state.semantics[0]
    np.testing.assert_array_equal(ids[dead.numpy()], ids[src.numpy()])
    assert (ids != ids0).any()          # some walls became road: their class went with them
    assert (run.field().semantic_ids == ids).all()
    tensors, meta = run.checkpoint()
    other = make_run(steps=20)
    other.restore(tensors, meta)
    np.testing.assert_array_equal(other.state.semantics[0], ids)
    torch.testing.assert_close(other.state.grounding.slot, run.state.grounding.slot)
    torch.testing.assert_close(other.state.grounding.point, run.state.grounding.point)
    for _ in range(10):
        run.step()
        other.step()
    for k in P.KEYS:
        torch.testing.assert_close(other.params[k], run.params[k], rtol=1e-5, atol=1e-6)
    assert _road_off_plane(run)[0] < 1e-5


def test_default_ground_classes_are_the_flat_ground():
    assert set(GGDSConfig().ground_classes.split(",")) == {"road", "lane_marking", "crosswalk",
                                                            "sidewalk", "curb"}
