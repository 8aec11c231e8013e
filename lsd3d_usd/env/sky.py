"""Analytic sky: Preetham et al. (1999) clear sky, CIE overcast sky, procedural clouds,
twilight, night (moon, dark-sky floor), sun and moon disks, a Lambertian ground hemisphere
and horizon haze/fog.

Units: scene-linear luminance in kcd/m^2 (1.0 in the map = 1000 cd/m^2), colour space
linear Rec.709 internally (converted at the end when ACEScg is asked for).

What is physical and what is a look:
* Preetham: Perez distribution with the paper's turbidity coefficients and zenith
  luminance / chromaticity fits; valid for the sun above the horizon.
* Sun: a 5778 K black body at 1 AU, attenuated by Rayleigh and Angstrom aerosol optical
  depth (Preetham's turbidity beta) along the Kasten-Young air mass, integrated against the
  CIE 1931 observer: its colour and illuminance.
* CIE overcast: L(theta) = Lz (1 + 2 cos theta) / 3, Lz from Krochmann (8.6 sin h + 0.123 kcd/m^2).
* Twilight (sun below the horizon) is an approximation: the day sky at the horizon fading
  exponentially with the sun's depression (about a factor 150 per 6 deg, as measured
  illuminance does), bluer zenith, and an orange glow toward the sun's azimuth.
* The sun disk is clamped so the half-float EXR can hold it; the clipped part of the sun's
  illuminance is reported (`SkyModel.sun_residual_illuminance`) so a DistantLight carries it.
"""
from __future__ import annotations

import math
import time

import numpy as np

from lsd3d_usd.env import colorspace as cs
from lsd3d_usd.env.mapping import check_resolution, pixel_directions, pixel_solid_angles
from lsd3d_usd.env.params import EnvParams
from lsd3d_usd.env.sun import azel_to_direction, lunar_position, solar_position

SUN_RADIUS = math.radians(0.2665)
MOON_RADIUS = math.radians(0.259)
DISK_PEAK_MAX = 60000.0          # below the half-float max (65504)
NIGHT_FLOOR = 2.0e-6             # kcd/m^2: a dark rural sky ~2 mcd/m^2 (airglow + starlight)
NIGHT_TINT = np.array([0.80, 0.90, 1.15], np.float32)
FULL_MOON_LUMINANCE = 2.5        # kcd/m^2
MOON_SUN_RATIO = 2.5e-6          # full-moon / sun illuminance
LIMB_U = 0.6                     # linear limb darkening coefficient (visible band)

# Preetham et al. 1999, Appendix: Perez coefficients as (slope, offset) in turbidity T.
_PEREZ_Y = np.array([[0.1787, -1.4630], [-0.3554, 0.4275], [-0.0227, 5.3251],
                     [0.1206, -2.5771], [-0.0670, 0.3703]])
_PEREZ_x = np.array([[-0.0193, -0.2592], [-0.0665, 0.0008], [-0.0004, 0.2125],
                     [-0.0641, -0.8989], [-0.0033, 0.0452]])
_PEREZ_y = np.array([[-0.0167, -0.2608], [-0.0950, 0.0092], [-0.0079, 0.2102],
                     [-0.0441, -1.6537], [-0.0109, 0.0529]])
# zenith chromaticity: [T^2, T, 1] @ M @ [theta^3, theta^2, theta, 1]
_ZEN_x = np.array([[0.00166, -0.00375, 0.00209, 0.0], [-0.02903, 0.06377, -0.03202, 0.00394],
                   [0.11693, -0.21196, 0.06052, 0.25886]])
_ZEN_y = np.array([[0.00275, -0.00610, 0.00317, 0.0], [-0.04214, 0.08970, -0.04153, 0.00516],
                   [0.15346, -0.26756, 0.06670, 0.26688]])


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def preetham_zenith(theta_s: float, T: float) -> tuple[float, float, float]:
    """Zenith (Y kcd/m^2, x, y) for sun zenith angle theta_s (rad) and turbidity T."""
    chi = (4.0 / 9.0 - T / 120.0) * (math.pi - 2.0 * theta_s)
    Yz = (4.0453 * T - 4.9710) * math.tan(chi) - 0.2155 * T + 2.4192
    tv = np.array([theta_s ** 3, theta_s ** 2, theta_s, 1.0])
    Tv = np.array([T * T, T, 1.0])
    return max(Yz, 1e-3), float(Tv @ _ZEN_x @ tv), float(Tv @ _ZEN_y @ tv)


