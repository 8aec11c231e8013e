"""The typed configuration tree: one definition → CLI flags, TOML keys, --set overrides,
provenance; every error one line naming the key."""
import argparse
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from lsd3d_usd import configtree as ct
from lsd3d_usd.config import GenerateConfig, generate_config
from lsd3d_usd.configtree import option
from lsd3d_usd.errors import InputError


@dataclass
class Inner:
    rate: float = option(0.5, help="a rate", lo=0.0, hi=1.0)
    size: tuple[int, int] = option((4, 3), help="a size", flag="--size", alias="size")


@dataclass
class Tree:
    steps: int = option(10, help="steps", flag="--steps", alias="steps", lo=0)
    name: str | None = option(None, help="a name", flag="--name")
    kind: str = option("a", help="kind", choices=("a", "b"), flag="--kind")
    on: bool = option(True, help="switch", negate="--no-on", alias="on")
    path: Path | None = option(None, help="a file", flag="--path")
    weights: dict[str, float | None] = option(help="weights", keys=lambda: {"x": 1.0, "y": None},
                                              default_factory=lambda: {"x": 1.0, "y": None},
                                              lo=0.0)
    inner: Inner = field(default_factory=Inner)
    derived: int = 0     # not an option


def test_leaves_keys_aliases_and_describe():
    keys = [lf.key for lf in ct.leaves(Tree)]
    assert keys == ["steps", "name", "kind", "on", "path", "weights", "inner.rate", "inner.size"]
    rows = {r["key"]: r for r in ct.describe(Tree)}
    assert rows["inner.size"]["default"] == "4x3" and rows["inner.size"]["alias"] == "size"
    assert rows["on"]["flag"] == "--no-on"


def test_tables_dotted_keys_aliases_and_dict_entries():
    cfg = ct.from_table(Tree, {"steps": 3, "size": "8x6", "inner": {"rate": 0.25},
                               "weights": {"y": 2.0}, "on": False})
    assert (cfg.steps, cfg.inner.size, cfg.inner.rate, cfg.on) == (3, (8, 6), 0.25, False)
    assert cfg.weights == {"x": 1.0, "y": 2.0}
    cfg2 = ct.apply(Tree(), {"inner.rate": "0.75", "weights.x": "none", "name": "none"})
    assert cfg2.inner.rate == 0.75 and cfg2.weights["x"] is None and cfg2.name is None
    assert Tree().weights == {"x": 1.0, "y": None}       # defaults not shared / mutated


@pytest.mark.parametrize("values,match", [
    ({"steps": "ten"}, r"^w: steps: expected an integer, got 'ten'$"),
    ({"steps": -1}, r"^w: steps: must be >= 0, got -1$"),
    ({"kind": "c"}, r"^w: kind: expected one of a, b, got 'c'$"),
    ({"inner.rate": 2}, r"must be in \[0.0, 1.0\], got 2.0"),
    ({"inner.size": "4by3"}, r"expected two positive integers as WxH"),
    ({"inner.size": [4.5, 3]}, r"expected two positive integers"),
    ({"weights.z": 1}, r"unknown key 'z'"),
    ({"weights.x": -1}, r"weights.x: must be >= 0.0"),
    ({"inner.rat": 1}, r"unknown key 'inner.rat' \(did you mean 'inner.rate'\?\)"),
    ({"steps": float("nan")}, r"steps: expected an integer"),
    ({"inner.rate": "inf"}, r"must be a finite number"),
    ({"on": "maybe"}, r"on: expected true or false"),
])
def test_bad_values_are_one_line_naming_the_key(values, match):
    with pytest.raises(InputError, match=match) as e:
        ct.apply(Tree(), values, "w: ")
    assert "\n" not in str(e.value)


def test_round_trip_and_diff():
    cfg = ct.apply(Tree(), {"steps": "7", "path": "/x/y", "inner.size": "2x2"})
    data = ct.to_dict(cfg)
    assert data["path"] == "/x/y" and data["inner"]["size"] == [2, 2] and data["derived"] == 0
    back = ct.from_dict(Tree, data)
    assert back == cfg and ct.diff(Tree(), back) == {"steps": (10, 7), "path": (None, Path("/x/y")),
                                                     "inner.size": ((4, 3), (2, 2))}


def test_argparse_flags_only_what_was_given():
    p = argparse.ArgumentParser()
    ct.add_arguments(p, Tree)
    args = p.parse_args(["--steps", "5", "--no-on", "--size", "6x2"])
    given = ct.from_args(args)
    assert given == {"steps": "5", "on": "false", "inner.size": "6x2"}
    cfg = ct.apply(Tree(), given, "", ct.flag_names(Tree))
    assert (cfg.steps, cfg.on, cfg.inner.size) == (5, False, (6, 2))
    assert "(default: 10)" in p.format_help()
    with pytest.raises(InputError, match=r"^--steps: expected an integer"):
        ct.apply(Tree(), {"steps": "x"}, "", ct.flag_names(Tree))


