"""The prior's own images as the baseline of the novel-view Fréchet distances.

`eval` compares the seen views' features with novel views displaced by 0.5-8 m and with fresh
on-lane views (the content change). A novel view 8 m off the lane looks at other things than
any lane view does (façades close up, the far side of a sidewalk, from up to 2 m higher), so
even a scene that reproduced its prior exactly would show a larger FD there than a mere change
of place gives. This module renders the prior's image at t = 1 of the same seen, novel and
held-out lane cameras, so each bin's ratio can be read against the ratio the prior itself
gives: the scene is as good as its prior can make it where the two ratios agree.

Cheap with the procedural prior (one G-buffer and one 2×2 supersampled procedural shade per
view, ~0.1 s at 320×180); a diffusion prior on the CPU takes minutes per view, so `auto` runs
it only for priors registered as cheap on a CPU (the procedural prior).
"""
from __future__ import annotations

import time

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.priors.registry import PRIORS
from lsd3d_usd.ggds.priors.scene import load_scene_prior, recorded_prior_is_cheap
from lsd3d_usd.views.deferred import DEFAULT_STEPS, Deferrer


def open_baseline(scene_path, mode: bool | None, n_heldout: int, display, run: str | None = None):
    """(PriorImages or None, why not or None) for the prior GGDS run ``run`` (default: the
    newest unmuted one) recorded. ``mode`` True forces it (an unusable scene prior is then
    an error), False turns it off, None (auto) runs it for a cheap prior when the scene has
    what it needs. ``n_heldout`` > 0 when forced is checked by eval's option checks."""
    if mode is False:
        return None, "turned off (--no-prior-baseline)"
    if n_heldout <= 0:
        return None, "no held-out lane views (--heldout 0)"
    try:
        if mode is None:
            cheap, name = recorded_prior_is_cheap(scene_path, run)
            if not cheap:
                return None, (f"the scene's prior {name!r} is slow on the CPU; ask for it with "
                              "--prior-baseline")
        return PriorImages(scene_path, display, run), None
    except InputError as e:
        if mode:
            raise
        return None, str(e)


class PriorImages:
    """Display images of the scene's prior at t = 1 for eval's cameras, by view set, made as
    GGDS's training targets are (the prior's pixel supersampling included)."""

    def __init__(self, scene_path, display, run: str | None = None):
        t = time.perf_counter()
        self.sp = load_scene_prior(scene_path, run=run, purpose="the prior baseline",
                                   override="--no-prior-baseline")
        self.deferrer = Deferrer(self.sp, 1.0, DEFAULT_STEPS)
        self.display = display
        self.images = {"seen": [], "novel": [], "heldout": [], "elevated": [], "off_path": []}
        self.seconds = time.perf_counter() - t

    def same_images(self, sp) -> bool:
        """Whether ``sp``'s held-out targets are this baseline's images: the same prior, and
        one whose image at t = 1 depends on the view alone (cheap on the CPU: procedural)."""
        return (sp is not None and sp.spec == self.sp.spec and sp.seed == self.sp.seed
                and PRIORS.get(sp.spec.split(":", 1)[0]).cheap_on_cpu)

    def add(self, kind: str, rgb: np.ndarray, camera, target: np.ndarray | None = None) -> None:
        """``rgb``: the scene's render of ``camera``. The procedural prior's image at t = 1
        does not depend on it; a diffusion prior's starts from it (then the baseline measures
        the scene too, not the views alone). ``target``: that image already made (the run's
        held-out target of the same view, when same_images), not made again."""
        t = time.perf_counter()
        y = target if target is not None else self.deferrer.images(rgb, camera, (1.0,), fine=True)[0]
        self.images[kind].append(self.display(y))
        self.seconds += time.perf_counter() - t


def baseline_fd(fd, embed, images: dict, bins, bins_arr, scene_fd: dict, sp,
                elevated=None, off_path=None) -> dict:
    """``images``: the prior's display images {"seen", "novel", "heldout", "elevated",
    "off_path"} (novel in the order of ``bins_arr``); ``scene_fd``: eval's fd_effnet_lite0 of
    the scene (with seen_vs_heldout_lane); ``sp``: the ScenePrior. ``fd(a, b)`` -> FDResult.
    ``elevated``: (group keys, group of each elevated view, the scene's features of those
    views), or None; ``off_path``: ({bin key: indices of its views}, the scene's features of
    the off-path views), or None. Returns the ``prior_baseline`` entry."""
    f_seen, f_novel = embed(images["seen"]), embed(images["novel"])
    content = fd(f_seen, embed(images["heldout"]))
    per_bin = {f"{b:g}": fd(f_seen, f_novel[bins_arr == b]) for b in bins}
    prior_ratio = {k: r.value / max(content.value, 1e-12) for k, r in per_bin.items()}
    extra = {}
    if elevated is not None and images["elevated"]:
        groups, groups_arr, f_scene = elevated
        idx = {g: np.flatnonzero(groups_arr == g) for g in groups}
        extra["elevated"] = _grouped(fd, f_seen, embed(images["elevated"]), f_scene, idx,
                                     content, "elevated")
    if off_path is not None and images["off_path"]:
        idx, f_scene = off_path
        extra["off_path"] = _grouped(fd, f_seen, embed(images["off_path"]), f_scene, idx,
                                     content, "off_path")
    scene_content = scene_fd["seen_vs_heldout_lane"]["value"]
    scene_ratio = {k: v["value"] / max(scene_content, 1e-12)
                   for k, v in scene_fd["seen_vs_novel"]["per_bin"].items()}
    return {
        "prior": sp.spec,
        "prior_source": sp.source,
        "views": "the prior's own image (t = 1) of the same seen, novel and held-out lane views",
        "seen_vs_novel": {"per_bin": {k: r.to_json() for k, r in per_bin.items()}},
        "seen_vs_heldout_lane": content.to_json(),
        "prior_novel_over_content": {k: round(v, 4) for k, v in prior_ratio.items()},
        "scene_novel_over_content": {k: round(v, 4) for k, v in scene_ratio.items()},
        "scene_over_prior": {k: round(scene_ratio[k] / max(prior_ratio[k], 1e-12), 4)
                             for k in prior_ratio},
        **extra,
    }


def _grouped(fd, f_seen, f_prior, f_scene, idx: dict, content, what: str) -> dict:
    """The prior's images of family ``what``'s groups of views (``idx``: key -> indices)
    against its seen images and over its content change, and the scene's images of those
    views against the prior's."""
    per = {k: fd(f_seen, f_prior[i]) for k, i in idx.items()}
    return {f"seen_vs_{what}": {k: r.to_json() for k, r in per.items()},
            f"prior_{what}_over_content": {k: round(r.value / max(content.value, 1e-12), 4)
                                           for k, r in per.items()},
            # the scene's images against the prior's own images of the same cameras
            "scene_vs_prior_images": {k: fd(f_scene[i], f_prior[i]).to_json()
                                      for k, i in idx.items()}}
