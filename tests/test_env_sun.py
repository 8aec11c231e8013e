"""Sun position against published values (NREL SPA paper example; Meeus examples)."""
import datetime as dt

import numpy as np
import pytest

from lsd3d_usd.env.sun import (azel_to_direction, find_time_for_elevation, julian_day,
                               lunar_position, solar_position, solar_position_jd)


def test_spa_reference_example():
    # Reda & Andreas (2004), NREL SPA example: 2003-10-17 12:30:30 local (UTC-7),
    # 39.742476 N, 105.1786 W -> topocentric zenith 50.11162 deg, azimuth 194.34024 deg.
    tz = dt.timezone(dt.timedelta(hours=-7))
    p = solar_position(dt.datetime(2003, 10, 17, 12, 30, 30, tzinfo=tz), 39.742476, -105.1786)
    assert abs((90.0 - p.elevation) - 50.11162) < 0.1
    assert abs(p.azimuth - 194.34024) < 0.1


def test_meeus_declination_and_equation_of_time():
    # Meeus, Astronomical Algorithms, ex. 25.a / 28.a: 1992 Oct 13.0 -> apparent declination
    # -7 deg 47' 01" and equation of time 13 min 42.6 s.
    r = solar_position_jd(2448908.5, 0.0, 0.0)
    assert abs(float(r["declination"]) - (-7.78361)) < 0.01
    assert abs(float(r["equation_of_time"]) - 13.710) < 0.05


def test_julian_day_epoch():
    assert julian_day(dt.datetime(2000, 1, 1, 12, tzinfo=dt.timezone.utc)) == pytest.approx(2451545.0)
    with pytest.raises(ValueError):
        julian_day(dt.datetime(2000, 1, 1, 12))


def test_equinox_noon_at_equator_is_overhead_and_solstice_declination():
    # March equinox 2026: 20 March 14:46 UTC. At the subsolar longitude the sun is ~ at zenith.
    t = dt.datetime(2026, 3, 20, 14, 46, tzinfo=dt.timezone.utc)
    r = solar_position_jd(julian_day(t), 0.0, 0.0)
    assert abs(float(r["declination"])) < 0.02
    s = dt.datetime(2026, 6, 21, 8, 24, tzinfo=dt.timezone.utc)   # June solstice
    assert float(solar_position_jd(julian_day(s), 0, 0)["declination"]) == pytest.approx(23.436, abs=0.01)


def test_sunrise_madrid_matches_almanac_within_two_minutes():
    # Published almanac (timeanddate / IGN): Madrid, 21 June 2026, sunrise 06:44, sunset 21:48 CEST.
    tz = dt.timezone(dt.timedelta(hours=2))
    rise = find_time_for_elevation(dt.date(2026, 6, 21), tz, 40.4168, -3.7038, -0.267, "am")
    sset = find_time_for_elevation(dt.date(2026, 6, 21), tz, 40.4168, -3.7038, -0.267, "pm")
    assert abs((rise - dt.datetime(2026, 6, 21, 6, 44, tzinfo=tz)).total_seconds()) < 120
    assert abs((sset - dt.datetime(2026, 6, 21, 21, 48, tzinfo=tz)).total_seconds()) < 120


def test_azel_direction_axes():
    np.testing.assert_allclose(azel_to_direction(0, 0), [0, 1, 0], atol=1e-12)     # north = +Y
    np.testing.assert_allclose(azel_to_direction(90, 0), [1, 0, 0], atol=1e-12)    # east = +X
    np.testing.assert_allclose(azel_to_direction(123, 90), [0, 0, 1], atol=1e-12)
    # north rotated 90 deg CCW: north becomes -X
    np.testing.assert_allclose(azel_to_direction(0, 0, north_deg=90), [-1, 0, 0], atol=1e-12)


def test_moon_phase_full_and_new():
    # Full moon 2026-03-03 11:38 UTC, new moon 2026-03-19 01:23 UTC (published lunar phases).
    full = lunar_position(dt.datetime(2026, 3, 3, 11, 38, tzinfo=dt.timezone.utc), 0, 0)
    new = lunar_position(dt.datetime(2026, 3, 19, 1, 23, tzinfo=dt.timezone.utc), 0, 0)
    assert full["illuminated_fraction"] > 0.97
    assert new["illuminated_fraction"] < 0.03
