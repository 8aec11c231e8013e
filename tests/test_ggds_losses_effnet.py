"""EfficientNet-Lite0 model code against the bundled ImageNet weights, and the perceptual loss."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.losses import effnet
from lsd3d_usd.ggds.losses.effnet import (EMBED_DIM, FEATURE_CHANNELS, EffNetFeatureExtractor, EfficientNetLite0, bundled_weights_path, load_efficientnet_lite0)
from lsd3d_usd.ggds.losses.perceptual import EffNetPerceptualLoss

skdata = pytest.importorskip("skimage.data")


@pytest.fixture(scope="module")
def extractor():
    return EffNetFeatureExtractor()


def photo(name):
    return torch.from_numpy(getattr(skdata, name)().copy()).float() / 255.0


def test_strict_load_covers_every_tensor():
    sd = torch.load(bundled_weights_path(), map_location="cpu", weights_only=True)
    model = EfficientNetLite0()
    assert set(model.state_dict()) == set(sd)
    for k, v in model.state_dict().items():
        assert v.shape == sd[k].shape, k
    m = load_efficientnet_lite0()
    assert not m.training and not any(p.requires_grad for p in m.parameters())
    assert sum(p.numel() for p in m.parameters()) == pytest.approx(4.65e6, rel=0.01)


def test_bad_weight_file_is_a_clear_error(tmp_path):
    p = tmp_path / "w.pth"
    torch.save({"_conv_stem.weight": torch.zeros(32, 3, 3, 3)}, p)
    with pytest.raises(InputError, match="not an EfficientNet-Lite0 state dict"):
        load_efficientnet_lite0(p)
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="cannot read"):
        load_efficientnet_lite0(tmp_path / "junk.pth")


def test_real_photos_classify_correctly(extractor):
    # skimage's bundled photos: a tabby cat (ImageNet 281-285 are domestic cats) and an espresso (967)
    cat = extractor.classify(photo("chelsea")).softmax(-1)[0]
    assert int(cat.argmax()) in range(281, 286) and float(cat[281:286].sum()) > 0.8
    coffee = extractor.classify(photo("coffee")).softmax(-1)[0]
    assert int(coffee.argmax()) == 967 and float(coffee[967]) > 0.6


def test_same_padding_matches_tensorflow_rule():
    x = torch.zeros(1, 1, 224, 223)
    y = effnet.same_pad(x, 3, 2)
    # out = ceil(in / s); pad total = (out-1)*s + k - in; TF puts the odd pixel after
    assert y.shape[-2:] == (225, 225)
    x = torch.ones(1, 1, 4, 4)
    y = effnet.same_pad(x, 3, 2)
    assert y[0, 0, 0].sum() == 4 and y[0, 0, -1].sum() == 0  # top row kept, bottom padded
    assert effnet.same_pad(torch.ones(1, 1, 5, 5), 5, 1).shape[-2:] == (9, 9)


def test_synthetic_top1_deterministic_and_features_batch_invariant(extractor):
    g = torch.Generator().manual_seed(0)
    a = torch.rand(64, 96, 3, generator=g)
    b = torch.rand(64, 96, 3, generator=g)
    l1 = extractor.classify(a)
    l2 = extractor.classify(a)
    assert torch.equal(l1, l2)
    f_alone = extractor.features(a)
    f_batch = extractor.features(torch.stack([b, a, b]))
    assert len(f_alone.scales) == len(FEATURE_CHANNELS)
    for fa, fb, c in zip(f_alone.scales, f_batch.scales, FEATURE_CHANNELS):
        assert fa.shape[1] == c
        assert torch.allclose(fa[0], fb[1], atol=1e-4, rtol=1e-5)  # float32 summation order only
    assert f_alone.embedding.shape == (1, EMBED_DIM)
    assert torch.allclose(f_alone.embedding[0], f_batch.embedding[1], atol=1e-5)
    # strides 2, 4, 8, 16, 32 (SAME padding: ceil)
    assert [tuple(f.shape[-2:]) for f in f_alone.scales] == [(32, 48), (16, 24), (8, 12), (4, 6), (2, 3)]


def test_embed_chunks_match_and_no_grad(extractor):
    x = torch.rand(5, 40, 40, 3, generator=torch.Generator().manual_seed(2))
    e1 = extractor.embed(x, batch_size=2)
    e2 = extractor.embed(x, batch_size=16)
    assert e1.shape == (5, EMBED_DIM) and torch.allclose(e1, e2, atol=1e-5)
    assert not e1.requires_grad and bool((e1 >= 0).all())  # ReLU6 head, average pooled


def test_perceptual_loss_properties():
    loss = EffNetPerceptualLoss(max_side=96)
    x = photo("chelsea")[::3, ::3].contiguous()
    assert float(loss(x, x)) == pytest.approx(0.0, abs=1e-6)
    xc = x.permute(2, 0, 1)[None]
    blur1 = F.avg_pool2d(xc, 3, 1, 1, count_include_pad=False)
    blur2 = F.avg_pool2d(xc, 9, 1, 4, count_include_pad=False)
    l1, l2 = float(loss(x, blur1)), float(loss(x, blur2))
    assert 0 < l1 < l2 <= 4
    # brightness-only change costs less than destroying structure of the same L1 size
    noise = (x + 0.1 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    assert float(loss(x, (x * 1.1).clamp(0, 1))) < float(loss(x, noise))
    # gradients reach the input
    y = x.clone().requires_grad_(True)
    loss(y, blur2.detach()).backward()
    assert y.grad is not None and float(y.grad.abs().sum()) > 0 and torch.isfinite(y.grad).all()
    with pytest.raises(ValueError):
        loss(x, x[:10])
