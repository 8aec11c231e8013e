"""Image priors by name: one registry (built-ins here, third-party ones from the
``lsd3d_usd.priors`` entry-point group) and the prior part of the configuration tree.

A registered prior is a :class:`PriorEntry`: a factory ``make(arg, config, seed) -> Prior``
plus a ``check(arg, config)`` run before anything is written (missing files, a device torch
cannot see), the prior's class (its default loss weights are known without making it),
whether it is cheap on a CPU (eval's prior baselines run only such priors unasked), and its
own configuration class: the options it takes beyond ``--prior NAME[:ARG]``
(``--set prior.options.KEY=VALUE``), which ``prior_options`` gives it typed.
``--prior NAME[:ARG]`` selects one: ``procedural`` or ``diffusers:DIR``.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from lsd3d_usd import configtree as ct
from lsd3d_usd.configtree import option
from lsd3d_usd.errors import InputError
from lsd3d_usd.registry import Registry


def check_prior_name(v: str, where: str = "--prior") -> str:
    """A registered prior's name (with its argument): one InputError line otherwise."""
    name = str(v).split(":", 1)[0]
    if name not in PRIORS.names():
        names = sorted(PRIORS.names(), key=lambda n: (n != "procedural", n))
        known = " or ".join(f"'{n}:DIR'" if PRIORS.get(n).takes_arg else f"'{n}'" for n in names)
        raise InputError(f"{where} {v!r}: use {known} (unknown prior)")
    return str(v)


def check_device(v: str, where: str = "--device") -> str:
    """cpu, cuda or cuda:N; one InputError line otherwise."""
    d = str(v)
    if d != "cpu" and not (d == "cuda" or (d.startswith("cuda:") and d[5:].isdigit())):
        raise InputError(f"{where} {v!r}: expected cpu, cuda or cuda:N")
    return d


@dataclass
class PriorConfig:
    name: str = option("procedural", help="image prior: 'procedural' (runs on CPU) or "
                                          "'diffusers:DIR' (a local latent-diffusion directory; "
                                          "never downloads), or another registered prior",
                       flag="--prior", alias="prior", check=check_prior_name, metavar="PRIOR")
    controlnet: Path | None = option(None, help="local depth ControlNet directory for the "
                                                "diffusers prior", flag="--controlnet",
                                     alias="controlnet", metavar="DIR")
    device: str = option("cpu", help="torch device of the prior (cuda only where torch sees "
                                     "one)", flag="--device", alias="device", check=check_device)
    guidance: float = option(7.5, help="classifier-free guidance scale (diffusers prior)",
                             lo=0.0, hi=100.0)
    supersample: int = option(2, help="procedural prior: each pixel the mean of S×S samples, "
                                      "as a camera integrates over its pixels (1 = the pixel "
                                      "centre, which aliases)", lo=1, hi=8, recorded=1)
    options: dict[str, str] = option(
        help="options of the chosen prior beyond its NAME:ARG (prior.options.KEY=VALUE; the "
             "keys a prior takes are listed by its registry entry)", default_factory=dict)

    @property
    def kind(self) -> str:
        return self.name.split(":", 1)[0]

    @property
    def arg(self) -> str | None:
        return self.name.split(":", 1)[1] if ":" in self.name else None


@dataclass(frozen=True)
class PriorEntry:
    make: Callable            # (arg, PriorConfig, seed) -> Prior
    check: Callable           # (arg, PriorConfig) -> None; raise InputError
    takes_arg: bool = False
    help: str = ""
    prior_class: str = "lsd3d_usd.ggds.priors.base:Prior"   # "module:Class" of what make returns
    cheap_on_cpu: bool = False    # a target in well under a second per view on 2 cores
    # the options it takes beyond NAME:ARG, a configtree dataclass of option leaves: their
    # values (prior.options.KEY=VALUE) reach make typed and checked through prior_options()
    config: type | None = None

    def prior_type(self) -> type:
        module, _, name = self.prior_class.partition(":")
        return getattr(importlib.import_module(module), name)

    def default_weight(self, term: str) -> float:
        """The prior's default weight of a loss term (Prior.default_weights), known without
        making the prior."""
        return float(self.prior_type().default_weights.get(term, 0.0))


def _check_device_available(cfg: PriorConfig) -> None:
    if cfg.device.startswith("cuda"):
        # local import: not loaded for --help
        import torch
        if not torch.cuda.is_available():
            raise InputError(f"--device {cfg.device}: torch sees no CUDA device here "
                             "(use --device cpu)")


# ----------------------------------------------------------------------------- built-ins
def _procedural_check(arg, cfg):
    if arg:
        raise InputError(f"--prior procedural:{arg}: the procedural prior takes no argument")
    _check_device_available(cfg)


def _procedural_make(arg, cfg, seed):
    # local import: not loaded for --help
    from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
    return ProceduralPrior(seed=seed, supersample=cfg.supersample)


def _diffusers_check(arg, cfg):
    if not arg:
        raise InputError("--prior diffusers:DIR needs a local model directory")
    if not Path(arg).is_dir():
        raise InputError(f"--prior diffusers:{arg}: no such directory (the diffusion prior "
                         "loads local weights only; nothing is downloaded)")
    # local import: not loaded for --help
    from lsd3d_usd.ggds.priors.diffusion import check_model_dir
    check_model_dir(arg, cfg.controlnet)
    _check_device_available(cfg)


def _diffusers_make(arg, cfg, seed):
    # local import: not loaded for --help
    from lsd3d_usd.ggds.priors.diffusion import DiffusersPrior
    return DiffusersPrior.from_pretrained(arg, cfg.controlnet, device=cfg.device,
                                          guidance_scale=cfg.guidance)


PROCEDURAL = PriorEntry(_procedural_make, _procedural_check,
                        help="procedural materials lit by the environment (CPU, deterministic)",
                        prior_class="lsd3d_usd.ggds.priors.procedural:ProceduralPrior",
                        cheap_on_cpu=True)
DIFFUSERS = PriorEntry(_diffusers_make, _diffusers_check, takes_arg=True,
                       help="latent diffusion + depth ControlNet from a local diffusers folder",
                       prior_class="lsd3d_usd.ggds.priors.diffusion:DiffusersPrior")

PRIORS = Registry("lsd3d_usd.priors", "prior", {
    "procedural": "lsd3d_usd.ggds.priors.registry:PROCEDURAL",
    "diffusers": "lsd3d_usd.ggds.priors.registry:DIFFUSERS",
})


def check_prior(cfg: PriorConfig) -> None:
    """Everything about the prior that can be checked without loading it."""
    entry = PRIORS.get(cfg.kind)
    prior_options(cfg)
    entry.check(cfg.arg, cfg)


def prior_options(cfg: PriorConfig):
    """The chosen prior's options as its own configuration class (PriorEntry.config), from
    ``cfg.options`` (text from --set, or TOML values), checked; None for a prior without one."""
    entry = PRIORS.get(cfg.kind)
    if entry.config is None:
        if cfg.options:
            key = sorted(cfg.options)[0]
            raise InputError(f"prior.options.{key}: the {cfg.kind} prior takes no such option "
                             "(its options: none)")
        return None
    values = ct.flatten(dict(cfg.options), entry.config, "prior.options: ")
    return ct.apply(entry.config(), values, "prior.options.")


def make_prior(cfg: PriorConfig, seed: int = 0):
    """The prior, loaded once (its seed follows the scene's)."""
    check_prior(cfg)
    return PRIORS.get(cfg.kind).make(cfg.arg, cfg, seed)
