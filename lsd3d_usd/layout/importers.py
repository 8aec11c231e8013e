"""Map importers, registered by name: the one front behind ``lsd3d-usd layout import``.

An importer is a name, a one-line description, a content sniffer and a read function. The
registry (``IMPORTERS``, a :class:`lsd3d_usd.registry.Registry`) holds OpenDRIVE, Lanelet2
and OpenStreetMap; a third-party package adds one through the Python entry point group
``lsd3d_usd.layout_importers`` (the entry point names an :class:`Importer`). The format of a
file is chosen by its content: every importer's sniffer sees the first bytes of the file (and
may read more), the first one to claim it in ``priority`` order wins; the file's extension
only breaks ties between equal priorities.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import model as m
from lsd3d_usd.registry import Registry

ENTRY_POINT_GROUP = "lsd3d_usd.layout_importers"
HEAD_BYTES = 64 * 1024


class MapWarning(UserWarning):
    """A part of a map was skipped or changed on import; the message names the element."""


@dataclass(frozen=True)
class ImportOptions:
    """Options of ``layout import``; each importer uses the ones that apply to its format.

    ``origin`` is (lat, lon) in degrees for geographic formats (None: the file's own);
    ``bbox`` is (min_lon, min_lat, max_lon, max_lat) for cutting an OpenStreetMap file;
    ``clip``: an OpenStreetMap file is cut at ``bbox``, else at its own ``<bounds>`` (False:
    the ways touching the area are kept whole).
    """
    tolerance: float = 0.02
    strict: bool = False
    origin: tuple[float, float] | None = None
    bbox: tuple[float, float, float, float] | None = None
    clip: bool = True


@dataclass(frozen=True)
class Importer:
    """``sniff(path, head)`` says whether ``head`` (the first HEAD_BYTES of the file) is this
    format; ``read(path, options)`` returns the Layout. Lower ``priority`` is asked first."""
    name: str
    description: str
    extensions: tuple[str, ...]
    sniff: Callable[[Path, bytes], bool]
    read: Callable[[Path, ImportOptions], m.Layout]
    priority: int = 500


# ================================================================ built-ins

_XML_ROOT = re.compile(rb"<([A-Za-z_][\w.:-]*)[\s/>]")


def xml_root_name(head: bytes) -> str | None:
    """Name of the first element of an XML document's head (after declaration, comments,
    doctype); None if the head does not look like XML."""
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    pos = 0
    while True:
        text = text[pos:].lstrip()
        if text.startswith(b"<?"):
            pos = text.find(b"?>") + 2
        elif text.startswith(b"<!--"):
            pos = text.find(b"-->") + 3
        elif text.startswith(b"<!"):
            pos = text.find(b">") + 1
        else:
            break
        if pos <= 1:
            return None
    mt = _XML_ROOT.match(text)
    return mt.group(1).decode("ascii", "replace").split(":")[-1] if mt else None


_DOCTYPE = re.compile(rb"<!DOCTYPE\b", re.I)


def refuse_doctype(path, head: bytes) -> None:
    """Refuse an XML map with a document type declaration (one line): an internal DTD
    subset can define entities that expand to gigabytes, or name external files; no map
    format we read needs one."""
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if text.startswith(b"<") and _DOCTYPE.search(head):
        raise InputError(f"{path}: XML with a document type declaration (<!DOCTYPE ...>) is "
                         "refused: DTDs can define entities and name outside files; remove it")


def _sniff_opendrive(path: Path, head: bytes) -> bool:
    return xml_root_name(head) == "OpenDRIVE"


def _read_opendrive(path: Path, options: ImportOptions) -> m.Layout:
    # local import: not loaded for --help
    from lsd3d_usd.layout import opendrive
    return opendrive.read_opendrive(path, tolerance=options.tolerance, strict=options.strict)


def _sniff_lanelet2(path: Path, head: bytes) -> bool:
    # local import: not loaded for --help
    from lsd3d_usd.layout import lanelet2_import
    return lanelet2_import.sniff(path, head)


def _read_lanelet2(path: Path, options: ImportOptions) -> m.Layout:
    # local import: not loaded for --help
    from lsd3d_usd.layout import lanelet2_import
    return lanelet2_import.read_lanelet2(path, options)


def _sniff_osm(path: Path, head: bytes) -> bool:
    # local import: not loaded for --help
    from lsd3d_usd.layout import osm_import
    return osm_import.sniff(path, head)


def _read_osm(path: Path, options: ImportOptions) -> m.Layout:
    # local import: not loaded for --help
    from lsd3d_usd.layout import osm_import
    return osm_import.read_osm(path, options)


OPENDRIVE = Importer("opendrive", "ASAM OpenDRIVE 1.4-1.8 (.xodr): roads, lanes, marks, junctions",
                     (".xodr",), _sniff_opendrive, _read_opendrive, priority=100)
LANELET2 = Importer("lanelet2", "Lanelet2 map (.osm XML with lanelet relations), read with lanelet2",
                    (".osm",), _sniff_lanelet2, _read_lanelet2, priority=200)
OSM = Importer("osm", "OpenStreetMap (.osm XML, .osm.pbf), read with osmium: highways, buildings, "
               "trees, parks", (".osm", ".pbf", ".osm.pbf"), _sniff_osm, _read_osm, priority=300)

IMPORTERS = Registry(ENTRY_POINT_GROUP, "map importer", {
    "opendrive": "lsd3d_usd.layout.importers:OPENDRIVE",
    "lanelet2": "lsd3d_usd.layout.importers:LANELET2",
    "osm": "lsd3d_usd.layout.importers:OSM",
})


# ================================================================ lookup

def registered() -> list[Importer]:
    """Every registered importer (built-ins and entry points), in priority order. An entry
    point that cannot be loaded, or does not name an Importer, is a one-line error."""
    out = []
    for name in IMPORTERS.names():
        imp = IMPORTERS.get(name)
        if not isinstance(imp, Importer):
            raise InputError(f"map importer {name!r} ({ENTRY_POINT_GROUP}) is a "
                             f"{type(imp).__name__}, not a lsd3d_usd.layout.importers.Importer")
        out.append(imp)
    return sorted(out, key=lambda i: (i.priority, i.name))


def get(name: str) -> Importer:
    imp = IMPORTERS.get(name)
    if not isinstance(imp, Importer):
        raise InputError(f"map importer {name!r} is not an Importer")
    return imp


def detect(path: str | Path) -> Importer:
    """The importer whose sniffer claims the file's content."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such file")
    with open(p, "rb") as f:
        head = f.read(HEAD_BYTES)
    if not head:
        raise InputError(f"{path}: empty file")
    refuse_doctype(path, head)
    imps = registered()
    name = p.name.lower()
    # equal priorities: the one whose extension matches the name is asked first
    imps.sort(key=lambda i: (i.priority, not any(name.endswith(e) for e in i.extensions)))
    for imp in imps:
        if imp.sniff(p, head):
            return imp
    raise InputError(f"{path}: not a map format lsd3d-usd reads (tried "
                     f"{', '.join(i.name for i in imps)})")


