"""Prompt control: "rainy autumn evening in Seattle" -> EnvParams (+ the words not understood).

Every word understood is in the tables below (and in docs/env.md). Explicit values given to
`build_params` override what the prompt says. Times of day are solved for the place and
date: "sunrise" is when the sun stands 1 deg above the horizon in the morning, "dusk"
when it is 4 deg below in the evening, and so on. City time zones are standard time
(UTC offset without daylight saving).
"""
from __future__ import annotations

import datetime as _dt
import re
import warnings

from lsd3d_usd.env.params import (
    DEFAULT_WHEN,
    SEASONS,
    WEATHERS,
    EnvParams,
    season_date,
    season_of,
)
from lsd3d_usd.env.sun import find_time_for_elevation, solar_noon
from lsd3d_usd.errors import InputError, excerpt
from lsd3d_usd.limits import PROMPT_CHARS

# name: (latitude, longitude, standard UTC offset in hours)
CITIES = {
    "amsterdam": (52.37, 4.90, 1), "athens": (37.98, 23.73, 2), "bangkok": (13.76, 100.50, 7),
    "barcelona": (41.39, 2.17, 1), "beijing": (39.90, 116.40, 8), "berlin": (52.52, 13.40, 1),
    "boston": (42.36, -71.06, -5), "buenos aires": (-34.60, -58.38, -3),
    "cairo": (30.04, 31.24, 2), "cape town": (-33.92, 18.42, 2), "chicago": (41.88, -87.63, -6),
    "delhi": (28.61, 77.21, 5.5), "detroit": (42.33, -83.05, -5), "dubai": (25.20, 55.27, 4),
    "hong kong": (22.32, 114.17, 8), "istanbul": (41.01, 28.98, 3), "lisbon": (38.72, -9.14, 0),
    "london": (51.51, -0.13, 0), "los angeles": (34.05, -118.24, -8), "madrid": (40.42, -3.70, 1),
    "mexico city": (19.43, -99.13, -6), "miami": (25.76, -80.19, -5), "montreal": (45.50, -73.57, -5),
    "moscow": (55.76, 37.62, 3), "mumbai": (19.08, 72.88, 5.5), "munich": (48.14, 11.58, 1),
    "new york": (40.71, -74.01, -5), "oslo": (59.91, 10.75, 1), "paris": (48.86, 2.35, 1),
    "phoenix": (33.45, -112.07, -7), "pittsburgh": (40.44, -80.00, -5), "reykjavik": (64.15, -21.94, 0),
    "rome": (41.90, 12.50, 1), "san francisco": (37.77, -122.42, -8), "sao paulo": (-23.55, -46.63, -3),
    "seattle": (47.61, -122.33, -8), "seoul": (37.57, 126.98, 9), "shanghai": (31.23, 121.47, 8),
    "singapore": (1.35, 103.82, 8), "stockholm": (59.33, 18.07, 1), "stuttgart": (48.78, 9.18, 1),
    "sydney": (-33.87, 151.21, 10), "tokyo": (35.68, 139.69, 9), "toronto": (43.65, -79.38, -5),
    "vancouver": (49.28, -123.12, -8), "vienna": (48.21, 16.37, 1), "zurich": (47.37, 8.54, 1),
}

WEATHER_WORDS = {
    "clear": "clear", "sunny": "clear", "cloudless": "clear", "fair": "clear",
    "partly cloudy": "partly-cloudy", "partly-cloudy": "partly-cloudy", "cloudy": "partly-cloudy",
    "scattered clouds": "partly-cloudy",
    "overcast": "overcast", "grey": "overcast", "gray": "overcast", "dull": "overcast",
    "fog": "fog", "foggy": "fog", "mist": "fog", "misty": "fog",
    "rain": "rain", "rainy": "rain", "raining": "rain", "drizzle": "rain", "showers": "rain",
    "storm": "rain", "stormy": "rain", "wet": "rain",
    "snow": "snow", "snowy": "snow", "snowing": "snow", "blizzard": "snow",
}
SEASON_WORDS = {"spring": "spring", "summer": "summer", "autumn": "autumn", "fall": "autumn",
                "autumnal": "autumn", "winter": "winter", "wintry": "winter"}
MONTHS = ("january", "february", "march", "april", "may", "june", "july", "august",
          "september", "october", "november", "december")
