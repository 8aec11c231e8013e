"""lsd3d_usd.proxy: layout -> coarse proxy meshes, chunk by chunk; proxy from point clouds.

See docs/proxy.md. Main entry points::

    build_proxy(layout, chunks=None) -> {(i, j): [MeshPart]}
    write_proxy(parts, path, hashes=None, layout_hash="")
    build_proxy_layer(layout, path, chunks=None)   # incremental: only changed chunks
    read_proxy(path, chunks=None) -> {(i, j): {class: ClassMesh}}
"""
from .chunks import ProxyParams, build_proxy
from .mesh import ClassMesh, MeshPart, check_part, merge_parts
from .usdio import build_proxy_layer, read_proxy, write_proxy

__all__ = ["ProxyParams", "build_proxy", "ClassMesh", "MeshPart", "check_part", "merge_parts",
           "build_proxy_layer", "read_proxy", "write_proxy"]
