"""The procedural prior: a deterministic, G-buffer-conditioned image prior (no learned model).

It renders the proxy G-buffer of a view with world-space procedural materials per semantic
class (ggds/priors/materials.py), lit by the environment: sun (with the caller's per-pixel
visibility, i.e. shadows ray-cast against the proxy), sky irradiance from SH, a Fresnel
reflection of the sky on glossy / wet surfaces, a sun highlight, and fog by distance.
Background pixels take the env sky lookup (or an SH sky gradient). Materials depend only on
world position, normal and class, so the same world point gets the same albedo from any
view: the prior is 3D-consistent by construction.

Noise level t sets how much of the target is re-synthesised versus kept from the render x:
    x_hat = (1 - w(t)) * GF_t(x) + w(t) * P,   w(t) = smoothstep(t_keep, t_full, t)
where P is the procedural render and GF_t a self-guided filter of x with radius
r(t) = max(1, round(gf_radius * t)) pixels and eps(t) = gf_eps0 + gf_eps1 * t (variance units):
at small t the target is x with its pixel noise smoothed (edges kept), at t >= t_full it is
the procedural render, in between a cross-fade. Defaults: t_keep 0.05, t_full 0.6.
"""
from __future__ import annotations

import math

import torch

from lsd3d_usd.ggds.priors import materials as mat
from lsd3d_usd.ggds.priors.lighting_kernel import light
from lsd3d_usd.ggds.priors.surface_kernel import surface_properties
from lsd3d_usd.ggds.filters import guided_filter
from lsd3d_usd.conditioning.gbuffer import GBuffer
from lsd3d_usd.ggds.priors.base import Prior, check_image, check_t
from lsd3d_usd.conditioning.light import PriorEnv
from lsd3d_usd.shmath import sh_basis9


def _smoothstep(e0, e1, x):
    x = min(1.0, max(0.0, (x - e0) / (e1 - e0)))
    return x * x * (3 - 2 * x)


