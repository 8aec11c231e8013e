"""The viewer's binary buffers (viewer/pack.py): what docs/viewer.md promises about their
precision, size and layout, checked by decoding them again."""
import struct

import numpy as np
import pytest

from lsd3d_usd.viewer import pack


def _field(n=5000, seed=0, deg=1, offset=(0.0, 0.0, 0.0)):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    pos = rng.uniform([0, 0, -3], [100, 100, 30], (n, 3)) + np.asarray(offset)
    k = (deg + 1) ** 2
    return dict(positions=pos, orientations=q, scales=rng.uniform(0.005, 20.0, (n, 2)),
                opacities=rng.uniform(0, 1, n), sh=rng.normal(size=(n, k, 3)) * 0.4,
                semantic_ids=rng.integers(-1, 12, n))


def _angle_deg(a, b):
    return np.degrees(2 * np.arccos(np.clip(np.abs((a * b).sum(1)), 0, 1)))


def test_chunk_round_trip_within_documented_precision():
    f = _field()
    buf = pack.pack_chunk((3, -2), **f)
    d = pack.decode_chunk(buf)
    assert d["key"] == (3, -2) and d["sh_degree"] == 1
    span = f["positions"].max(0) - f["positions"].min(0)
    assert np.all(np.abs(d["positions"] - f["positions"]) <= span / 65535 / 2 + 1e-9)
    assert _angle_deg(d["orientations"], f["orientations"]).max() < 0.25
    assert np.all(np.abs(d["scales"] / f["scales"] - 1) < 2 ** -11)
    assert np.all(np.abs(d["opacities"] - f["opacities"]) <= 0.5 / 255 + 1e-9)
    assert np.all(np.abs(d["sh"][:, 0] - f["sh"][:, 0]) <= np.abs(f["sh"][:, 0]) * 2 ** -11 + 1e-7)
    band1 = np.abs(f["sh"][:, 1:4]).reshape(len(f["sh"]), -1).max(1)
    assert np.all(np.abs(d["sh"][:, 1:4] - f["sh"][:, 1:4]).reshape(len(band1), -1).max(1)
                  <= band1 * (0.5 / 127 + 2 ** -10))
    assert np.array_equal(d["semantic_ids"], f["semantic_ids"])
    # 96-byte header, 6 + 16 + 16 bytes per surfel (position padding to 4 bytes)
    n = len(f["positions"])
    assert len(buf) == 96 + n * 6 + (-(n * 6) % 4) + 32 * n


def _band_error_ok(decoded, original, band):
    """Each surfel's band within half an i8 step of its largest |coefficient| (+ f16 rounding up)."""
    sl = slice(band * band, (band + 1) ** 2)
    n = len(original)
    scale = np.abs(original[:, sl]).reshape(n, -1).max(1)
    err = np.abs(decoded[:, sl] - original[:, sl]).reshape(n, -1).max(1)
    return np.all(err <= scale * (0.5 / 127 + 2 ** -10))


def test_degree_two_round_trip():
    f = _field(deg=2, seed=4)
    f["sh"][::7, 4:] *= 30.0                                    # band 2 larger than band 1 ...
    f["sh"][1::7, 4:] *= 1e-3                                   # ... and much smaller
    buf = pack.pack_chunk((-1, 5), **f)
    d = pack.decode_chunk(buf)
    assert d["key"] == (-1, 5) and d["sh_degree"] == 2 and d["sh"].shape == (len(f["sh"]), 9, 3)
    assert struct.unpack_from("<HB", buf, 4) == (pack.CHUNK_VERSION, 2)
    assert np.all(np.abs(d["sh"][:, 0] - f["sh"][:, 0]) <= np.abs(f["sh"][:, 0]) * 2 ** -11 + 1e-7)
    assert _band_error_ok(d["sh"], f["sh"], 1) and _band_error_ok(d["sh"], f["sh"], 2)
    assert np.array_equal(d["semantic_ids"], f["semantic_ids"])
    # 6 + 16 + 16 (sh1, its spare bytes now m2 and 3 band-2 values) + 16 (sh2) bytes per surfel
    n = len(f["positions"])
    assert len(buf) == 96 + n * 6 + (-(n * 6) % 4) + 48 * n
    # the sh2 block's last 4 bytes are 0
    sh2 = np.frombuffer(buf, np.uint8, 16 * n, len(buf) - 16 * n).reshape(n, 16)
    assert not sh2[:, 12:].any()
    # degree 1 of the same surfels: the degree-2 buffer's sh1 block minus the 5 band-2 bytes
    one = dict(f, sh=f["sh"][:, :4])
    buf1 = pack.pack_chunk((-1, 5), **one)
    assert len(buf1) == len(buf) - 16 * n
    sh1_a = np.frombuffer(buf, np.uint8, 16 * n, len(buf) - 32 * n).reshape(n, 16)
    sh1_b = np.frombuffer(buf1, np.uint8, 16 * n, len(buf1) - 16 * n).reshape(n, 16)
    assert np.array_equal(sh1_a[:, :11], sh1_b[:, :11]) and not sh1_b[:, 11:].any()


def test_degree_zero_and_higher_degrees():
    f = _field(n=7, deg=0)
    d = pack.decode_chunk(pack.pack_chunk((0, 0), **f))
    assert d["sh_degree"] == 0 and d["sh"].shape == (7, 1, 3)
    assert len(pack.pack_chunk((0, 0), **f)) == 96 + 7 * 6 + 2 + 7 * 16
    f3 = _field(n=9, deg=3)
    buf3 = pack.pack_chunk((0, 0), **f3)
    d3 = pack.decode_chunk(buf3)
    assert d3["sh_degree"] == 2 and d3["sh"].shape == (9, 9, 3)   # bands above 2 are not sent
    assert len(buf3) == 96 + 9 * 6 + 2 + 9 * 48
    assert _band_error_ok(d3["sh"], f3["sh"], 1) and _band_error_ok(d3["sh"], f3["sh"], 2)
    # the same as packing the degree-2 truncation
    assert buf3 == pack.pack_chunk((0, 0), **dict(f3, sh=f3["sh"][:, :9]))


