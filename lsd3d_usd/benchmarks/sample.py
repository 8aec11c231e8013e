"""The scene most benchmarks run on: the README sample (samples/layouts/hand_crossing.usda,
"sunny afternoon in Madrid"), generated into a folder when no scene is given."""
from __future__ import annotations

import tempfile
from contextlib import contextmanager
from pathlib import Path

SAMPLE = Path(__file__).resolve().parents[2] / "samples" / "layouts" / "hand_crossing.usda"


def generate_sample(target: Path, quick: bool, what: str, log=print) -> None:
    """Generate the README sample into ``target``: generate's defaults, or with ``quick`` no
    GGDS and 100 k surfels. ``what``: the benchmark's name for the progress line."""
    from lsd3d_usd.config import generate_config
    from lsd3d_usd.pipeline import RunOptions, generate
    kw = dict(steps=0, surfels=100_000) if quick else {}
    log(f"{what}: generating the README sample ({'quick' if quick else 'defaults'})")
    generate(generate_config(layout=SAMPLE, prompt="sunny afternoon in Madrid", **kw),
             RunOptions(out=target, progress=False, log=lambda *a: None))


@contextmanager
def scene_or_sample(scene, quick: bool, what: str, log=print):
    """``scene`` as a Path, or (None) the README sample generated into a temporary folder
    that lives as long as the block."""
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(scene) if scene else Path(tmp) / "scene"
        if scene is None:
            generate_sample(target, quick, what, log)
        yield target
