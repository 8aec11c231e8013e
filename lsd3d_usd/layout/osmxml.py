"""Errors of OSM XML / PBF files read with osmium, as one line naming the element.

osmium's XML parser stops at a coordinate that is not a number (``lat="nan"``) with
"wrong format for coordinate" and no element id; a truncated file ends in a parser error.
``osmium_errors`` turns both into ``InputError``; ``bad_location`` finds the first node
whose ``lat``/``lon`` is not a finite coordinate, by a linear scan of the XML text, so
the message can name the node.
"""
from __future__ import annotations

import math
import mmap
import re
from contextlib import contextmanager
from pathlib import Path

import osmium

from lsd3d_usd.errors import InputError, excerpt

_NODE = re.compile(rb"<node\b[^>]*>")
_ATTR = re.compile(rb"""\b(id|lat|lon)\s*=\s*(?:"([^"]*)"|'([^']*)')""")
_RANGE = {b"lat": 90.0, b"lon": 180.0}


def bad_location(path: str | Path) -> str | None:
    """'node 9: lat 'NaN' is not a latitude in degrees' for the first XML node with a bad
    coordinate, or None (also for PBF files, which store integers)."""
    p = Path(path)
    if p.stat().st_size == 0:
        return None
    with open(p, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        if mm[:1] not in (b"<", b"\xef", b" ", b"\n", b"\r", b"\t"):
            return None
        for mt in _NODE.finditer(mm):
            attrs = {k: a or b for k, a, b in _ATTR.findall(mt.group(0))}
            for key, bound in _RANGE.items():
                raw = attrs.get(key)
                if raw is None:
                    continue
                try:
                    v = float(raw)
                except ValueError:
                    v = math.nan
                if not (math.isfinite(v) and abs(v) <= bound):
                    nid = attrs.get(b"id", b"?").decode("ascii", "replace")
                    what = "latitude" if key == b"lat" else "longitude"
                    return (f"node {nid[:40]}: {key.decode()} "
                            f"{excerpt(raw.decode('utf-8', 'replace'))} is not a {what} in degrees")
    return None


@contextmanager
def osmium_errors(path: str | Path, reader: str = "osmium"):
    """Reading with osmium inside: its errors become one InputError line."""
    try:
        yield
    except osmium.InvalidLocationError as e:
        where = bad_location(path)
        raise InputError(f"{path}: {where or f'{reader}: {e}'}; fix or remove the node") from None
    except RuntimeError as e:
        msg = " ".join(str(e).split())
        hint = " (the file is truncated or damaged)" if re.search(
            r"EOF|no element found|unclosed|truncated|parsing error", msg, re.I) else ""
        raise InputError(f"{path}: {reader} cannot read it: {msg[:300]}{hint}") from None


def header_centre(path: str | Path) -> tuple[float, float] | None:
    """(lat, lon) of the centre of an OSM file's header bounds, None when it has none (read
    errors as InputError)."""
    with osmium_errors(path):
        reader = osmium.io.Reader(str(path), osmium.osm.osm_entity_bits.NOTHING)
        try:
            box = reader.header().box()
        finally:
            reader.close()
    if not box.valid():
        return None
    bl, tr = box.bottom_left, box.top_right
    return (bl.lat + tr.lat) / 2, (bl.lon + tr.lon) / 2
