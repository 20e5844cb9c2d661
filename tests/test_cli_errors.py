"""A failure inside any asset ends `simart run` with one line naming the partition and the
project's own message, exit status 1, and no stack trace unless --verbose; so does every failure of
`simart scene build`, `simart ckm` (its export) and `simart validate`, whose last line names the file,
the key or topic and what is wrong."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO

from simart_pipeline import versions
from simart_pipeline.assets import versioning
from simart_pipeline.cli import main

ASSETS = ["osm_extract", "paired_meshes", "trajectory", "sensor_frames", "cirs", "kpis", "session", "ckm_layers",
          "ckm_map"]


@pytest.fixture(scope="module")
def materialised(tmp_path_factory):
    """tests/scenes/tiny materialised by `simart run` on a DAGSTER_HOME of its own."""
    from conftest import TESTS

    root = tmp_path_factory.mktemp("cli_errors")
    scene, home, data = root / "tiny", root / "dagster_home", root / "data"
    shutil.copytree(TESTS / "scenes" / "tiny", scene)
    home.mkdir()
    mp = pytest.MonkeyPatch()
    mp.setenv("DAGSTER_HOME", str(home))
    try:
        assert main(["run", str(scene), "--data", str(data), "--weather", "sunny", "--tile", "r0c0"]) == 0
    finally:
        mp.undo()
    return scene, home, data


@pytest.mark.parametrize("asset", ASSETS)
def test_a_failure_inside_an_asset_is_one_line(asset, materialised, monkeypatch, capsys):
    scene, home, data = materialised
    monkeypatch.setenv("DAGSTER_HOME", str(home))
    real_code_version, real_version = versions.code_version, versioning.partition_version
    # the asset's code "changed", so the run computes it again; computing it raises the project's error
    monkeypatch.setattr(versions, "code_version", lambda a: "edited" if a == asset else real_code_version(a))

    def failing(context, project, name):
        if name == asset:
            raise ValueError(f"{scene / 'scene.yaml'}: some.key: what is wrong in {asset}, and what to try")
        return real_version(context, project, name)

    monkeypatch.setattr(versioning, "partition_version", failing)
    capsys.readouterr()
    code = main(["run", str(scene), "--data", str(data), "--weather", "sunny", "--tile", "r0c0"])
    out, err = capsys.readouterr()
    assert code == 1
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"error: {asset} (tiny")
    assert f"some.key: what is wrong in {asset}, and what to try (ValueError)" in last
    assert "Traceback" not in out + err and "DagsterExecutionStepExecutionError" not in out + err

    capsys.readouterr()
    assert main(["run", str(scene), "--data", str(data), "--weather", "sunny", "--tile", "r0c0", "--verbose"]) == 1
    out, err = capsys.readouterr()
    assert "Traceback" in out + err or 'File "' in out + err  # the trace, when asked for


# --- the other commands: scene build, ckm (export), validate --------------------------------------

URBAN = REPO / "scenes" / "urban" / "urban.osm"  # a small valid extract


def _fails_with_one_line(argv, capsys, *parts, code=1) -> str:
    """``simart ARGV`` exits ``code``; the last line of stderr holds every one of ``parts`` (the
    file, the key or topic, what is wrong) and nothing prints a trace; returns that line."""
    capsys.readouterr()
    if code == 2:  # argparse: a bad argument value
        with pytest.raises(SystemExit) as e:
            main(argv)
        got = e.value.code
    else:
        got = main(argv)
    out, err = capsys.readouterr()
    assert got == code, out + err
    last = err.strip().splitlines()[-1]
    for part in parts:
        assert str(part) in last, (part, last)
    assert "Traceback" not in out + err
    return last


@pytest.fixture
def bad_sources(tmp_path):
    d = tmp_path / "src"
    d.mkdir()
    (d / "malformed.osm").write_text("<osm version='0.6'><node id='1' lat='48.1' lon='10.0'><tag k='a'")
    (d / "empty.osm").write_text("<?xml version='1.0'?>\n<osm version='0.6'></osm>\n")
    (d / "garbage.osm.pbf").write_bytes(bytes(range(256)) * 2)
    (d / "broken.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 9\n")
    (d / "broken.ply").write_bytes(b"garbage\x00\x01")
    (d / "notes.txt").write_text("hello")
    return d


@pytest.mark.parametrize("source,parts", [
    ("malformed.osm", ["malformed.osm: not a readable OSM file", "XML parsing error"]),
    ("garbage.osm.pbf", ["garbage.osm.pbf: not a readable OSM file"]),
    ("empty.osm", ["empty.osm: the extract is empty"]),
    ("broken.obj", ["broken.obj: cannot read the .obj file"]),
    ("broken.ply", ["broken.ply: cannot read the .ply file"]),
    ("notes.txt", ["notes.txt: unknown source type"]),
    ("missing.osm", ["missing.osm: no such file"]),
])
def test_scene_build_bad_sources_are_one_line_and_keep_the_existing_scene(source, parts, bad_sources, tmp_path,
                                                                          capsys):
    out = tmp_path / "scene"
    assert main(["scene", "build", str(URBAN), "--out", str(out)]) == 0
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    last = _fails_with_one_line(["scene", "build", str(bad_sources / source), "--out", str(out), "--force"],
                                capsys, *parts)
    assert last.startswith(f"error: {bad_sources / source}: ")
    # the scene already built is untouched, and nothing is left aside
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene", "src"]


@pytest.mark.parametrize("args,parts", [
    (["--bbox", "10,48,11"], ["argument --bbox", "expected 4 numbers, got 3"]),
    (["--bbox", "11,48,10,49"], ["argument --bbox", "MIN_LON < MAX_LON"]),
    (["--origin", "100,10"], ["argument --origin", "latitude 100.0", "out of range"]),
    (["--origin", "north,10"], ["argument --origin", "not a comma-separated list of numbers"]),
])
def test_scene_build_bad_arguments_are_one_line(args, parts, tmp_path, capsys):
    _fails_with_one_line(["scene", "build", str(URBAN), "--out", str(tmp_path / "o"), *args], capsys, *parts,
                         code=2)
    assert not (tmp_path / "o").exists()


def test_scene_build_a_bbox_without_buildings_is_one_line(tmp_path, capsys):
    _fails_with_one_line(["scene", "build", str(URBAN), "--out", str(tmp_path / "o"), "--bbox",
                          "10,10,10.001,10.001"], capsys, f"{URBAN}: no building inside the bounding box")
    assert not (tmp_path / "o").exists()


def test_scene_build_unsafe_and_existing_outputs_are_refused(tmp_path, capsys, monkeypatch):
    work = tmp_path / "work"
    (work / "sub").mkdir(parents=True)
    keep = work / "sub" / "keep.txt"
    keep.write_text("mine")
    src = work / "sub" / "urban.osm"
    src.write_bytes(URBAN.read_bytes())
    monkeypatch.chdir(work)
    _fails_with_one_line(["scene", "build", str(src), "--out", ".", "--force"], capsys,
                         "error: .: unsafe output directory")
    _fails_with_one_line(["scene", "build", str(src), "--out", str(tmp_path), "--force"], capsys,
                         f"error: {tmp_path}: unsafe output directory")  # a parent of the working dir
    _fails_with_one_line(["scene", "build", str(src), "--out", "sub", "--force"], capsys,
                         "error: sub: holds the source file")
    _fails_with_one_line(["scene", "build", str(src), "--out", "sub"], capsys,
                         "error: sub: holds the source file")
    _fails_with_one_line(["scene", "build", str(src), "--out", "sub/keep.txt/x"], capsys,
                         "error: sub/keep.txt/x: --out:", "keep.txt is a file, not a directory")
    _fails_with_one_line(["scene", "build", str(src), "--out", "sub/keep.txt", "--force"], capsys,
                         "error: sub/keep.txt: exists and is not a directory")
    other = work / "other"
    other.mkdir()
    (other / "x").write_text("x")
    _fails_with_one_line(["scene", "build", str(src), "--out", "other"], capsys,
                         "error: other: directory exists and is not empty; pass --force")
    assert keep.read_text() == "mine" and src.read_bytes() == URBAN.read_bytes() and (other / "x").exists()
    assert sorted(p.name for p in work.iterdir()) == ["other", "sub"]
    assert sorted(p.name for p in (work / "sub").iterdir()) == ["keep.txt", "urban.osm"]


def test_ckm_failures_are_one_line(materialised, tmp_path, capsys):
    scene, home, data = materialised
    the_map = data / "ckm" / "tiny" / "sunny.zarr"
    _fails_with_one_line(["ckm", str(scene), "--data", str(tmp_path / "empty")], capsys,
                         f"no channel knowledge map at {tmp_path / 'empty' / 'ckm' / 'tiny' / 'sunny.zarr'}",
                         "materialise ckm_layers first")
    _fails_with_one_line(["ckm", "no_such_scene", "--data", str(data)], capsys,
                         "scene 'no_such_scene': not registered in")
    _fails_with_one_line(["ckm", str(scene), "--data", str(data), "--weather", "hail"], capsys,
                         "weather 'hail'", "ckm.weathers")
    _fails_with_one_line(["ckm", str(scene), "--data", str(data), "--layer", "sinr_db", "no_layer"], capsys,
                         f"error: {the_map}: --layer: no layer no_layer; layers:")
    _fails_with_one_line(["ckm", str(scene), "--data", str(data), "--export", str(tmp_path / "x.nc")], capsys,
                         f"error: {tmp_path / 'x.nc'}: --export: give a .zarr path")
    not_a_store = tmp_path / "mine.zarr"
    not_a_store.mkdir()
    (not_a_store / "notes").write_text("mine")
    _fails_with_one_line(["ckm", str(scene), "--data", str(data), "--export", str(not_a_store)], capsys,
                         f"error: {not_a_store}: --export: exists and is not a Zarr store")
    assert (not_a_store / "notes").read_text() == "mine"
    before = sorted(p.relative_to(the_map) for p in the_map.rglob("*"))
    _fails_with_one_line(["ckm", str(scene), "--data", str(data), "--export", str(the_map)], capsys,
                         f"error: {the_map}: --export: is (or holds, or lies inside) the map")
    assert sorted(p.relative_to(the_map) for p in the_map.rglob("*")) == before
    (tmp_path / "afile").write_text("x")
    _fails_with_one_line(["ckm", str(scene), "--data", str(data), "--export", str(tmp_path / "afile" / "m.zarr")],
                         capsys, "--export:", "afile is a file, not a directory")
    # unwritable: /proc takes no new directories, even for root
    _fails_with_one_line(["ckm", str(scene), "--data", str(data), "--export", "/proc/simart_test.zarr"], capsys,
                         "error: /proc/simart_test.zarr: --export: cannot write there:")
    # and the export works, twice (a previous export is a store: replaced)
    out = tmp_path / "copy.zarr"
    for _ in range(2):
        assert main(["ckm", str(scene), "--data", str(data), "--layer", "sinr_db", "--export", str(out)]) == 0


def test_run_argument_failures_are_one_line(tiny_scene, tmp_path, capsys):
    data = tmp_path / "data"
    _fails_with_one_line(["run", str(tiny_scene), "--data", str(data), "--weather", "hail"], capsys,
                         "error: --weather hail: not among the weathers of scene 'tiny': ['sunny'")
    _fails_with_one_line(["run", str(tiny_scene), "--data", str(data), "--tile", "r9c9"], capsys,
                         "error: --tile r9c9: not among the tiles of scene 'tiny': ['r0c0'")
    _fails_with_one_line(["run", str(tmp_path / "nowhere"), "--data", str(data)], capsys,
                         f"- {tmp_path / 'nowhere' / 'scene.yaml'}: (top level): no scene.yaml")
    assert not list(data.rglob("*.zarr"))  # nothing was run


def test_a_config_with_several_problems_ends_with_the_last_one(tiny_scene, tmp_path, capsys):
    yaml_file = tiny_scene / "scene.yaml"
    text = yaml_file.read_text().replace("max_depth: 2", "max_depth: 2, max_dept: 1, max_dpth: 1")
    yaml_file.write_text(text)
    last = _fails_with_one_line(["ckm", str(tiny_scene), "--data", str(tmp_path)], capsys,
                                "error: 2 problems, the last:", f"{yaml_file}: ray_tracing.max_dpth:")
    assert "Extra inputs are not permitted" in last


def test_validate_failures_are_one_line(tmp_path, capsys):
    _fails_with_one_line(["validate", str(tmp_path / "nowhere")], capsys,
                         f"error: {tmp_path / 'nowhere'}: no such directory")
    bad_yaml, not_utf8, yaml_dir = tmp_path / "bad_yaml", tmp_path / "not_utf8", tmp_path / "yaml_dir"
    for d in (bad_yaml, not_utf8, yaml_dir):
        d.mkdir()
    (bad_yaml / "scene.yaml").write_text("name: [unclosed\n")
    (not_utf8 / "scene.yaml").write_bytes(b"\xff\xfename: x\n")
    (yaml_dir / "scene.yaml").mkdir()
    _fails_with_one_line(["validate", str(bad_yaml)], capsys,
                         f"- {bad_yaml / 'scene.yaml'}: line 2, column 1: not valid YAML:")
    _fails_with_one_line(["validate", str(not_utf8)], capsys, f"- {not_utf8 / 'scene.yaml'}: (top level): not UTF-8 text")
    _fails_with_one_line(["validate", str(yaml_dir)], capsys, f"- {yaml_dir / 'scene.yaml'}:")


def test_verbose_prints_the_trace_before_the_one_line(bad_sources, tmp_path, capsys):
    for argv in (["scene", "build", str(bad_sources / "malformed.osm"), "--out", str(tmp_path / "o"), "--verbose"],
                 ["--verbose", "ckm", str(tmp_path / "no_scene"), "--data", str(tmp_path)]):
        capsys.readouterr()
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert "Traceback" in err and err.strip().splitlines()[-1].startswith("error: ")


@pytest.mark.parametrize("argv", [["validate", "{tmp}/nowhere"], ["scene", "build", "{src}/malformed.osm", "--out",
                                  "{tmp}/o"], ["ckm", "{tmp}", "--data", "{tmp}/data"]])
def test_a_failing_command_in_a_process_prints_no_trace(argv, bad_sources, tmp_path):
    (tmp_path / "scene.yaml").write_text(Path(REPO / "tests" / "scenes" / "tiny" / "scene.yaml").read_text())
    argv = [a.format(tmp=tmp_path, src=bad_sources) for a in argv]
    r = subprocess.run([sys.executable, "-m", "simart_pipeline.cli", *argv], capture_output=True, text=True,
                       cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=120)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stdout + r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("error: ")
