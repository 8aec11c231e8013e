"""Dataset writers: registered parts (``lsd3d_usd.dataset_writers``), one per format.

A writer is a class built as ``Writer(root, options)`` (root: the dataset folder;
options: datasets.build.DatasetOptions) with

    begin_log(info)       a log starts (datasets.drive.LogInfo: rig, calibrations, layout)
    write(sample)         one datasets.drive.Sample, in time order; files go to disk now
    end_log() -> dict     the log is done: a JSON-able record of it (its table rows), kept
                          under root/.lsd3d/logs/ so a resumed or batched run can merge it
    finish(records)       every log's record, in log order: write the tables / indexes

and a ``record_shape`` (datasets.build.record_problem: what a record read back from disk
must hold, so a tampered one is one error line, not a traceback in ``finish``)

and, optionally, ``checkpoint() -> dict`` (called after every keyframe: what the log gained
since the previous checkpoint, JSON-able; its files must be on disk when it returns) and
``restore(info, deltas)`` (continue a log from its checkpoints' deltas, in order): with them
a resumed run continues a killed log after its last keyframe (datasets.build.Checkpoints
journals the deltas, so a checkpoint costs what it adds); without them the log starts again.

Writers only reformat what they are given: they own no rendering, and they keep nothing per
sample but small rows, so memory stays bounded for any route length. A third-party package
adds a format by declaring::

    [project.entry-points."lsd3d_usd.dataset_writers"]
    myformat = "mypkg.writer:MyWriter"
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.registry import Registry

WRITERS = Registry("lsd3d_usd.dataset_writers", "dataset format", {
    "nuscenes": "lsd3d_usd.datasets.nuscenes:NuScenesWriter",
    "kitti": "lsd3d_usd.datasets.kitti:KittiWriter",
    "mcap": "lsd3d_usd.datasets.mcap:McapWriter",
})


def encode_image(img: np.ndarray, fmt: str) -> bytes:
    """JPEG (quality 95, no subsampling) or PNG bytes of a uint8 image; deterministic."""
    from PIL import Image
    buf = io.BytesIO()
    if fmt == "jpg":
        Image.fromarray(img).save(buf, format="JPEG", quality=95, subsampling=0)
    else:
        Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def write_bytes(path: Path, data: bytes) -> Path:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return S.atomic_write_bytes(Path(path), data)


def quat_wxyz(R: np.ndarray) -> list:
    from scipy.spatial.transform import Rotation
    x, y, z, w = Rotation.from_matrix(np.asarray(R, np.float64)[:3, :3]).as_quat()
    q = np.array([w, x, y, z])
    return (q if w >= 0 else -q).tolist()
