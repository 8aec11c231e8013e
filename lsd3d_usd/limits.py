"""Work limits: the explicit bounds every reader checks before it allocates or writes.

A tiny file must not make the tool run for hours or allocate gigabytes: a 450-byte
OpenDRIVE file can claim a 1e8 m road, a PLY header 1e12 vertices, a layout a chunk
size of 1 cm. Each bound lives here once, so readers, commands and docs/limits.md use
the same numbers. This module is the bottom layer: it imports nothing heavy.

A ``Limit`` checks a value and raises ``InputError`` with one line naming where, what,
the value and the limit (and the flag that raises it, where one exists). A value that
is not a number (NaN) fails every check. Overrides are explicit: a command that offers
one has a ``--max-...`` flag (``cliutil.add_limit_option``), and the library functions
take the raised value as a keyword argument; nothing global changes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from lsd3d_usd.errors import InputError


def _fmt(x) -> str:
    """A number for a message: integers as integers, others in 6 significant digits."""
    try:
        xf = float(x)
    except (TypeError, ValueError):
        return repr(x)
    if not math.isfinite(xf):
        return str(xf)
    if xf == int(xf) and abs(xf) < 1e15:
        return str(int(xf))
    return f"{xf:.6g}"


@dataclass(frozen=True)
class Limit:
    """One documented bound. ``kind`` 'max': value <= bound; 'min': value >= bound."""
    name: str               # id in docs/limits.md
    value: float
    unit: str               # appended to numbers in messages ("m", " chunks", ...)
    what: str               # what is measured ("road length", "chunk count", ...)
    where: str              # where it is checked (for docs/limits.md)
    flag: str | None = None  # the command-line flag that raises it, if any
    kind: str = "max"

    def ok(self, value, bound=None) -> bool:
        b = self.value if bound is None else bound
        try:
            v = float(value)
        except (TypeError, ValueError, OverflowError):
            return False
        if math.isnan(v):
            return False
        return v <= b if self.kind == "max" else v >= b

    def describe(self, value, bound=None, what: str | None = None) -> str:
        """'<what> <value> exceeds the limit of <bound>' (no location)."""
        b = self.value if bound is None else bound
        what = self.what if what is None else what
        try:
            nan = math.isnan(float(value))
        except (TypeError, ValueError, OverflowError):
            nan = True
        if nan:
            return f"{what} is {value!r}, not a number"
        rel = "exceeds the limit of" if self.kind == "max" else "is below the minimum of"
        hint = f" (raise it with {self.flag})" if self.flag and self.kind == "max" else ""
        return f"{what} {_fmt(value)}{self.unit} {rel} {_fmt(b)}{self.unit}{hint}"

    def message(self, value, where: str, bound=None, what: str | None = None) -> str:
        return f"{where}: {self.describe(value, bound, what)}"

    def check(self, value, where: str, bound=None, what: str | None = None) -> None:
        """Raise InputError (one line) unless ``value`` is within the bound (``bound``
        overrides the default, e.g. from a --max-... flag; ``what`` renames the quantity)."""
        if not self.ok(value, bound):
            raise InputError(self.message(value, where, bound, what))


# --------------------------------------------------------------------- OpenDRIVE
OPENDRIVE_FILE_BYTES = Limit(
    "opendrive_file_bytes", 512 * 1024 * 1024, " bytes", "file size",
    "layout import (before parsing)")
ROAD_LENGTH = Limit(
    "road_length", 100_000.0, " m", "length",
    "layout import: each <road> length and each <geometry> length, before sampling")
LANE_WIDTH = Limit(
    "lane_width", 100.0, " m", "lane width",
    "layout import: every lane width sample, before the polylines are refined")
LATERAL_OFFSET = Limit(
    "lateral_offset", 1_000.0, " m", "lateral offset of a lane boundary",
    "layout import: laneOffset + widths of every boundary from the reference line")
ROAD_POINTS = Limit(
    "road_points", 1_000_000, " points", "polyline points (samples x boundary lines)",
    "layout import: the adaptive sampler of each road stops there (road skipped; a larger "
    "--tolerance needs fewer)")
TOTAL_ROAD_LENGTH = Limit(
    "total_road_length", 10_000_000.0, " m", "total road length",
    "layout import: the sum of the road lengths of one file, before any road is sampled")

# ------------------------------------------------------------------------ layouts
LAYOUT_EXTENT = Limit(
    "layout_extent", 50_000.0, " m", "layout size",
    "USD layout reader (extent metadata and feature bounds), layout import; "
    "layout points are float32 in USD: 4 mm resolution at 50 km")
COORDINATE = Limit(
    "coordinate", 10_000_000.0, " m", "distance from the origin",
    "USD layout reader and layout import: every coordinate (UTM northings fit; beyond, "
    "float32 points lose whole metres and overflow)")
FEATURE_POINTS = Limit(
    "feature_points", 100_000, " points", "points of one feature",
    "USD layout reader (every command that reads a layout), before the points are converted")
LAYOUT_POINTS = Limit(
    "layout_points", 2_000_000, " points", "points of all features",
    "USD layout reader, as the features are read")
CHUNK_SIZE_MIN = Limit(
    "chunk_size_min", 10.0, " m", "chunk size",
    "USD layout reader (lsd3dLayout.chunkSize), proxy from-points --chunk-size", kind="min")
CHUNK_SIZE_MAX = Limit(
    "chunk_size_max", 1_000.0, " m", "chunk size",
    "USD layout reader (lsd3dLayout.chunkSize), proxy from-points --chunk-size")
CHUNKS = Limit(
    "chunks", 10_000, " chunks", "chunk count",
    "proxy build and proxy from-points, before the first chunk is built", flag="--max-chunks")
CHUNK_VOXELS = Limit(
    "chunk_voxels", 100_000_000, " voxels", "voxel grid",
    "proxy from-points: each chunk's occupancy grid (chunk + padding, height of its "
    "points) before it is allocated")

# ------------------------------------------------------------------ splats / USD
PLY_VERTICES = Limit(
    "ply_vertices", 50_000_000, " vertices", "vertex count",
    "PLY readers (splats import-ply, proxy from-points), before reading the body; the "
    "body must also hold the bytes the header claims", flag="--max-vertices")
PLY_HEADER_BYTES = Limit(
    "ply_header_bytes", 1 << 20, " bytes", "header size",
    "PLY readers (splats import-ply, proxy from-points), while the header is read")
USDA_PARTICLES = Limit(
    "usda_particles", 10_000, " particles", "particle count in a .usda (text) layer",
    "surfel writers (splats init / import-ply / export-3dgs -o *.usda) refuse; validate "
    "reports BulkDataInUsda")

# ---------------------------------------------------------------------- prompts
PROMPT_CHARS = Limit(
    "prompt_chars", 10_000, " characters", "prompt length",
    "env / generate / batch --prompt, before it is parsed (the prompt is kept in provenance)")

# -------------------------------------------------------------------------- OSM
OSM_WAY_NODES = Limit(
    "osm_way_nodes", 2000, " nodes", "node references of one way",
    "layout import (OSM): each way while the file is read, before its nodes are kept "
    "(the way is skipped with a warning; OpenStreetMap's own API allows 2000)")

# ------------------------------------------------------------------------ batch
BATCH_SPEC_BYTES = Limit(
    "batch_spec_bytes", 16 * 1024 * 1024, " bytes", "batch spec size",
    "batch, before the spec is parsed")
BATCH_SCENES = Limit(
    "batch_scenes", 10_000, " scenes", "scene count",
    "batch, right after parsing, before any scene is checked")

# ----------------------------------------------------------------------- viewer
VIEWER_PROBLEMS = Limit(
    "viewer_problems", 200, " problems", "problems listed by the viewer",
    "view: /api/problems lists the first ones and says that more were found")
VIEWER_CONNECTIONS = Limit(
    "viewer_connections", 32, " connections", "open connections to the viewer",
    "view: a connection beyond it is answered 503 and closed")
VIEWER_IDLE_SECONDS = Limit(
    "viewer_idle_seconds", 30, " s", "idle time of a viewer connection",
    "view: a connection that sends nothing for this long is closed")

# ----------------------------------------------------------------------- images
IMAGE_PIXELS = Limit(
    "image_pixels", 8192 * 4096, " pixels", "image size",
    "--resolution / --size flags (cliutil.parse_size), env map rendering")

# ------------------------------------------------------------------------ actors
PEDESTRIANS = Limit(
    "pedestrians", 2000, " pedestrians", "pedestrian count",
    "actors add --pedestrians, generate actors.pedestrians (each walker is checked against "
    "every other actor's box per sample)", flag="--pedestrians")
CYCLISTS = Limit(
    "cyclists", 500, " cyclists", "cyclist count",
    "actors add --cyclists, generate actors.cyclists", flag="--cyclists")

# ---------------------------------------------------------------------- datasets
DATASET_STATE_BYTES = Limit(
    "dataset_state_bytes", 256 * 1024 * 1024, " bytes", "state file size",
    "dataset --resume / --overwrite: .lsd3d/dataset.json, logs/<k>.json, logs/<k>.partial.json "
    "and the journal, before they are read")

# ------------------------------------------------------------------------ LiDAR
LIDAR_BEAMS = Limit(
    "lidar_beams", 1024, " beams", "beam count",
    "--lidar FILE.toml (sensors.lidar) and LidarModel.check, before any ray is cast")
LIDAR_COLUMNS = Limit(
    "lidar_columns", 100_000, " columns", "column count",
    "--lidar FILE.toml and LidarModel.check, before any ray is cast")
LIDAR_RAYS = Limit(
    "lidar_rays", 20_000_000, " rays", "rays per sweep (beams x columns)",
    "--lidar FILE.toml and LidarModel.check: a sweep's arrays are allocated per ray")
LIDAR_RANGE = Limit(
    "lidar_range", 10_000.0, " m", "max_range",
    "--lidar FILE.toml and LidarModel.check")

LIDAR_MOUNT = Limit(
    "lidar_mount", 100.0, " m", "mount offset",
    "--lidar FILE.toml and LidarModel.check: |x|, |y|, |z| of the mount on the ego (a sensor "
    "1e308 m away sees nothing)")

LIDAR_FILE_BYTES = Limit(
    "lidar_file_bytes", 1024 * 1024, " bytes", "LiDAR file size",
    "--lidar FILE.toml (render, dataset, batch), before the TOML is parsed")
LIDAR_NAME_CHARS = Limit(
    "lidar_name_chars", 200, " characters", "LiDAR name length",
    "--lidar FILE.toml: the name is written into rig.usda and dataset tables")
TRAJECTORY_FILE_BYTES = Limit(
    "trajectory_file_bytes", 64 * 1024 * 1024, " bytes", "trajectory file size",
    "render --rig --trajectory poses.json, before the JSON is parsed")

# ----------------------------------------------------------------- times, rates
CLIP_SECONDS = Limit(
    "clip_seconds", 86_400.0, " s", "length",
    "dataset --seconds (datasets.timeline), actors add --seconds, render --rig --seconds "
    "(views.options), before anything is simulated")
FRAMES = Limit(
    "frames", 1_000_000, " frames", "frames (rate x seconds)",
    "render --rig (--fps x --seconds), dataset (ticks of a log: the rates' common tick rate x "
    "--seconds), actors add (--fps x --seconds samples), before anything is simulated")
ACTOR_SAMPLES = Limit(
    "actor_samples", 20_000_000, " samples", "actor time samples (moving actors, pedestrians "
    "and cyclists x --fps x --seconds)",
    "actors add and generate's actors, before the traffic is simulated")

ALL = (OPENDRIVE_FILE_BYTES, ROAD_LENGTH, TOTAL_ROAD_LENGTH, LANE_WIDTH, LATERAL_OFFSET, ROAD_POINTS,
       LAYOUT_EXTENT, COORDINATE, FEATURE_POINTS, LAYOUT_POINTS, CHUNK_SIZE_MIN, CHUNK_SIZE_MAX,
       CHUNKS, CHUNK_VOXELS, PLY_VERTICES, PLY_HEADER_BYTES, USDA_PARTICLES, PROMPT_CHARS,
       IMAGE_PIXELS, OSM_WAY_NODES, BATCH_SPEC_BYTES, BATCH_SCENES, VIEWER_PROBLEMS,
       VIEWER_CONNECTIONS, VIEWER_IDLE_SECONDS, PEDESTRIANS, CYCLISTS, LIDAR_BEAMS, LIDAR_COLUMNS, LIDAR_RAYS,
       LIDAR_RANGE, LIDAR_MOUNT, DATASET_STATE_BYTES, LIDAR_FILE_BYTES, LIDAR_NAME_CHARS,
       TRAJECTORY_FILE_BYTES, CLIP_SECONDS, FRAMES, ACTOR_SAMPLES)


def check_image_size(width: int, height: int, where: str, bound=None) -> None:
    """One check of an image's pixel count for every command that allocates images."""
    if not IMAGE_PIXELS.ok(int(width) * int(height), bound):
        b = IMAGE_PIXELS.value if bound is None else bound
        raise InputError(f"{where} {width}x{height}: {_fmt(int(width) * int(height))} pixels "
                         f"exceed the limit of {_fmt(b)} pixels (e.g. 8192x4096)")
