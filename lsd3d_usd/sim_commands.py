"""`lsd3d-usd sim`: a policy drives in a generated scene (closed loop); runs compared.
docs/sim.md. (Beside the sim package, so `lsd3d-usd --help` does not import Gymnasium.)"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lsd3d_usd.errors import InputError
from lsd3d_usd.views.options import DEFAULT_LOD_PX


def _check_out(out: Path, scene: Path) -> None:
    o, sc = out.resolve(), scene.resolve()
    if o == sc or sc in o.parents:
        raise InputError(f"-o {out}: inside the scene folder {scene}; the scene is never written")
    if o.exists() and not o.is_dir():
        raise InputError(f"-o {out}: exists and is not a folder")
    if o.is_dir():
        foreign = [p.name for p in sorted(o.iterdir())
                   if not (p.name.startswith("episode_") or p.name.startswith(".episode_")
                           or p.name in ("run.json",))]
        if foreign:
            raise InputError(f"-o {out}: holds {foreign[0]!r}, not a `sim run` output; "
                             "choose an empty or new folder")


def _env_kwargs(args) -> dict:
    # seeded traffic sizes only when given (a scenario's entities are its whole world)
    traffic = {k: getattr(args, k) for k in ("vehicles", "pedestrians", "cyclists")
               if getattr(args, k) is not None}
    if getattr(args, "scenario", None) is not None:      # sim run --scenario: who the ego is
        traffic.update(ego=args.ego, ego_driver="scenario" if args.policy == "scenario" else "policy")
    return dict(rig=args.rig, lidar=args.lidar, width=args.width, action=args.action,
                hz=args.hz, seconds=args.seconds, route_length=args.route_length,
                ep_reference="none" if args.no_reference else "planner",
                lod_px=0.0 if args.no_lod else args.lod_px,
                outputs=tuple(args.outputs.split(",")) if args.outputs else ("rgb",), **traffic)


def _live(args):
    """The Foxglove live view of --live (None without it: nothing listens)."""
    if not args.live:
        return None
    from lsd3d_usd.sim.live import LiveView
    view = LiveView(args.live_host, args.live_port, getattr(args, "allow_remote", False))
    print(f"live view: ws://{args.live_host}:{view.port} (Foxglove: Open connection -> "
          "Foxglove WebSocket)", flush=True)
    return view


def _run(args) -> int:
    from lsd3d_usd.scene import atomic_write_bytes
    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.episodes import plan_routes
    from lsd3d_usd.sim.policies import POLICIES
    scene, out = Path(args.scene), Path(args.output)
    _check_out(out, scene)
    if args.policy not in POLICIES and ":" not in args.policy:
        raise InputError(f"--policy {args.policy!r}: choose {', '.join(POLICIES)} or MODULE:CALLABLE")
    if getattr(args, "scenario", None) is not None:
        return _run_scenarios(args, scene, out, _env_kwargs(args))
    if args.ego is not None or args.policy == "scenario":
        what = f"--ego {args.ego}" if args.ego is not None else "--policy scenario"
        raise InputError(f"{what}: needs --scenario FILE.xosc|DIR")
    env = DriveEnv(scene, **_env_kwargs(args))
    routes = plan_routes(env.scene.graph, args.route, args.routes, args.episodes,
                         args.route_length, args.seed)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / "run.json", json.dumps({
        "scene": str(scene.resolve()), "policy": args.policy, "seed": args.seed,
        "routes": routes, "argv": sys.argv[1:]}, indent=1).encode())
    live = _live(args)
    failed = []
    try:
        for k, route in enumerate(routes):
            _episode(args, env, k, route, out, failed, live)
    finally:
        env.close()
        if live is not None:
            live.close()
    return _failed(failed)


def _episode(args, env, k, route, out, failed: list, live=None) -> None:
    """Episode k into OUT; a policy's failure is added to ``failed``."""
    from tqdm import tqdm

    from lsd3d_usd.sim.episodes import run_episode, summary_line
    show = not args.no_progress and sys.stderr.isatty()
    bar = tqdm(total=int(round(args.seconds * args.hz)), desc=f"episode {k}", unit="step",
               disable=not show, leave=False)
    res = run_episode(env, args.policy, k, args.seed + k, route, out, video=args.video,
                      mcap=args.mcap, progress=lambda e: bar.update(1), live=live)
    bar.close()
    name = f" [{env.scenario_state()['name']}]" if env.scenario is not None else ""
    print(f"episode {k}{name}: {res.reason}, {res.steps} steps, {summary_line(res.summary)} -> {res.folder}")
    if res.error:
        failed.append(f"episode {k}: {res.error}")


def _failed(failed) -> int:
    if failed:
        raise InputError(f"{len(failed)} episode(s) ended by the policy: {failed[0]} "
                         f"(metrics.json has it; the other episodes are written)")
    return 0


