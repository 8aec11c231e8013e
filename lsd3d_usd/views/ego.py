"""Ego trajectories: poses of the ego car over time, along lanes of the layout (IDM on an
empty road, or a constant speed) or from a pose list (poses.json), resampled at frame times."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from lsd3d_usd.actors import traffic as T
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.routes import constant_speed_route
from lsd3d_usd.limits import TRAJECTORY_FILE_BYTES


@dataclass
class EgoTrack:
    """Ego poses at times (seconds): positions (n,3) and rotations (n,3,3) (world-from-ego)."""
    times: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray

    def matrices(self) -> np.ndarray:
        M = np.tile(np.eye(4), (len(self.times), 1, 1))
        M[:, :3, :3], M[:, :3, 3] = self.rotations, self.positions
        return M

    def yaws(self) -> np.ndarray:
        return np.unwrap(np.arctan2(self.rotations[:, 1, 0], self.rotations[:, 0, 0]))

    def at(self, times) -> np.ndarray:
        """(n, 4, 4) world-from-ego at any ``times`` (seconds): positions linear and
        rotations slerped between the samples, extended beyond them with the first / last
        segment's motion (a LiDAR sweep that starts at the last frame ends after it)."""
        t = np.asarray(times, np.float64).reshape(-1)
        T = self.times
        if len(T) == 1:
            M = np.tile(np.eye(4), (len(t), 1, 1))
            M[:, :3, :3], M[:, :3, 3] = self.rotations[0], self.positions[0]
            return M
        k = np.clip(np.searchsorted(T, t, side="right") - 1, 0, len(T) - 2)
        f = (t - T[k]) / (T[k + 1] - T[k])
        pos = self.positions[k] + f[:, None] * (self.positions[k + 1] - self.positions[k])
        rel = Rotation.from_matrix(self.rotations[k]).inv() * Rotation.from_matrix(self.rotations[k + 1])
        rot = Rotation.from_matrix(self.rotations[k]) * Rotation.from_rotvec(rel.as_rotvec() * f[:, None])
        M = np.tile(np.eye(4), (len(t), 1, 1))
        M[:, :3, :3], M[:, :3, 3] = rot.as_matrix(), pos
        return M