def _perez(coef, T, cos_theta, gamma, cos_gamma):
    A, B, C, D, E = (float(a * T + b) for a, b in coef)
    return (1.0 + A * np.exp(B / cos_theta)) * (1.0 + C * np.exp(D * gamma) + E * cos_gamma ** 2)


def preetham_xyY(dirs: np.ndarray, sun: np.ndarray, T: float):
    """Preetham sky (Y kcd/m^2, x, y) for upper-hemisphere dirs (N,3) and a sun at or above
    the horizon (unit vector)."""
    theta_s = math.acos(min(1.0, max(0.0, float(sun[2]))))
    cos_t = np.maximum(dirs[:, 2], 1e-3)
    cos_g = np.clip(dirs @ sun.astype(dirs.dtype), -1.0, 1.0)
    gamma = np.arccos(cos_g)
    Yz, xz, yz = preetham_zenith(theta_s, T)
    one = np.ones(1, dirs.dtype)
    out = []
    for coef, zval in ((_PEREZ_Y, Yz), (_PEREZ_x, xz), (_PEREZ_y, yz)):
        norm = _perez(coef, T, one, np.array([theta_s]), np.array([math.cos(theta_s)]))[0]
        out.append(np.float32(zval / norm) * _perez(coef, T, cos_t, gamma, cos_g))
    return out[0], out[1], out[2]


def air_mass(elev_deg: float) -> float:
    """Kasten & Young (1989) relative optical air mass."""
    h = max(elev_deg, 0.0)
    return 1.0 / (math.sin(math.radians(h)) + 0.50572 * (h + 6.07995) ** -1.6364)


def sun_illuminance_rgb(elev_deg: float, turbidity: float) -> np.ndarray:
    """Direct-normal sun illuminance as linear Rec.709 (Y = lux) after the atmosphere."""
    lam_nm, cmf = cs.cmfs_1931()
    lam = lam_nm * 1e-9
    h, c, k, Tsun = 6.62607015e-34, 2.99792458e8, 1.380649e-23, 5778.0
    B = 2 * h * c * c / lam ** 5 / np.expm1(h * c / (lam * k * Tsun))     # W / m^2 / sr / m
    E = math.pi * B * (6.957e8 / 1.495978707e11) ** 2 * 1e-9               # W / m^2 / nm
    lum = lam_nm * 1e-3
    beta = 0.04608 * turbidity - 0.04586
    tau = 0.008735 * lum ** -4.08 + beta * lum ** -1.3
    Et = E * np.exp(-air_mass(elev_deg) * tau)
    xyz = 683.0 * (Et @ cmf)                                                # lux, 1 nm steps
    return cs.xyz_to_rec709() @ xyz


def _luminance(rgb) -> np.ndarray:
    rgb = np.asarray(rgb)
    return 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]


def _chroma(rgb) -> np.ndarray:
    rgb = np.maximum(np.asarray(rgb, np.float64), 0.0)
    return rgb / max(float(_luminance(rgb)), 1e-12)


class CloudNoise:
    """Deterministic fractal value noise over a cloud plane (seeded, periodic lattice)."""

    def __init__(self, seed: int, octaves: int = 5, size: int = 128):
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xC10D]))
        self.size = size
        self.octaves = octaves
        self.lattice = rng.random((size, size), dtype=np.float32)
        self.offsets = rng.random((octaves, 2)).astype(np.float32) * size
        self.rotations = rng.random(octaves) * 2 * math.pi

    def plane_coords(self, dirs: np.ndarray) -> np.ndarray:
        # cloud plane: perspective projection (d.xy / d.z), damped near the horizon
        s = 1.0 / (np.maximum(dirs[:, 2], 0.0) + 0.12)
        return dirs[:, :2] * s[:, None] * np.float32(1.6)

    def __call__(self, dirs: np.ndarray) -> np.ndarray:
        p = np.ascontiguousarray(self.plane_coords(dirs), dtype=np.float32)
        rot = np.stack([np.cos(self.rotations), np.sin(self.rotations)], -1).astype(np.float32)
        return _fbm(p, self.lattice, self.offsets, rot)


