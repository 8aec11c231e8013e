"""The ground beyond the scene: a horizontal plane at the scene's ground height, behind every
surfel, so a view from above sees the land go on to a horizon in the colour of the scene's own
ground instead of the scene ending in a square over the env map's ground half.

It is part of the background, not of the scene's geometry: every consumer that draws the env
map behind the surfels (the prior's targets, GGDS and eval renders, rig views, the usdview
plugin, the browser viewer) draws it the same way, so targets and renders agree pixel for pixel
and nothing is trained on it. A ray below the horizon from above the plane meets it after
t = (o_z - height) / -d_z metres. There the env map's ground half is re-coloured from the map's
own ground (its radiance straight down, ``ground``) to the plane's, faded by the scene's fog
T = exp(-density * t):

    L = max(env(d) + (radiance - ground) * T, 0)

The env map's horizon haze stays where the map has it (a lane camera sees the horizon as
before), and at the horizon (t -> inf) the plane is the env map itself. ``radiance`` is a
Lambertian ground of the scene's ground albedo lit by the env's sky and sun (no shadows), in
the env map's units.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lsd3d_usd.env.sh import eval_sh_irradiance

# Rays this close to horizontal meet the plane beyond any fog's reach: the env map alone.
MIN_DOWN = 1e-6     # the same bound in env.lookup's kernel and the viewer's env shader


@dataclass(frozen=True)
class FarField:
    height: float                 # world z of the plane (m)
    radiance: tuple               # (3,) radiance of the plane, in the env map's units
    fog_density: float = 0.0      # extinction (1/m) towards env(d)
    ground: tuple = (0.0, 0.0, 0.0)   # the env map's own ground radiance (straight down)

    def scaled(self, gain) -> "FarField":
        """The same plane with its radiances multiplied by ``gain`` (a scalar or (3,))."""
        g = np.asarray(gain, np.float64)
        return FarField(self.height, _tuple(np.asarray(self.radiance) * g), self.fog_density,
                        _tuple(np.asarray(self.ground) * g))

    def over(self, lookup) -> "FarField":
        """The plane over the env map ``lookup`` ((N, 3) directions -> (N, 3) radiance in the
        plane's units): its ground is the map's radiance straight down."""
        down = np.asarray(lookup(np.array([[0.0, 0.0, -1.0]], np.float32)), np.float64)
        return FarField(self.height, self.radiance, self.fog_density, _tuple(down.reshape(-1, 3)[0]))

    def apply(self, background: np.ndarray, origin, dirs: np.ndarray) -> np.ndarray:
        """``background`` (..., 3): the env map along ``dirs`` (..., 3, unit) from ``origin``
        (3,). Returns a new float32 array with the plane where the rays meet it."""
        bg = np.array(background, np.float32, copy=True)
        oz = float(np.asarray(origin, np.float64).reshape(3)[2]) - float(self.height)
        if oz <= 0.0:               # at or below the plane: it is never seen from underneath
            return bg
        dz = np.asarray(dirs, np.float32)[..., 2]
        down = dz < -MIN_DOWN
        if not down.any():
            return bg
        t = oz / -dz[down].astype(np.float64)
        T = np.exp(-max(float(self.fog_density), 0.0) * t).astype(np.float32)[:, None]
        shift = (np.asarray(self.radiance, np.float64) - np.asarray(self.ground, np.float64))
        bg[down] = np.maximum(bg[down] + shift.astype(np.float32)[None, :] * T, 0.0)
        return bg


def _tuple(a) -> tuple:
    return tuple(float(v) for v in np.asarray(a, np.float64).reshape(3))


def ground_radiance(albedo, sh_irradiance, sun_direction, sun_illuminance) -> np.ndarray:
    """(3,) radiance of a level Lambertian ground of ``albedo`` (3,) under the sky's irradiance
    SH (9, 3) and the sun (unit direction, (3,) illuminance at normal incidence), in the
    units of the SH (the env map's)."""
    sky = eval_sh_irradiance(np.asarray(sh_irradiance, np.float64), np.array([[0.0, 0.0, 1.0]]))[0]
    s = np.asarray(sun_direction, np.float64)
    n = float(np.linalg.norm(s))
    cos = max(float(s[2]) / n, 0.0) if n > 0 else 0.0
    E = np.clip(sky, 0.0, None) + np.asarray(sun_illuminance, np.float64) * cos
    return np.asarray(albedo, np.float64) * E / math.pi

