"""LPIPS (Zhang et al. 2018) from local files only: a torchvision AlexNet/VGG16 backbone
state dict plus LPIPS's learned per-channel linear weights. Nothing is ever downloaded.

The backbone is our own `features` stack whose module indices match torchvision's, so
its state dict (`features.0.weight`, `features.3.weight`, ...) loads with strict=True;
a full classifier-bearing file loads too (`classifier.*` is dropped explicitly).

    alex:  conv11/4 64 · pool · conv5 192 · pool · conv3 384 · conv3 256 · conv3 256 · pool
           taps after the ReLUs of conv1..conv5 (indices 1, 4, 7, 9, 11)
    vgg16: 13 conv3 layers in 5 blocks (64 64 | 128 128 | 256×3 | 512×3 | 512×3), pools between
           taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (indices 3, 8, 15, 22, 29)

Distance: x in [0, 1] → [−1, 1] → (x − shift)/scale; at each tap the activations are
divided by their channel norm (+1e-10) per pixel, the squared difference is weighted per
channel by the non-negative 1×1 linear layer (no bias), averaged over pixels, and the five
layer terms are summed.

The linear weights come from a file the user names, or from an installed `lpips` PyPI
package found WITHOUT importing it (its weights/v0.1/{alex,vgg}.pth; layout
`lin{k}.model.1.weight`, shape (1, C_k, 1, 1)).
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.losses.effnet import linear_to_srgb, to_batch

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
EPS = 1e-10

# Layer specs: ("conv", cin, cout, kernel, stride, padding) | ("relu",) | ("pool", kernel, stride).
_ALEX = [("conv", 3, 64, 11, 4, 2), ("relu",), ("pool", 3, 2),
         ("conv", 64, 192, 5, 1, 2), ("relu",), ("pool", 3, 2),
         ("conv", 192, 384, 3, 1, 1), ("relu",),
         ("conv", 384, 256, 3, 1, 1), ("relu",),
         ("conv", 256, 256, 3, 1, 1), ("relu",), ("pool", 3, 2)]


def _vgg16_spec():
    spec, cin = [], 3
    for block in ((64, 64), (128, 128), (256, 256, 256), (512, 512, 512), (512, 512, 512)):
        for cout in block:
            spec += [("conv", cin, cout, 3, 1, 1), ("relu",)]
            cin = cout
        spec.append(("pool", 2, 2))
    return spec


NETS = {
    "alex": (_ALEX, (1, 4, 7, 9, 11), (64, 192, 384, 256, 256)),
    "vgg": (_vgg16_spec(), (3, 8, 15, 22, 29), (64, 128, 256, 512, 512)),
}


def _build(spec) -> nn.Sequential:
    layers = []
    for s in spec:
        if s[0] == "conv":
            _, cin, cout, k, st, p = s
            layers.append(nn.Conv2d(cin, cout, k, stride=st, padding=p))
        elif s[0] == "relu":
            layers.append(nn.ReLU())  # not in-place: the tapped activations must survive
        else:
            layers.append(nn.MaxPool2d(s[1], s[2]))
    return nn.Sequential(*layers)


class Backbone(nn.Module):
    """`features` laid out like torchvision's alexnet()/vgg16() (frozen, eval mode)."""

    def __init__(self, net: str):
        super().__init__()
        if net not in NETS:
            raise InputError(f"LPIPS net {net!r}: use 'alex' or 'vgg'")
        spec, self.taps, self.channels = NETS[net]
        self.net = net
        self.features = _build(spec)

    def forward(self, x: torch.Tensor) -> list:
        out, last = [], self.taps[-1]
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
            if i == last:
                break  # the final pool is not needed
        return out


# ------------------------------------------------------------------ file loading
def _load_dict(path, what: str) -> dict:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} {path}: no such file (LPIPS loads local weights only; "
                         "nothing is downloaded)")
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # pickled modules, corrupt files, non-torch files
        raise InputError(f"{what} {path}: not a readable torch state dict ({type(e).__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''})") from None
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict) or not sd or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise InputError(f"{what} {path}: not a state dict (expected a mapping of names to tensors)")
    return sd


def infer_net(sd: dict, path="") -> str:
    """'alex' or 'vgg' from the first conv's kernel (11×11 vs 3×3)."""
    w = sd.get("features.0.weight")
    if w is None:
        raise InputError(f"LPIPS backbone {path}: no 'features.0.weight' (expected a torchvision "
                         "AlexNet or VGG16 state dict)")
    shape = tuple(w.shape)
    if shape == (64, 3, 11, 11):
        return "alex"
    if shape == (64, 3, 3, 3):
        return "vgg"
    raise InputError(f"LPIPS backbone {path}: features.0.weight has shape {shape}; AlexNet has "
                     "(64, 3, 11, 11), VGG16 (64, 3, 3, 3)")


