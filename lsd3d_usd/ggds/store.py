"""Where a GGDS run keeps its results in a scene: the run layer (overs of the optimised surfel
attributes, nothing else) and, while the run can be resumed, a checkpoint that cannot execute
code: tensors in safetensors, everything else in JSON. Checkpoints of older versions
(pickled ``state.pt``) are refused, never loaded.
"""
from __future__ import annotations

import json
from pathlib import Path

from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError

RUN_ATTRIBUTES = ("positions", "orientations", "scales", "opacities", "sh")
CHECKPOINT_VERSION = 1


def _json_default(v):
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")


class SceneRunStore:
    """The files of run ``name`` in scene ``sc``; ``provenance`` is merged into every write of
    the run layer (configuration, prior, dependencies, training views)."""

    def __init__(self, sc: S.Scene, name: str, provenance: dict | None = None,
                 checkpoint_meta: dict | None = None):
        self.scene = sc
        self.name = name
        self.files = sc.run_files(name)
        self.provenance = dict(provenance or {})
        self.checkpoint_meta = dict(checkpoint_meta or {})   # e.g. the whole configuration

    @property
    def layer_path(self) -> Path:
        return self.scene.layer_path(f"{self.name}.usdc")

    @property
    def plot_dir(self) -> Path:
        return self.files.dir

    # ------------------------------------------------------------------ checkpoint
    def has_checkpoint(self) -> bool:
        return self.files.meta.is_file()

    def load_checkpoint(self) -> tuple[dict, dict]:
        """(tensors, meta) of the run's checkpoint; one-line InputError when it is missing,
        pickled (older versions), truncated or inconsistent."""
        f = self.files
        if f.legacy_state.is_file() and not f.meta.is_file():
            raise InputError(f"{f.legacy_state}: a pickled checkpoint of an older lsd3d-usd "
                             "version; it is not loaded (unpickling can run code). Start a new "
                             "run without --resume (the scene's layers are kept)")
        if not f.meta.is_file():
            raise InputError(f"{f.dir}: no checkpoint to resume (no {f.meta.name})")
        try:
            meta = json.loads(f.meta.read_text(encoding="utf-8"))
        except (OSError, ValueError, UnicodeDecodeError) as e:
            raise InputError(f"{f.meta}: unreadable checkpoint metadata ({e})") from None
        if not isinstance(meta, dict) or meta.get("version") != CHECKPOINT_VERSION:
            raise InputError(f"{f.meta}: not a version-{CHECKPOINT_VERSION} lsd3d-usd checkpoint")
        name = str(meta.get("tensors", ""))
        if not name.startswith("state-") or "/" in name or not name.endswith(".safetensors"):
            raise InputError(f"{f.meta}: bad tensor file name {name!r}")
        path = self.scene.inside(f.dir / name, "checkpoint file")
        from safetensors import SafetensorError
        from safetensors.torch import load_file
        try:
            tensors = load_file(str(path))
        except (SafetensorError, OSError, ValueError) as e:
            raise InputError(f"{path}: unreadable checkpoint ({str(e).splitlines()[0]})") from None
        return tensors, meta

    def save_checkpoint(self, tensors: dict, meta: dict) -> None:
        """Crash-consistent: the tensors go to a new file named by step, then the JSON that
        names it replaces the old JSON (atomic), then older tensor files are removed. A crash
        at any point leaves a JSON whose tensor file exists."""
        from safetensors.torch import save
        d = self.files.dir
        d.mkdir(parents=True, exist_ok=True)
        name = f"state-{int(meta['step']):08d}.safetensors"
        S.atomic_write_bytes(d / name, save(tensors))
        meta = {**self.checkpoint_meta, **meta, "version": CHECKPOINT_VERSION, "run": self.name,
                "tensors": name}
        S.atomic_write_text(self.files.meta, json.dumps(meta, default=_json_default))
        for old in d.glob("state-*.safetensors"):
            if old.name != name:
                old.unlink(missing_ok=True)

    def drop_checkpoint(self) -> None:
        self.files.meta.unlink(missing_ok=True)
        for old in self.files.dir.glob("state-*.safetensors"):
            old.unlink(missing_ok=True)

    # ------------------------------------------------------------------ the run layer
    def write_layer(self, field, provenance: dict) -> Path:
        """Overs of the optimised attributes on /World/Surfels (the layer defines nothing)."""
        from pxr import Usd, UsdGeom

        from lsd3d_usd.splats.usdio import write_surfels
        stage = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        write_surfels(stage, S.SURFELS_PATH, field, over=True, attributes=RUN_ATTRIBUTES)
        return self.scene.write_layer(f"{self.name}.usdc", stage,
                                      S.provenance("ggds", **{**self.provenance, **provenance}))

    def write_summary(self, summary: dict) -> Path:
        self.files.dir.mkdir(parents=True, exist_ok=True)
        return S.atomic_write_text(self.files.summary,
                                   json.dumps(summary, indent=2, default=_json_default))
