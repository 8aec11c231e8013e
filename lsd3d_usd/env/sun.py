"""Sun (and Moon) position from date, time, latitude and longitude.

Sun: the NOAA solar-calculator equations (after Meeus, *Astronomical Algorithms*),
with NOAA's atmospheric-refraction approximation. Accurate to about 0.01 deg for
years 1800-2100. Moon: the low-precision series of the Astronomical Almanac
(about 0.3 deg), enough to place a moon disk and light a night sky.

Angles in degrees; azimuth measured from north, clockwise (east = 90).
World directions follow the stage: x east, y north, z up (rotated by
``north_deg`` when the stage's north is not +Y).
"""
from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass

import numpy as np

_J2000 = 2451545.0
_UNIX_EPOCH_JD = 2440587.5


def julian_day(when: _dt.datetime) -> float:
    """Julian day (UT) of a timezone-aware datetime."""
    if when.tzinfo is None:
        raise ValueError("julian_day: datetime must be timezone-aware")
    return _UNIX_EPOCH_JD + when.timestamp() / 86400.0


@dataclass(frozen=True)
class SolarPosition:
    elevation: float        # apparent (refracted) elevation above the horizon, deg
    azimuth: float          # from north, clockwise, deg
    declination: float      # apparent, deg
    equation_of_time: float  # minutes
    hour_angle: float       # deg


def _refraction_deg(elev: np.ndarray) -> np.ndarray:
    """NOAA approximation of atmospheric refraction (deg) for true elevation `elev` (deg)."""
    e = np.asarray(elev, dtype=np.float64)
    t = np.tan(np.radians(np.where(np.abs(e) < 1e-6, 1e-6, e)))
    high = 58.1 / t - 0.07 / t**3 + 0.000086 / t**5
    low = 1735.0 + e * (-518.2 + e * (103.4 + e * (-12.79 + e * 0.711)))
    below = -20.774 / t
    arcsec = np.where(e > 85.0, 0.0, np.where(e > 5.0, high, np.where(e > -0.575, low, below)))
    return arcsec / 3600.0


def solar_position_jd(jd, lat: float, lon: float, refraction: bool = True):
    """Vectorised NOAA solar position. jd: Julian day(s) UT. Returns a dict of arrays (deg)."""
    jd = np.asarray(jd, dtype=np.float64)
    T = (jd - _J2000) / 36525.0
    L0 = np.mod(280.46646 + T * (36000.76983 + 0.0003032 * T), 360.0)
    M = 357.52911 + T * (35999.05029 - 0.0001537 * T)
    ecc = 0.016708634 - T * (0.000042037 + 0.0000001267 * T)
    Mr = np.radians(M)
    C = (np.sin(Mr) * (1.914602 - T * (0.004817 + 0.000014 * T))
         + np.sin(2 * Mr) * (0.019993 - 0.000101 * T) + np.sin(3 * Mr) * 0.000289)
    true_long = L0 + C
    omega = np.radians(125.04 - 1934.136 * T)
    app_long = np.radians(true_long - 0.00569 - 0.00478 * np.sin(omega))
    eps0 = 23.0 + (26.0 + (21.448 - T * (46.815 + T * (0.00059 - T * 0.001813))) / 60.0) / 60.0
    eps = np.radians(eps0 + 0.00256 * np.cos(omega))
    decl = np.arcsin(np.sin(eps) * np.sin(app_long))
    y = np.tan(eps / 2.0) ** 2
    L0r = np.radians(L0)
    eot = 4.0 * np.degrees(y * np.sin(2 * L0r) - 2 * ecc * np.sin(Mr)
                           + 4 * ecc * y * np.sin(Mr) * np.cos(2 * L0r)
                           - 0.5 * y * y * np.sin(4 * L0r) - 1.25 * ecc * ecc * np.sin(2 * Mr))
    minutes_utc = np.mod(jd - 0.5, 1.0) * 1440.0
    true_solar = np.mod(minutes_utc + eot + 4.0 * lon, 1440.0)
    ha = true_solar / 4.0 - 180.0
    latr, har = math.radians(lat), np.radians(ha)
    cos_zen = np.clip(math.sin(latr) * np.sin(decl) + math.cos(latr) * np.cos(decl) * np.cos(har),
                      -1.0, 1.0)
    elev = 90.0 - np.degrees(np.arccos(cos_zen))
    az = np.degrees(np.arctan2(np.sin(har), np.cos(har) * math.sin(latr)
                               - np.tan(decl) * math.cos(latr))) + 180.0
    if refraction:
        elev = elev + _refraction_deg(elev)
    return {"elevation": elev, "azimuth": np.mod(az, 360.0), "declination": np.degrees(decl),
            "equation_of_time": eot, "hour_angle": ha}


def solar_position(when: _dt.datetime, lat: float, lon: float,
                   refraction: bool = True) -> SolarPosition:
    r = solar_position_jd(julian_day(when), lat, lon, refraction)
    return SolarPosition(*(float(r[k]) for k in
                           ("elevation", "azimuth", "declination", "equation_of_time", "hour_angle")))


def azel_to_direction(azimuth_deg, elevation_deg, north_deg: float = 0.0) -> np.ndarray:
    """World direction (x east, y north, z up) of azimuth/elevation.

    north_deg rotates the compass: the stage's north is +Y rotated by north_deg about +Z
    (counter-clockwise), for layouts whose +Y is not north.
    """
    a = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
    e = np.radians(np.asarray(elevation_deg, dtype=np.float64))
    d = np.stack([np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)], axis=-1)
    if north_deg:
        c, s = math.cos(math.radians(north_deg)), math.sin(math.radians(north_deg))
        d = np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)
    return d


