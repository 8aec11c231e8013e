"""`sim run`: episodes of a policy driving a scene, each written to its own folder.

OUT/episode_<k>/ holds ``metrics.json`` (settings, route, seed, reason it ended, per-step
scores and the episode's), ``trajectories.csv`` (the ego and every agent at every step; its ``point`` column names the
point a row reports: ``rear_axle`` the ego's rear axle centre (the ego frame's origin),
``reference`` a scenario entity's OpenSCENARIO reference point (a vehicle's rear axle
centre), ``box_centre`` a traffic agent's bounding box centre),
``birdseye.png`` (route, ego path, agents' paths, infractions marked), with ``video`` an MP4
per camera, and with ``mcap`` an MCAP log written by the datasets' MCAP writer. An episode is
written to a hidden partial folder and renamed when complete, so Ctrl-C leaves every finished
episode whole and no half episode behind.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import shutil
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.routes import parse_route, random_routes
from lsd3d_usd.scene import atomic_write_bytes
from lsd3d_usd.sim.metrics import AgentBox

MAX_EPISODES = 1000


@dataclass
class EpisodeResult:
    index: int
    folder: Path | None
    seed: int
    route: list
    reason: str
    steps: int
    summary: dict
    error: str | None = None
    seconds: float = 0.0
    files: dict = field(default_factory=dict)


def plan_routes(graph, route: str | None, routes: int | None, episodes: int | None,
                length: float, seed: int) -> list[list[str] | None]:
    """The route of each episode: ``route`` (lane ids) for every episode, or ``routes`` seeded
    random routes, one episode each; None: the env draws one per episode from its seed."""
    if route is not None and routes is not None:
        raise InputError("--route and --routes exclude each other")
    n = routes if routes is not None else (episodes or 1)
    if not isinstance(n, int) or not 1 <= n <= MAX_EPISODES:
        raise InputError(f"--routes/--episodes {n!r}: a whole number from 1 to {MAX_EPISODES}")
    if route is not None:
        ids = parse_route(route)
        graph.route(ids)                  # one clear error before anything runs
        return [ids] * n
    if routes is not None:
        return random_routes(graph, routes, length, seed)
    return [None] * n


class _Recorder:
    """What an episode writes as it goes: per-step scores, trajectories, camera frames."""

    def __init__(self, env, video: bool):
        self.env = env
        self.steps: list[dict] = []
        self.rows: list[tuple] = []
        self.video = video
        self.frames: dict[str, list[bytes]] = {}
        self.ego_path: list[tuple] = []
        self.agent_paths: dict[str, list] = {}
        self.events: list[dict] = []

    def record(self, obs, info, action=None, reward=0.0) -> None:
        env = self.env
        e = env.ego
        sc = info["scores"]
        self.steps.append({"t": info["t"], "reward": reward,
                           "action": None if action is None else np.asarray(action).round(5).tolist(),
                           **sc})
        if "scenario" in info:          # the storyboard's state at this step
            self.steps[-1]["scenario"] = {k: info["scenario"][k]
                                          for k in ("stop_trigger_fired", "storyboard_completed")}
        self.rows.append(("ego", "ego", info["t"], e.x, e.y, e.z, e.yaw, e.v, "rear_axle"))
        self.ego_path.append((e.x, e.y))
        refs = env.world.reference_poses() if hasattr(env.world, "reference_poses") else {}
        for b in map(AgentBox.from_json, info["boxes"]):
            if b.id.startswith("parked:"):
                continue
            if b.id in refs:
                x, y, z, yaw, v = refs[b.id]
                self.rows.append((b.id, b.kind, info["t"], x, y, z, yaw, v, "reference"))
            else:
                v = float(np.hypot(*b.velocity))
                self.rows.append((b.id, b.kind, info["t"], b.center[0], b.center[1],
                                  float("nan"), b.yaw, v, "box_centre"))
            self.agent_paths.setdefault(b.id, []).append((b.center[0], b.center[1], b.kind))
        for key, what in (("new_collisions", "collision"),):
            for c in sc.get(key) or []:
                self.events.append({"t": info["t"], "kind": what, "with": c, "xy": [e.x, e.y]})
        if not sc.get("dac", 1):
            self.events.append({"t": info["t"], "kind": "off_road", "xy": [e.x, e.y]})
        if self.video and "cameras" in obs:
            from PIL import Image
            for name, d in obs["cameras"].items():
                buf = io.BytesIO()
                Image.fromarray(d["rgb"]).save(buf, format="PNG", compress_level=1)
                self.frames.setdefault(name, []).append(buf.getvalue())

    def write(self, folder: Path, meta: dict, summary: dict) -> dict:
        files = {}
        data = {**meta, "summary": summary, "events": self.events, "steps": self.steps}
        files["metrics"] = atomic_write_bytes(folder / "metrics.json",
                                              json.dumps(_jsonable(data), indent=1).encode())
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["id", "kind", "t", "x", "y", "z", "yaw", "speed", "point"])
        for r in self.rows:
            w.writerow([r[0], r[1], f"{r[2]:.3f}"] + [("" if not math.isfinite(v) else f"{v:.4f}")
                                                     for v in r[3:-1]] + [r[-1]])
        files["trajectories"] = atomic_write_bytes(folder / "trajectories.csv", buf.getvalue().encode())
        files["birdseye"] = self._birdseye(folder / "birdseye.png", meta)
        if self.frames:
            from PIL import Image

            from lsd3d_usd.views.video import write_mp4

            class Decoded:
                """The episode's PNG frames decoded as they are read, as often as read (so
                write_mp4 can encode them again when ffmpeg ends early)."""
                def __init__(self, frames):
                    self.frames = frames

                def __iter__(self):
                    for b in self.frames:
                        yield np.asarray(Image.open(io.BytesIO(b)).convert("RGB"))
            for name, frames in self.frames.items():
                files[f"video:{name}"] = write_mp4(folder / f"{name}.mp4", Decoded(frames),
                                                   self.env.settings.hz)
        return {k: str(Path(v).name) for k, v in files.items()}

    def _birdseye(self, path: Path, meta: dict) -> Path:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from lsd3d_usd.sim.birdseye import _polygons
        env = self.env
        pts, _ = env.route.polyline()
        ego = np.array(self.ego_path)
        lo = np.vstack([pts[:, :2], ego]).min(0) - 25
        hi = np.vstack([pts[:, :2], ego]).max(0) + 25
        w, h = hi - lo
        fig, ax = plt.subplots(figsize=(9, float(np.clip(9 * h / max(w, 1.0), 3.0, 12.0)) + 0.6),
                               dpi=110)
        for poly in _polygons(env.scene.drivable):
            x, y = poly.exterior.xy
            ax.fill(x, y, color="0.82", zorder=0, lw=0)
            for hole in poly.interiors:
                hx, hy = hole.xy
                ax.fill(hx, hy, color="white", zorder=0, lw=0)
        for b in env.scene.layout.buildings:
            fp = np.vstack([b.footprint, b.footprint[:1]])
            ax.fill(fp[:, 0], fp[:, 1], color="#d9c9b0", zorder=1, lw=0)
        ax.plot(pts[:, 0], pts[:, 1], color="tab:green", lw=6, alpha=0.35, label="route", zorder=2)
        colours = {"vehicle": "tab:blue", "cyclist": "tab:orange", "pedestrian": "tab:pink"}
        for trail in self.agent_paths.values():
            p = np.array([q[:2] for q in trail], float)
            jump = np.flatnonzero(np.hypot(*np.diff(p, axis=0).T) > 10.0)   # left and came back
            p = np.insert(p, jump + 1, np.nan, axis=0)
            c = colours.get(trail[0][2], "0.4")
            ax.plot(p[:, 0], p[:, 1], color=c, lw=0.8, alpha=0.7, zorder=3)
            ax.plot(p[-1, 0], p[-1, 1], "o", ms=2.5, color=c, zorder=3)
        ax.plot(ego[:, 0], ego[:, 1], color="tab:red", lw=2, label="ego", zorder=4)
        ax.plot(ego[0, 0], ego[0, 1], "s", color="tab:red", ms=6, zorder=5)
        for ev in self.events:
            ax.plot(ev["xy"][0], ev["xy"][1], "x" if ev["kind"] == "collision" else "^",
                    color="black", ms=10, mew=2, zorder=6)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        s = meta["summary_line"]
        ax.set_title(f"episode {meta['episode']}: {meta['reason']} - {s}", fontsize=8)
        ax.legend(loc="upper right", fontsize=7)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        plt.close(fig)
        return atomic_write_bytes(path, buf.getvalue())


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, Path):
        return str(x)
    return x


def summary_line(s: dict) -> str:
    def f(k):
        v = s.get(k)
        return "-" if v is None else f"{v:.2f}"
    return f"RC {f('rc')} DS {f('driving_score')} PDMS {f('pdms')} NC {f('nc')} DAC {f('dac')}"


def run_episode(env, policy_spec: str, index: int, seed: int, route, out: Path,
                video: bool = False, mcap: bool = False, progress=None, live=None) -> EpisodeResult:
    """One episode into OUT/episode_<index>/ (see the module doc); ``live``: a sim.live
    LiveView that streams it too."""
    from lsd3d_usd.sim.policies import load_policy
    final = out / f"episode_{index:03d}"
    part = out / f".episode_{index:03d}.partial"
    if part.exists():
        shutil.rmtree(part)
    part.mkdir(parents=True)
    t0 = time.perf_counter()
    try:
        obs, info = env.reset(seed=seed, options={"route": route} if route else None)
        policy = load_policy(policy_spec, env)
        rec = _Recorder(env, video)
        rec.record(obs, info)
        writer = None
        if mcap:
            from lsd3d_usd.sim.record import EpisodeMcap
            writer = EpisodeMcap(part, env, index)
            writer.write(obs, info)
        stream = live.episode(env, index) if live is not None else None
        if stream is not None:
            stream.write(obs, info)
        error = None
        reason = None
        while True:
            try:
                action = policy(obs, info)
            except Exception as e:          # the stack under test failed: end the episode
                error = f"policy {policy_spec!r} raised {type(e).__name__}: {e}"
                reason = "policy_error"
                rec.steps.append({"t": info["t"], "error": error,
                                  "traceback": traceback.format_exc(limit=5)})
                break
            obs, reward, term, trunc, info = env.step(action)
            rec.record(obs, info, action, reward)
            if writer is not None:
                writer.write(obs, info)
            if stream is not None:
                stream.write(obs, info)
            if progress is not None:
                progress(env)
            if term or trunc:
                reason = info.get("reason")
                break
        summary = env.episode_summary()
        files = {}
        if writer is not None:
            files["mcap"] = writer.close()
        meta = {"episode": index, "seed": seed, "route": env.route.ids,
                "route_length_m": env.route.length, "policy": policy_spec, "reason": reason,
                "error": error, "steps": env.k, "clipped_actions": env.clipped,
                "settings": {k: v for k, v in asdict(env.settings).items()},
                "summary_line": summary_line(summary)}
        if getattr(env, "scenario", None) is not None:
            meta["scenario"] = env.scenario_state()
        files.update(rec.write(part, meta, summary))
        if final.exists():
            shutil.rmtree(final)
        os.replace(part, final)
        return EpisodeResult(index, final, seed, env.route.ids, reason, env.k, summary, error,
                             time.perf_counter() - t0, files)
    except BaseException:
        shutil.rmtree(part, ignore_errors=True)
        raise
