"""Where a layout lies on the Earth: its geoReference, and moving layouts between frames.

A layout's frame is a projected coordinate system (a PROJ string, WKT or ``EPSG:n`` that
pyproj reads) plus an offset: a layout point p (x east, y north, metres) lies at

    projected = R(hdg) p + (x0, y0, z0)

in that system (``offset`` = (x0, y0, z0, hdg); the OpenDRIVE header ``<offset>``: the
dataset is translated, then rotated by hdg about the new origin). Where it comes from:

- OpenDRIVE: the header ``<geoReference>`` and ``<offset>``;
- Lanelet2 and OpenStreetMap: the importer's origin. Both are projected with lanelet2's
  ``LocalCartesianProjector`` (east-north-up around the origin), which is the ellipsoidal
  orthographic projection about that origin (EPSG method 9840): the layout's frame is
  ``+proj=ortho +lat_0=LAT +lon_0=LON +ellps=WGS84`` (agreement measured below 1e-8 m within
  5 km of the origin).

It is kept in the layout's ``metadata["geoReference"]`` (``proj``, ``offset``, ``from``), so
it survives the USD layer and ``layout export`` writes it back. ``reproject`` moves a layout
into another frame through longitude / latitude (pyproj, exact, per point); ``frame_offset``
says how two frames sit relative to each other (the rigid motion that best maps one onto the
other over an area, and how far the exact reprojection departs from it).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import model as m

KEY = "geoReference"


@dataclass(frozen=True)
class GeoReference:
    """A projected CRS (anything ``pyproj.CRS.from_user_input`` reads) and the offset of the
    layout's frame in it (x0, y0, z0 in metres, hdg in radians)."""
    proj: str
    offset: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    source: str = ""

    def __post_init__(self):
        off = tuple(float(v) for v in self.offset)
        if len(off) != 4 or not all(np.isfinite(off)):
            raise ValueError(f"geoReference offset {self.offset!r}: expected 4 finite numbers")
        object.__setattr__(self, "offset", off)

    # -- conversions
    def crs(self):
        from pyproj import CRS
        from pyproj.exceptions import CRSError
        try:
            crs = CRS.from_user_input(self.proj)
        except CRSError as e:
            raise InputError(f"geoReference {self.proj!r} is not a coordinate system pyproj "
                             f"reads: {e}") from None
        if not crs.is_projected:
            raise InputError(f"geoReference {self.proj!r} is not a projected coordinate system "
                             "(a layout is in metres)")
        return crs

    def _transformer(self, inverse: bool):
        from pyproj import Transformer
        crs = self.crs()
        return (Transformer.from_crs(crs, "EPSG:4326", always_xy=True) if inverse
                else Transformer.from_crs("EPSG:4326", crs, always_xy=True))

    def to_lonlat(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Longitude, latitude (degrees, WGS84) of layout points (N, 2+)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, np.shape(xy)[-1])[:, :2]
        x0, y0, _, h = self.offset
        c, s = np.cos(h), np.sin(h)
        px = x0 + c * xy[:, 0] - s * xy[:, 1]
        py = y0 + s * xy[:, 0] + c * xy[:, 1]
        lon, lat = self._transformer(True).transform(px, py)
        return np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64)

    def from_lonlat(self, lon, lat) -> np.ndarray:
        """Layout points (N, 2) of longitudes, latitudes."""
        px, py = self._transformer(False).transform(np.asarray(lon, dtype=np.float64),
                                                    np.asarray(lat, dtype=np.float64))
        x0, y0, _, h = self.offset
        dx, dy = np.asarray(px) - x0, np.asarray(py) - y0
        c, s = np.cos(h), np.sin(h)
        return np.column_stack([c * dx + s * dy, -s * dx + c * dy])

    # -- storage
    def to_json(self) -> dict:
        return {"proj": self.proj, "offset": list(self.offset), "from": self.source}

    @classmethod
    def from_json(cls, d: dict) -> "GeoReference":
        if not isinstance(d, dict) or not isinstance(d.get("proj"), str):
            raise InputError(f"metadata {KEY} {d!r}: expected {{'proj': str, 'offset': [4 numbers]}}")
        try:
            return cls(d["proj"], tuple(d.get("offset", (0, 0, 0, 0))), str(d.get("from", "")))
        except (TypeError, ValueError) as e:
            raise InputError(f"metadata {KEY}: {e}") from None


