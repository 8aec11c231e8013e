"""When each sensor of a dataset log fires: cameras at ``camera_hz``, the LiDAR at
``lidar_hz``, keyframes every 1 / ``keyframe_hz`` seconds, all on one grid of ticks whose rate
is the least common multiple of the three (12, 20 and 2 Hz: 60 ticks per second), so every
event falls exactly on a tick and the ego's pose is sampled where each sensor needs it.

A keyframe is a tick where every sensor fires (nuScenes' samples): ``keyframe_hz`` must divide
both sensor rates.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import CLIP_SECONDS, FRAMES

MAX_TICK_HZ = 1200


def _rate(v: float, flag: str) -> Fraction:
    if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
        raise InputError(f"{flag} {v}: must be a positive number")
    f = Fraction(v).limit_denominator(1000)
    if abs(float(f) - v) > 1e-9 * max(1.0, v):
        raise InputError(f"{flag} {v}: give a rate with at most three decimals")
    return f


def _lcm(a: Fraction, b: Fraction) -> Fraction:
    return Fraction(math.lcm(a.numerator, b.numerator), math.gcd(a.denominator, b.denominator))


@dataclass(frozen=True)
class Tick:
    index: int          # tick number
    time: float         # seconds from the log's start
    cameras: bool
    lidar: bool
    keyframe: bool
    camera_frame: int   # index among camera frames (-1 when the cameras do not fire)
    lidar_frame: int    # index among LiDAR sweeps (-1 ...)
    keyframe_index: int  # index among keyframes (-1 ...)


@dataclass(frozen=True)
class Timeline:
    camera_hz: float
    lidar_hz: float | None      # None: no LiDAR
    keyframe_hz: float
    seconds: float

    def __post_init__(self):
        c = _rate(self.camera_hz, "--camera-hz")
        k = _rate(self.keyframe_hz, "--keyframe-hz")
        pairs = [(c, "--camera-hz")]
        if self.lidar_hz is not None:
            pairs.append((_rate(self.lidar_hz, "--lidar-hz"), "--lidar-hz"))
        for r, flag in pairs:
            if (r / k).denominator != 1:
                raise InputError(f"--keyframe-hz {self.keyframe_hz:g} must divide {flag} "
                                 f"{float(r):g} (keyframes are ticks where every sensor fires)")
        if not (math.isfinite(self.seconds) and self.seconds > 0):
            raise InputError(f"--seconds {self.seconds}: must be > 0")
        if float(self.tick_rate) > MAX_TICK_HZ:
            raise InputError(f"--camera-hz / --lidar-hz / --keyframe-hz: their common tick rate "
                             f"{float(self.tick_rate):g} Hz exceeds {MAX_TICK_HZ} Hz")
        CLIP_SECONDS.check(self.seconds, "--seconds")
        FRAMES.check(self.seconds * float(self.tick_rate), "--seconds x the tick rate",
                     what="ticks of a log")

    @property
    def tick_rate(self) -> Fraction:
        r = _lcm(_rate(self.camera_hz, ""), _rate(self.keyframe_hz, ""))
        return r if self.lidar_hz is None else _lcm(r, _rate(self.lidar_hz, ""))

    def _every(self, hz) -> int:
        return int(self.tick_rate / Fraction(hz).limit_denominator(1000))

    @property
    def n_ticks(self) -> int:
        """Ticks in [0, seconds): at least one keyframe."""
        return max(1, math.ceil(self.seconds * self.tick_rate - 1e-9))

    def ticks(self):
        cam, kf = self._every(self.camera_hz), self._every(self.keyframe_hz)
        lid = self._every(self.lidar_hz) if self.lidar_hz is not None else None
        rate = float(self.tick_rate)
        for i in range(self.n_ticks):
            c, k = i % cam == 0, i % kf == 0
            li = lid is not None and i % lid == 0
            if c or li:
                yield Tick(i, i / rate, c, li, k, i // cam if c else -1,
                           i // lid if li else -1, i // kf if k else -1)

    def counts(self) -> dict:
        n = {"camera_frames": 0, "sweeps": 0, "keyframes": 0}
        for t in self.ticks():
            n["camera_frames"] += t.cameras
            n["sweeps"] += t.lidar
            n["keyframes"] += t.keyframe
        return n
