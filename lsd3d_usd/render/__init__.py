"""lsd3d_usd.render: the differentiable 2DGS rasteriser (arrays in, images out).

    rasterize      the entry point: rasterize(...) -> RasterResult
    raster_types   RasterSettings, RasterResult, RasterStats; the backend contract
    checks         input validation, one place for every backend
    backends       the registry: "numba" (numba_backend.py), "torch" (reference.py)
    kernels, kernels_prep, projection, sh   the numba kernels and the shared maths
    camera         pinhole cameras, OpenCV convention, UsdGeom.Camera IO
    gbuffer        triangle-mesh G-buffers (depth, normal, class, position)
    benchmark      `lsd3d-usd bench render`

Scenes (stages) become pictures in lsd3d_usd.views.
"""
