"""The importer registry: content sniffing, --format, the entry point group (with the example
of docs/extending.md), bad input, and `generate --layout` end to end on a layout imported from
each format."""
import importlib.util
import re
from importlib import metadata
from pathlib import Path

import pytest

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import importers, opendrive_export, usdio
from lsd3d_usd.scene import read_provenance
from pxr import Sdf

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("make_maps", ROOT / "samples/maps/make_maps.py")
make_maps = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_maps)


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    d = tmp_path_factory.mktemp("maps")
    return {"lanelet2": make_maps.lanelet2_crossing(d / "crossing_lanelet2.osm"),
            "osm": make_maps.osm_town(d / "town.osm"),
            "opendrive": make_maps.opendrive_from_layout(d / "crossing.xodr",
                                                         ROOT / "samples/layouts/hand_crossing.usda")}


def test_builtins_in_priority_order():
    names = [i.name for i in importers.registered()]
    assert names[:3] == ["opendrive", "lanelet2", "osm"]
    assert "lanelet2" in importers.formats_help() and "osm" in importers.formats_help()


def test_format_chosen_by_content_not_extension(maps, tmp_path):
    for fmt, path in maps.items():
        renamed = tmp_path / f"map_{fmt}.xml"          # extensions say nothing
        renamed.write_bytes(path.read_bytes())
        assert importers.detect(renamed).name == fmt
    # a Lanelet2 file is OSM XML too: the Lanelet2 importer claims it first; read as plain OSM
    # (--format osm) it has no highways
    assert importers.detect(maps["lanelet2"]).name == "lanelet2"
    with pytest.raises(InputError, match="no drivable highway"):
        importers.read_map(maps["lanelet2"], format="osm")


def test_xml_root_name():
    assert importers.xml_root_name(b'\xef\xbb\xbf<?xml version="1.0"?>\n<!-- c -->\n<OpenDRIVE>') == "OpenDRIVE"
    assert importers.xml_root_name(b"<!DOCTYPE x><osm version='0.6'>") == "osm"
    assert importers.xml_root_name(b"<ns:OpenDRIVE xmlns:ns='u'>") == "OpenDRIVE"
    assert importers.xml_root_name(b"PK\x03\x04 zip") is None
    assert importers.xml_root_name(b"<?xml unterminated") is None


def test_not_the_claimed_format_and_unknown_files(maps, tmp_path):
    with pytest.raises(InputError, match="is not a opendrive file"):
        importers.read_map(maps["osm"], format="opendrive")
    with pytest.raises(InputError, match="is not a lanelet2 file"):
        importers.read_map(maps["osm"], format="lanelet2")
    with pytest.raises(InputError, match="unknown map format 'shapefile'.*opendrive"):
        importers.read_map(maps["osm"], format="shapefile")
    junk = tmp_path / "junk.xodr"
    junk.write_text("<html><body>not a map</body></html>")
    with pytest.raises(InputError, match="not a map format lsd3d-usd reads"):
        importers.read_map(junk)
    empty = tmp_path / "empty.osm"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="empty file"):
        importers.read_map(empty)
    with pytest.raises(InputError, match="no such file"):
        importers.read_map(tmp_path / "missing.osm")
    with pytest.raises(InputError, match="tolerance"):
        importers.read_map(maps["opendrive"], importers.ImportOptions(tolerance=0))


