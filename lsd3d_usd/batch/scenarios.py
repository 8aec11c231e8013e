"""Scenario sets over a batch's scenes (docs/batch.md): the spec's ``[scenarios]`` table runs
`lsd3d-usd sim run SCENE --scenario FILE|DIR` on each scene, one task per scene after the
scene's own task, on the batch's pool.

    [scenarios]
    scenario = "xosc"            # a .xosc or a folder of them, relative to the spec file
    output = "sim"               # relative to [batch].output; a folder per scene in it
    policy = "planner"           # planner | constant | scenario | MODULE:CALLABLE
    ego = "Ego"                  # default: each scenario's first entity
    seconds = 30.0               # hz, rig, lidar, width, seed, episodes
    scenes = ["crossing"]        # default: every scene of the batch

The scenario files are read when the batch is planned, so a scenario that cannot be played
(or names no entity --ego) is refused before any task runs. A task runs `sim run` in its
own process (the CLI's one error line becomes the task's error).
"""
from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from lsd3d_usd.batch.dataset import check_table
from lsd3d_usd.errors import InputError
from lsd3d_usd.hashing import content_hash, file_hash

TASK_VERSION = "batch-scenarios-v1"
KEYS = {"scenario": str, "output": str, "policy": str, "ego": str, "seconds": float, "hz": float,
        "rig": str, "lidar": str, "width": int, "seed": int, "episodes": int, "scenes": list}
FLAGS = ("policy", "ego", "seconds", "hz", "rig", "lidar", "width", "seed", "episodes")


@dataclass
class ScenariosSpec:
    scenario: Path
    output: Path
    options: dict                                    # sim run flags (FLAGS) given
    scenes: list = field(default_factory=list)      # scene names (empty: all)


def parse_scenarios(table, where: str, spec_dir: Path, base_output: Path) -> ScenariosSpec:
    check_table(table, where, KEYS)
    if "scenario" not in table:
        raise InputError(f"{where}: missing key 'scenario' (a .xosc file or a folder of them)")
    src = Path(table["scenario"]).expanduser()
    src = (src if src.is_absolute() else spec_dir / src).absolute()
    out = Path(table.get("output", "sim")).expanduser()
    out = (out if out.is_absolute() else base_output / out).absolute()
    opts = {k: table[k] for k in FLAGS if k in table}
    return ScenariosSpec(src, out, opts, [str(s) for s in table.get("scenes", [])])


@dataclass
class ScenariosPlan:
    spec: ScenariosSpec
    files: list
    tasks: list

    def prepare(self) -> None:
        """Driver side, before the tasks: the output folder (a `sim run` folder per scene)."""
        self.spec.output.mkdir(parents=True, exist_ok=True)


def plan_scenarios(spec, scene_plans, task_cls, logs_dir: Path) -> ScenariosPlan:
    """A task per chosen scene: `sim run SCENE --scenario ...` after the scene's task."""
    import warnings

    from lsd3d_usd.sim.scenario.reader import ScenarioWarning, read_scenario
    from lsd3d_usd.sim.scenario.world import scenario_files
    s = spec.scenarios
    where = f"{spec.path.name}: scenarios"
    by_name = {p.scene.name: p for p in scene_plans}
    names = s.scenes or list(by_name)
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise InputError(f"{where}.scenes: no scene named {unknown[0]!r}")
    try:
        files = scenario_files(s.scenario)
        with warnings.catch_warnings():          # sim run prints them, once, in its log
            warnings.simplefilter("ignore", ScenarioWarning)
            for f in files:
                read_scenario(f, s.options.get("ego"))
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    inputs = content_hash(TASK_VERSION, sorted(s.options.items()),
                          [(f.name, file_hash(f)) for f in files])
    tasks = []
    for n in names:
        sp = by_name[n]
        scene_task = next(t for t in sp.tasks if t.kind == "scene")
        out = s.output / n
        argv = ["sim", "run", str(sp.scene.output), "-o", str(out), "--scenario", str(s.scenario),
                "--no-progress"]
        for k, v in s.options.items():
            argv += [f"--{k}", str(v)]
        tid = f"scenarios/{n}"
        h = content_hash(inputs, scene_task.inputs_hash)
        tasks.append(task_cls(tid, "sim_scenarios", n, h, {
            "target": "lsd3d_usd.batch.tasks:run_task", "kind": "sim_scenarios", "id": tid,
            "argv": argv, "log": str(logs_dir / f"{n}.scenarios.log")},
            deps=(scene_task.id,), outputs=(str(out / "run.json"),)))
    return ScenariosPlan(s, files, tasks)


# ----------------------------------------------------------------------- on workers
def run_scenarios_task(p: dict, log) -> dict:
    """`lsd3d-usd sim run ...` in its own process (the sim's kernels and scene stay there)."""
    log(f"{p['id']}: lsd3d-usd {' '.join(p['argv'])}")
    r = subprocess.run([sys.executable, "-m", "lsd3d_usd", *p["argv"]], capture_output=True,
                       text=True)
    for line in (r.stdout + r.stderr).splitlines():
        log(line)
    if r.returncode != 0:
        last = next((ln for ln in reversed(r.stderr.splitlines()) if ln.strip()), "")
        raise RuntimeError(f"sim run exited {r.returncode}: {last}")
    return {"episodes": sum(ln.startswith("episode ") for ln in r.stdout.splitlines())}