def _fbm_py(p, lattice, offsets, rot):
    """Fractal value noise (smoothstep-interpolated lattice, octaves halving in amplitude)."""
    n = lattice.shape[0]
    total = np.zeros(p.shape[0], np.float32)
    amp, freq, norm = 1.0, 1.0, 0.0
    for o in range(offsets.shape[0]):
        c, s = rot[o, 0], rot[o, 1]
        for k in range(p.shape[0]):
            x = (c * p[k, 0] - s * p[k, 1]) * freq + offsets[o, 0]
            y = (s * p[k, 0] + c * p[k, 1]) * freq + offsets[o, 1]
            x0, y0 = math.floor(x), math.floor(y)
            fx, fy = x - x0, y - y0
            fx = fx * fx * (3 - 2 * fx)
            fy = fy * fy * (3 - 2 * fy)
            i0, j0 = int(x0) % n, int(y0) % n
            i1, j1 = (i0 + 1) % n, (j0 + 1) % n
            v = ((lattice[j0, i0] * (1 - fx) + lattice[j0, i1] * fx) * (1 - fy)
                 + (lattice[j1, i0] * (1 - fx) + lattice[j1, i1] * fx) * fy)
            total[k] += amp * v
        norm += amp
        amp *= 0.5
        freq *= 2.0
    return total / np.float32(norm)


try:  # numba: ~20x the numpy version of the same loop; the plain one is the fallback
    import numba as _nb
    _fbm = _nb.njit(cache=True, fastmath=True)(_fbm_py)
except ImportError:  # pragma: no cover
    _fbm = _fbm_py


