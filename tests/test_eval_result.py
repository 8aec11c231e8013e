"""`evaluate`'s typed result: its to_json() is eval.json's layout, key for key and in order, as
the single-dict evaluate wrote it (tests/data/eval_json_keys.json: the key paths that evaluate
gave for these options on the small scene before it was split by view family), and the
attributes the report reads hold the same values as the JSON."""
import json
from pathlib import Path

import numpy as np

from lsd3d_usd.eval.evaluate import eval_options, evaluate

KEYS = Path(__file__).parent / "data" / "eval_json_keys.json"


def key_paths(d, prefix=""):
    """Every key path of a JSON value, in order; the items of a list of dicts as "[]"."""
    out = []
    if isinstance(d, dict):
        for k, v in d.items():
            out.append(prefix + k)
            out += key_paths(v, prefix + k + ".")
    elif isinstance(d, list):
        for v in d:
            out += [p for p in key_paths(v, prefix + "[].") if p not in out]
    return out


def test_to_json_keeps_the_eval_json_layout(small_scene, tmp_path):
    import OpenImageIO as oiio
    ref = tmp_path / "ref"
    ref.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):   # every optional family on: reference images and deferred rendering
        p = ref / f"r{i}.png"
        out = oiio.ImageOutput.create(str(p))
        out.open(str(p), oiio.ImageSpec(50, 40, 3, "uint8"))
        out.write_image((rng.uniform(size=(40, 50, 3)) * 255).astype(np.uint8))
        out.close()
    res = evaluate(eval_options(scene=small_scene, out_dir=tmp_path / "e", n_seen=3, per_bin=2,
                                bins=(0.5, 4.0), resolution=(64, 48), frames=4, per_height=2,
                                progress=False, log=lambda *a: None, reference=ref,
                                deferred={"enabled": True, "strength": 0.3}))
    js = json.loads(json.dumps(res.to_json(), default=str))
    assert key_paths(js) == json.loads(KEYS.read_text())
    assert json.loads((tmp_path / "e" / "eval.json").read_text()) == js
    fd = js["fd_effnet_lite0"]
    assert res.distances.seen_vs_novel.per_bin == fd["seen_vs_novel"]["per_bin"]
    assert res.distances.vs_reference == fd["vs_reference"]
    assert res.counts.novel == js["counts"]["novel"] == 4
    assert res.multiview.median == js["multiview_depth_err"]["median"]
    assert res.geometry.seen == js["geometry"]["seen"]
    assert res.deferred.vs_prior_raw == js["deferred"]["fd_effnet_lite0"]["vs_prior_target"]["raw"]
    assert res.deferred.provenance["prior"] == js["deferred"]["prior"] == "procedural"
