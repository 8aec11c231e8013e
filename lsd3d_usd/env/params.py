"""Environment parameters: what a sky is made from, plus the hints the prior and renderer use.

Fields left as ``None`` are derived by :meth:`EnvParams.resolved` from weather, season
and date (documented in docs/env.md); any field given explicitly wins.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import math
from dataclasses import dataclass, field

from lsd3d_usd.errors import InputError

# Bump when the sky model changes in a way that changes pixels, so cached EXRs are redone.
MODEL_VERSION = "sky-1"

WEATHERS = ("clear", "partly-cloudy", "overcast", "fog", "rain", "snow")
SEASONS = ("spring", "summer", "autumn", "winter")
VEGETATION = ("green", "autumn", "bare", "snow")
COLOR_SPACES = ("lin_rec709", "acescg")

# Per-weather defaults: turbidity, cloud coverage, fog extinction (1/m), wet ground, snow cover,
# overcast brightness relative to the CIE overcast zenith luminance.
WEATHER_DEFAULTS = {
    "clear":         dict(turbidity=2.5, cloud_coverage=0.0, fog_density=1.0e-4, wet_ground=0.0,
                          snow_cover=0.0, overcast_gain=1.0),
    "partly-cloudy": dict(turbidity=3.0, cloud_coverage=0.45, fog_density=1.5e-4, wet_ground=0.0,
                          snow_cover=0.0, overcast_gain=1.0),
    "overcast":      dict(turbidity=4.0, cloud_coverage=1.0, fog_density=3.0e-4, wet_ground=0.1,
                          snow_cover=0.0, overcast_gain=1.0),
    "fog":           dict(turbidity=6.0, cloud_coverage=1.0, fog_density=2.0e-2, wet_ground=0.3,
                          snow_cover=0.0, overcast_gain=0.9),
    "rain":          dict(turbidity=4.5, cloud_coverage=1.0, fog_density=1.0e-3, wet_ground=1.0,
                          snow_cover=0.0, overcast_gain=0.45),
    "snow":          dict(turbidity=3.5, cloud_coverage=1.0, fog_density=2.0e-3, wet_ground=0.3,
                          snow_cover=1.0, overcast_gain=0.8),
}

# Linear-RGB albedo of the distant ground hemisphere (a landscape mix, not one material).
GROUND_COLORS = {
    "green":  (0.090, 0.115, 0.060),
    "autumn": (0.135, 0.105, 0.060),
    "bare":   (0.110, 0.100, 0.085),
    "snow":   (0.780, 0.800, 0.830),
}
SEASON_VEGETATION = {"spring": "green", "summer": "green", "autumn": "autumn", "winter": "bare"}

DEFAULT_TZ = _dt.timezone(_dt.timedelta(hours=2))
DEFAULT_WHEN = _dt.datetime(2026, 6, 21, 13, 0, tzinfo=DEFAULT_TZ)


def season_of(date: _dt.date, latitude: float) -> str:
    """Meteorological season of a date at a latitude (southern hemisphere flipped)."""
    northern = ("winter", "winter", "spring", "spring", "spring", "summer", "summer", "summer",
                "autumn", "autumn", "autumn", "winter")[date.month - 1]
    if latitude >= 0:
        return northern
    return {"winter": "summer", "summer": "winter", "spring": "autumn", "autumn": "spring"}[northern]


def season_date(season: str, latitude: float, year: int = 2026) -> _dt.date:
    """A representative mid-season date for a season in the hemisphere of `latitude`."""
    north = {"spring": (4, 20), "summer": (7, 15), "autumn": (10, 15), "winter": (1, 15)}
    south = {"spring": (10, 15), "summer": (1, 15), "autumn": (4, 20), "winter": (7, 15)}
    m, d = (north if latitude >= 0 else south)[season]
    return _dt.date(year, m, d)


@dataclass
class FogParams:
    """Fog the renderer applies to geometry: transmittance exp(-density * distance), with the
    density falling off with height as exp(-height_falloff * max(0, z - base_height))."""
    density: float                           # extinction coefficient, 1/m
    color: tuple[float, float, float]        # in-scattered radiance, map units, map colour space
    height_falloff: float = 0.0              # 1/m; 0 = homogeneous
    base_height: float = 0.0                 # m

    @property
    def visibility_m(self) -> float:
        """Meteorological visibility (Koschmieder, 2 % contrast threshold)."""
        return 3.912 / self.density if self.density > 0 else float("inf")


@dataclass
class EnvParams:
    when: _dt.datetime = DEFAULT_WHEN          # timezone-aware local time
    latitude: float = 40.42
    longitude: float = -3.70
    place: str | None = "madrid"
    weather: str = "clear"
    season: str | None = None                  # None: from date + hemisphere
    time_of_day: str | None = None             # label only (the prompt word that set `when`)
    turbidity: float | None = None
    cloud_coverage: float | None = None        # 0..1 fraction of sky covered
    ground_color: tuple[float, float, float] | None = None
    fog_density: float | None = None           # 1/m
    fog_height_falloff: float | None = None    # 1/m
    wet_ground: float | None = None            # 0..1 hint for the prior
    snow_cover: float | None = None            # 0..1 hint for the prior
    vegetation: str | None = None              # green | autumn | bare | snow
    seed: int = 0
    north_deg: float = 0.0                     # stage north = +Y rotated CCW by this (deg)
    color_space: str = "lin_rec709"
    sun_disk: bool = True
    extras: dict = field(default_factory=dict)  # free-form, e.g. prompt text; not hashed

    def __post_init__(self):
        self.validate()

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        if not isinstance(self.when, _dt.datetime) or self.when.tzinfo is None:
            raise InputError(f"environment time {self.when!r}: need a timezone-aware datetime "
                             f"(e.g. 2026-06-21T13:00+02:00)")
        if not -90.0 <= float(self.latitude) <= 90.0:
            raise InputError(f"latitude {self.latitude}: must be in [-90, 90]")
        if not -180.0 <= float(self.longitude) <= 180.0:
            raise InputError(f"longitude {self.longitude}: must be in [-180, 180]")
        if not math.isfinite(float(self.north_deg)):
            raise InputError(f"north {self.north_deg}: must be a finite angle in degrees")
        if self.weather not in WEATHERS:
            raise InputError(f"weather {self.weather!r}: choose one of {', '.join(WEATHERS)}")
        if self.season is not None and self.season not in SEASONS:
            raise InputError(f"season {self.season!r}: choose one of {', '.join(SEASONS)}")
        if self.vegetation is not None and self.vegetation not in VEGETATION:
            raise InputError(f"vegetation {self.vegetation!r}: choose one of {', '.join(VEGETATION)}")
        if self.color_space not in COLOR_SPACES:
            raise InputError(f"colour space {self.color_space!r}: choose one of {', '.join(COLOR_SPACES)}")
        if self.turbidity is not None and not 1.7 <= self.turbidity <= 10.0:
            raise InputError(f"turbidity {self.turbidity}: the Preetham model is valid for 1.7..10")
        for name in ("cloud_coverage", "wet_ground", "snow_cover"):
            v = getattr(self, name)
            if v is not None and not 0.0 <= v <= 1.0:
                raise InputError(f"{name} {v}: must be in [0, 1]")
        for name in ("fog_density", "fog_height_falloff"):
            v = getattr(self, name)
            if v is not None and not v >= 0.0:
                raise InputError(f"{name} {v}: must be >= 0")
        if self.ground_color is not None and (len(self.ground_color) != 3
                                              or min(self.ground_color) < 0):
            raise InputError(f"ground_color {self.ground_color}: need 3 non-negative linear values")

    # ------------------------------------------------------------------ derived values
    def resolved(self) -> "EnvParams":
        """A copy with every None field filled from weather / season / date."""
        wd = WEATHER_DEFAULTS[self.weather]
        season = self.season or season_of(self.when.date(), self.latitude)
        snow = wd["snow_cover"] if self.snow_cover is None else self.snow_cover
        veg = self.vegetation
        if veg is None:
            veg = "snow" if snow >= 0.5 else SEASON_VEGETATION[season]
        ground = self.ground_color
        if ground is None:
            ground = GROUND_COLORS["snow" if snow >= 0.5 else veg]
        return dataclasses.replace(
            self, season=season,
            turbidity=wd["turbidity"] if self.turbidity is None else self.turbidity,
            cloud_coverage=wd["cloud_coverage"] if self.cloud_coverage is None else self.cloud_coverage,
            fog_density=wd["fog_density"] if self.fog_density is None else self.fog_density,
            fog_height_falloff=(0.0 if self.weather != "fog" else 0.02)
            if self.fog_height_falloff is None else self.fog_height_falloff,
            wet_ground=wd["wet_ground"] if self.wet_ground is None else self.wet_ground,
            snow_cover=snow, vegetation=veg, ground_color=tuple(float(c) for c in ground))

    @property
    def ground_albedo(self) -> tuple:
        """Linear-RGB albedo of the distant ground (of resolved parameters): the ground
        colour, darker when wet (water fills the pores)."""
        return tuple(float(c) * (1.0 - 0.35 * float(self.wet_ground)) for c in self.ground_color)

    @property
    def overcast_gain(self) -> float:
        return WEATHER_DEFAULTS[self.weather]["overcast_gain"]

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["when"] = self.when.isoformat()
        d.pop("extras")
        if d["ground_color"] is not None:
            d["ground_color"] = [round(float(c), 6) for c in d["ground_color"]]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "EnvParams":
        d = dict(d)
        d["when"] = _dt.datetime.fromisoformat(d["when"])
        if d.get("ground_color") is not None:
            d["ground_color"] = tuple(d["ground_color"])
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def content_hash(self, width: int | None = None, height: int | None = None) -> str:
        """Hash of everything that changes pixels (resolved params, model version, size)."""
        payload = {"model": MODEL_VERSION, "params": self.resolved().to_dict(),
                   "size": [width, height]}
        blob = json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def fog(self, color=(0.0, 0.0, 0.0)) -> FogParams:
        r = self.resolved()
        return FogParams(density=float(r.fog_density), color=tuple(float(c) for c in color),
                         height_falloff=float(r.fog_height_falloff))

    def variant_name(self) -> str:
        """A USD-safe variant name: weather_timeofday_season (or HHMM when no label)."""
        r = self.resolved()
        tod = r.time_of_day or r.when.strftime("t%H%M")
        name = f"{r.weather}_{tod}_{r.season}".replace("-", "_").replace(" ", "_")
        return "".join(c if c.isalnum() or c == "_" else "_" for c in name)
