"""LPIPS from local files: torchvision-layout loading, lin-weight discovery, the distance
against a float64 reference written out here, and generate's refusal of bad paths."""
import types
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.losses import lpips as lp
from lsd3d_usd.ggds.losses.lpips import LPIPSLoss, load_backbone

# torchvision's feature conv indices (what a real alexnet()/vgg16() state dict holds).
CONV_IDX = {"alex": (0, 3, 6, 8, 10), "vgg": (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)}
CONV_SHAPES = {
    "alex": [(64, 3, 11, 11), (192, 64, 5, 5), (384, 192, 3, 3), (256, 384, 3, 3), (256, 256, 3, 3)],
    "vgg": [(64, 3, 3, 3), (64, 64, 3, 3), (128, 64, 3, 3), (128, 128, 3, 3), (256, 128, 3, 3),
            (256, 256, 3, 3), (256, 256, 3, 3), (512, 256, 3, 3), (512, 512, 3, 3), (512, 512, 3, 3),
            (512, 512, 3, 3), (512, 512, 3, 3), (512, 512, 3, 3)],
}
LIN_C = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}


def random_backbone(net, seed=0, classifier=False):
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for i, s in zip(CONV_IDX[net], CONV_SHAPES[net]):
        fan_in = s[1] * s[2] * s[3]
        sd[f"features.{i}.weight"] = torch.randn(s, generator=g) * (2.0 / fan_in) ** 0.5
        sd[f"features.{i}.bias"] = torch.randn(s[0], generator=g) * 0.05
    if classifier:  # stand-ins for the ImageNet head (real shapes would be 200 MB+)
        sd["classifier.1.weight"] = torch.randn(8, 16, generator=g)
        sd["classifier.1.bias"] = torch.zeros(8)
    return sd


def random_lin(net, seed=1):
    g = torch.Generator().manual_seed(seed)
    return {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g)
            for k, c in enumerate(LIN_C[net])}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("lpips")
    out = {}
    for net in ("alex", "vgg"):
        torch.save(random_backbone(net), d / f"{net}_features.pth")
        torch.save(random_lin(net), d / f"{net}_lin.pth")
        out[net] = (d / f"{net}_features.pth", d / f"{net}_lin.pth")
    torch.save(random_backbone("alex", classifier=True), d / "alex_full.pth")
    out["alex_full"] = d / "alex_full.pth"
    return out


def images(seed, n=1, size=64):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, size, size, 3, generator=g)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_torchvision_layout_loads_strict_and_net_is_inferred(files, net):
    bb = load_backbone(files[net][0])
    assert bb.net == net
    sd = torch.load(files[net][0], weights_only=True)
    assert set(bb.state_dict()) == set(sd)
    for k, v in bb.state_dict().items():
        assert torch.equal(v, sd[k]), k
    assert not bb.training and not any(p.requires_grad for p in bb.parameters())


def test_full_classifier_file_loads(files):
    loss = LPIPSLoss.from_files(files["alex_full"], files["alex"][1])
    assert loss.net == "alex"


