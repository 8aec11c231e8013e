"""Seconds per deferred frame with the diffusion prior at Stable Diffusion 1.5's size.

No weights can be downloaded here, so the components are SD-1.5-sized networks with random
weights, saved to a temp folder and loaded through DiffusersPrior.from_pretrained (the real
loading path): UNet (320/640/1280/1280, cross-attention 768), a depth ControlNet made from it,
the SD VAE (128/256/512/512) and a small text encoder (its cost is one call per prompt, cached).
Time does not depend on the weights' values, so this is the cost of the real model; the
pictures are noise. One frame = VAE encode, N DDIM inversion steps (ControlNet + UNet), N
guided steps (batch 2: ControlNet + UNet), VAE decode.

usage: python tools/bench_deferred_diffusers.py [--resolution 480x270] [--steps 5]
           [--strength 0.3] [--frames 2] [--no-controlnet] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def build(root: Path, controlnet: bool):
    import diffusers
    import transformers
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_ggds_priors_diffusion import tiny_clip_tokenizer
    n_vocab = tiny_clip_tokenizer(root / "tokenizer")
    unet = diffusers.UNet2DConditionModel(cross_attention_dim=768, attention_head_dim=8)
    unet.save_pretrained(root / "unet")
    diffusers.AutoencoderKL(block_out_channels=(128, 256, 512, 512), layers_per_block=2,
                            down_block_types=("DownEncoderBlock2D",) * 4,
                            up_block_types=("UpDecoderBlock2D",) * 4,
                            latent_channels=4).save_pretrained(root / "vae")
    transformers.CLIPTextModel(transformers.CLIPTextConfig(
        vocab_size=n_vocab, hidden_size=768, intermediate_size=1024, num_hidden_layers=2,
        num_attention_heads=12, max_position_embeddings=16, bos_token_id=n_vocab - 2,
        eos_token_id=n_vocab - 1, pad_token_id=n_vocab - 1)).save_pretrained(root / "text_encoder")
    if controlnet:
        diffusers.ControlNetModel.from_unet(unet).save_pretrained(root / "controlnet")
    return root, (root / "controlnet" if controlnet else None)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--resolution", default="480x270")
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--strength", type=float, default=0.3)
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--no-controlnet", action="store_true")
    ap.add_argument("--json")
    a = ap.parse_args(argv)

    from lsd3d_usd.ggds.priors.diffusion import DiffusersPrior
    from lsd3d_usd.conditioning.light import PriorEnv
    from lsd3d_usd.render.camera import Camera, look_at
    from lsd3d_usd.conditioning.scene import Conditioning
    from lsd3d_usd.ggds.priors.scene import ScenePrior
    from lsd3d_usd.views.deferred import Deferrer

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_views_deferred import street_proxy

    w, h = (int(v) for v in a.resolution.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        root, cn = build(Path(tmp), not a.no_controlnet)
        prior = DiffusersPrior.from_pretrained(root, controlnet_dir=cn)
        setup = time.perf_counter() - t0
        sp = ScenePrior(prior, Conditioning.of_arrays(street_proxy(), PriorEnv(prompt="a street")),
                        "diffusers:<SD-1.5-sized, random weights>", "benchmark", 0)
        d = Deferrer(sp, a.strength, a.steps)
        eye = np.array([0.0, -1.5, 1.6])
        times = []
        for k in range(a.frames):
            cam = Camera.from_fov(w, h, 70.0, look_at(eye + [k, 0, 0], eye + [k + 1, 0, -0.08]))
            x = np.random.default_rng(k).uniform(0, 1, (h, w, 3)).astype(np.float32)
            t1 = time.perf_counter()
            d.defer(x, cam)
            times.append(time.perf_counter() - t1)
            print(f"frame {k}: {times[-1]:.1f} s")
    res = {"resolution": a.resolution, "work_size": list(prior.work_size(h, w)), "steps": a.steps,
           "strength": a.strength, "controlnet": not a.no_controlnet, "setup_s": round(setup, 1),
           "s_per_frame": [round(t, 2) for t in times], "torch_threads": torch.get_num_threads()}
    print(json.dumps(res))
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()
