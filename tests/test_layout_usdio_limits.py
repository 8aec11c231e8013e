"""USD layout reader: size limits, chunk size, units and up axis (issue 17, items 5 and 8),
and the chunk-count limit of `proxy build`."""
import math
import os

import numpy as np
import pytest

from lsd3d_usd import limits
from lsd3d_usd.cli import main
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import usdio


def layout_text(points, meta="", layer_data="", width=None):
    """A one-lane layout layer; ``meta`` adds stage metadata lines, ``layer_data`` the
    lsd3dLayout dictionary body."""
    pts = ", ".join(f"({x}, {y}, {z})" for x, y, z in points)
    data = f'customLayerData = {{ dictionary lsd3dLayout = {{ {layer_data} }} }}' if layer_data else ""
    widths = f"float[] widths = [{width}]" if width is not None else ""
    return f'''#usda 1.0
(
    defaultPrim = "World"
    {meta}
    {data}
)
def Xform "World"
{{
    def Scope "Layout"
    {{
        def BasisCurves "lane"
        {{
            uniform token lsd3d:featureType = "LaneCenter"
            point3f[] points = [{pts}]
            {widths}
        }}
    }}
}}
'''


def write(tmp_path, text, name="L.usda"):
    p = tmp_path / name
    p.write_text(text)
    return p


Z_UP = 'upAxis = "Z"\n    metersPerUnit = 1'




def test_layout_100km_across_is_refused_up_front(tmp_path, capsys, cli_error):
    p = write(tmp_path, layout_text([(0, 0, 0), (100_000, 0, 0)], Z_UP))
    with pytest.raises(InputError, match=r"features span 100004 m x 3.5 m, more than the limit of 50000 m"):
        usdio.read_layout(p)
    line = cli_error(["proxy", "build", "--layout", str(p), "-o", str(tmp_path / "P.usdc")])
    assert "L.usda" in line and "50000" in line
    assert os.listdir(tmp_path) == ["L.usda"]       # nothing written
    # extent metadata is checked too
    q = write(tmp_path, layout_text([(0, 0, 0), (10, 0, 0)], Z_UP,
                                    "double[] extent = [0, 0, 100000, 100000]"), "E.usda")
    with pytest.raises(InputError, match=r"extent .*: side 100000 m exceeds the limit of 50000 m"):
        usdio.read_layout(q)


@pytest.mark.parametrize("chunk,match", [
    ("0.01", "chunkSize 0.01 m is below the minimum of 10 m"),
    ("0", "chunkSize 0 m is below the minimum of 10 m"),
    ("-5", "below the minimum"),
    ("nan", "chunkSize is nan, not a number"),
    ("inf", "exceeds the limit of 1000 m"),
    ("1e9", "exceeds the limit of 1000 m"),
])
def test_bad_chunk_size_is_refused(tmp_path, chunk, match):
    p = write(tmp_path, layout_text([(0, 0, 0), (10, 0, 0)], Z_UP, f"double chunkSize = {chunk}"))
    with pytest.raises(InputError, match=match):
        usdio.read_layout(p)


@pytest.mark.parametrize("extent,match", [
    ("[0, 0, nan, 100]", "non-finite"),
    ("[0, 0, inf, 100]", "non-finite"),
    ("[100, 0, 0, 100]", "not \\(xmin, ymin, xmax, ymax\\)"),
    ("[0, 0, 100]", "4 numbers"),
])
def test_bad_extent_is_refused(tmp_path, extent, match):
    p = write(tmp_path, layout_text([(0, 0, 0), (10, 0, 0)], Z_UP, f"double[] extent = {extent}"))
    with pytest.raises(InputError, match=match):
        usdio.read_layout(p)


def test_nan_extent_through_proxy_build_is_one_line(tmp_path, capsys, cli_error):
    p = write(tmp_path, layout_text([(0, 0, 0), (10, 0, 0)], Z_UP, "double[] extent = [0, 0, nan, 5]"))
    line = cli_error(["proxy", "build", "--layout", str(p), "-o", str(tmp_path / "P.usdc")])
    assert "lsd3dLayout" in line and "non-finite" in line


def test_centimetre_layout_is_converted_to_metres(tmp_path):
    p = write(tmp_path, layout_text([(1000, 1000, 0), (6000, 1000, 0)], 'upAxis = "Z"\n    metersPerUnit = 0.01',
                                    "double chunkSize = 10000", width=350))
    L = usdio.read_layout(p)
    lane = L.lanes[0]
    np.testing.assert_allclose(lane.points[-1], [60, 10, 0])
    np.testing.assert_allclose(lane.widths, 3.5)
    assert L.chunk_size == 100.0
    assert len(L.chunk_range()[0]) == 1          # 60 m: one chunk, not 60 of them


