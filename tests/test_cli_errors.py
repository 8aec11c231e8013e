"""One-line errors instead of tracebacks (issue 17): env, PLY and shared CLI checks."""
import os

import numpy as np
import pytest

from lsd3d_usd.errors import InputError
from lsd3d_usd.splats.ply import splat_vertex_array, write_ply_vertices




# ------------------------------------------------------------------------------ env
def test_env_output_below_a_file(tmp_path, capsys, cli_error):
    (tmp_path / "FILE").write_text("x")
    line = cli_error(["env", "-o", tmp_path / "FILE" / "e.exr", "--resolution", "64x32"])
    assert "FILE is a file, not a folder" in line
    assert os.listdir(tmp_path) == ["FILE"]


def test_env_output_is_a_folder(tmp_path, capsys, cli_error):
    line = cli_error(["env", "-o", str(tmp_path) + "/", "--resolution", "64x32"])
    assert "is a folder" in line and os.listdir(tmp_path) == []


@pytest.mark.parametrize("north", ["inf", "-inf", "nan"])
def test_env_non_finite_north(tmp_path, capsys, north, cli_error):
    line = cli_error(["env", "-o", tmp_path / "e.exr", "--resolution", "64x32",
                                   f"--north={north}"])
    # refused by the configuration tree before anything is written
    assert "--north" in line and repr(north) in line and os.listdir(tmp_path) == []


def test_env_huge_resolution_is_refused_before_rendering(tmp_path, capsys, cli_error):
    line = cli_error(["env", "-o", tmp_path / "e.exr", "--resolution", "16384x8192"])
    assert "16384x8192" in line and "exceed the limit of 33554432 pixels" in line
    # a side beyond the tree's bound is refused while the flags are read
    line = cli_error(["env", "-o", tmp_path / "e.exr", "--resolution", "200000x100000"])
    assert "--resolution" in line and "200000" in line
    assert os.listdir(tmp_path) == []


def test_parse_size_limit_is_shared():
    from lsd3d_usd.cliutil import parse_size
    assert parse_size("8192x4096") == (8192, 4096)
    with pytest.raises(InputError, match="--resolution 100000x100000: 10000000000 pixels exceed"):
        parse_size("100000x100000")
    with pytest.raises(InputError, match="exceed"):
        parse_size("100000000", width_only=True)


def test_check_output_path(tmp_path):
    from lsd3d_usd.cliutil import check_output_path
    (tmp_path / "d").mkdir()
    (tmp_path / "f").write_text("")
    assert check_output_path(tmp_path / "new" / "x.usda", suffixes=(".usda",)).name == "x.usda"
    for bad, match in [(tmp_path / "d", "is a folder"), (str(tmp_path / "n") + "/", "is a folder"),
                       (tmp_path / "f" / "a" / "b.usda", "is a file, not a folder"),
                       (tmp_path / "x.txt", "must end in .usda")]:
        with pytest.raises(InputError, match=match):
            check_output_path(bad, suffixes=(".usda",))


# ------------------------------------------------------------------------------ PLY
def _ply(tmp_path, field_factory, n=5):
    path = tmp_path / "s.ply"
    write_ply_vertices(path, splat_vertex_array(field_factory(n, sh_degree=0, semantic=False)))
    return path


@pytest.mark.parametrize("claim,shown", [("1000000000000", "1000000000000"), (str(10**40), "1e+40")])
def test_ply_header_claiming_huge_vertex_counts(tmp_path, field_factory, capsys, claim, shown, cli_error):
    path = _ply(tmp_path, field_factory)
    path.write_bytes(path.read_bytes().replace(b"element vertex 5", f"element vertex {claim}".encode()))
    line = cli_error(["splats", "import-ply", path, "-o", tmp_path / "o.usdc"])
    assert f"vertex count {shown} vertices exceeds the limit of 50000000 vertices" in line
    assert "--max-vertices" in line and sorted(os.listdir(tmp_path)) == ["s.ply"]
    # raising the limit does not make the reader trust the header: the body is too short
    line = cli_error(["splats", "import-ply", path, "-o", tmp_path / "o.usdc",
                                   "--max-vertices", "1e45"])
    assert "truncated" in line and sorted(os.listdir(tmp_path)) == ["s.ply"]


def test_ply_errors_do_not_echo_kilobytes_of_header(tmp_path, field_factory, capsys, cli_error):
    path = _ply(tmp_path, field_factory)
    raw = path.read_bytes()
    for junk in (b"element vertex " + b"9" * 3000, b"property float " + b"q" * 5000 + b" r",
                 b"x" * 5000, b"format " + b"z" * 4000 + b" 1.0"):
        path.write_bytes(raw.replace(b"end_header", junk + b"\nend_header"))
        line = cli_error(["splats", "import-ply", path, "-o", tmp_path / "o.usdc"])
        assert len(line) < 300, line


def test_ply_point_cloud_shares_the_bounded_reader(tmp_path, capsys, cli_error):
    path = tmp_path / "c.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n"
                     b"property float x\nproperty float y\nproperty float z\nend_header\n" + b"\0" * 12)
    line = cli_error(["proxy", "from-points", path, "-o", tmp_path / "p.usdc"])
    assert "vertex count 1000000000000 vertices exceeds the limit" in line


def test_npz_cloud_count_checked_before_decompressing(tmp_path, capsys, cli_error):
    np.savez_compressed(tmp_path / "c.npz", points=np.zeros((1000, 3)))
    line = cli_error(["proxy", "from-points", tmp_path / "c.npz", "-o", tmp_path / "p.usdc",
                                   "--max-vertices", "10"])
    assert "c.npz: array 'points': point count 1000 vertices exceeds the limit of 10 vertices" in line


def test_point_cloud_chunk_limits(tmp_path, capsys, cli_error):
    rng = np.random.default_rng(0)
    np.savez(tmp_path / "c.npz", points=rng.uniform(0, 50, (500, 3)))
    line = cli_error(["proxy", "from-points", tmp_path / "c.npz", "-o", tmp_path / "p.usdc",
                                   "--chunk-size", "0.001"])
    assert "chunk size 0.001 m is below the minimum of 10 m" in line
    line = cli_error(["proxy", "from-points", tmp_path / "c.npz", "-o", tmp_path / "p.usdc",
                                   "--voxel", "0.001"])
    assert "voxel grid" in line and "use a larger --voxel" in line
    line = cli_error(["proxy", "from-points", tmp_path / "c.npz", "-o", tmp_path / "p.usdc",
                                   "--chunk-size", "10", "--max-chunks", "3"])
    assert "chunk count" in line and "exceeds the limit of 3 chunks" in line
    assert sorted(os.listdir(tmp_path)) == ["c.npz"]


def test_ply_out_of_range_values_do_not_leak_numpy_warnings(tmp_path, field_factory, run_cli):
    """opacity logits of -1e30 and log scales of 1e30 overflow exp(): one error line, no
    RuntimeWarning on stderr (run as a user would, in a subprocess)."""
    from lsd3d_usd.splats.ply import read_ply_vertices
    path = _ply(tmp_path, field_factory)
    arr = read_ply_vertices(path).copy()
    arr["opacity"][1] = -1e30
    arr["scale_0"][3] = 1e30
    write_ply_vertices(path, arr)
    r = run_cli("splats", "import-ply", path, "-o", tmp_path / "o.usdc")
    assert r.returncode == 1, r.stderr
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "scales: non-finite values in 1 particle(s), first index 3" in lines[0], lines
    assert "Warning" not in r.stderr
