"""Mapping convention, sky rendering, SH irradiance."""
import datetime as dt
import math

import numpy as np
import pytest

from lsd3d_usd.env import (EnvParams, direction_to_uv, eval_sh_irradiance, pixel_directions,
                           pixel_solid_angles, render_sky, sh_irradiance, sun_direction,
                           uv_to_direction)
from lsd3d_usd.env.sky import SkyModel, preetham_zenith
from lsd3d_usd.errors import InputError

TZ = dt.timezone(dt.timedelta(hours=2))


def test_mapping_matches_domelight_poleaxis_z_convention():
    # UsdLux DomeLight_1 docs: with poleAxis Z, latitude +-pi/2 -> +-Z and latitude 0,
    # longitude 0 (image centre) -> -Y; OpenEXR: longitude +pi/2 -> +X, left edge = +pi.
    np.testing.assert_allclose(uv_to_direction(np.array([0.5, 0.5])), [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(uv_to_direction(np.array([0.25, 0.5])), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(uv_to_direction(np.array([0.75, 0.5])), [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(uv_to_direction(np.array([0.0, 0.5])), [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(uv_to_direction(np.array([0.3, 0.0])), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(uv_to_direction(np.array([0.3, 1.0])), [0, 0, -1], atol=1e-12)
    # right-handed: the rotation from the Y-up EXR frame is proper (x, y, z) -> (x, -z, y)
    e, n, z = (uv_to_direction(np.array(p)) for p in ([0.25, 0.5], [0.0, 0.5], [0.1, 0.0]))
    assert np.dot(np.cross(e, n), z) == pytest.approx(1.0)


def test_uv_direction_roundtrip_float64():
    rng = np.random.default_rng(0)
    uv = np.stack([rng.random(1000), 0.001 + 0.998 * rng.random(1000)], -1)
    back = direction_to_uv(uv_to_direction(uv))
    np.testing.assert_allclose(back, uv, atol=1e-12)
    with pytest.raises(ValueError):
        direction_to_uv(np.zeros(3))


def test_pixel_solid_angles_sum_to_sphere():
    assert pixel_solid_angles(64, 32).sum() * 64 == pytest.approx(4 * math.pi, rel=1e-12)


@pytest.mark.parametrize("when,lat,lon", [
    (dt.datetime(2026, 6, 21, 9, 0, tzinfo=TZ), 40.42, -3.70),     # morning, sun in the east
    (dt.datetime(2026, 6, 21, 14, 0, tzinfo=TZ), 40.42, -3.70),    # near noon, south
    (dt.datetime(2026, 12, 21, 16, 0, tzinfo=dt.timezone(dt.timedelta(hours=10))), -33.87, 151.21),
])
def test_brightest_pixel_is_the_sun_through_the_dome_convention(when, lat, lon):
    p = EnvParams(when=when, latitude=lat, longitude=lon, weather="clear")
    img = render_sky(p, 512, 256)
    lum = img @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    j, i = np.unravel_index(np.argmax(lum), lum.shape)
    d = uv_to_direction(np.array([(i + 0.5) / 512, (j + 0.5) / 256]))
    s = sun_direction(p)
    ang = math.degrees(math.acos(np.clip(np.dot(d, s), -1, 1)))
    assert ang < 1.0, f"brightest pixel {ang:.2f} deg from the sun"


def test_top_row_is_zenith_and_ground_below():
    p = EnvParams(when=dt.datetime(2026, 6, 21, 14, 0, tzinfo=TZ), weather="overcast")
    img = render_sky(p, 256, 128)
    assert img.shape == (128, 256, 3) and img.dtype == np.float32
    # CIE overcast: zenith three times brighter than the horizon; ground darker than sky
    lum = img.mean(axis=(1, 2))
    assert lum[0] > lum[60] and lum[:64].mean() > lum[64:].mean()
    assert np.all(np.isfinite(img)) and img.min() >= 0


def test_preetham_zenith_luminance_published_trend():
    # zenith luminance grows with sun elevation; a clear zenith is bluer than D65 (x < 0.3127)
    Y30, x30, y30 = preetham_zenith(math.radians(60), 2.5)
    Y60, _, _ = preetham_zenith(math.radians(30), 2.5)
    assert 1.0 < Y30 < Y60 < 20.0
    assert 0.2 < x30 < 0.3127 and 0.2 < y30 < 0.329


def test_time_of_day_and_weather_ordering():
    def mean_lum(**kw):
        img = render_sky(EnvParams(**kw), 128, 64)
        return float(img[:32].mean())
    noon = dt.datetime(2026, 6, 21, 14, 0, tzinfo=TZ)
    night = dt.datetime(2026, 6, 21, 2, 0, tzinfo=TZ)
    dusk = dt.datetime(2026, 6, 21, 22, 15, tzinfo=TZ)
    assert mean_lum(when=noon) > mean_lum(when=dusk) > mean_lum(when=night) > 0
    assert mean_lum(when=noon, weather="overcast") > mean_lum(when=noon, weather="rain")
    # night has a low, non-zero floor (dark sky), far below daylight
    assert mean_lum(when=night) < 1e-3


def test_sunrise_is_warm_noon_is_blue():
    rise = EnvParams(when=dt.datetime(2026, 6, 21, 6, 55, tzinfo=TZ))
    noon = EnvParams(when=dt.datetime(2026, 6, 21, 14, 0, tzinfo=TZ))
    a = render_sky(rise, 256, 128)
    b = render_sky(noon, 256, 128)
    s = sun_direction(rise)
    # horizon band toward the sun: red > blue at sunrise
    u = direction_to_uv(np.array([s[0], s[1], 0.05]))
    i, j = int(u[0] * 256), int(u[1] * 128)
    assert a[j, i, 0] > a[j, i, 2]
    # zenith at noon: blue > red
    assert b[2, :, 2].mean() > b[2, :, 0].mean()


def test_clouds_are_deterministic_per_seed_and_cover_as_asked():
    when = dt.datetime(2026, 6, 21, 14, 0, tzinfo=TZ)
    a = render_sky(EnvParams(when=when, weather="partly-cloudy", seed=1), 128, 64)
    b = render_sky(EnvParams(when=when, weather="partly-cloudy", seed=1), 128, 64)
    c = render_sky(EnvParams(when=when, weather="partly-cloudy", seed=2), 128, 64)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 0.1
    m = SkyModel(EnvParams(when=when, weather="partly-cloudy", cloud_coverage=0.3, seed=3))
    rng = np.random.default_rng(7)
    z = rng.random(20000)
    phi = rng.random(20000) * 2 * math.pi
    d = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], -1)
    alpha, _ = m.cloud_alpha(d.astype(np.float32))
    assert abs(float(alpha.mean()) - 0.3) < 0.05


def test_acescg_output_is_the_rec709_map_converted():
    when = dt.datetime(2026, 6, 21, 14, 0, tzinfo=TZ)
    a = render_sky(EnvParams(when=when, weather="overcast"), 64, 32)
    b = render_sky(EnvParams(when=when, weather="overcast", color_space="acescg"), 64, 32)
    from lsd3d_usd.env.colorspace import rec709_to
    np.testing.assert_allclose(b, np.maximum(a @ rec709_to("acescg").T.astype(np.float32), 0),
                               rtol=1e-4, atol=1e-6)
    # white stays white (Bradford-adapted)
    np.testing.assert_allclose(rec709_to("acescg") @ np.ones(3), np.ones(3), atol=1e-3)


def test_bad_resolution_and_params():
    with pytest.raises(InputError):
        render_sky(EnvParams(), 100, 100)
    with pytest.raises(InputError):
        EnvParams(weather="sunny")
    with pytest.raises(InputError):
        EnvParams(turbidity=20.0)
    with pytest.raises(InputError):
        EnvParams(when=dt.datetime(2026, 1, 1))


# ---------------------------------------------------------------- SH irradiance

def _brute_irradiance(img, normals):
    H, W, _ = img.shape
    d = pixel_directions(W, H, np.float64).reshape(-1, 3)
    w = np.repeat(pixel_solid_angles(W, H), W)
    L = img.reshape(-1, 3).astype(np.float64)
    cos = np.maximum(normals @ d.T, 0.0)                    # (N, HW)
    return (cos * w[None]) @ L


def _normals(n=64):
    rng = np.random.default_rng(1)
    v = rng.normal(size=(n, 3))
    v = np.concatenate([v, [[0, 0, 1], [0, 0, -1], [1, 0, 0]]])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_sh_of_low_order_radiance_is_exact():
    # radiance that is exactly order <= 2 in direction: irradiance from SH must match brute force
    H, W = 128, 256
    d = pixel_directions(W, H, np.float64)
    L = np.stack([1 + 0.5 * d[..., 2], 1 + 0.3 * d[..., 0] * d[..., 1],
                  0.7 + 0.2 * d[..., 1] + 0.4 * d[..., 2] ** 2], -1)
    n = _normals()
    np.testing.assert_allclose(eval_sh_irradiance(sh_irradiance(L), n), _brute_irradiance(L, n),
                               rtol=2e-3)
    # constant radiance 1 -> irradiance pi everywhere
    np.testing.assert_allclose(eval_sh_irradiance(sh_irradiance(np.ones((H, W, 3))), n), math.pi,
                               rtol=1e-3)


@pytest.mark.parametrize("weather,hour,tol", [
    ("overcast", 14, 0.01), ("rain", 19, 0.01), ("fog", 9, 0.01), ("partly-cloudy", 11, 0.01),
    # a clear sky's circumsolar peak and sharp horizon carry energy above order 2: the order-2
    # clamped-cosine truncation (Ramamoorthi & Hanrahan) leaves up to ~2 % there
    ("clear", 14, 0.025)])
def test_sh_irradiance_matches_numerical_integration_of_sky(weather, hour, tol):
    p = EnvParams(when=dt.datetime(2026, 6, 21, hour, 0, tzinfo=TZ), weather=weather, sun_disk=False)
    img = render_sky(p, 128, 64)
    n = _normals()
    ref = _brute_irradiance(img, n)
    got = eval_sh_irradiance(sh_irradiance(img), n)
    err = np.abs(got - ref) / ref.max(axis=0)
    assert err.max() < tol, err.max()