def extending_example() -> str:
    text = (ROOT / "docs/extending.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1
    return blocks[0]


def test_plugin_from_docs_registers_and_imports(monkeypatch, tmp_path):
    (tmp_path / "my_lanes_importer.py").write_text(extending_example())
    monkeypatch.syspath_prepend(str(tmp_path))
    ep = metadata.EntryPoint("lanes_txt", "my_lanes_importer:IMPORTER", importers.ENTRY_POINT_GROUP)
    real = metadata.entry_points
    monkeypatch.setattr(importers.metadata, "entry_points",
                        lambda group=None: [ep] if group == importers.ENTRY_POINT_GROUP else real(group=group))
    assert "lanes-txt" in importers.formats_help()
    f = tmp_path / "city.txt"
    f.write_text("# lanes-txt 1\nin 3.5 0,0 50,0\nout 3.25 50,0 100,10\n")
    layout, imp = importers.read_map(f)
    assert imp.name == "lanes-txt" and [ln.id for ln in layout.lanes] == ["in", "out"]
    assert layout.lanes[1].widths.tolist() == [3.25, 3.25]
    assert layout.metadata["source"]["format"] == "lanes-txt"
    usdio.write_layout(layout, tmp_path / "l.usda")
    assert len(usdio.read_layout(tmp_path / "l.usda").lanes) == 2
    bad = tmp_path / "bad.txt"
    bad.write_text("# lanes-txt 1\nx 3.5 0,0 nope\n")
    with pytest.raises(InputError, match=r"bad.txt:2: lane x"):
        importers.read_map(bad)
    # a built-in format is still found first for its files
    assert importers.detect(ROOT / "samples/layouts/xodr/curved_road.xodr").name == "opendrive"


def test_broken_plugin_warns_and_name_clash_fails(monkeypatch):
    broken = metadata.EntryPoint("broken", "no_such_module_xyz:IMPORTER", importers.ENTRY_POINT_GROUP)
    monkeypatch.setattr(importers.metadata, "entry_points", lambda group=None: [broken])
    with pytest.warns(importers.MapWarning, match="'broken'.*failed to load"):
        names = [i.name for i in importers.registered()]
    assert names == ["opendrive", "lanelet2", "osm"]
    clash = metadata.EntryPoint("osm2", "lsd3d_usd.layout.importers:BUILTIN", importers.ENTRY_POINT_GROUP)
    monkeypatch.setattr(importers.metadata, "entry_points", lambda group=None: [clash])
    with pytest.warns(importers.MapWarning, match="does not give an Importer"):
        importers.registered()


def test_cli_help_lists_formats(run_cli):
    r = run_cli("layout", "import", "--help")
    assert r.returncode == 0
    for name in ("opendrive", "lanelet2", "osm", "--origin LAT,LON", "--bbox"):
        assert name in r.stdout


@pytest.mark.parametrize("fmt", ["opendrive", "lanelet2", "osm"])
def test_generate_runs_on_an_imported_layout(fmt, maps, run_cli, tmp_path):
    """`layout import` then `generate --layout ... --steps 0 --no-actors` (small) per format.
    OpenDRIVE: the curved-road sample (the exported README crossing trips the proxy builder on
    road areas whose edges lie on a chunk border; reported, proxy/ is not this change's)."""
    layout = tmp_path / "layout.usda"
    src = ROOT / "samples/layouts/xodr/curved_road.xodr" if fmt == "opendrive" else maps[fmt]
    r = run_cli("layout", "import", src, "-o", layout)
    assert r.returncode == 0, r.stderr
    prov = read_provenance(Sdf.Layer.FindOrOpen(str(layout)))
    assert prov["params"]["format"] == fmt
    if fmt != "opendrive":
        assert len(prov["params"]["origin"]) == 2
    r = run_cli("generate", "--layout", layout, "-o", tmp_path / "scene", "--steps", "0", "--no-actors",
                "--surfels", "5000", "--resolution", "64x36")
    assert r.returncode == 0, r.stderr[-2000:]
    scene = tmp_path / "scene"
    assert (scene / "scene.usda").is_file() and (scene / "layers/proxy.usdc").is_file()
    assert (scene / "layers/surfels.usdc").is_file()
    assert len(usdio.read_layout(scene / "layers/layout.usda").lanes) > 0


def test_exported_sample_is_valid(maps):
    assert opendrive_export.validate(maps["opendrive"]) == []
