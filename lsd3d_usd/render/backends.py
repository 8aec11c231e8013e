"""The renderer backends, by name: `rasterize(..., backend=NAME)`, one registry
(lsd3d_usd.registry) with the entry-point group ``lsd3d_usd.render_backends``.

  numba  the fast CPU path (float32 tile kernels, hand-written backward): the default.
  torch  the plain torch implementation (render/reference.py) on any torch device, float64
         or float32, differentiable by autograd; small scenes only.

A backend is an object with a `name` and `forward(inputs, settings) -> BackendOutput`
(raster_types.Backend); `rasterize` validates the inputs before and composes the shared
outputs after it, so a new backend (e.g. gsplat on CUDA) is one class and one registration,
and nothing that calls `rasterize` changes. ``ggds.backend`` chooses the backend of a GGDS
run; register it by ``"module:ATTRIBUTE"`` target (or an entry point) so GGDS's region
workers resolve it too.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from lsd3d_usd.errors import InputError
from lsd3d_usd.registry import Registry

if TYPE_CHECKING:   # annotations only: listing the backends needs no torch
    from lsd3d_usd.render.raster_types import Backend

BACKENDS = Registry("lsd3d_usd.render_backends", "renderer backend", {
    "numba": "lsd3d_usd.render.numba_backend:NUMBA",
    "torch": "lsd3d_usd.render.reference:TORCH",
})


def register_backend(backend: Backend | str, name: str | None = None) -> None:
    """Make ``backend`` (an object, or a ``"module:ATTRIBUTE"`` target naming one) available as
    ``rasterize(..., backend=name)`` (default: the object's ``name``)."""
    if isinstance(backend, str):
        if not name:
            raise TypeError("register_backend of a target needs a name")
        BACKENDS.register(name, backend)
        return
    name = name or backend.name
    if not callable(getattr(backend, "forward", None)):
        raise TypeError(f"backend {name!r} has no forward(inputs, settings) method")
    BACKENDS.register(name, backend)


def check_backend_name(name: str, where: str = "backend") -> str:
    """A registered backend's name; one InputError line otherwise."""
    if name not in BACKENDS.names():
        raise InputError(f"{where} {name!r}: unknown renderer backend; known: "
                         f"{', '.join(BACKENDS.names())}")
    return name


def get_backend(backend: str | Backend) -> Backend:
    """The backend registered under a name, or ``backend`` itself when it is a backend object
    (e.g. TorchBackend(dtype=torch.float64))."""
    if not isinstance(backend, str):
        if not callable(getattr(backend, "forward", None)):
            raise InputError(f"rasterize: backend {backend!r} is neither a name nor a backend object")
        return backend
    if backend not in BACKENDS.names():
        raise InputError(f"rasterize: unknown backend {backend!r}; known: "
                         f"{', '.join(BACKENDS.names())}")
    return BACKENDS.get(backend)