def load_backbone(path, net: str | None = None) -> Backbone:
    """A torchvision AlexNet/VGG16 state dict (features only, or the full classifier-bearing
    file) → frozen Backbone; errors name the file and what is wrong."""
    sd = _load_dict(path, "LPIPS backbone")
    # A full torchvision file also holds the ImageNet classifier, which LPIPS never uses.
    feats = {k: v for k, v in sd.items() if not k.startswith("classifier.")}
    other = sorted(k for k in feats if not k.startswith("features."))
    if other and all(k.startswith("lin") for k in other):
        raise InputError(f"LPIPS backbone {path}: holds LPIPS linear weights ({other[0]}, ...), not "
                         "a torchvision backbone: pass it as the linear weights (--lpips-lin)")
    if other:
        raise InputError(f"LPIPS backbone {path}: unexpected keys {other[:5]} (expected "
                         "torchvision 'features.*' and optionally 'classifier.*')")
    net = net or infer_net(feats, path)
    model = Backbone(net)
    want = model.state_dict()
    missing = sorted(set(want) - set(feats))
    extra = sorted(set(feats) - set(want))
    bad = [f"{k} {tuple(feats[k].shape)} (want {tuple(want[k].shape)})"
           for k in want if k in feats and feats[k].shape != want[k].shape]
    if missing or extra or bad:
        parts = ([f"missing {missing[:5]}"] if missing else []) + \
                ([f"unexpected {extra[:5]}"] if extra else []) + \
                ([f"wrong shape {bad[:3]}"] if bad else [])
        raise InputError(f"LPIPS backbone {path}: not a torchvision {net} features state dict: "
                         + "; ".join(parts))
    model.load_state_dict({k: v.float() for k, v in feats.items()}, strict=True)
    model.eval().requires_grad_(False)
    return model


def installed_lin_path(net: str) -> Path | None:
    """weights/v0.1/<net>.pth inside an installed `lpips` package, located without importing it."""
    try:
        spec = importlib.util.find_spec("lpips")
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    roots = list(spec.submodule_search_locations or [])
    if not roots and spec.origin:
        roots = [str(Path(spec.origin).parent)]
    for r in roots:
        p = Path(r) / "weights" / "v0.1" / f"{net}.pth"
        if p.is_file():
            return p
    return None


def load_lin(path, net: str) -> list:
    """The five LPIPS linear weight vectors (C_k,) from an lpips-layout file."""
    sd = _load_dict(path, "LPIPS linear weights")
    channels = NETS[net][2]
    out = []
    for k, c in enumerate(channels):
        key = f"lin{k}.model.1.weight"
        if key not in sd:
            raise InputError(f"LPIPS linear weights {path}: missing {key!r} (expected the lpips "
                             f"package's weights/v0.1/{net}.pth layout)")
        w = sd[key]
        if tuple(w.shape) != (1, c, 1, 1):
            raise InputError(f"LPIPS linear weights {path}: {key} has shape {tuple(w.shape)}, the "
                             f"{net} backbone needs (1, {c}, 1, 1) — weights for another net?")
        if not torch.isfinite(w).all() or (w < 0).any():
            raise InputError(f"LPIPS linear weights {path}: {key} has negative or non-finite "
                             "values (LPIPS's linear layers are non-negative)")
        out.append(w.reshape(c).float())
    return out


# ------------------------------------------------------------------ the distance
class LPIPSLoss(nn.Module):
    """loss(x, y) for images (H, W, 3) / (B, H, W, 3) / (B, 3, H, W) in [0, 1]; mean over the batch.

    linear:   inputs are scene-linear (sRGB-encoded before the network, as for the EffNet loss).
    max_side: downscale (antialiased) so the longer side is at most this (None: full size).
    Gradients flow to both inputs; pass a detached target.
    """

    def __init__(self, backbone: Backbone, lin: list, linear: bool = False,
                 max_side: int | None = None):
        super().__init__()
        self.backbone = backbone
        self.net = backbone.net
        for k, w in enumerate(lin):
            self.register_buffer(f"lin{k}", w.reshape(1, -1, 1, 1).clone())
        self.register_buffer("shift", torch.tensor(SHIFT).reshape(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).reshape(1, 3, 1, 1))
        self.linear = linear
        self.max_side = max_side

    @classmethod
    def from_files(cls, backbone_path, lin_path=None, net: str | None = None, **kw) -> "LPIPSLoss":
        backbone = load_backbone(backbone_path, net)
        if lin_path is None:
            lin_path = installed_lin_path(backbone.net)
            if lin_path is None:
                raise InputError(
                    f"LPIPS: no linear weights for the {backbone.net} backbone ({backbone_path}): "
                    f"pass the lpips package's weights/v0.1/{backbone.net}.pth (--lpips-lin) or "
                    "install the lpips package; nothing is downloaded")
        return cls(backbone, load_lin(lin_path, backbone.net), **kw)

    def _prepare(self, x: torch.Tensor) -> torch.Tensor:
        x = to_batch(x)
        if self.linear:
            x = linear_to_srgb(x)
        h, w = x.shape[-2:]
        if self.max_side is not None and max(h, w) > self.max_side:
            s = self.max_side / max(h, w)
            x = F.interpolate(x, size=(max(1, round(h * s)), max(1, round(w * s))),
                              mode="bilinear", align_corners=False, antialias=True)
        return ((2 * x - 1) - self.shift) / self.scale

    def per_layer(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """(B, 5) layer terms; their sum is the LPIPS distance of each pair."""
        xb, yb = self._prepare(x), self._prepare(y)
        if xb.shape != yb.shape:
            raise ValueError(f"LPIPS: shapes differ {tuple(xb.shape)} vs {tuple(yb.shape)}")
        n = xb.shape[0]
        feats = self.backbone(torch.cat([xb, yb]))
        terms = []
        for k, f in enumerate(feats):
            # vector_norm has a zero subgradient at 0 (a dead pixel), where sqrt would give NaN.
            u = f / (torch.linalg.vector_norm(f, dim=1, keepdim=True) + EPS)
            d = (u[:n] - u[n:]) ** 2
            terms.append((d * getattr(self, f"lin{k}")).sum(dim=1).mean(dim=(1, 2)))
        return torch.stack(terms, dim=1)

    def distance(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """(B,) LPIPS distances."""
        return self.per_layer(x, y).sum(dim=1)

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return self.distance(x, y).mean()
