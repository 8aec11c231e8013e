"""A finished run's pictures: loss.png (losses and PSNR against the prior per step) and
before_after.png (initial surfels, after GGDS, the prior's held-out target for the first
held-out views)."""
from __future__ import annotations

import numpy as np
import torch
from matplotlib.figure import Figure   # no pyplot: no global backend, files only

from lsd3d_usd.colour import srgb_encode
from lsd3d_usd.ggds.priors.base import heldout_target

BEFORE_AFTER_VIEWS = 2


def render_rgb(run, view) -> torch.Tensor:
    """The run's render of ``view`` over the env map."""
    cam = view.camera
    return run.render(cam, background=run.conditioning.background(cam)).rgb


@torch.no_grad()
def write_plots(run, held_out: list, before: list, out_dir) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    h = run.history
    if h:
        fig = Figure(figsize=(10, 3.2))
        ax = fig.subplots(1, 2)
        steps = [r["step"] for r in h]
        for key in ("loss", "l1", "disparity", "normal"):
            ys = np.array([r.get(key, np.nan) for r in h])
            k = max(1, len(ys) // 20)
            ax[0].plot(steps, np.convolve(ys, np.ones(k) / k, mode="same"), label=key)
        ax[0].set_yscale("log"); ax[0].set_xlabel("step"); ax[0].legend(); ax[0].set_title("GGDS losses")
        ax[1].plot(steps, [r["psnr_target"] for r in h], ".", ms=3)
        ax[1].set_xlabel("step"); ax[1].set_ylabel("PSNR render vs prior target (dB)")
        fig.tight_layout(); fig.savefig(out_dir / "loss.png", dpi=100)
    rows = []
    cond = run.conditioning
    for i, v in enumerate(held_out[:BEFORE_AFTER_VIEWS]):
        x = render_rgb(run, v)
        tgt = heldout_target(run.prior, x, cond.gbuffer(v.camera), cond.env, i)
        rows.append((before[i] if i < len(before) else x, x, tgt))
    if rows:
        fig = Figure(figsize=(12, 2.4 * len(rows)))
        ax = fig.subplots(len(rows), 3, squeeze=False)
        for i, imgs in enumerate(rows):
            for j, (img, title) in enumerate(zip(imgs, ("initial surfels", "after GGDS",
                                                         "prior target"))):
                ax[i, j].imshow(srgb_encode(img.clamp(0, 1)).numpy()); ax[i, j].set_axis_off()
                if i == 0:
                    ax[i, j].set_title(title)
        fig.tight_layout(); fig.savefig(out_dir / "before_after.png", dpi=100)
