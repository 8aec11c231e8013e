"""batch's [scenarios] table: `sim run --scenario DIR` per scene, planned after each scene's
task (a dry run: nothing runs); bad input refused before any task."""
from __future__ import annotations

import pytest

pytest.importorskip("scenariogeneration")

from conftest import ROOT  # noqa: E402
from tests.test_sim_scenario import lanepos, scenario, speed  # noqa: E402

LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"


def _spec(tmp_path, table):
    xosc = tmp_path / "xosc"
    xosc.mkdir(exist_ok=True)
    scenario(xosc, [("Ego", lanepos(10)), ("Target", lanepos(40)), ("Target", speed(5))], [],
             name="lead.xosc")
    p = tmp_path / "spec.toml"
    p.write_text(f'''
[batch]
output = "out"
[defaults]
steps = 0
[[scene]]
name = "a"
layout = "{LAYOUT}"
[[scene]]
name = "b"
layout = "{LAYOUT}"
seed = 3
[scenarios]
{table}
''')
    return p


def test_dry_run_plans_a_sim_run_per_scene(tmp_path, capsys):
    from lsd3d_usd.batch.tasks import plan_batch
    from lsd3d_usd.batch.spec import load_spec
    from lsd3d_usd.cli import main
    spec_file = _spec(tmp_path, 'scenario = "xosc"\npolicy = "scenario"\nego = "Target"\nseconds = 5')
    assert main(["batch", str(spec_file), "--dry-run"]) == 0
    printed = capsys.readouterr().out
    for n in ("a", "b"):
        line = next(ln for ln in printed.splitlines() if ln.startswith(f"scenarios/{n} "))
        assert "sim_scenarios" in line and f"(after {n}/scene)" in line
    spec = load_spec(spec_file)
    plans = plan_batch(spec)
    tasks = {t.id: t for p in plans for t in p.tasks}
    argv = tasks["scenarios/a"].payload["argv"]
    out = (tmp_path / "out" / "sim" / "a").resolve()
    assert argv[:6] == ["sim", "run", str((tmp_path / "out" / "a").resolve()), "-o", str(out),
                        "--scenario"] and argv[6] == str((tmp_path / "xosc").absolute())
    assert argv[argv.index("--policy") + 1] == "scenario" and argv[argv.index("--ego") + 1] == "Target"
    # the scenario files are part of the task's inputs
    h = tasks["scenarios/a"].inputs_hash
    (tmp_path / "xosc" / "lead.xosc").write_text(
        (tmp_path / "xosc" / "lead.xosc").read_text().replace('value="5', 'value="6'))
    assert {t.id: t for p in plan_batch(load_spec(spec_file)) for t in p.tasks}["scenarios/a"].inputs_hash != h


@pytest.mark.parametrize("table, needle", [
    ('scenario = "nope"', "--scenario"),
    ('scenario = "xosc"\nego = "Nobody"', "--ego 'Nobody'"),
    ('scenario = "xosc"\nscenes = ["c"]', "no scene named 'c'"),
    ('scenario = "xosc"\npolcy = "x"', "unknown key 'polcy'"),
    ('scenario = "xosc"\noutput = "../../elsewhere"', "outside the spec's folder"),
])
def test_bad_scenarios_table_is_one_error_line(tmp_path, cli_error, table, needle):
    cli_error(["batch", _spec(tmp_path, table), "--dry-run"], needle)
    assert not (tmp_path / "out").exists()
