"""The scene as eval measures it: its surfels over the env map, without actors."""
from __future__ import annotations

from lsd3d_usd.views.frame import env_background, render_surfels


def render_view(field, env, camera) -> dict:
    """The scene's surfels + env background for one camera (no actors: eval measures the
    generated scene): numpy dict with rgb (linear), alpha, depth_median, depth_expected,
    normal_world (un-normalised)."""
    out = render_surfels(field, camera, background=env_background(env, camera), normal_space="world")
    return {"rgb": out.rgb.numpy(), "alpha": out.alpha.numpy(),
            "depth_median": out.depth_median.numpy(), "depth_expected": out.depth_expected.numpy(),
            "normal_world": out.normal.numpy()}