def _run_scenarios(args, scene: Path, out: Path, kw: dict) -> int:
    """--scenario FILE|DIR: an env per scenario file on the scene opened once; --episodes
    episodes of each (default 1), numbered on across the files."""
    from lsd3d_usd.scene import atomic_write_bytes
    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.episodes import MAX_EPISODES
    from lsd3d_usd.sim.scenario.world import scenario_files
    from lsd3d_usd.sim.scene import SimScene
    if args.route is not None or args.routes is not None:
        raise InputError("--scenario: the scenario's Init and routes place the ego; drop --route/--routes")
    files = scenario_files(args.scenario)
    n = args.episodes or 1
    if not 1 <= n * len(files) <= MAX_EPISODES:
        raise InputError(f"--episodes {n} x {len(files)} scenarios: at most {MAX_EPISODES} episodes")
    opened = SimScene(scene)
    live = None
    try:
        envs = [DriveEnv(opened, scenario=str(f), **kw) for f in files]   # every file read first
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(out / "run.json", json.dumps({
            "scene": str(scene.resolve()), "policy": args.policy, "seed": args.seed,
            "scenarios": [str(f.resolve()) for f in files], "episodes_per_scenario": n,
            "argv": sys.argv[1:]}, indent=1).encode())
        live = _live(args)
        failed = []
        k = 0
        for env in envs:
            for _ in range(n):
                _episode(args, env, k, None, out, failed, live)
                k += 1
    finally:
        opened.close()
        if live is not None:
            live.close()
    return _failed(failed)


def _serve(args) -> int:
    import signal
    import threading

    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.service import check_options, serve
    scene = Path(args.scene)
    check_options(args.host, args.allow_remote, args.timeout, args.max_message_mb)
    env = DriveEnv(scene, **_env_kwargs(args))
    live = None
    try:
        live = _live(args)
        server, servicer, port = serve(env, args.host, args.port, args.allow_remote,
                                       args.timeout, args.max_message_mb, live=live)
        print(f"sim serve: {scene} on {args.host}:{port} (Ctrl-C stops)", flush=True)
        done = threading.Event()
        signal.signal(signal.SIGTERM, lambda *a: done.set())
        try:
            while not done.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        servicer.stop()
        server.stop(grace=2.0).wait()
    finally:
        env.close()
        if live is not None:
            live.close()
    return 0


def _report(args) -> int:
    from lsd3d_usd.sim.report import compare, format_table, plot
    runs = compare(args.runs)
    print(format_table(runs))
    if args.png:
        print(f"plot: {plot(runs, args.png)}")
    if args.json:
        from lsd3d_usd.scene import atomic_write_bytes
        atomic_write_bytes(args.json, json.dumps(runs, indent=1).encode())
    return 0


