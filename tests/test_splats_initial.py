"""Initial surfels chunk by chunk: parts that wait for a neighbour are parked on disk and come
back unchanged; nothing parked is left behind."""
from pathlib import Path

import numpy as np

from conftest import ROOT
from lsd3d_usd.config import generate_config
from lsd3d_usd.splats import initial
from lsd3d_usd.pipeline import RunOptions, generate
from lsd3d_usd.splats import chunkio

LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"   # 4 chunks


def _init(out):
    generate(generate_config(layout=LAYOUT, steps=0, surfels=4000, env_resolution=(64, 32),
                             perceptual=False, actors=False),
             RunOptions(out=Path(out), progress=False, log=lambda *a: None, workers=1))
    root = Path(out) / "layers" / "surfels.usdc"
    return {k: chunkio.read_chunk(root, k) for k in chunkio.read_chunk_map(root)}, root


class _InMemory:
    """The stash's interface without the disk: what holding the parts in memory gives."""

    def __init__(self, parent):
        self.parts = {}

    def put(self, field, src, face):
        self.parts[len(self.parts)] = (field, src, face)
        return len(self.parts) - 1

    def take(self, key):
        return self.parts.pop(key)

    def close(self):
        pass


def test_parked_parts_come_back_unchanged_and_nothing_is_left(tmp_path, monkeypatch):
    parked, root = _init(tmp_path / "a")
    assert len(parked) == 4 and sum(f.n for f in parked.values()) == 4000
    assert not list(chunkio.chunks_base(root).glob(".pending-*"))
    for key, f in parked.items():      # each surfel in the chunk holding it (1 mm tolerance)
        lo = np.asarray(key) * 100.0
        assert np.all((f.positions[:, :2] >= lo - 1e-3) & (f.positions[:, :2] <= lo + 100 + 1e-3))
    monkeypatch.setattr(initial, "Stash", _InMemory)
    held, _ = _init(tmp_path / "b")
    assert held.keys() == parked.keys()
    for key in held:
        a, b = parked[key], held[key]
        for name in ("positions", "orientations", "scales", "opacities", "sh", "semantic_ids"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert a.semantic_classes == b.semantic_classes