def local_tangent(lat: float, lon: float, source: str = "") -> GeoReference:
    """The frame of a Lanelet2 / OSM import about (lat, lon): east-north-up metres (the
    ellipsoidal orthographic projection, which is what lanelet2's LocalCartesianProjector
    computes on the ellipsoid)."""
    return GeoReference(f"+proj=ortho +lat_0={float(lat)!r} +lon_0={float(lon)!r} +x_0=0 "
                        "+y_0=0 +ellps=WGS84 +units=m +no_defs", source=source)


def of_layout(layout: m.Layout) -> GeoReference | None:
    """The layout's geoReference (``metadata["geoReference"]``), or None."""
    d = layout.metadata.get(KEY) if isinstance(layout.metadata, dict) else None
    return None if d is None else GeoReference.from_json(d)


def attach(layout: m.Layout, ref: GeoReference) -> None:
    layout.metadata[KEY] = ref.to_json()


def from_opendrive_header(text: str | None, offset: dict | None, where: str,
                          warn) -> GeoReference | None:
    """The geoReference of an OpenDRIVE header (``text``: the geoReference element's text,
    ``offset``: the <offset> attributes). A text pyproj cannot read is ``warn``\\ ed once and
    left as text (None)."""
    if not text or not text.strip():
        return None
    off = (0.0, 0.0, 0.0, 0.0)
    if offset:
        try:
            off = tuple(float(offset.get(k, 0.0)) for k in ("x", "y", "z", "hdg"))
            GeoReference("EPSG:3857", off)     # checks the numbers
        except (TypeError, ValueError):
            warn(f"{where}: header <offset> {offset!r} is not four numbers; ignored")
            off = (0.0, 0.0, 0.0, 0.0)
    ref = GeoReference(text.strip(), off, "OpenDRIVE header")
    try:
        ref.crs()
    except InputError as e:
        warn(f"{where}: {e}; kept as text only")
        return None
    return ref


# ================================================================ frames

def _map_xy(fn, pts: np.ndarray) -> np.ndarray:
    out = np.array(pts, dtype=np.float64, copy=True)
    out[..., :2] = fn(out.reshape(-1, out.shape[-1])[:, :2]).reshape(out[..., :2].shape)
    return out


def _heading_at(fn, p: np.ndarray, heading: float, step: float = 1.0) -> float:
    d = np.array([[p[0], p[1]], [p[0] + step * np.cos(heading), p[1] + step * np.sin(heading)]])
    q = fn(d)
    return float(np.arctan2(q[1, 1] - q[0, 1], q[1, 0] - q[0, 0]))