def test_set_assignments():
    assert ct.parse_assignments(["inner.rate=0.1", "steps=3"], Tree) == {"inner.rate": "0.1",
                                                                       "steps": "3"}
    with pytest.raises(InputError, match="use KEY=VALUE"):
        ct.parse_assignments(["inner.rate"], Tree)


def test_generate_config_knobs_are_all_reachable():
    """Every leaf of generate's tree can be set by key (nothing needs a code edit)."""
    for lf in ct.leaves(GenerateConfig):
        if lf.base in (int, float) and lf.meta["choices"] is None:
            lo = lf.meta["lo"]
            v = lo if lo is not None else 1
            cfg = ct.apply(GenerateConfig(), {lf.key: v}, "")
            assert ct.value(cfg, lf.key) == v
    flags = [lf.meta["flag"] for lf in ct.leaves(GenerateConfig) if lf.meta["flag"]]
    for f in ("--steps", "--resolution", "--views", "--surfels", "--prior", "--seed", "--layout",
              "--prompt", "--env-resolution", "--parked", "--moving", "--actor-seconds",
              "--checkpoint-every", "--lpips", "--lpips-lin", "--extent", "--style", "--when",
              "--lat", "--lon", "--weather", "--season", "--controlnet", "--device", "--omega"):
        assert f in flags, f


def test_config_file_relative_paths_and_errors(tmp_path):
    f = tmp_path / "gen.toml"
    f.write_text('steps = 5\nlayout = "maps/l.usda"\n[ggds.lr]\nsh_dc = 0.02\n')
    vals = ct.load_file(f, GenerateConfig)
    assert vals["layout"] == str((tmp_path / "maps" / "l.usda").resolve())
    assert vals["ggds.lr.sh_dc"] == 0.02 and vals["ggds.steps"] == 5
    f.write_text("[ggds.lrr]\nsh_dc = 1\n")
    with pytest.raises(InputError, match=r"gen.toml: unknown key 'ggds.lrr'"):
        ct.load_file(f, GenerateConfig)
    f.write_text("steps = \n")
    with pytest.raises(InputError, match="not valid TOML"):
        ct.load_file(f, GenerateConfig)


def test_prior_seed_follows_the_scene_seed():
    from lsd3d_usd.ggds.priors.registry import make_prior
    assert make_prior(generate_config(seed=7).prior, seed=7).seed == 7


def test_stored_configuration_without_a_newer_leaf_keeps_its_old_behaviour():
    """A run recorded before an option existed is read back with the value that matches what
    the code did then (the option's ``recorded``), not the new default."""
    from lsd3d_usd.ggds.priors.registry import PriorConfig
    old = ct.from_dict(PriorConfig, {"name": "procedural"})
    assert old.supersample == 1 and PriorConfig().supersample == 2
    assert ct.from_dict(PriorConfig, {"name": "procedural", "supersample": 3}).supersample == 3
    from lsd3d_usd.ggds.settings import RegionConfig
    # a retired key (one knob under two names, now ggds.world_init_views) reads back dropped
    assert ct.from_dict(RegionConfig, {"mode": "chunk", "fit_inner_frac": 0.0}) == \
        RegionConfig(mode="chunk", fit_context=False, share_views=False)
    # options a stored configuration predates read back as off, whatever the default
    stored = ct.from_dict(RegionConfig, {"mode": "chunk"})
    assert stored.fit_context is False and stored.share_views is False


def test_a_prior_declares_its_options_as_its_own_configuration_class():
    from dataclasses import dataclass

    from lsd3d_usd.configtree import option
    from lsd3d_usd.errors import InputError
    from lsd3d_usd.ggds.priors import registry as R

    @dataclass
    class FlatOptions:
        strength: float = option(0.5, help="how flat", lo=0.0, hi=1.0)

    R.PRIORS.register("flat_opts", R.PriorEntry(lambda a, c, s: None, lambda a, c: None,
                                                config=FlatOptions))
    try:
        got = R.prior_options(R.PriorConfig(name="flat_opts", options={"strength": "0.25"}))
        assert got == FlatOptions(strength=0.25)        # typed, from --set text
        with pytest.raises(InputError, match=r"prior.options.strength: must be in"):
            R.prior_options(R.PriorConfig(name="flat_opts", options={"strength": "2"}))
        with pytest.raises(InputError, match="did you mean 'strength'"):
            R.check_prior(R.PriorConfig(name="flat_opts", options={"strenght": "0.1"}))
        with pytest.raises(InputError, match="takes no such option"):
            R.check_prior(R.PriorConfig(options={"strength": "0.1"}))   # procedural: none
    finally:
        R.PRIORS.unregister("flat_opts")