def test_version_one_buffers_still_decode():
    """Version 1 (degree 0/1 only) is version 2's layout with the sh1 spare bytes 0."""
    f = _field(n=11)
    buf = bytearray(pack.pack_chunk((2, 2), **f))
    buf[4:6] = struct.pack("<H", 1)
    d = pack.decode_chunk(bytes(buf))
    assert d["sh_degree"] == 1 and _band_error_ok(d["sh"], f["sh"], 1)
    buf2 = bytearray(pack.pack_chunk((2, 2), **_field(n=11, deg=2)))
    buf2[4:6] = struct.pack("<H", 1)                            # v1 never had degree 2
    with pytest.raises(ValueError, match="LSDV v1"):
        pack.decode_chunk(bytes(buf2))
    buf2[4:6] = struct.pack("<H", 3)
    with pytest.raises(ValueError, match="LSDV"):
        pack.decode_chunk(bytes(buf2))


def test_positions_far_from_the_origin_keep_millimetres():
    f = _field(n=2000, offset=(9800.0, -4200.0, 0.0))
    d = pack.decode_chunk(pack.pack_chunk((98, -42), **f))
    assert np.abs(d["positions"] - f["positions"]).max() < 1e-3


def test_degenerate_inputs():
    one = _field(n=1)
    d = pack.decode_chunk(pack.pack_chunk((0, 0), **one))     # zero extent: lo == hi
    assert np.allclose(d["positions"], one["positions"])
    flat = _field(n=50)
    flat["sh"][:, 1:] = 0.0                                     # zero band-1 scale
    flat["orientations"][:] = [0, 0, 0, -1]                     # q and -q are one rotation
    d = pack.decode_chunk(pack.pack_chunk((0, 0), **flat))
    assert np.all(d["sh"][:, 1:] == 0) and _angle_deg(d["orientations"], flat["orientations"]).max() < 1e-6
    two = _field(n=50, deg=2)
    two["sh"][:, 4:] = 0.0                                      # zero band-2 scale
    two["sh"][:5, 1:4] = 0.0                                    # and some with band 1 zero too
    d = pack.decode_chunk(pack.pack_chunk((0, 0), **two))
    assert d["sh_degree"] == 2 and np.all(d["sh"][:, 4:] == 0) and np.all(d["sh"][:5, 1:4] == 0)
    assert _band_error_ok(d["sh"], two["sh"], 1)
    one2 = _field(n=1, deg=2)                                   # one surfel: lo == hi, degree 2
    d = pack.decode_chunk(pack.pack_chunk((0, 0), **one2))
    assert d["sh"].shape == (1, 9, 3) and _band_error_ok(d["sh"], one2["sh"], 2)
    empty = {k: v[:0] for k, v in _field(n=3).items()}
    assert pack.decode_chunk(pack.pack_chunk((1, 1), **empty))["positions"].shape == (0, 3)
    empty2 = {k: v[:0] for k, v in _field(n=3, deg=2).items()}
    assert pack.decode_chunk(pack.pack_chunk((1, 1), **empty2))["sh"].shape == (0, 9, 3)
    with pytest.raises(ValueError, match="LSDV"):
        pack.decode_chunk(b"XXXX" + bytes(200))


def test_binning_is_the_scene_grid():
    pos = np.array([[0.0, 0.0, 0], [99.99, 0.0, 0], [100.0, 0.0, 0], [-0.01, -100.0, 0], [-100.0, 250.0, 0]])
    bins = pack.bin_by_chunk(pos, 100.0)
    assert {k: v.tolist() for k, v in bins.items()} == {(0, 0): [0, 1], (1, 0): [2], (-1, -1): [3], (-1, 2): [4]}


def test_env_and_mesh_buffers():
    img = np.random.default_rng(1).uniform(0, 5, (8, 16, 3)).astype(np.float32)
    img[0, 0] = [1e6, np.nan, -1]                               # out of half range, NaN, negative
    buf = pack.pack_env(img)
    magic, _, _, w, h = pack.ENV_HEADER.unpack_from(buf, 0)
    px = np.frombuffer(buf, "<f2", offset=16).reshape(h, w, 4).astype(np.float32)
    assert (magic, w, h) == (b"LSDE", 16, 8)
    assert np.allclose(px[1:, :, :3], img[1:], rtol=1e-3) and np.all(px[..., 3] == 1)
    assert px[0, 0, :3].tolist() == [65504.0, 0.0, 0.0]
    wide = np.ones((2048, 4096, 3), np.float32)
    assert pack.ENV_HEADER.unpack_from(pack.pack_env(wide), 0)[3:] == (2048, 1024)

    tri = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.]]), np.array([[0, 1, 2]]), np.array([0.5, 0.25, 1.0]))
    buf = pack.pack_mesh([tri, tri])
    _, _, _, nv, nt = pack.MESH_HEADER.unpack_from(buf, 0)
    assert (nv, nt) == (6, 2)
    idx = np.frombuffer(buf, "<u4", offset=16 + nv * 16)
    assert idx.tolist() == [0, 1, 2, 3, 4, 5]
    col = np.frombuffer(buf, np.uint8, nv * 4, 16 + nv * 12).reshape(nv, 4)
    assert col[0].tolist() == [128, 64, 255, 255]
    assert struct.unpack_from("<3f", buf, 16 + 12) == (1.0, 0.0, 0.0)