def reproject(layout: m.Layout, target: GeoReference) -> m.Layout:
    """A copy of ``layout`` in ``target``'s frame: every coordinate through longitude /
    latitude (pyproj), headings turned by the local rotation between the frames; lengths
    and heights are kept. The copy's geoReference is ``target``. InputError when the layout
    has no geoReference."""
    src = of_layout(layout)
    if src is None:
        raise InputError("the layout has no geoReference (OpenDRIVE header geoReference, or a "
                         "Lanelet2 / OSM import) to move it into another frame with")

    def fn(xy):
        return target.from_lonlat(*src.to_lonlat(xy))

    out = m.Layout(extent=None, chunk_size=layout.chunk_size,
                   metadata=dict(layout.metadata))
    for f in layout.features():
        changes = {}
        for fl in dataclasses.fields(f):
            v = getattr(f, fl.name)
            if fl.name in ("points", "polygon", "footprint") and isinstance(v, np.ndarray):
                changes[fl.name] = _map_xy(fn, v)
            elif fl.name in ("position", "center") and isinstance(v, np.ndarray):
                changes[fl.name] = _map_xy(fn, v[None])[0]
        for name in ("heading",):
            if hasattr(f, name):
                p = getattr(f, "position", getattr(f, "center", None))
                changes[name] = _heading_at(fn, p, getattr(f, name))
        out.add(dataclasses.replace(f, **changes))
    if layout.extent is not None:
        (x0, y0), (x1, y1) = layout.extent
        c = fn(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))
        out.extent = ((float(c[:, 0].min()), float(c[:, 1].min())),
                      (float(c[:, 0].max()), float(c[:, 1].max())))
    out.metadata = dict(layout.metadata)
    out.metadata[KEY] = target.to_json()
    out.metadata.setdefault("source", {})
    out.metadata["reprojectedFrom"] = src.to_json()
    m.check_size(out, "reprojected layout")
    out.reindex()
    return out


@dataclass
class FrameOffset:
    """How frame B sits in frame A near ``at`` (A coordinates): a B point p lies at
    R(rotation) p + (dx, dy) in A, to within ``residual_m`` over the area measured."""
    dx: float
    dy: float
    rotation_deg: float
    scale: float
    residual_m: float
    at: tuple[float, float]
    radius_m: float

    def to_json(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v)
                for k, v in dataclasses.asdict(self).items()}

    def line(self) -> str:
        return (f"B's frame in A's: dx {self.dx:.3f} m, dy {self.dy:.3f} m, rotated "
                f"{self.rotation_deg:.6f} deg, scale {self.scale:.8f}; rigid within "
                f"{self.residual_m * 100:.2f} cm over {self.radius_m:.0f} m around "
                f"({self.at[0]:.0f}, {self.at[1]:.0f})")


def frame_offset(a: GeoReference, b: GeoReference, at=(0.0, 0.0), radius: float = 500.0
                 ) -> FrameOffset:
    """The similarity transform (Umeyama least squares over a grid of radius ``radius``
    around ``at`` in B's frame) mapping B coordinates to A coordinates, and its largest
    departure from the exact reprojection on that grid."""
    g = np.linspace(-radius, radius, 11)
    X, Y = np.meshgrid(g, g)
    pb = np.column_stack([X.ravel() + at[0], Y.ravel() + at[1]])
    pa = a.from_lonlat(*b.to_lonlat(pb))
    mb, ma = pb.mean(0), pa.mean(0)
    qb, qa = pb - mb, pa - ma
    u, sv, vt = np.linalg.svd(qa.T @ qb / len(pb))
    d = np.sign(np.linalg.det(u @ vt))
    D = np.diag([1.0, d])
    R = u @ D @ vt
    scale = float(np.trace(np.diag(sv) @ D) / (qb ** 2).sum(axis=1).mean())
    t = ma - scale * R @ mb
    fit = (scale * (R @ pb.T)).T + t
    res = float(np.hypot(*(fit - pa).T).max())
    return FrameOffset(float(t[0]), float(t[1]), float(np.degrees(np.arctan2(R[1, 0], R[0, 0]))),
                       scale, res, (float(at[0]), float(at[1])), float(radius))


def opendrive_header_text(ref: GeoReference) -> tuple[str, dict | None]:
    """(geoReference text, <offset> attributes or None) to write in an OpenDRIVE header."""
    x, y, z, h = ref.offset
    off = None if not any(ref.offset) else {"x": repr(x), "y": repr(y), "z": repr(z), "hdg": repr(h)}
    return ref.proj, off


def attach_origin(layout: m.Layout, source: str) -> None:
    """Give a Lanelet2 / OSM import (``metadata.source.origin`` = [lat, lon]) its frame."""
    origin = layout.metadata.get("source", {}).get("origin")
    if origin is not None:
        attach(layout, local_tangent(origin[0], origin[1], source))