# time word -> ("elev", apparent sun elevation in deg, "am"/"pm") | ("solar", hours from solar noon)
TIME_WORDS = {
    "dawn": ("elev", -4.0, "am"), "daybreak": ("elev", -4.0, "am"),
    "sunrise": ("elev", 1.0, "am"),
    "morning": ("solar", -3.0), "noon": ("solar", 0.0), "midday": ("solar", 0.0),
    "afternoon": ("solar", 3.0),
    "golden hour": ("elev", 6.0, "pm"), "evening": ("elev", 5.0, "pm"),
    "sunset": ("elev", 1.0, "pm"), "dusk": ("elev", -4.0, "pm"), "twilight": ("elev", -4.0, "pm"),
    "blue hour": ("elev", -5.0, "pm"),
    "night": ("solar", 12.0), "nighttime": ("solar", 12.0), "midnight": ("solar", 12.0),
}
MODIFIER_WORDS = {  # word -> EnvParams field overrides
    "hazy": {"turbidity": 6.0}, "haze": {"turbidity": 6.0}, "smoggy": {"turbidity": 8.0},
    "crisp": {"turbidity": 2.0}, "dry": {"wet_ground": 0.0},
    "puddles": {"wet_ground": 1.0}, "snow-covered": {"snow_cover": 1.0},
}
FILLER_WORDS = {"a", "an", "the", "in", "at", "on", "of", "during", "with", "and", "day", "time",
                "sky", "weather", "scene", "city", "street", "road", "near", "around", "late",
                "early"}


def _phrases() -> list[tuple[str, str, object]]:
    """All known phrases, longest first (so "partly cloudy" beats "cloudy", "new york" is one)."""
    table = []
    for k, v in CITIES.items():
        table.append((k, "city", v))
    for k, v in WEATHER_WORDS.items():
        table.append((k, "weather", v))
    for k, v in SEASON_WORDS.items():
        table.append((k, "season", v))
    for i, m in enumerate(MONTHS):
        table.append((m, "month", i + 1))
    for k, v in TIME_WORDS.items():
        table.append((k, "time", v))
    for k, v in MODIFIER_WORDS.items():
        table.append((k, "modifier", v))
    return sorted(table, key=lambda t: -len(t[0].split()))


def tokenize(text: str) -> list[str]:
    return re.findall(r"[a-z]+(?:-[a-z]+)*", text.lower())


def understand(text: str) -> tuple[dict, list[str]]:
    """Prompt text -> (dict of what it says, unknown words)."""
    words = tokenize(text)
    found: dict = {}
    unknown: list[str] = []
    phrases = _phrases()
    i = 0
    while i < len(words):
        for phrase, kind, value in phrases:
            n = len(phrase.split())
            if " ".join(words[i:i + n]) == phrase:
                if kind == "city":
                    found["place"] = phrase
                    found["city"] = value
                elif kind == "modifier":
                    found.setdefault("modifiers", {}).update(value)
                else:
                    found[kind] = value
                    if kind == "time":
                        found["time_word"] = phrase
                i += n
                break
        else:
            if words[i] not in FILLER_WORDS:
                unknown.append(words[i])
            i += 1
    return found, unknown


def _tz(hours: float) -> _dt.timezone:
    return _dt.timezone(_dt.timedelta(hours=hours))


def parse_when(text: str, tz_hours: float | None = None) -> _dt.datetime:
    """ISO date-time; without an offset, `tz_hours` (e.g. the place's) is assumed."""
    try:
        t = _dt.datetime.fromisoformat(text)
    except ValueError:
        raise InputError(f"--when {text!r}: expected an ISO date-time such as "
                         f"2026-06-21T13:00+02:00") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=_tz(tz_hours if tz_hours is not None else 0.0))
    return t


