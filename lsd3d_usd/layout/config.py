"""The `layout` subcommands' configuration trees (lsd3d_usd.configtree): their flags are these
leaves. Text leaves (--extent, --origin, --bbox) keep the command's own parsing and messages."""
from __future__ import annotations

from dataclasses import dataclass

from lsd3d_usd.configtree import option

STYLES = ("urban", "suburban", "highway")


@dataclass
class LayoutGenerateConfig:
    seed: int = option(0, help="master seed", flag="--seed", metavar="SEED")
    extent: str = option("400x400", help="WIDTHxHEIGHT in metres, from the origin",
                         flag="--extent", metavar="EXTENT")
    style: str = option("urban", help="road/building style", flag="--style", choices=STYLES)


@dataclass
class LayoutImportConfig:
    format: str | None = option(None, help="read as this format instead of detecting it (one of "
                                           "the names above)", flag="--format", metavar="NAME")
    tolerance: float = option(0.02, help="max distance of the sampled polylines from the exact "
                                         "curves, m", flag="--tolerance", metavar="TOLERANCE")
    strict: bool = option(False, help="fail on the first bad element instead of skipping it "
                                      "with a warning", flag="--strict")
    origin: str | None = option(None, help="geographic origin of the layout's (0, 0) for "
                                           "Lanelet2 / OSM, degrees (default: the file's own, "
                                           "see docs/layout.md)", flag="--origin",
                                metavar="LAT,LON")
    bbox: str | None = option(None, help="OSM: read only this area (degrees), e.g. a district of "
                                         "a city file", flag="--bbox",
                              metavar="MINLON,MINLAT,MAXLON,MAXLAT")
    clip: bool = option(True, help="OSM: every feature cut at --bbox or, without it, at the "
                                   "file's <bounds> (off: the ways touching the area are kept "
                                   "whole)", negate="--no-clip")
    frame: str | None = option(None, help="write the layout in the frame of this georeferenced "
                                          "layout (or scene): every point is moved through "
                                          "longitude/latitude, so maps of one place from "
                                          "different formats overlay (both need a "
                                          "geoReference)", flag="--frame", metavar="LAYOUT")


@dataclass
class LayoutExportConfig:
    tolerance: float = option(0.02, help="max distance of the fitted reference lines from the "
                                         "lane centres, m (vertices within half of it)",
                              flag="--tolerance", metavar="TOLERANCE")
    validate: bool = option(False, help="check the file against the ASAM OpenDRIVE XSD (needs "
                                        "scenariogeneration)", flag="--validate")
