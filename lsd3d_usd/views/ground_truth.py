"""The camera outputs of `render` beside the colour: ground truth from the same composite
(views.frame.FrameLabels), written per camera and frame next to the RGB file <stem>.png:

  <stem>.depth.exr             metric z-depth along the optical axis, float32, channel Z
                               (inf where nothing is drawn)
  <stem>.semantic.png          uint8 class ids (OUT/classes.json), and
  <stem>.semantic_preview.png  the same coloured
  <stem>.instance.png          uint16 instance ids (OUT/instances.json), 0 for stuff
  <stem>.normal.exr            world-space unit normals, float32 (X, Y, Z), 0 for the sky

``boxes`` among the outputs writes OUT/boxes/<frame>.json (views.boxes).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.views import labels as L
from lsd3d_usd.views.images import write_image

OUTPUTS = ("rgb", "depth", "semantic", "instance", "normal", "boxes")
LABEL_OUTPUTS = ("depth", "semantic", "instance", "normal", "boxes")
# lossless; on rig frames as fast to write as "zips", "rle" or none within the noise of the
# measurement, and the smallest of them (zips +10 %, rle +20 %, none +30 % for depth)
EXR_COMPRESSION = "zip"


def parse_outputs(text: str, where: str = "--outputs") -> tuple[str, ...]:
    """'rgb,depth' → ('rgb', 'depth'); one InputError line naming an unknown one."""
    names = tuple(dict.fromkeys(n.strip() for n in str(text).split(",") if n.strip()))
    if not names:
        raise InputError(f"{where}: give at least one of {', '.join(OUTPUTS)}")
    bad = [n for n in names if n not in OUTPUTS]
    if bad:
        raise InputError(f"{where} {text!r}: unknown output {bad[0]!r}; choose from "
                         f"{', '.join(OUTPUTS)}")
    return names


def check_outputs(v: str, where: str) -> str:
    parse_outputs(v, where)
    return v


def needs_labels(outputs) -> bool:
    return any(o in LABEL_OUTPUTS for o in outputs)


def stem_of(rgb_path: Path) -> Path:
    p = Path(rgb_path)
    return p.with_name(p.name[: -len(p.suffix)] if p.suffix else p.name)


def write_ground_truth(rgb_path: Path, labels, outputs) -> dict:
    """The label images of one frame beside ``rgb_path`` (module doc); {output: path}."""
    stem = stem_of(rgb_path)
    files = {}
    if "depth" in outputs:
        files["depth"] = write_image(f"{stem}.depth.exr", labels.z.astype(np.float32), ("Z",),
                                     EXR_COMPRESSION)
    if "semantic" in outputs:
        files["semantic"] = write_image(f"{stem}.semantic.png", labels.class_id)
        files["semantic_preview"] = write_image(f"{stem}.semantic_preview.png",
                                                L.palette()[labels.class_id])
    if "instance" in outputs:
        files["instance"] = write_image(f"{stem}.instance.png", labels.instance_id)
    if "normal" in outputs:
        files["normal"] = write_image(f"{stem}.normal.exr", labels.normal.astype(np.float32),
                                      ("X", "Y", "Z"), EXR_COMPRESSION)
    return files