def build_params(prompt: str | None = None, *, when: _dt.datetime | str | None = None,
                 lat: float | None = None, lon: float | None = None,
                 weather: str | None = None, season: str | None = None,
                 time_of_day: str | None = None, **fields) -> tuple[EnvParams, list[str]]:
    """EnvParams from a prompt and explicit values (explicit values win).

    Returns (params, unknown prompt words)."""
    if prompt and not PROMPT_CHARS.ok(len(prompt)):
        PROMPT_CHARS.check(len(prompt), f"--prompt {excerpt(prompt, 40)}")
    said, unknown = understand(prompt) if prompt else ({}, [])
    if (lat is None) != (lon is None):
        raise InputError("--lat and --lon go together: give both or neither")
    if weather is not None and weather not in WEATHERS:
        raise InputError(f"weather {weather!r}: choose one of {', '.join(WEATHERS)}")
    if season is not None and season not in SEASONS:
        raise InputError(f"season {season!r}: choose one of {', '.join(SEASONS)}")
    if time_of_day is not None and time_of_day not in TIME_WORDS:
        raise InputError(f"time of day {time_of_day!r}: choose one of {', '.join(TIME_WORDS)}")

    # place
    place = "madrid"
    la, lo, tzh = CITIES[place]
    if "city" in said:
        place = said["place"]
        la, lo, tzh = said["city"]
    if lat is not None:
        la, lo, place = float(lat), float(lon), None
        tzh = None
    if not (-90 <= la <= 90) or not (-180 <= lo <= 180):
        raise InputError(f"--lat {la} --lon {lo}: latitude must be in [-90, 90], longitude in [-180, 180]")
    if tzh is None:                      # no city: the nominal zone of the longitude
        tzh = round(lo / 15.0)
    tz = _tz(tzh)

    season_final = season or said.get("season")
    tword = time_of_day or said.get("time_word")
    if when is not None:
        t = parse_when(when, tzh) if isinstance(when, str) else when
        if t.tzinfo is None:
            t = t.replace(tzinfo=tz)
        tword = None if time_of_day is None else tword
        label = time_of_day
    else:
        # date: explicit season > prompt month > prompt season > default (northern midsummer)
        if season is not None:
            date = season_date(season, la)
        elif "month" in said:
            date = _dt.date(DEFAULT_WHEN.year, said["month"], 15)
        elif "season" in said:
            date = season_date(said["season"], la)
        else:
            date = DEFAULT_WHEN.date() if la >= 0 else _dt.date(DEFAULT_WHEN.year, 12, 21)
        t = None
        label = tword
        tword = tword or "default"
    if tword is not None:
        date = t.date() if t is not None else date
        tzinfo = t.tzinfo if t is not None else tz
        spec = TIME_WORDS.get(tword, ("solar", 1.0))
        if spec[0] == "elev":
            t = find_time_for_elevation(date, tzinfo, la, lo, spec[1], spec[2])
        else:
            t = solar_noon(date, tzinfo, la, lo) + _dt.timedelta(hours=spec[1])
        t = t.replace(second=0, microsecond=0)
    if season_final is None:
        season_final = season_of(t.date(), la)

    kw = dict(when=t, latitude=la, longitude=lo, place=place,
              weather=weather or said.get("weather", "clear"), season=season_final,
              time_of_day=label)
    kw.update(said.get("modifiers", {}))
    kw.update({k: v for k, v in fields.items() if v is not None})
    params = EnvParams(**kw)
    if prompt:
        params.extras["prompt"] = prompt
    return params, unknown


def unknown_words(words: list[str], limit: int = 10) -> str:
    """The words not understood, for a warning: at most ``limit``, each cut short."""
    shown = ", ".join(w if len(w) <= 40 else w[:40] + "..." for w in words[:limit])
    return shown + (f" (and {len(words) - limit} more)" if len(words) > limit else "")


def parse_prompt(text: str, warn: bool = True) -> tuple[EnvParams, list[str]]:
    """`parse_prompt("rainy autumn evening in Seattle") -> (EnvParams, unknown_words)`.
    Unknown words are listed in a warning (and returned); the environment is still made."""
    params, unknown = build_params(text)
    if unknown and warn:
        warnings.warn(f"environment prompt: words not understood (ignored): {unknown_words(unknown)}",
                      UserWarning, stacklevel=2)
    return params, unknown


def vocabulary() -> dict[str, dict]:
    """Every word understood, grouped, for documentation."""
    return {"weather": WEATHER_WORDS, "season": SEASON_WORDS,
            "month": {m: f"{m.title()} 15" for m in MONTHS}, "time": TIME_WORDS,
            "modifier": MODIFIER_WORDS,
            "city": {k: f"{v[0]:.2f}, {v[1]:.2f}, UTC{v[2]:+g}" for k, v in CITIES.items()},
            "filler": {w: "ignored" for w in sorted(FILLER_WORDS)}}
