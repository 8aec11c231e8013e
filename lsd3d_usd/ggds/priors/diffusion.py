"""The paper's prior: a latent diffusion model (Stable Diffusion 1.x/2.x layout, via `diffusers`)
with a depth/disparity ControlNet, loaded only from local directories (never the hub).

target(x, gbuffer, env, t, n_steps):
  1. x (scene-linear) -> sRGB -> [-1, 1] -> VAE encoder mean * scaling_factor = z_0
  2. DDIM inversion of z_0 up to level k(t) (ggds/priors/ddim.py), with the conditional noise
     prediction (guidance 1: inverting with classifier-free guidance is unstable)
  3. n_steps deterministic DDIM steps back to level 0 with classifier-free guidance on the
     prompt (env.prompt / env.negative_prompt), every UNet call given the ControlNet
     residuals for the G-buffer disparity (1/depth normalised to [0, 1] per view, sky 0,
     as the depth ControlNets were trained on)
  4. VAE decode -> sRGB -> linear.
t -> 0 (level -1) skips 2-3: x_hat is the VAE reconstruction decode(encode(x)).

`diffusers` and `transformers` are imported lazily (optional extra `[diffusion]`); the
process sets HF_HUB_OFFLINE=1 and every from_pretrained call uses local_files_only=True.

Expected layout of the model directory (a diffusers pipeline folder):
    unet/         config.json + diffusion_pytorch_model.(safetensors|bin)
    vae/          config.json + diffusion_pytorch_model.(safetensors|bin)
    text_encoder/ config.json + model.safetensors | pytorch_model.bin
    tokenizer/    vocab.json + merges.txt (CLIP BPE) or tokenizer.json
    scheduler/    scheduler_config.json (optional: SD's scaled-linear schedule otherwise)
The ControlNet directory: config.json + diffusion_pytorch_model.(safetensors|bin).
SDXL pipelines (text_encoder_2 / added time conditioning) are refused with a clear message.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import torch
import torch.nn.functional as F

from lsd3d_usd.colour import srgb_decode as srgb_to_linear  # noqa: F401
from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.priors.ddim import DDIMSchedule, eps_from_model_output
from lsd3d_usd.ggds.losses.effnet import linear_to_srgb
from lsd3d_usd.conditioning.gbuffer import GBuffer
from lsd3d_usd.ggds.priors.base import Prior, check_image, check_t
from lsd3d_usd.conditioning.light import PriorEnv

_MODEL_WEIGHTS = ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin")
_TEXT_WEIGHTS = ("model.safetensors", "pytorch_model.bin")


def _need_dir(root: Path, sub: str, files_any: tuple[str, ...], what: str, config="config.json") -> Path:
    d = root / sub if sub else root
    if not d.is_dir():
        raise InputError(f"{what}: missing directory {d}")
    if config and not (d / config).is_file():
        raise InputError(f"{what}: missing {d / config}")
    if files_any and not any((d / f).is_file() for f in files_any):
        raise InputError(f"{what}: no weights in {d} (expected one of {', '.join(files_any)})")
    return d


def check_model_dir(local_dir, controlnet_dir=None) -> None:
    """InputError naming the first missing component/file of a local diffusion model."""
    root = Path(local_dir)
    if not root.is_dir():
        raise InputError(f"diffusion model directory not found: {root}")
    if (root / "text_encoder_2").exists() or (root / "tokenizer_2").exists():
        raise InputError(f"{root}: SDXL pipelines (text_encoder_2) are not supported by the diffusers prior yet; "
                         "use a Stable Diffusion 1.x/2.x directory")
    _need_dir(root, "unet", _MODEL_WEIGHTS, "UNet")
    _need_dir(root, "vae", _MODEL_WEIGHTS, "VAE")
    _need_dir(root, "text_encoder", _TEXT_WEIGHTS, "text encoder")
    tok = _need_dir(root, "tokenizer", (), "tokenizer", config=None)
    if not ((tok / "tokenizer.json").is_file() or ((tok / "vocab.json").is_file() and (tok / "merges.txt").is_file())):
        raise InputError(f"tokenizer: {tok} needs vocab.json + merges.txt or tokenizer.json")
    if controlnet_dir is not None:
        _need_dir(Path(controlnet_dir), "", _MODEL_WEIGHTS, "ControlNet")


def _import_diffusers():
    os.environ["HF_HUB_OFFLINE"] = "1"
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    os.environ.setdefault("HF_HUB_DISABLE_TELEMETRY", "1")
    try:
        # local import: optional dependency
        import diffusers
        import transformers
    except ImportError:
        raise InputError("the diffusers prior needs the optional packages 'diffusers' and 'transformers' "
                         "(pip install 'lsd3d-usd[diffusion]')") from None
    return diffusers, transformers


def disparity_condition(gb: GBuffer, height: int, width: int) -> torch.Tensor:
    """(1, 3, height, width) ControlNet image: disparity / max disparity in view, sky 0."""
    disp = gb.disparity().float()
    m = float(disp.max()) if disp.numel() else 0.0
    if m > 0:
        disp = disp / m
    img = disp[None, None]
    if tuple(img.shape[-2:]) != (height, width):
        img = F.interpolate(img, size=(height, width), mode="bilinear", align_corners=False)
    return img.expand(1, 3, height, width).contiguous()


class DiffusersPrior(Prior):
    name = "diffusers"

    def __init__(self, unet, vae, text_encoder, tokenizer, controlnet=None, *, schedule=None,
                 prediction_type="epsilon", guidance_scale: float = 7.5,
                 controlnet_scale: float = 1.0, max_side: int | None = 512,
                 device="cpu", dtype=torch.float32, source: str = ""):
        self.unet, self.vae, self.text_encoder, self.tokenizer = unet, vae, text_encoder, tokenizer
        self.controlnet = controlnet
        self.schedule = schedule or DDIMSchedule()
        self.prediction_type = prediction_type
        self.guidance_scale = float(guidance_scale)
        self.controlnet_scale = float(controlnet_scale)
        self.max_side = max_side
        self.device, self.dtype = device, dtype
        self.source = source
        self.vae_factor = 2 ** (len(vae.config.block_out_channels) - 1)
        self.scaling = float(getattr(vae.config, "scaling_factor", 0.18215))
        self._text_cache: dict = {}

    @classmethod
    def from_pretrained(cls, local_dir, controlnet_dir=None, device="cpu", dtype=torch.float32,
                        **kwargs) -> "DiffusersPrior":
        """Load from local directories only (see module doc); InputError names what is missing."""
        check_model_dir(local_dir, controlnet_dir)
        diffusers, transformers = _import_diffusers()
        root = Path(local_dir)
        kw = dict(local_files_only=True, torch_dtype=dtype)
        try:
            unet = diffusers.UNet2DConditionModel.from_pretrained(root / "unet", **kw)
            vae = diffusers.AutoencoderKL.from_pretrained(root / "vae", **kw)
            text_encoder = transformers.CLIPTextModel.from_pretrained(root / "text_encoder", **kw)
            tokenizer = transformers.CLIPTokenizer.from_pretrained(root / "tokenizer", local_files_only=True)
            controlnet = (diffusers.ControlNetModel.from_pretrained(Path(controlnet_dir), **kw)
                          if controlnet_dir is not None else None)
        except (OSError, ValueError, EnvironmentError) as e:
            raise InputError(f"cannot load the diffusion model from {root}: {str(e).splitlines()[0]}") from None
        schedule, pred = DDIMSchedule(), "epsilon"
        sc = root / "scheduler" / "scheduler_config.json"
        if sc.is_file():
            try:
                cfg = json.loads(sc.read_text())
            except ValueError as e:
                raise InputError(f"{sc}: not valid JSON ({e})") from None
            schedule = DDIMSchedule.from_diffusers_config(cfg)
            pred = cfg.get("prediction_type", "epsilon")
        for m in (unet, vae, text_encoder, controlnet):
            if m is not None:
                m.to(device).eval().requires_grad_(False)
        return cls(unet, vae, text_encoder, tokenizer, controlnet, schedule=schedule,
                   prediction_type=pred, device=device,
                   dtype=dtype, source=str(root), **kwargs)

    def describe(self) -> dict:
        return {"prior": self.name, "model": self.source, "guidance_scale": self.guidance_scale,
                "controlnet": self.controlnet is not None, "controlnet_scale": self.controlnet_scale,
                "prediction_type": self.prediction_type, "max_side": self.max_side}

    # -- pieces -------------------------------------------------------------------------------
    def encode_text(self, prompt: str) -> torch.Tensor:
        if prompt not in self._text_cache:
            tok = self.tokenizer([prompt], padding="max_length", truncation=True,
                                 max_length=self.tokenizer.model_max_length, return_tensors="pt")
            with torch.no_grad():
                emb = self.text_encoder(tok.input_ids.to(self.device))[0]
            self._text_cache[prompt] = emb.to(self.dtype)
        return self._text_cache[prompt]

    def work_size(self, H: int, W: int) -> tuple[int, int]:
        s = 1.0
        if self.max_side is not None and max(H, W) > self.max_side:
            s = self.max_side / max(H, W)
        f = self.vae_factor
        return max(f, round(H * s / f) * f), max(f, round(W * s / f) * f)

    @torch.no_grad()
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(H, W, 3) linear image -> latent z_0 (1, C, h, w) at the working size."""
        H, W = x.shape[:2]
        h, w = self.work_size(H, W)
        img = linear_to_srgb(x.float()).permute(2, 0, 1)[None]
        if (h, w) != (H, W):
            img = F.interpolate(img, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        img = (img * 2 - 1).to(self.device, self.dtype)
        return self.vae.encode(img).latent_dist.mean * self.scaling

    @torch.no_grad()
    def decode(self, z: torch.Tensor, H: int, W: int) -> torch.Tensor:
        img = self.vae.decode(z / self.scaling).sample.float()
        img = ((img + 1) / 2).clamp(0, 1)
        if tuple(img.shape[-2:]) != (H, W):
            img = F.interpolate(img, size=(H, W), mode="bilinear", align_corners=False)
        return srgb_to_linear(img[0].permute(1, 2, 0)).cpu()

    def eps_fn(self, cond_emb, uncond_emb, control, guidance: float):
        def eps(z, k):
            kt = torch.tensor(max(k, 0), device=self.device)
            if guidance == 1.0:
                zin, emb = z, cond_emb
            else:
                zin, emb = torch.cat([z, z]), torch.cat([uncond_emb, cond_emb])
            extra = {}
            if self.controlnet is not None:
                c = control.expand(zin.shape[0], -1, -1, -1)
                down, mid = self.controlnet(zin, kt, encoder_hidden_states=emb, controlnet_cond=c,
                                            conditioning_scale=self.controlnet_scale, return_dict=False)
                extra = {"down_block_additional_residuals": down, "mid_block_additional_residual": mid}
            out = self.unet(zin, kt, encoder_hidden_states=emb, **extra).sample
            a = self.schedule.alpha_bar(max(k, 0))
            e = eps_from_model_output(out, zin, a, self.prediction_type)
            if guidance == 1.0:
                return e
            eu, ec = e.chunk(2)
            return eu + guidance * (ec - eu)
        return eps

    # -- the prior --------------------------------------------------------------------------
    @torch.no_grad()
    def target(self, x: torch.Tensor, gbuffer: GBuffer, env: PriorEnv, t: float,
               n_steps: int = 5, seed: int | None = None) -> torch.Tensor:
        """See module doc. Deterministic (DDIM eta = 0, VAE posterior mean): `seed` is accepted
        for interface compatibility and does not change the result."""
        check_image(x)
        t = check_t(t)
        H, W = x.shape[:2]
        gbuffer.validate(H, W)
        z0 = self.encode(x.detach())
        k = self.schedule.level(t)
        if k >= 0:
            h, w = self.work_size(H, W)
            control = disparity_condition(gbuffer, h, w).to(self.device, self.dtype)
            cond = self.encode_text(env.prompt)
            uncond = self.encode_text(env.negative_prompt)
            zt = self.schedule.invert(z0, self.eps_fn(cond, uncond, control, 1.0), k, n_steps)
            z0 = self.schedule.denoise(zt, self.eps_fn(cond, uncond, control, self.guidance_scale), k, n_steps)
        return self.decode(z0, H, W).to(x.device)
