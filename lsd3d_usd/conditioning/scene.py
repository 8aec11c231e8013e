"""What a prior and an evaluation need of a scene, built once: the proxy arrays, the scene's
light, the sun's shadow map of the proxy and the face tables G-buffers are unpacked with.

``Conditioning`` is the one place this chain (env parameters → EXR → scene light → shadow
map → G-buffers) is put together; GGDS regions, eval, deferral and the benchmarks all take
theirs from here. Built from a scene it only reads: the env layer's parameters and the EXR
its DomeLight names (``generate`` wrote both), never a new file.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Hashable

import torch
from pxr import Usd

from lsd3d_usd import scene as S
from lsd3d_usd.conditioning.gbuffer import (
    FaceTable,
    GBuffer,
    PackedGBuffer,
    finer,
    pack_view_gbuffer,
)
from lsd3d_usd.conditioning.light import PriorEnv, SceneLight, scene_light
from lsd3d_usd.conditioning.shadow import ShadowMap, shadow_map
from lsd3d_usd.env.params import EnvParams
from lsd3d_usd.env.usdlayer import VARIANT_SET as ENV_VARIANT_SET
from lsd3d_usd.env.usdlayer import read_env_prim, read_far_field
from lsd3d_usd.errors import InputError
from lsd3d_usd.proxy.usdio import proxy_arrays


@dataclass
class Conditioning:
    """The proxy (V (n,3), F (m,3), face class ids (m,)), the light as the prior sees it
    (``env``), the sun's shadow map of that proxy (None: all lit) and its FaceTable; the
    scene light (``light``: exposure, env map behind the surfels) when built from one, else
    ``backdrop`` (camera -> (H, W, 3), or None: no background). G-buffers and backgrounds
    per camera."""
    proxy: tuple
    env: PriorEnv
    shadow: ShadowMap | None
    faces: FaceTable
    light: SceneLight | None = None
    backdrop: Callable | None = None

    @classmethod
    def build(cls, proxy, light: SceneLight) -> "Conditioning":
        """From a scene light: its shadow map of ``proxy`` and env map background."""
        V, F, C = proxy
        return cls((V, F, C), light.prior_env, shadow_map(V, F, light.sun_direction),
                   FaceTable.of(V, F, C), light)

    @classmethod
    def of_arrays(cls, proxy, env: PriorEnv | None = None, shadow: ShadowMap | None = None,
                  backdrop: Callable | None = None) -> "Conditioning":
        """From arrays alone (synthetic scenes, tests): no env map; the given shadow map and
        background."""
        V, F, C = proxy
        return cls((V, F, C), env if env is not None else PriorEnv(), shadow,
                   FaceTable.of(V, F, C), backdrop=backdrop)

    @classmethod
    def of_scene(cls, sc: S.Scene, *, proxy=None, prompt: str = "",
                 purpose: str = "GGDS") -> "Conditioning":
        """The scene's conditioning: its env layer's light and ``proxy`` (default: every proxy
        chunk). ``prompt`` goes to text-conditioned priors; ``purpose`` names the consumer in
        errors."""
        stage = sc.open_stage(load=False)
        params, texture = scene_env(sc, purpose, stage)
        params.extras["prompt"] = prompt
        if proxy is None:
            path = sc.layer_path("proxy")
            if not path.is_file():
                raise InputError(f"{path}: {purpose} needs the scene's proxy layer (the prior's "
                                 "G-buffer)")
            proxy = proxy_arrays(path)
        light = scene_light(params, texture)
        far = read_far_field(stage)
        if far is not None and light.envmap is not None:
            far = far.over(lambda d: light.envmap(torch.from_numpy(d)).numpy())
        light.prior_env.far_field = far
        return cls.build(proxy, light)

    def packed(self, camera) -> PackedGBuffer:
        """The compact G-buffer of ``camera`` (what GGDS keeps per training view)."""
        V, F, _ = self.proxy
        return pack_view_gbuffer(camera, V, F, self.shadow)

    def finer(self, camera):
        """GBuffer.fine of ``camera``: k -> its G-buffer at k× the resolution."""
        V, F, _ = self.proxy
        return finer(camera, V, F, self.faces, self.shadow)

    def unpack(self, packed: PackedGBuffer, *, key: Hashable | None = None,
               fine: bool = True) -> GBuffer:
        return packed.unpack(self.faces, key=key, fine=self.finer(packed.camera) if fine else None)

    def gbuffer(self, camera, *, fine: bool = True, key: Hashable | None = None) -> GBuffer:
        """The proxy G-buffer of ``camera`` with the sun's visibility; with ``fine``, made again
        at k× the resolution on demand (a supersampling prior's pixels)."""
        return self.unpack(self.packed(camera), key=key, fine=fine)

    def background(self, camera):
        """(H, W, 3) display-scaled env radiance behind every pixel of ``camera`` (None
        without a scene light or backdrop)."""
        if self.light is not None:
            return self.light.background(camera)
        return None if self.backdrop is None else self.backdrop(camera)


def _recorded_params(sc: S.Scene, purpose: str) -> tuple[EnvParams, Path]:
    """(the environment `generate` recorded on the scene's env layer, that layer's path); one
    InputError line naming what is missing or unreadable."""
    env_layer = next((li for li in sc.layers() if li.name == "env"), None)
    if env_layer is None or not env_layer.exists or "params" not in env_layer.provenance:
        raise InputError(f"{sc.layer_path('env')}: {purpose} needs the scene's env layer with "
                         "its parameters (customLayerData lsd3d.params)")
    try:
        return EnvParams.from_dict(dict(env_layer.provenance["params"])), env_layer.path
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{env_layer.path}: unreadable env parameters ({e})") from None


def made_environment(sc: S.Scene) -> EnvParams | None:
    """The environment `generate` made for the scene (its env layer's recorded parameters),
    or None when there are none or they do not read (scene_env names what is wrong, for
    whoever needs them)."""
    try:
        return _recorded_params(sc, "")[0]
    except InputError:
        return None


def select_generated_environment(sc: S.Scene, stage) -> None:
    """In ``stage``'s session layer, select the environment variant `generate` made for the
    scene (when its env layer records its parameters and holds that variant): what eval
    renders against targets conditioned on that environment. Nothing otherwise."""
    params = made_environment(sc)
    if params is not None:
        _select_made_variant(stage, params)


def _select_made_variant(stage, params: EnvParams) -> None:
    """Select, in ``stage``'s session layer, the environment variant `generate` made (named
    by its parameters), when the env layer's selection is another one: a variant added with
    `lsd3d-usd env --usd` and selected changes what views draw, not the light the surfels
    were fitted under, which GGDS and eval condition on."""
    env = stage.GetPrimAtPath(S.ENV_PATH)
    vset = env.GetVariantSets().GetVariantSet(ENV_VARIANT_SET) if env else None
    name = params.variant_name()
    if vset and name in vset.GetVariantNames() and vset.GetVariantSelection() != name:
        with Usd.EditContext(stage, stage.GetSessionLayer()):
            vset.SetVariantSelection(name)


def scene_env(sc: S.Scene, purpose: str = "GGDS", stage=None) -> tuple[EnvParams, Path]:
    """(environment parameters of the scene's env layer, its EXR); one InputError line naming
    what is missing. ``stage``: the scene's stage if the caller has it open (its session layer
    then selects generate's environment variant, as the one this returns)."""
    params, layer_path = _recorded_params(sc, purpose)
    stage = stage or sc.open_stage(load=False)
    _select_made_variant(stage, params)
    texture = read_env_prim(stage).get("texture")
    if not texture or not Path(texture).is_file():
        raise InputError(f"{layer_path}: the env map texture {texture!r} is missing")
    return params, Path(texture)
