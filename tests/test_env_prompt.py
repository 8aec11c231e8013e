"""Prompt words map as documented; explicit values win; unknown words warn."""
import datetime as dt

import pytest

from lsd3d_usd.env import parse_prompt, sun_direction
from lsd3d_usd.env.prompt import CITIES, TIME_WORDS, WEATHER_WORDS, build_params, vocabulary
from lsd3d_usd.env.sun import solar_position
from lsd3d_usd.errors import InputError


def test_rainy_autumn_evening_in_seattle():
    p, unknown = parse_prompt("rainy autumn evening in Seattle")
    assert unknown == []
    assert p.weather == "rain" and p.season == "autumn" and p.place == "seattle"
    assert (p.latitude, p.longitude) == CITIES["seattle"][:2]
    assert p.when.utcoffset() == dt.timedelta(hours=-8)
    assert p.when.month == 10                      # autumn in the northern hemisphere
    elev = solar_position(p.when, p.latitude, p.longitude).elevation
    assert abs(elev - 5.0) < 0.5 and p.when.hour >= 12    # "evening": sun 5 deg, afternoon side
    r = p.resolved()
    assert r.wet_ground == 1.0 and r.vegetation == "autumn"


def test_multiword_phrases_and_southern_hemisphere_season():
    p, unknown = parse_prompt("partly cloudy winter morning in Buenos Aires")
    assert unknown == [] and p.weather == "partly-cloudy" and p.place == "buenos aires"
    assert p.when.month == 7                       # southern winter
    p, _ = parse_prompt("snowy night in New York")
    assert p.weather == "snow" and p.resolved().vegetation == "snow"
    assert solar_position(p.when, p.latitude, p.longitude).elevation < -18


@pytest.mark.parametrize("word,lo,hi", [("dawn", -5, -3), ("sunrise", 0.5, 1.5), ("dusk", -5, -3),
                                        ("sunset", 0.5, 1.5), ("golden hour", 5.5, 6.5)])
def test_time_words_solve_sun_elevation(word, lo, hi):
    p, _ = parse_prompt(f"{word} in London")
    e = solar_position(p.when, p.latitude, p.longitude).elevation
    assert lo <= e <= hi


def test_noon_is_highest():
    p_noon, _ = parse_prompt("noon in Tokyo")
    p_aft, _ = parse_prompt("afternoon in Tokyo")
    assert sun_direction(p_noon)[2] > sun_direction(p_aft)[2] > 0


def test_unknown_words_warn_and_still_yield_an_environment():
    with pytest.warns(UserWarning, match="blorp"):
        p, unknown = parse_prompt("blorp foggy zzz")
    assert unknown == ["blorp", "zzz"] and p.weather == "fog"
    with pytest.warns(UserWarning, match="qwerty"):
        p, unknown = parse_prompt("qwerty")
    assert unknown == ["qwerty"] and p.weather == "clear"


def test_explicit_values_override_the_prompt():
    p, _ = build_params("rainy autumn evening in Seattle", weather="clear",
                        when="2026-06-21T13:00+02:00", lat=40.42, lon=-3.70)
    assert p.weather == "clear" and p.latitude == 40.42 and p.place is None
    assert p.when == dt.datetime(2026, 6, 21, 13, 0, tzinfo=dt.timezone(dt.timedelta(hours=2)))
    p, _ = build_params("winter in Paris", season="summer")
    assert p.season == "summer" and p.when.month == 7
    p, _ = build_params("hazy noon", turbidity=3.0)
    assert p.turbidity == 3.0
    p, _ = build_params("hazy noon")
    assert p.turbidity == 6.0


def test_naive_when_uses_place_time_zone_and_bad_values_error():
    p, _ = build_params("in Tokyo", when="2026-06-21T12:00")
    assert p.when.utcoffset() == dt.timedelta(hours=9)
    for kw in (dict(lat=10.0), dict(when="tomorrow"), dict(weather="sunny"),
               dict(time_of_day="brunch"), dict(lat=95.0, lon=0.0)):
        with pytest.raises(InputError):
            build_params(None, **kw)


def test_every_documented_word_is_understood():
    import pathlib
    doc = pathlib.Path(__file__).resolve().parents[1] / "docs" / "env.md"
    text = doc.read_text()
    vocab = vocabulary()
    for group in ("weather", "season", "time", "modifier", "city"):
        for word in vocab[group]:
            assert f"`{word}`" in text, f"{word} missing from docs/env.md"
    for word in list(WEATHER_WORDS) + list(TIME_WORDS):
        _, unknown = parse_prompt(word, warn=False)
        assert unknown == []