def _env_arguments(r) -> None:
    """The env's settings: the same options for `sim run` and `sim serve`."""
    r.add_argument("--route-length", type=float, default=200.0, metavar="M",
                   help="length of a drawn route in metres (default 200)")
    r.add_argument("--rig", default="nuscenes6",
                   help="sensor rig: a name (nuscenes6, waymo5), a rig FILE.toml, or none "
                        "(world and scores only); default nuscenes6")
    r.add_argument("--lidar", default="auto",
                   help="auto (the rig's own), a preset (hdl32, waymo_top), a FILE.toml, or none")
    r.add_argument("--width", type=int, default=480, help="camera width in pixels (default 480)")
    r.add_argument("--lod-px", type=float, default=DEFAULT_LOD_PX, metavar="PX",
                   help="cameras' level of detail: a merged node stands for its surfels when it "
                        "covers at most PX pixels (default 4; docs/render.md)")
    r.add_argument("--no-lod", action="store_true",
                   help="cameras draw every surfel (full detail, slower)")
    r.add_argument("--outputs", default="rgb",
                   help="camera outputs, comma-separated: rgb,depth,semantic,instance")
    r.add_argument("--action", default="control", choices=("control", "trajectory"),
                   help="control: (acceleration, steering angle); trajectory: 8 waypoints "
                        "0.5 s apart in the ego frame (default control)")
    r.add_argument("--seconds", type=float, default=60.0, help="time limit of an episode (s)")
    r.add_argument("--hz", type=float, default=10.0, help="steps per second (default 10)")
    r.add_argument("--vehicles", type=int, help="vehicles around the ego (default 8; none with --scenario)")
    r.add_argument("--pedestrians", type=int, help="pedestrians (default 12; none with --scenario)")
    r.add_argument("--cyclists", type=int, help="cyclists (default 2; none with --scenario)")
    r.add_argument("--no-reference", action="store_true",
                   help="skip the planner's shadow run that ego progress (EP, PDMS) compares with")
    r.add_argument("--live", action="store_true",
                   help="stream the drive to Foxglove as it happens (foxglove-sdk WebSocket "
                        "server; the topics of --mcap)")
    r.add_argument("--live-host", default="127.0.0.1", help="the live view's address (default "
                                                             "127.0.0.1)")
    r.add_argument("--live-port", type=int, default=8765,
                   help="the live view's port (default 8765; 0: a free one)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="closed loop: a driving policy drives in a scene (docs/sim.md)",
                       description="Closed-loop driving in a generated scene: the ego is driven "
                                   "by a policy, traffic and pedestrians react, every sensor of "
                                   "the rig renders each step, driving scores are kept. "
                                   "Python: gymnasium.make('lsd3d_usd/Drive-v0', scene=...) "
                                   "after `import lsd3d_usd.sim`. See docs/sim.md.")
    s = p.add_subparsers(dest="sim_command", metavar="SUBCOMMAND")
    r = s.add_parser("run", help="run episodes of a policy; one folder per episode",
                     description="Run episodes of a policy in SCENE and write, per episode, "
                                 "metrics.json (per step and per episode), trajectories.csv, "
                                 "birdseye.png, and with --video an MP4 per camera, with --mcap "
                                 "an MCAP log (Foxglove). Ctrl-C keeps every finished episode.")
    r.add_argument("scene", metavar="SCENE", help="a generated scene folder")
    r.add_argument("-o", "--output", required=True, metavar="DIR", help="output folder")
    r.add_argument("--policy", default="planner",
                   help="planner (privileged rule-based driver), constant (constant velocity "
                        "along the start heading), scenario (with --scenario: the storyboard's "
                        "own actions drive the ego, no stack) or MODULE:CALLABLE taking "
                        "(obs, info) and returning an action (default planner)")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--route", metavar="IDS", help="lane ids of the route, comma-separated "
                                                  "(`lsd3d-usd layout lanes SCENE` lists them)")
    g.add_argument("--routes", type=int, metavar="N", help="N episodes on N seeded random routes")
    r.add_argument("--episodes", type=int, metavar="N",
                   help="N episodes (on --route, or a route drawn per episode; default 1)")
    _env_arguments(r)
    r.add_argument("--scenario", metavar="FILE.xosc|DIR",
                   help="play an OpenSCENARIO file, or every .xosc in a folder (an episode each): "
                        "its entities are the world, the ego starts at its Init (docs/sim.md)")
    r.add_argument("--ego", metavar="NAME",
                   help="with --scenario: the entity the ego is (default the first "
                        "ScenarioObject); an error when a scenario has no entity NAME")
    r.add_argument("--seed", type=int, default=0, help="seed of episode 0 (episode k: seed + k)")
    r.add_argument("--video", action="store_true", help="an MP4 per camera per episode")
    r.add_argument("--mcap", action="store_true", help="an MCAP log per episode (Foxglove)")
    r.add_argument("--no-progress", action="store_true", help="no progress bars")
    r.set_defaults(func=_run, compiles_kernels=True)
    v = s.add_parser("serve", help="serve the env over gRPC for a stack in its own process",
                     description="Serve SCENE's closed-loop env over gRPC (the service in "
                                 "lsd3d_usd/sim/proto/sim.proto): a driving stack in another "
                                 "process or venv drives it with lsd3d_usd.sim.remote."
                                 "RemoteDriveEnv. One episode at a time; loopback only unless "
                                 "--allow-remote. docs/sim.md, \"Remote stacks\".")
    v.add_argument("scene", metavar="SCENE", help="a generated scene folder")
    v.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    v.add_argument("--port", type=int, default=50051, help="port (default 50051; 0: a free one)")
    v.add_argument("--allow-remote", action="store_true",
                   help="allow a --host beyond loopback (no authentication, no encryption)")
    v.add_argument("--timeout", type=float, default=60.0,
                   help="a client silent this many seconds loses its episode (default 60)")
    v.add_argument("--max-message-mb", type=float, default=64.0,
                   help="largest reply (an observation) in MB (default 64); requests: 1 MB")
    _env_arguments(v)
    v.set_defaults(func=_serve, compiles_kernels=True)
    q = s.add_parser("report", help="compare runs: mean scores with 95 %% intervals, a plot",
                     description="A table of mean scores over each run's episodes with 95 %% "
                                 "confidence intervals (Student t), and with --png a bar plot.")
    q.add_argument("runs", nargs="+", metavar="DIR", help="`sim run` output folders")
    q.add_argument("--png", metavar="FILE", help="bar plot of the mean scores")
    q.add_argument("--json", metavar="FILE", help="the table as JSON")
    q.set_defaults(func=_report)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