def read_map(path: str | Path, options: ImportOptions | None = None,
             format: str | None = None) -> tuple[m.Layout, Importer]:
    """Import ``path`` with the named importer, or the one that claims its content."""
    options = options or ImportOptions()
    if not (options.tolerance > 0):
        raise InputError(f"tolerance must be > 0, got {options.tolerance}")
    imp = get(format) if format else detect(path)
    if format and not Path(path).is_file():
        raise InputError(f"{path}: no such file")
    if format:
        with open(path, "rb") as f:
            head = f.read(HEAD_BYTES)
        refuse_doctype(path, head)
        if not imp.sniff(Path(path), head):
            raise InputError(f"{path}: is not a {imp.name} file ({imp.description})")
    layout = imp.read(Path(path), options)
    m.check_size(layout, str(path))   # what every reader would refuse is refused here
    src = layout.metadata.setdefault("source", {})
    src.setdefault("format", imp.name)
    src.setdefault("file", Path(path).name)
    return layout, imp


def formats_help() -> str:
    """One line per registered format, for ``layout import --help``."""
    return "\n".join(f"  {imp.name:10s} {imp.description}" for imp in registered())


def reach_line(layout: m.Layout) -> str:
    """One line: how far the layout reaches (its features' bounds, the chunks they cover)
    and, for a clipped import, what it was clipped to."""
    (x0, y0), (x1, y1) = layout.bounds()
    ri, rj = layout.chunk_range()
    line = (f"layout reaches {x1 - x0:.0f} m x {y1 - y0:.0f} m (x {x0:.0f}..{x1:.0f}, y "
            f"{y0:.0f}..{y1:.0f}; {len(ri) * len(rj)} chunks of {layout.chunk_size:g} m)")
    clip = layout.metadata.get("source", {}).get("clip") if isinstance(layout.metadata, dict) else None
    if isinstance(clip, dict) and clip.get("from"):
        cx0, cy0, cx1, cy1 = clip["extent"]
        what = "the file's <bounds>" if clip["from"] == "file bounds" else "--bbox"
        line += (f"; clipped to {what}, {cx1 - cx0:.0f} m x {cy1 - cy0:.0f} m (--no-clip keeps "
                 "whole ways)")
    elif isinstance(clip, dict):
        line += "; not clipped (--no-clip)"
    return line