def yaw_rotations(yaw) -> np.ndarray:
    y = np.asarray(yaw, np.float64).reshape(-1)
    c, s = np.cos(y), np.sin(y)
    R = np.zeros((len(y), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def frame_times(fps: float, seconds: float) -> np.ndarray:
    if not (fps > 0) or not (seconds > 0):
        raise InputError(f"rig: need --fps > 0 and --seconds > 0, got fps={fps}, seconds={seconds}")
    n = max(1, int(round(seconds * fps)))
    return np.arange(n) / float(fps)


CROSSWALK_REACH = 1.0     # m around a crosswalk where a pedestrian makes the ego wait


def track_from_route(layout, lane_ids, times, speed: float | None = None, seed: int = 0,
                     pedestrians=None) -> EgoTrack:
    """Drive ``lane_ids`` from the start of the first lane: at constant ``speed`` (m/s), or
    (default) with IDM on an empty road (accelerates towards the lanes' speed limits, yields at
    junctions, stops at the end of the route). ``pedestrians(t)`` -> (n, 2) xy of the scene's
    pedestrians at t seconds: with IDM the ego stops before every crosswalk with one on it
    (or within CROSSWALK_REACH of it)."""
    times = np.asarray(times, np.float64)
    if speed is not None:
        pos, yaw = constant_speed_route(layout, lane_ids, speed, times)
        return EgoTrack(times, pos, yaw_rotations(yaw))
    fps = 1.0 / (times[1] - times[0]) if len(times) > 1 else 10.0
    sim = T.Simulation(layout, seed)
    sim.add_ego(sim.g.route_indices(list(lane_ids)), 4.8)
    on_step = None
    if pedestrians is not None and layout.crosswalks:
        import shapely

        from lsd3d_usd.proxy.planar import area_from_points
        polys = [area_from_points(c.polygon) for c in layout.crosswalks]
        sim.g.set_crosswalks(polys)
        reach = [p.buffer(CROSSWALK_REACH) for p in polys]
        clock = [0.0]

        def on_step(s, dt):
            xy = np.asarray(pedestrians(clock[0]), np.float64).reshape(-1, 2)
            s.occupied = {k for k, r in enumerate(reach)
                          if len(xy) and shapely.contains_xy(r, xy[:, 0], xy[:, 1]).any()}
            clock[0] += dt
    run = sim.run(float(times[-1]), fps, on_step=on_step)
    return EgoTrack(times, run.position[0][:len(times)], yaw_rotations(run.yaw[0][:len(times)]))


def load_trajectory(path) -> EgoTrack:
    """poses.json: a list (or {"poses": [...]}) of {"t", "x", "y", "z", "yaw"} with yaw in
    degrees (counter-clockwise from +X, z defaults to 0) or {"t", "matrix"} with a 4x4
    world-from-ego matrix (row-major nested lists, translation in the last column)."""
    p = Path(path)
    if p.exists() and not p.is_file():
        raise InputError(f"--trajectory {path}: not a regular file")
    if p.is_file():
        TRAJECTORY_FILE_BYTES.check(p.stat().st_size, f"--trajectory {path}")
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise InputError(f"--trajectory {path}: no such file") from None
    except (OSError, ValueError) as e:
        raise InputError(f"--trajectory {path}: not valid JSON ({str(e)[:100]})") from None
    except RecursionError:
        raise InputError(f"--trajectory {path}: lists or objects nested too deeply") from None
    poses = data.get("poses") if isinstance(data, dict) else data
    if not isinstance(poses, list) or not poses:
        raise InputError(f"--trajectory {path}: expected a non-empty list of poses (or {{\"poses\": [...]}})")
    T, P, R = [], [], []
    for k, q in enumerate(poses):
        where = f"--trajectory {path}: pose {k}"
        if not isinstance(q, dict) or "t" not in q:
            raise InputError(f"{where}: needs \"t\" and either x/y/yaw or matrix")
        try:
            t = float(q["t"])
            if not math.isfinite(t):
                raise ValueError(f"t must be a finite number, got {q['t']!r}")
            if "matrix" in q:
                M = np.asarray(q["matrix"], np.float64)
                if M.shape != (4, 4) or not np.all(np.isfinite(M)):
                    raise ValueError("matrix must be 4x4 and finite")
                U, _, Vt = np.linalg.svd(M[:3, :3])
                Rk = U @ Vt
                if np.linalg.det(Rk) < 0:
                    raise ValueError("matrix is mirrored")
                P.append(M[:3, 3])
                R.append(Rk)
            else:
                x, y, z = float(q["x"]), float(q["y"]), float(q.get("z", 0.0))
                yaw = float(q["yaw"])
                if not all(map(math.isfinite, (x, y, z, yaw))):
                    raise ValueError("x, y, z and yaw must be finite numbers")
                P.append(np.array([x, y, z]))
                R.append(yaw_rotations(np.radians(yaw))[0])
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"{where}: {e}") from None
        T.append(t)
    T = np.asarray(T)
    if not np.all(np.isfinite(T)) or np.any(np.diff(T) <= 0):
        raise InputError(f"--trajectory {path}: times \"t\" must be finite and strictly increasing")
    return EgoTrack(T, np.asarray(P), np.asarray(R))


def resample(track: EgoTrack, times) -> tuple[EgoTrack, int]:
    """The track at ``times`` (linear positions, slerped rotations); times outside the track
    hold its first/last pose. Returns (track, number of clamped times)."""
    times = np.asarray(times, np.float64)
    tc = np.clip(times, track.times[0], track.times[-1])
    clamped = int(np.sum(tc != times))
    pos = np.stack([np.interp(tc, track.times, track.positions[:, k]) for k in range(3)], 1)
    if len(track.times) == 1:
        rot = np.repeat(track.rotations[:1], len(times), 0)
    else:
        rot = Slerp(track.times, Rotation.from_matrix(track.rotations))(tc).as_matrix()
    return EgoTrack(times, pos, rot), clamped
