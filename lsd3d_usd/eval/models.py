"""The paper's metrics that need third-party network weights: Inception FID, FD-DINOv2,
CLIP score and FVD. Nothing is ever downloaded: they are computed only from local files in
`--weights DIR`, under these names:

    inception FID : pt_inception-2015-12-05-6726825d.pth   (the FID Inception-v3 of pytorch-fid)
    FD-DINOv2     : dinov2_vitl14_pretrain.pth / dinov2_vitb14_pretrain.pth / dinov2_vits14_pretrain.pth
    CLIP score    : ViT-L-14.pt / ViT-B-32.pt / ViT-B-16.pt     (OpenAI CLIP TorchScript archives)
    FVD           : i3d_torchscript.pt                          (the StyleGAN-V / FVD I3D export)

This version has none of these network architectures (no torchvision / timm / open_clip in
the environment, and our own re-implementations are not verified against the reference
outputs), so every metric here is reported as unavailable with the reason — whether the
file is missing or present. `status()` is the single place that decides.
"""
from __future__ import annotations

from pathlib import Path

from lsd3d_usd.errors import InputError

WEIGHT_FILES = {
    "fid_inception": ("pt_inception-2015-12-05-6726825d.pth",),
    "fd_dinov2": ("dinov2_vitl14_pretrain.pth", "dinov2_vitb14_pretrain.pth",
                  "dinov2_vits14_pretrain.pth"),
    "clip_score": ("ViT-L-14.pt", "ViT-B-32.pt", "ViT-B-16.pt"),
    "fvd": ("i3d_torchscript.pt",),
}
_NETWORK = {"fid_inception": "Inception-v3 (FID variant)", "fd_dinov2": "DINOv2 ViT",
            "clip_score": "CLIP (image and text towers, BPE tokenizer)",
            "fvd": "I3D video network (Kinetics-400)"}


def check_weights_dir(weights) -> Path | None:
    if weights is None:
        return None
    p = Path(weights)
    if not p.is_dir():
        raise InputError(f"--weights {weights}: no such directory (local weight files only; "
                         "see docs/eval.md for the expected names)")
    return p


def status(weights: Path | None) -> list[dict]:
    """[{"metric", "reason"}] for every weight-based metric that is not computed."""
    out = []
    for metric, names in WEIGHT_FILES.items():
        if weights is None:
            reason = f"no --weights DIR given (needs one of: {', '.join(names)})"
        else:
            found = [n for n in names if (weights / n).is_file()]
            if not found:
                reason = f"{weights}: none of {', '.join(names)} found"
            else:
                reason = (f"weights found ({weights / found[0]}) but the {_NETWORK[metric]} network "
                          "is not implemented in this version of lsd3d-usd")
        out.append({"metric": metric, "reason": reason})
    return out