def find_time_for_elevation(date: _dt.date, tz: _dt.tzinfo, lat: float, lon: float,
                            target_elev: float, side: str) -> _dt.datetime:
    """Local time on `date` when the sun reaches `target_elev` in the morning ("am") or
    afternoon ("pm"). Where it never does (polar day/night), the closest minute on that side."""
    start = _dt.datetime(date.year, date.month, date.day, tzinfo=tz)
    minutes = np.arange(0, 1440, 1.0)
    jd = julian_day(start) + minutes / 1440.0
    r = solar_position_jd(jd, lat, lon)
    elev = r["elevation"]
    noon = int(np.argmax(elev))
    idx = np.arange(0, noon + 1) if side == "am" else np.arange(noon, 1440)
    seg = elev[idx] - target_elev
    cross = np.nonzero(np.sign(seg[:-1]) != np.sign(seg[1:]))[0]
    if len(cross):
        i = cross[0] if side == "am" else cross[-1]
        # linear interpolation between the bracketing minutes
        f = seg[i] / (seg[i] - seg[i + 1])
        m = float(idx[i] + f)
    else:
        m = float(idx[int(np.argmin(np.abs(seg)))])
    return start + _dt.timedelta(minutes=m)


def solar_noon(date: _dt.date, tz: _dt.tzinfo, lat: float, lon: float) -> _dt.datetime:
    start = _dt.datetime(date.year, date.month, date.day, tzinfo=tz)
    minutes = np.arange(0, 1440, 1.0)
    elev = solar_position_jd(julian_day(start) + minutes / 1440.0, lat, lon)["elevation"]
    return start + _dt.timedelta(minutes=float(np.argmax(elev)))


# ---------------------------------------------------------------- moon


def lunar_position(when: _dt.datetime, lat: float, lon: float) -> dict:
    """Low-precision Moon position (Astronomical Almanac series; ~0.3 deg) and phase.

    Returns elevation/azimuth (deg, topocentric parallax applied approximately) and the
    illuminated fraction of the disk (0 new .. 1 full).
    """
    jd = julian_day(when)
    T = (jd - _J2000) / 36525.0

    def s(a):
        return math.sin(math.radians(a))

    lam = (218.32 + 481267.881 * T + 6.29 * s(134.9 + 477198.85 * T) - 1.27 * s(259.2 - 413335.38 * T)
           + 0.66 * s(235.7 + 890534.23 * T) + 0.21 * s(269.9 + 954397.70 * T)
           - 0.19 * s(357.5 + 35999.05 * T) - 0.11 * s(186.6 + 966404.05 * T))
    beta = (5.13 * s(93.3 + 483202.03 * T) + 0.28 * s(228.2 + 960400.87 * T)
            - 0.28 * s(318.3 + 6003.18 * T) - 0.17 * s(217.6 - 407332.20 * T))
    parallax = (0.9508 + 0.0518 * math.cos(math.radians(134.9 + 477198.85 * T))
                + 0.0095 * math.cos(math.radians(259.2 - 413335.38 * T)))
    lr, br = math.radians(lam), math.radians(beta)
    eps = math.radians(23.439 - 0.0130 * T)
    # ecliptic -> equatorial
    x = math.cos(br) * math.cos(lr)
    y = math.cos(eps) * math.cos(br) * math.sin(lr) - math.sin(eps) * math.sin(br)
    z = math.sin(eps) * math.cos(br) * math.sin(lr) + math.cos(eps) * math.sin(br)
    ra = math.atan2(y, x)
    dec = math.asin(z)
    gmst = 280.46061837 + 360.98564736629 * (jd - _J2000)
    ha = math.radians(gmst + lon) - ra
    latr = math.radians(lat)
    sin_alt = math.sin(latr) * math.sin(dec) + math.cos(latr) * math.cos(dec) * math.cos(ha)
    alt = math.degrees(math.asin(max(-1.0, min(1.0, sin_alt))))
    alt -= parallax * math.cos(math.radians(alt))          # topocentric correction
    az = math.degrees(math.atan2(math.sin(ha), math.cos(ha) * math.sin(latr)
                                 - math.tan(dec) * math.cos(latr))) + 180.0
    # phase from the elongation between Moon and Sun ecliptic longitudes (lat ignored)
    L0 = 280.46646 + 36000.76983 * T
    M = math.radians(357.52911 + 35999.05029 * T)
    sun_long = L0 + 1.914602 * math.sin(M) + 0.019993 * math.sin(2 * M)
    cos_psi = math.cos(br) * math.cos(lr - math.radians(sun_long))
    illum = (1.0 - cos_psi) / 2.0
    alt += float(_refraction_deg(alt))
    return {"elevation": alt, "azimuth": az % 360.0, "illuminated_fraction": illum}


def sun_direction(params) -> np.ndarray:
    """Unit vector toward the sun of EnvParams ``params`` (world, Z up, x east / y north unless
    north_deg is set); below the horizon it points down."""
    p = solar_position(params.when, params.latitude, params.longitude)
    return azel_to_direction(p.azimuth, p.elevation, params.north_deg)