def test_missing_key_and_wrong_shape_name_the_file(tmp_path):
    sd = random_backbone("alex")
    del sd["features.8.weight"]
    p = tmp_path / "missing.pth"
    torch.save(sd, p)
    with pytest.raises(InputError, match=r"missing\.pth.*missing \['features\.8\.weight'\]"):
        load_backbone(p)
    sd = random_backbone("alex")
    sd["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    p = tmp_path / "shape.pth"
    torch.save(sd, p)
    with pytest.raises(InputError, match=r"shape\.pth.*wrong shape.*features\.3\.weight"):
        load_backbone(p)
    sd = random_backbone("alex")
    sd["features.0.weight"] = torch.zeros(64, 3, 7, 7)
    torch.save(sd, tmp_path / "first.pth")
    with pytest.raises(InputError, match=r"first\.pth.*\(64, 3, 7, 7\)"):
        load_backbone(tmp_path / "first.pth")


def test_bad_files_are_clear_errors(tmp_path, files):
    with pytest.raises(InputError, match=r"nope\.pth: no such file.*nothing is downloaded"):
        LPIPSLoss.from_files(tmp_path / "nope.pth", files["alex"][1])
    (tmp_path / "text.pth").write_text("hello")
    with pytest.raises(InputError, match=r"text\.pth: not a readable torch state dict"):
        load_backbone(tmp_path / "text.pth")
    torch.save([1, 2], tmp_path / "list.pth")
    with pytest.raises(InputError, match=r"list\.pth: not a state dict"):
        load_backbone(tmp_path / "list.pth")
    # vgg lin weights for an alex backbone
    with pytest.raises(InputError, match=r"vgg_lin\.pth.*lin1\.model\.1\.weight.*\(1, 192, 1, 1\)"):
        LPIPSLoss.from_files(files["alex"][0], files["vgg"][1])
    neg = random_lin("alex")
    neg["lin2.model.1.weight"][0, 0] = -1.0
    torch.save(neg, tmp_path / "neg.pth")
    with pytest.raises(InputError, match=r"neg\.pth.*non-negative"):
        LPIPSLoss.from_files(files["alex"][0], tmp_path / "neg.pth")


def test_lin_weights_found_in_installed_package_without_import(tmp_path, files, monkeypatch):
    pkg = tmp_path / "site" / "lpips"
    (pkg / "weights" / "v0.1").mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise RuntimeError('must not be imported')\n")
    torch.save(random_lin("alex"), pkg / "weights" / "v0.1" / "alex.pth")
    real = lp.importlib.util.find_spec

    def fake(name, *a):
        if name == "lpips":
            return types.SimpleNamespace(origin=str(pkg / "__init__.py"),
                                         submodule_search_locations=[str(pkg)])
        return real(name, *a)
    monkeypatch.setattr(lp.importlib.util, "find_spec", fake)
    loss = LPIPSLoss.from_files(files["alex"][0])
    assert torch.equal(loss.lin0.flatten(), random_lin("alex")["lin0.model.1.weight"].flatten())
    # none for vgg in that package: the error says how to supply them
    with pytest.raises(InputError, match=r"no linear weights for the vgg backbone.*--lpips-lin.*"
                                         r"nothing is downloaded"):
        LPIPSLoss.from_files(files["vgg"][0])


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_distance_properties_and_gradients(files, net):
    loss = LPIPSLoss.from_files(*files[net])
    x, y = images(0, 2), images(1, 2)
    assert float(loss(x, x)) == 0.0
    dxy, dyx = loss.distance(x, y), loss.distance(y, x)
    assert torch.all(dxy > 0)
    assert torch.allclose(dxy, dyx, rtol=1e-5, atol=0)
    xg = x.clone().requires_grad_(True)
    loss(xg, y).backward()
    assert xg.grad is not None and torch.isfinite(xg.grad).all() and xg.grad.abs().sum() > 0
    # a closer image is closer
    assert float(loss(x, x + 0.02 * (y - x))) < float(loss(x, y))


def reference(sd, lin, net, x, y):
    """Plain float64 LPIPS: conv/pool per torchvision index, explicit per-layer head."""
    taps = {"alex": (1, 4, 7, 9, 11), "vgg": (3, 8, 15, 22, 29)}[net]
    spec = lp.NETS[net][0]
    shift = np.array([-0.030, -0.088, -0.188])
    scale = np.array([0.458, 0.448, 0.450])

    def feats(img):
        a = (2 * img.astype(np.float64) - 1 - shift) / scale           # (H, W, 3)
        t = torch.from_numpy(a).permute(2, 0, 1)[None]
        out = []
        for i, s in enumerate(spec[:taps[-1] + 1]):
            if s[0] == "conv":
                t = F.conv2d(t, sd[f"features.{i}.weight"].double(), sd[f"features.{i}.bias"].double(),
                             stride=s[4], padding=s[5])
            elif s[0] == "relu":
                t = t.clamp_min(0)
            else:
                t = F.max_pool2d(t, s[1], s[2])
            if i in taps:
                out.append(t[0].numpy())                                  # (C, h, w)
        return out

    total = 0.0
    for k, (fx, fy) in enumerate(zip(feats(x), feats(y))):
        w = lin[f"lin{k}.model.1.weight"].double().numpy().reshape(-1)
        nx = np.sqrt(np.einsum("chw,chw->hw", fx, fx)) + 1e-10
        ny = np.sqrt(np.einsum("chw,chw->hw", fy, fy)) + 1e-10
        d = (fx / nx - fy / ny) ** 2
        layer = 0.0
        for r in range(d.shape[1]):
            for c in range(d.shape[2]):
                layer += float(np.dot(w, d[:, r, c]))
        total += layer / (d.shape[1] * d.shape[2])
    return total


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_matches_float64_reference(files, net):
    sd = torch.load(files[net][0], weights_only=True)
    lin = torch.load(files[net][1], weights_only=True)
    x, y = images(2)[0], images(3)[0]
    got = float(LPIPSLoss.from_files(*files[net])(x, y))
    want = reference(sd, lin, net, x.numpy(), y.numpy())
    assert want > 0
    assert got == pytest.approx(want, rel=1e-5)  # measured ~1e-7; a 1% change of one layer is 3e-4


def test_generate_refuses_missing_lpips_path(tmp_path, files):
    from lsd3d_usd.config import generate_config
    from lsd3d_usd.pipeline import check_config

    def check(**kw):
        return check_config(generate_config(**{"ggds": {"weights": {"perceptual": 0.1}}, **kw}))
    with pytest.raises(InputError) as e:
        check(lpips=tmp_path / "absent.pth")
    msg = str(e.value)
    assert msg.count("\n") == 0 and "--lpips" in msg and "absent.pth" in msg and "no such file" in msg
    assert not (tmp_path / "scene").exists()
    # a good pair passes (and is loaded once, for the run); with a zero perceptual weight
    # --lpips would do nothing: refused
    state = check(lpips=files["alex"][0], lpips_lin=files["alex"][1])
    assert isinstance(state["perceptual"], LPIPSLoss)
    with pytest.raises(InputError, match="--lpips.*perceptual weight is 0"):
        check_config(generate_config(lpips=files["alex"][0], lpips_lin=files["alex"][1]))
    with pytest.raises(InputError, match=r"--lpips-lin .*absent_lin\.pth: no such file"):
        check(lpips=files["alex"][0], lpips_lin=tmp_path / "absent_lin.pth")