class SkyModel:
    """All per-environment constants, then `radiance(dirs)` evaluates the sky anywhere."""

    def __init__(self, params: EnvParams):
        p = params.resolved()
        self.params = p
        self.timings: dict[str, float] = {}
        self.sun_map_fraction = 0.0
        t0 = time.perf_counter()
        sp = solar_position(p.when, p.latitude, p.longitude)
        self.sun_elevation = sp.elevation
        self.sun_azimuth = sp.azimuth
        self.sun_dir = azel_to_direction(sp.azimuth, sp.elevation, p.north_deg)
        self.sun_dir_eff = azel_to_direction(sp.azimuth, max(sp.elevation, 0.0), p.north_deg)
        mp = lunar_position(p.when, p.latitude, p.longitude)
        self.moon_elevation = mp["elevation"]
        self.moon_phase = mp["illuminated_fraction"]
        self.moon_dir = azel_to_direction(mp["azimuth"], mp["elevation"], p.north_deg)
        self.timings["sun+moon position"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        T = float(p.turbidity)
        e = self.sun_elevation
        self.sun_up = e > -SUN_RADIUS * 180 / math.pi
        # direct-normal sun illuminance (lux, rgb); fades out as the disk sets
        self.sun_rgb_lux = (sun_illuminance_rgb(e, T) * float(_smoothstep(-0.5, 0.5, e))
                            if self.sun_up else np.zeros(3))
        self.sun_chroma = _chroma(sun_illuminance_rgb(max(e, 0.5), T))
        self.twilight = 1.0 if e >= 0 else math.exp(e / 1.2)
        self.low_sun = 0.3 + 0.7 * float(_smoothstep(0.0, 12.0, e))
        self.zenith_blue = float(_smoothstep(4.0, -6.0, e))
        self.glow = float(_smoothstep(10.0, 1.0, e)) * (1.0 if e >= 0 else math.exp(e / 2.0))
        Yz_h, _, _ = preetham_zenith(math.acos(max(0.0, float(self.sun_dir_eff[2]))), T)
        self.glow_level = 1.2 * Yz_h * self.low_sun
        # CIE overcast zenith luminance (Krochmann), twilight-faded
        self.overcast_Lz = (8.6 * math.sin(math.radians(max(e, 0.0))) + 0.123) * self.twilight \
            * p.overcast_gain
        # overcast colour: daylight ~6800 K, warmed a little by a low sun (not at night)
        warm = 0.2 * float(_smoothstep(15.0, 2.0, e) * _smoothstep(-6.0, -1.0, e))
        self.cloud_sun_chroma = _chroma(sun_illuminance_rgb(max(e, 6.0), T))
        self.overcast_rgb = _chroma((1 - warm) * np.array(cs.daylight_rgb(6800.0))
                                    + warm * self.cloud_sun_chroma)
        self.moon_up = self.moon_elevation > 0.0
        self.moon_k = MOON_SUN_RATIO * self.moon_phase ** 1.5 * float(self.moon_up)
        self.coverage = float(p.cloud_coverage)
        self.overcast = self.coverage >= 0.999
        self.clouds = CloudNoise(p.seed) if self.coverage > 0 else None
        self.cloud_threshold = self._coverage_threshold() if self.clouds is not None else 1.0
        # horizon haze: stronger and reaching higher as the fog extinction grows
        fs = min(0.97, max(0.08, 1.0 - math.exp(-float(p.fog_density) * 4000.0)))
        self.fog_strength = fs
        self.fog_width = 0.03 + 2.0 * (1.0 - math.exp(-float(p.fog_density) * 300.0))
        self.timings["constants"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        self._init_ground_and_fog()
        self.timings["ground+fog integrals"] = time.perf_counter() - t0

    # ------------------------------------------------------------------ helpers
    def _coverage_threshold(self) -> float:
        """Noise level such that `coverage` of the upper hemisphere (by solid angle) is cloud."""
        rng = np.random.default_rng(12345)
        z = rng.random(8192)
        phi = rng.random(8192) * 2 * math.pi
        r = np.sqrt(1 - z * z)
        d = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1).astype(np.float32)
        return float(np.quantile(self.clouds(d), 1.0 - self.coverage))

    def cloud_alpha(self, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self.clouds(dirs)
        if self.overcast:
            return np.ones(len(dirs), np.float32), n
        w = 0.07
        a = _smoothstep(self.cloud_threshold - w, self.cloud_threshold + w, n).astype(np.float32)
        return a, n

    def _init_ground_and_fog(self):
        W, H = 96, 48
        d = pixel_directions(W, H)[: H // 2].reshape(-1, 3)
        L = self._sky(d)
        dw = np.repeat(pixel_solid_angles(W, H)[: H // 2], W)
        self.sky_horizontal_illuminance = (L * (d[:, 2] * dw)[:, None]).sum(0)   # kcd (rgb)
        sun_vis = 0.0
        if self.sun_up and not self.overcast:
            sun_vis = 1.0 if self.clouds is None else 1.0 - float(self.cloud_alpha(
                self.sun_dir_eff[None].astype(np.float32))[0][0])
        self.sun_visibility = sun_vis
        self.sun_direct_lux = self.sun_rgb_lux * sun_vis                    # normal incidence
        E = self.sky_horizontal_illuminance + self.sun_direct_lux / 1000.0 * max(
            0.0, float(self.sun_dir[2]))
        albedo = np.array(self.params.ground_albedo)
        self.ground_rgb = (albedo * E / math.pi).astype(np.float32)
        # fog colour: the sky just above the horizon, averaged over azimuth
        phi = np.linspace(0, 2 * math.pi, 64, endpoint=False)
        hz = np.stack([np.cos(phi) * 0.9995, np.sin(phi) * 0.9995, np.full(64, 0.03)], -1)
        self.fog_rgb = self._sky(hz.astype(np.float32)).mean(0).astype(np.float32)

    # ------------------------------------------------------------------ sky (upper hemisphere)
    def _sky(self, d: np.ndarray) -> np.ndarray:
        p = self.params
        T = float(p.turbidity)
        out = np.zeros((len(d), 3), np.float32)
        if len(d) == 0:
            return out
        z = np.maximum(d[:, 2], 0.0)
        floor = (NIGHT_FLOOR * NIGHT_TINT * (1.0 + 1.5 * (1.0 - z))[:, None]).astype(np.float32)
        if self.overcast:     # the clear sky is fully hidden: skip it
            return self._cloud_base(d, z, floor, T) * (0.78 + 0.44 * self.clouds(d))[:, None]
        # clear sky (Preetham), scaled for low sun / twilight
        Y, x, y = preetham_xyY(d, self.sun_dir_eff.astype(np.float32), T)
        clear = cs.xyY_to_rec709(x, y, Y.astype(np.float32))
        clear *= np.float32(self.twilight * self.low_sun)
        if self.zenith_blue > 0:
            tint = 1 + self.zenith_blue * (np.array([0.55, 0.75, 1.35], np.float32) - 1)
            wz = _smoothstep(0.0, 0.5, z)[:, None]
            clear *= (1 + (tint - 1) * wz).astype(np.float32)
        if self.glow > 1e-4:
            s = self.sun_dir_eff
            horiz = np.hypot(d[:, 0], d[:, 1]) + 1e-6
            cos_az = (d[:, 0] * s[0] + d[:, 1] * s[1]) / (horiz * max(math.hypot(s[0], s[1]), 1e-6))
            az = np.arccos(np.clip(cos_az, -1, 1))
            g = (np.exp(-(az / np.float32(0.8)) ** 2) + np.float32(0.12)) * np.exp(-z / np.float32(0.16))
            clear += (np.float32(self.glow * self.glow_level) * g)[:, None] \
                * self.sun_chroma.astype(np.float32)
        if self.moon_k > 0 and self.sun_elevation < 0:
            Ym, xm, ym = preetham_xyY(d, self.moon_dir.astype(np.float32), T)
            clear += cs.xyY_to_rec709(xm, ym, (Ym * self.moon_k).astype(np.float32))
        clear += floor

        if self.clouds is None:
            return clear
        alpha, n = self.cloud_alpha(d)
        base = self._cloud_base(d, z, floor, T)
        # partly cloudy: bright, sun-tinted cumulus over the clear sky; silver lining near the sun
        cg = np.clip(d @ self.sun_dir_eff.astype(np.float32), -1, 1)
        lit = 3.4 * (1.1 - 0.35 * alpha)[:, None] * float(_smoothstep(-8.0, 2.0, self.sun_elevation)) \
            + 0.6
        tint = (0.8 + 0.2 * self.cloud_sun_chroma * (1 - self.glow)
                + 0.2 * self.sun_chroma * self.glow).astype(np.float32)
        cloud = base * lit * tint + (np.exp((cg - 1.0) / 0.02) * 3.0 * self.overcast_Lz)[:, None] \
            * self.sun_chroma.astype(np.float32)
        return clear * (1 - alpha)[:, None] + cloud.astype(np.float32) * alpha[:, None]

    def _cloud_base(self, d, z, floor, T):
        """CIE overcast luminance (sun- and moon-lit) in the overcast colour."""
        law = ((1.0 + 2.0 * z) / 3.0)[:, None]
        base = (self.overcast_Lz * law * self.overcast_rgb[None, :]).astype(np.float32) + floor * 1.5
        if self.moon_k > 0 and self.sun_elevation < 0:     # moonlit overcast (same CIE law)
            base += (np.float32(self.moon_k * (8.6 * math.sin(math.radians(self.moon_elevation))
                                               + 0.123) * self.params.overcast_gain)
                     * law * self.overcast_rgb).astype(np.float32)
        return base

    # ------------------------------------------------------------------ disks
    def _disk(self, d, centre, radius, pixel_angle, luminance_rgb):
        """Add a limb-darkened disk of mean radiance `luminance_rgb`, widened to at least
        ~1.5 pixels (energy kept), antialiased over one pixel."""
        r = max(radius, 0.75 * pixel_angle)
        cg = d @ centre.astype(np.float32)
        near = cg > math.cos(r + pixel_angle)
        if not np.any(near):
            return None, None, 0.0
        g = np.arccos(np.clip(cg[near], -1, 1))
        cov = np.clip((r - g) / pixel_angle + 0.5, 0.0, 1.0)
        mu = np.sqrt(np.clip(1 - (g / r) ** 2, 0, 1))
        limb = (1 - LIMB_U * (1 - mu)) / (1 - LIMB_U / 3)
        mean = luminance_rgb * (radius * radius) / (r * r)        # same energy over a wider disk
        peak = float(np.max(mean)) / (1 - LIMB_U / 3)
        scale = min(1.0, DISK_PEAK_MAX / peak) if peak > 0 else 1.0
        vals = (cov * limb)[:, None] * (mean * scale)[None, :]
        return near, vals.astype(np.float32), scale

    # ------------------------------------------------------------------ public
    @property
    def sun_residual_illuminance(self) -> np.ndarray:
        """Direct sun illuminance (lux, rgb) NOT represented in the last rendered map (the
        disk is clamped to fit half floats): give it to a DistantLight."""
        return self.sun_direct_lux * (1.0 - self.sun_map_fraction)

    def radiance(self, dirs: np.ndarray, pixel_angle: float = math.radians(0.5)) -> np.ndarray:
        """(N,3) directions (Z up, unit) -> (N,3) float32 radiance, linear Rec.709, kcd/m^2."""
        d = np.ascontiguousarray(dirs, dtype=np.float32).reshape(-1, 3)
        out = np.empty((len(d), 3), np.float32)
        up = d[:, 2] > 0
        t0 = time.perf_counter()
        out[up] = self._sky(d[up])
        self.timings["sky"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        out[~up] = self.ground_rgb
        # horizon haze / fog: toward the horizon colour, symmetric about the horizon
        w = (self.fog_strength * np.exp(-np.abs(d[:, 2]) / self.fog_width)).astype(np.float32)
        out += w[:, None] * (self.fog_rgb[None, :] - out)
        self.timings["ground+haze"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        self.sun_map_fraction = 0.0
        if self.params.sun_disk and self.sun_up and float(np.max(self.sun_direct_lux)) > 0:
            sub = np.nonzero(up | (d[:, 2] > -0.02))[0]
            L = self.sun_direct_lux / 1000.0 / (math.pi * SUN_RADIUS ** 2)
            near, vals, scale = self._disk(d[sub], self.sun_dir, SUN_RADIUS, pixel_angle, L)
            if near is not None:
                out[sub[near]] += vals * (d[sub[near], 2] > 0)[:, None]
                self.sun_map_fraction = scale
        if self.moon_up:
            vis = 1.0
            if self.clouds is not None:
                vis = 1.0 - float(self.cloud_alpha(self.moon_dir[None].astype(np.float32))[0][0])
            tr = float(_luminance(sun_illuminance_rgb(self.moon_elevation, float(self.params.turbidity)))
                       / _luminance(sun_illuminance_rgb(90.0, float(self.params.turbidity))))
            L = FULL_MOON_LUMINANCE * self.moon_phase * vis * tr * _chroma(
                sun_illuminance_rgb(self.moon_elevation, float(self.params.turbidity)))
            if float(np.max(L)) > 0:
                near, vals, _ = self._disk(d, self.moon_dir, MOON_RADIUS, pixel_angle, L)
                if near is not None:
                    out[near] += vals
        self.timings["disks"] = time.perf_counter() - t0
        return out


def render_sky(params: EnvParams, width: int = 2048, height: int = 1024,
               model: SkyModel | None = None) -> np.ndarray:
    """The equirectangular environment map: float32 (H, W, 3), top row = zenith, in
    `params.color_space`, kcd/m^2. See `mapping` for the direction convention."""
    check_resolution(width, height)
    model = model or SkyModel(params)
    t0 = time.perf_counter()
    dirs = pixel_directions(width, height).reshape(-1, 3)
    model.timings["directions"] = time.perf_counter() - t0
    img = model.radiance(dirs, pixel_angle=math.pi / height).reshape(height, width, 3)
    t0 = time.perf_counter()
    space = model.params.color_space
    if space != "lin_rec709":
        M = cs.rec709_to(space).astype(np.float32)
        img = img @ M.T
    np.maximum(img, 0.0, out=img)
    model.timings["colour space"] = time.perf_counter() - t0
    return np.ascontiguousarray(img, dtype=np.float32)
