"""The typed interface of `rasterize`: settings in, result out, and the contract a backend
implements (validated inputs in, raw accumulations out).

`rasterize` (rasterize.py) checks the inputs once for every backend, calls the backend's
`forward`, then does what is the same for all of them: the background behind the final
transmittance, expected depth, world-space normals and the semantic lookup.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import torch


@dataclass(frozen=True)
class RasterSettings:
    """How to rasterise (the same for every backend).

    near, far: camera depth range (metres); surfels whose centre lies outside are culled.
    sh_degree: SH degree to evaluate (None: all the coefficients given).
    tile: tile size in pixels of the numba backend, a multiple of 8 (its lane block).
    alpha_min: a surfel contributes to a pixel only where its alpha is >= this.
    t_min: compositing stops once the transmittance falls below this.
    alpha_max: alpha is clamped to this (keeps the transmittance invertible for the backward).
    bound_sigma: None = exact opacity-aware screen bounds (no pixel with alpha >= alpha_min is
        missed); a number = fixed k-sigma bounds (faster, lossy). The torch backend evaluates
        every surfel at every pixel, so it is always exact and ignores this.
    normal_space: "camera" (OpenCV camera axes) or "world" for the normal image.
    distortion: also compute the 2DGS depth-distortion image (and its gradients).
    """
    near: float = 0.05
    far: float = 1e4
    sh_degree: int | None = None
    tile: int = 16
    alpha_min: float = 1.0 / 255.0
    t_min: float = 1e-4
    alpha_max: float = 0.99
    bound_sigma: float | None = None
    normal_space: str = "camera"
    distortion: bool = False

    @classmethod
    def for_camera(cls, camera, **overrides) -> "RasterSettings":
        """Settings with the depth range of a `render.camera.Camera` (its near/far), other
        fields at their defaults unless given."""
        return cls(near=float(camera.near), far=float(camera.far), **overrides)


@dataclass
class RasterStats:
    """What a render cost.

    n_visible: surfels projected as visible (len(visible_index)).
    n_pairs: (tile, surfel) pairs the numba kernels composited; 0 for the torch backend.
    evals: Gaussian evaluations (surfel x pixel) done by the backend.
    evals_rect: those inside the surfels' exact screen rectangles (the useful part); the
        torch backend evaluates every pixel, so there evals_rect = evals.
    timings: seconds per phase, backend-specific keys (numba: project_s, bin_s, raster_s;
        every backend: backend_s and total_s). After a backward pass the numba backend adds
        backward_kernel_s and backward_s.
    """
    n_visible: int
    n_pairs: int
    evals: int
    evals_rect: int
    timings: dict = field(default_factory=dict)


@dataclass
class RasterResult:
    """The images of one render (float tensors on the backend's device; (H, W) or (H, W, 3)).

    rgb: colour, background included. alpha: 1 - final transmittance.
    depth_expected: sum(w z) / alpha (camera z, metres), 0 where alpha < 1e-6.
    depth_acc: sum(w z), un-normalised (as 2DGS). depth_median: depth where the
    transmittance crosses 0.5 (last contributor entered with T > 0.5), 0 where none.
    normal: sum(w n), un-normalised, each surfel normal oriented towards the camera, in the
    axes of settings.normal_space.
    semantic: (H, W) int64 id of the largest-weight contributor, -1 where none; None without
    semantic_ids. distortion: the 2DGS depth distortion, None unless settings.distortion.
    visible_index: int64 indices of the surfels the backend projected as visible: only these
    can receive non-zero gradients (GGDS's selective Adam updates these rows).
    """
    rgb: torch.Tensor
    alpha: torch.Tensor
    depth_expected: torch.Tensor
    depth_acc: torch.Tensor
    depth_median: torch.Tensor
    normal: torch.Tensor
    semantic: torch.Tensor | None
    distortion: torch.Tensor | None
    visible_index: torch.Tensor
    stats: RasterStats

    IMAGES = ("rgb", "alpha", "depth_expected", "depth_acc", "depth_median", "normal",
              "semantic", "distortion")

    def numpy(self) -> dict:
        """The images as detached CPU numpy arrays (None-valued ones left out)."""
        return {k: getattr(self, k).detach().cpu().numpy() for k in self.IMAGES
                if getattr(self, k) is not None}


@dataclass
class RasterInputs:
    """Validated inputs handed to a backend. The five surfel tensors keep the dtype and device
    they came with (all on one device); viewmat and K are float64 CPU tensors."""
    means: torch.Tensor          # (N, 3)
    quats: torch.Tensor          # (N, 4) xyzw, norm >= checks.QUAT_MIN_NORM
    scales: torch.Tensor         # (N, 2) >= 0
    opacities: torch.Tensor      # (N,)
    sh: torch.Tensor             # (N, K, 3), |value| <= checks.SH_MAX
    viewmat: torch.Tensor        # (4, 4) world -> camera, OpenCV axes
    K: torch.Tensor              # (3, 3) pinhole, last row (0, 0, 1)
    width: int
    height: int
    sh_degree: int               # resolved: <= the degree of sh
    want_argmax: bool            # the caller asked for semantics

    @property
    def n(self) -> int:
        return int(self.means.shape[0])

    @property
    def device(self) -> torch.device:
        return self.means.device


@dataclass
class BackendOutput:
    """What a backend returns: accumulations before the background, differentiable with
    respect to the five surfel tensors of RasterInputs.

    rgb (H, W, 3) sum(w c); alpha (H, W); depth_acc (H, W) sum(w z); depth_median (H, W);
    normal (H, W, 3) sum(w n) in OpenCV camera axes; distortion (H, W) or None (only when
    settings.distortion); argmax (H, W) int64 index into the N input surfels of the
    largest-weight contributor, -1 where none (only when inputs.want_argmax, else None);
    visible_index (M,) int64 ascending, on any device; stats.
    """
    rgb: torch.Tensor
    alpha: torch.Tensor
    depth_acc: torch.Tensor
    depth_median: torch.Tensor
    normal: torch.Tensor
    distortion: torch.Tensor | None
    argmax: torch.Tensor | None
    visible_index: torch.Tensor
    stats: RasterStats


class Backend(Protocol):
    """A rasteriser implementation: one `forward`. Backward passes come from autograd (a
    custom autograd.Function or plain torch ops), so callers just call .backward()."""
    name: str

    def forward(self, inputs: RasterInputs, settings: RasterSettings) -> BackendOutput: ...