def test_y_up_layout_is_rotated_to_z_up(tmp_path):
    # Y up: ground plane X-Z; a lane along -Z at height 2 is a lane along +Y at z = 2
    p = write(tmp_path, layout_text([(0, 2, 0), (0, 2, -60)], 'upAxis = "Y"\n    metersPerUnit = 1'))
    lane = usdio.read_layout(p).lanes[0]
    np.testing.assert_allclose(lane.points, [[0, 0, 2], [0, 60, 2]])


def test_unauthored_units_mean_z_up_metres(tmp_path):
    # USD's own fallbacks would be Y up and centimetres; a hand-authored layout means metres
    lane = usdio.read_layout(write(tmp_path, layout_text([(0, 0, 0), (60, 0, 0)]))).lanes[0]
    np.testing.assert_allclose(lane.points[-1], [60, 0, 0])


@pytest.mark.parametrize("meta,match", [
    ('upAxis = "X"', "upAxis 'X' is not Y or Z"),
    ("metersPerUnit = 0", "metersPerUnit 0.0 is not a positive number"),
    ("metersPerUnit = -1", "not a positive number"),
])
def test_bad_units_are_refused(tmp_path, meta, match):
    with pytest.raises(InputError, match=match):
        usdio.read_layout(write(tmp_path, layout_text([(0, 0, 0), (60, 0, 0)], meta)))


def test_proxy_build_chunk_count_limit_and_override(tmp_path, capsys, cli_error):
    big = write(tmp_path, layout_text([(0, 0, 0), (10, 0, 0)], Z_UP,
                                      "double[] extent = [0, 0, 20000, 20000]"), "big.usda")
    line = cli_error(["proxy", "build", "--layout", str(big), "-o", str(tmp_path / "P.usdc")])
    assert "chunk count 40000 chunks exceeds the limit of 10000 chunks" in line and "--max-chunks" in line
    assert not (tmp_path / "P.usdc").exists() and not (tmp_path / "P_chunks").exists()
    small = write(tmp_path, layout_text([(0, 0, 0), (10, 0, 0)], Z_UP,
                                        "double[] extent = [0, 0, 200, 200]"), "small.usda")
    args = ["proxy", "build", "--layout", str(small), "-o", str(tmp_path / "S.usdc")]
    line = cli_error(args + ["--max-chunks", "3"])
    assert "chunk count 4 chunks exceeds the limit of 3 chunks" in line
    assert main(args + ["--max-chunks", "4", "--no-windows"]) == 0


def test_proxy_build_negative_chunk_index(tmp_path, capsys):
    p = write(tmp_path, layout_text([(-50, 10, 0), (50, 10, 0)], Z_UP))
    assert main(["proxy", "build", "--layout", str(p), "-o", str(tmp_path / "P.usdc"),
                 "--chunk", "-1,0", "--no-windows"]) == 0
    assert (tmp_path / "P_chunks" / "chunk_m1_0.usdc").is_file()
    assert "built 1 chunk" in capsys.readouterr().out


def test_limits_are_one_set_of_numbers():
    names = [lim.name for lim in limits.ALL]
    assert len(names) == len(set(names))
    assert all(lim.value > 0 and math.isfinite(lim.value) for lim in limits.ALL)
    doc = (os.path.dirname(__file__) + "/../docs/limits.md")
    text = open(doc).read()
    for lim in limits.ALL:            # docs/limits.md lists every limit with its value
        assert f"`{lim.name}`" in text, lim.name
        assert f"{int(lim.value) if lim.value == int(lim.value) else lim.value}" in text.replace(" ", ""), lim.name


def test_layout_far_from_the_origin_is_refused(tmp_path):
    p = write(tmp_path, layout_text([(0, 2e7, 0), (10, 2e7, 0)], Z_UP))
    with pytest.raises(InputError, match="a coordinate at 2e\\+07 m exceeds the limit of 10000000 m"):
        usdio.read_layout(p)
    q = write(tmp_path, layout_text([(0, 0, 0), (10, 0, 0)], Z_UP, "double[] extent = [1e30, 0, 1e30, 5]"),
              "E.usda")
    with pytest.raises(InputError, match="a corner at 1e\\+30 m exceeds the limit"):
        usdio.read_layout(q)
