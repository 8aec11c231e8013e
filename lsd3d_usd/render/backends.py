"""The renderer backends, by name: `rasterize(..., backend=NAME)`.

  numba  the fast CPU path (float32 tile kernels, hand-written backward): the default.
  torch  the plain torch implementation (render/reference.py) on any torch device, float64
         or float32, differentiable by autograd; small scenes only.

A backend is an object with a `name` and `forward(inputs, settings) -> BackendOutput`
(raster_types.Backend); `rasterize` validates the inputs before and composes the shared
outputs after it, so a new backend (e.g. gsplat on CUDA) is one class and one
`register_backend` call, and nothing that calls `rasterize` changes.
"""
from __future__ import annotations

from lsd3d_usd.errors import InputError
from lsd3d_usd.render.numba_backend import NumbaBackend
from lsd3d_usd.render.raster_types import Backend
from lsd3d_usd.render.reference import TorchBackend

BACKENDS: dict[str, Backend] = {}


def register_backend(backend: Backend, name: str | None = None) -> None:
    """Make ``backend`` available as ``rasterize(..., backend=name)`` (default: backend.name)."""
    name = name or backend.name
    if not callable(getattr(backend, "forward", None)):
        raise TypeError(f"backend {name!r} has no forward(inputs, settings) method")
    BACKENDS[name] = backend


def get_backend(backend: str | Backend) -> Backend:
    """The backend registered under a name, or ``backend`` itself when it is a backend object
    (e.g. TorchBackend(dtype=torch.float64))."""
    if not isinstance(backend, str):
        if not callable(getattr(backend, "forward", None)):
            raise InputError(f"rasterize: backend {backend!r} is neither a name nor a backend object")
        return backend
    try:
        return BACKENDS[backend]
    except KeyError:
        raise InputError(f"rasterize: unknown backend {backend!r}; known: "
                         f"{', '.join(sorted(BACKENDS))}") from None


register_backend(NumbaBackend())
register_backend(TorchBackend())