class ProceduralPrior(Prior):
    """Deterministic procedural image prior (see module doc). `seed` selects the material
    variation of the scene; it is fixed per prior (not per call) so every view agrees."""

    name = "procedural"
    # Its targets are exact per pixel: the perceptual term only added chroma speckle
    # (README sample, 150 steps: 23.88 dB with it, 24.43 dB without).
    default_weights = {"perceptual": 0.0}

    def __init__(self, seed: int = 0, *, floor_height: float = 3.2, ground_z: float = 0.0,
                 window_spacing: float = 2.6, t_keep: float = 0.05, t_full: float = 0.6,
                 gf_radius: int = 8, gf_eps0: float = 1e-4, gf_eps1: float = 4e-3,
                 supersample: int = 1):
        if not 0 <= t_keep < t_full <= 1:
            raise ValueError(f"need 0 <= t_keep < t_full <= 1, got {t_keep}, {t_full}")
        if not 1 <= int(supersample) <= 8:
            raise ValueError(f"supersample must be 1..8 samples per pixel side, got {supersample}")
        self.supersample = int(supersample)
        self.seed = int(seed)
        self.floor_height = float(floor_height)
        self.ground_z = float(ground_z)
        self.window_spacing = float(window_spacing)
        self.t_keep, self.t_full = float(t_keep), float(t_full)
        self.gf_radius, self.gf_eps0, self.gf_eps1 = int(gf_radius), float(gf_eps0), float(gf_eps1)

    def describe(self) -> dict:
        return {"prior": self.name, "seed": self.seed, "floor_height": self.floor_height,
                "ground_z": self.ground_z, "window_spacing": self.window_spacing,
                "t_keep": self.t_keep, "t_full": self.t_full, "gf_radius": self.gf_radius,
                "gf_eps0": self.gf_eps0, "gf_eps1": self.gf_eps1, "supersample": self.supersample}

    def settings(self, env: PriorEnv) -> mat.MaterialSettings:
        return mat.MaterialSettings(seed=self.seed, floor_height=self.floor_height, ground_z=self.ground_z,
                                    window_spacing=self.window_spacing, wetness=float(env.wetness),
                                    snow_cover=float(env.snow_cover), vegetation=env.vegetation)

    # -- schedule ---------------------------------------------------------------------------
    def blend_weight(self, t: float) -> float:
        """Fraction of the procedural render in the target at level t."""
        return _smoothstep(self.t_keep, self.t_full, t)

    def filter_params(self, t: float) -> tuple[int, float]:
        return max(1, round(self.gf_radius * t)), self.gf_eps0 + self.gf_eps1 * t

    # -- the procedural render -----------------------------------------------------------
    def surface(self, gb: GBuffer, env: PriorEnv):
        """Per-pixel albedo (H,W,3), spec (H,W), rough (H,W), mirror (H,W), surface mask (H,W)."""
        H, W = gb.shape
        flat, valid = self._surface_flat(gb, env)
        flat = flat.reshape(H, W, 6).to(gb.depth.device)
        albedo, spec, rough, mirror = flat[..., :3], flat[..., 3], flat[..., 4], flat[..., 5]
        return albedo, spec, rough, mirror, valid.reshape(H, W).to(gb.depth.device)

    def _surface_flat(self, gb: GBuffer, env: PriorEnv):
        """(P, 6) albedo, spec, rough, mirror and the (P,) covered mask of the G-buffer's
        pixels, on the CPU: every covered pixel's material and weather in one pass
        (surface_kernel; the torch reference is materials.surface_reference)."""
        pos = gb.world_pos.detach().reshape(-1, 3).to(torch.float64).cpu()
        valid = (gb.valid.reshape(-1).cpu() & torch.isfinite(pos).all(-1))
        nrm = torch.nn.functional.normalize(gb.normal.detach().reshape(-1, 3).float().cpu(), dim=-1)
        return surface_properties(pos, nrm, gb.semantic.reshape(-1), self.settings(env), valid), valid

    @torch.no_grad()
    def ground_albedo(self, env: PriorEnv):
        """Mean albedo of the terrain material (weather applied) over a 512 m square sampled
        every 2 m: what the ground beyond the scene continues."""
        g = torch.arange(-256.0, 256.0, 2.0, dtype=torch.float64)
        x, y = torch.meshgrid(g, g, indexing="ij")
        p = torch.stack([x.reshape(-1), y.reshape(-1), torch.full((x.numel(),), self.ground_z,
                                                                 dtype=torch.float64)], -1)
        n = torch.zeros(len(p), 3)
        n[:, 2] = 1.0
        cls = torch.full((len(p),), mat.CLASS_ID["terrain"])
        return surface_properties(p, n, cls, self.settings(env))[:, :3].mean(0).double().numpy()

    def background(self, dirs: torch.Tensor, origin, env: PriorEnv) -> torch.Tensor:
        """What is seen behind the proxy along ``dirs`` (N, 3) from ``origin``: the sky, and
        the ground beyond the scene where the env has one (env units, before exposure)."""
        sky = self.sky(dirs, env)
        if env.far_field is None or len(dirs) == 0:
            return sky
        out = env.far_field.apply(sky.cpu().numpy(), torch.as_tensor(origin).cpu().numpy(),
                                  dirs.cpu().numpy())
        return torch.from_numpy(out).to(sky.device)

    def sky(self, dirs: torch.Tensor, env: PriorEnv) -> torch.Tensor:
        """Background radiance (..., 3) in world directions (env units, before exposure)."""
        if env.sky_lookup is not None:
            return env.sky_lookup(dirs.float()).float()
        # no env map: the radiance a uniform-per-direction sky with this irradiance would have,
        # E(d) / pi, brightened towards the horizon (haze)
        base = (sh_basis9(dirs.float()) @ env.sh_irradiance.to(dirs.device)).clamp_min(0) / math.pi
        haze = torch.exp(-4.0 * dirs[..., 2:3].abs().float())
        return base * (1.0 + 0.6 * haze)

    def _diffuse(self, albedo, n, vis, env, dev):
        sdir = env.sun_direction.to(dev)
        e_sun = env.sun_irradiance.to(dev) * _smoothstep(-0.02, 0.02, float(sdir[2]))
        ndl = (n @ sdir).clamp_min(0) * vis
        e_sky = (sh_basis9(n) @ env.sh_irradiance.to(dev)).clamp_min(0)
        return albedo / math.pi * (ndl[..., None] * e_sun + e_sky), ndl, e_sun, sdir

    @torch.no_grad()
    def shade_at(self, points, normals, semantic, env: PriorEnv, view_dirs=None,
                 sun_visibility=None) -> torch.Tensor:
        """Radiance of the materials at world points (N,3) seen along `view_dirs` (N,3) (default:
        head-on), display scaled, without fog: the prior evaluated in 3D, which lets GGDS start
        each surfel at the colour views will ask of it (the prior is world-space by design)."""
        pts = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 1, 3)
        nrm = torch.nn.functional.normalize(torch.as_tensor(normals, dtype=torch.float32).reshape(-1, 1, 3), dim=-1)
        n = pts.shape[0]
        v = -nrm if view_dirs is None else torch.nn.functional.normalize(
            torch.as_tensor(view_dirs, dtype=torch.float32).reshape(-1, 1, 3), dim=-1)
        gb = GBuffer(depth=torch.ones(n, 1), normal=nrm, semantic=torch.as_tensor(semantic).reshape(n, 1).long(),
                     world_pos=pts.float(), view_dirs=v, camera_position=torch.zeros(3),
                     sun_visibility=None if sun_visibility is None
                     else torch.as_tensor(sun_visibility, dtype=torch.float32).reshape(n, 1))
        fog = env.fog_density
        env.fog_density = 0.0  # fog belongs to the view, not to the surface
        try:
            return self.render(gb, env).reshape(n, 3)
        finally:
            env.fog_density = fog

    def render(self, gb: GBuffer, env: PriorEnv) -> torch.Tensor:
        """The procedural image P (H, W, 3) in display range (exposure applied, clamped to [0, 1]):
        the surface lit per pixel in one pass (lighting_kernel; `render_reference` is the
        same in torch), the sky seen in reflections, fog, the background."""
        gb.validate()
        dev = gb.depth.device
        H, W = gb.shape
        surf, valid = self._surface_flat(gb, env)
        sdir = env.sun_direction.detach().cpu()
        e_sun = torch.broadcast_to(env.sun_irradiance.detach().cpu(), (3,)) * _smoothstep(
            -0.02, 0.02, float(sdir[2]))
        vis = gb.sun_visibility if gb.sun_visibility is not None else torch.ones_like(gb.depth)
        view = gb.view_dirs.detach().reshape(-1, 3).float().cpu()
        col, refl = light(surf.numpy(), valid.numpy(), view.numpy(),
                          gb.normal.detach().reshape(-1, 3).float().cpu().numpy(),
                          vis.detach().reshape(-1).float().cpu().numpy(), sdir.numpy(),
                          e_sun.numpy(), env.sh_irradiance.detach().cpu().numpy())
        col, refl = torch.from_numpy(col), torch.from_numpy(refl)
        # the sky is looked up where it is seen: reflected on surfaces, straight on background
        at = valid.nonzero()[:, 0]
        if len(at):
            col[at] += self.sky(refl[at, :3], env).cpu() * refl[at, 3:]
        if env.fog_density > 0:
            dist = (gb.world_pos.reshape(-1, 3).to(torch.float64).cpu()
                    - gb.camera_position.to(torch.float64).cpu()).norm(dim=-1).float()
            T = torch.exp(-env.fog_density * torch.nan_to_num(dist, nan=0.0, posinf=1e9))[..., None]
            col = col * T + env.fog_color.cpu() * (1 - T)
        bg = ~valid
        if bool(bg.any()):
            col[bg] = self.background(torch.nn.functional.normalize(view[bg], dim=-1),
                                      gb.camera_position, env).cpu()
        return (col * env.exposure).clamp(0, 1).reshape(H, W, 3).to(dev)

    def render_reference(self, gb: GBuffer, env: PriorEnv) -> torch.Tensor:
        """`render`'s lighting in whole-image torch operations: the reference of its lighting
        kernel (the surface comes from the same `surface`, itself held to
        materials.surface_reference)."""
        gb.validate()
        dev = gb.depth.device
        albedo, spec, rough, mirror, valid = self.surface(gb, env)
        V = torch.nn.functional.normalize(gb.view_dirs.float(), dim=-1)
        n = torch.nn.functional.normalize(gb.normal.float(), dim=-1)
        n = torch.where(((n * V).sum(-1, keepdim=True) > 0), -n, n)     # face the camera
        vis = gb.sun_visibility.float() if gb.sun_visibility is not None else torch.ones_like(gb.depth)
        diffuse, ndl, e_sun, sdir = self._diffuse(albedo, n, vis, env, dev)
        # specular: Schlick Fresnel, sky reflection (glossy / wet) and a normalised Blinn-Phong sun lobe
        cos_v = (-(V * n).sum(-1)).clamp(0, 1)
        F = spec + (1 - spec) * (1 - cos_v) ** 5
        r = V - 2 * (V * n).sum(-1, keepdim=True) * n
        refl_w = F * torch.maximum(mirror, (1 - rough) ** 2)
        # the sky is looked up where it is seen: reflected on surfaces, straight on background
        refl = torch.zeros(valid.shape + (3,), device=dev)
        refl[valid] = self.sky(r[valid], env) * refl_w[valid][:, None]
        h = torch.nn.functional.normalize(sdir - V, dim=-1)
        alpha = (2.0 / rough ** 2 - 2.0).clamp(1.0, 2000.0)
        lobe = (alpha + 8) / (8 * math.pi) * (n * h).sum(-1).clamp_min(0) ** alpha
        sun_spec = (F * lobe * ndl)[..., None] * e_sun
        col = diffuse + refl + sun_spec
        if env.fog_density > 0:
            dist = (gb.world_pos.to(torch.float64) - gb.camera_position.to(torch.float64)).norm(dim=-1).float()
            T = torch.exp(-env.fog_density * torch.nan_to_num(dist, nan=0.0, posinf=1e9))[..., None]
            col = col * T + env.fog_color.to(dev) * (1 - T)
        col[~valid] = self.background(V[~valid], gb.camera_position, env)
        return (col * env.exposure).clamp(0, 1).float()

    def render_view(self, gb: GBuffer, env: PriorEnv) -> torch.Tensor:
        """render() of a view; with ``supersample`` S > 1 (and a G-buffer that can be made
        finer) the mean of S×S samples per pixel, as a camera integrates over its pixels:
        edges, shadow boundaries and texture finer than a pixel (paving joints, lane paint)
        no longer alias, and the target is what surfels seen from there can reproduce."""
        S = self.supersample
        if S <= 1 or gb.fine is None:
            return self.render(gb, env)
        H, W = gb.shape
        return self.render(gb.fine(S), env).reshape(H, S, W, S, 3).mean(dim=(1, 3))

    # -- the prior ---------------------------------------------------------------------------
    @torch.no_grad()
    def target(self, x: torch.Tensor, gbuffer: GBuffer, env: PriorEnv, t: float,
               n_steps: int = 5, seed: int | None = None) -> torch.Tensor:
        """x_hat = (1 - w(t)) GF_t(x) + w(t) P (module doc). Deterministic; n_steps and seed are
        accepted for interface compatibility and do not change the result."""
        check_image(x)
        t = check_t(t)
        H, W = x.shape[:2]
        gbuffer.validate(H, W)
        x = x.detach().float()
        w = self.blend_weight(t)
        r, eps = self.filter_params(t)
        kept = guided_filter(x, r, eps) if w < 1 else torch.zeros_like(x)
        if w <= 0:
            return kept
        P = self.cached_render(gbuffer, env).to(x.device)
        return (1 - w) * kept + w * P

    def cached_render(self, gbuffer: GBuffer, env: PriorEnv) -> torch.Tensor:
        """render(), remembered per view: P depends only on the view. The view is the
        G-buffer's ``key`` when it has one (GGDS's training views), else the G-buffer object."""
        cache = self.__dict__.setdefault("_render_cache", {})
        keyed = gbuffer.key is not None
        key = (("key", gbuffer.key) if keyed else ("id", id(gbuffer)), id(env))
        hit = cache.get(key)
        if hit is not None and (keyed or hit[0] is gbuffer) and hit[1] is env:
            return hit[2]
        P = self.render_view(gbuffer, env)
        if len(cache) >= 256:  # bounded: drop the oldest entry
            cache.pop(next(iter(cache)))
        cache[key] = (None if keyed else gbuffer, env, P)
        return P

    def cached_views(self) -> list:
        """The view keys whose render is cached: a training view's G-buffer key, or
        ("id", object id) of a G-buffer without one."""
        return [k[0][1] if k[0][0] == "key" else k[0]
                for k in self.__dict__.get("_render_cache", {})]

    def forget(self, keys) -> None:
        cache = self.__dict__.get("_render_cache", {})
        gone = {("key", k) for k in keys}
        for key in [k for k in cache if k[0] in gone]:
            del cache[key]
