"""Config fuzzing (part of issue 16): randomly mutated bundled scene.yaml files either load or
raise ConfigError with one ``file: key.path: message`` line per problem; never a traceback."""

import math
import os
import random
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from simart_pipeline.config import ConfigError, load_scene_config

ROOT = Path(__file__).resolve().parents[1]
SCENES = sorted(p.parent for p in [*ROOT.glob("scenes/*/scene.yaml"), *ROOT.glob("tests/scenes/*/scene.yaml")])
WEIRD = [None, "", "ü∞☃", 1e308, math.inf, -math.inf, math.nan, 10**40, -1, True, [], {}, "../../etc/passwd",
         "/etc/passwd", [1, "a"], {"x": 1}]


def _keys(node, prefix=()):
    if isinstance(node, dict):
        for k, v in node.items():
            yield (*prefix, k)
            yield from _keys(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield (*prefix, i)
            yield from _keys(v, (*prefix, i))


def _mutate(raw, rng):
    keys = list(_keys(raw))
    if not keys:
        return raw
    key = rng.choice(keys)
    parent = raw
    for k in key[:-1]:
        parent = parent[k]
    op = rng.randrange(3)
    if op == 0:
        parent[key[-1]] = rng.choice(WEIRD)
    elif op == 1 and isinstance(parent, dict):
        del parent[key[-1]]
    elif isinstance(parent, dict):
        parent["unknown_key_" + str(rng.randrange(100))] = rng.choice(WEIRD)
    return raw


# one problem line: the file, a key path (dotted, list indices as numbers) or a place in the YAML
# text, and a message, all on one line
KEY_PATH = r"(\(top level\)|line \d+, column \d+|[A-Za-z_][\w-]*(\.[\w-]+)*)"


def assert_problem_line(line: str, file: Path) -> None:
    assert "\n" not in line, line
    assert re.fullmatch(re.escape(str(file)) + ": " + KEY_PATH + r": \S.*", line), line


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.name)
def test_mutated_scene_yaml_loads_or_lists_problems(scene, tmp_path, capsys):
    from simart_pipeline.cli import main

    rng = random.Random(16)
    original = yaml.safe_load((scene / "scene.yaml").read_text())
    validated = 0
    for i in range(40):
        work = tmp_path / f"m{i}" / scene.name  # the folder keeps the scene's name
        shutil.copytree(scene, work, symlinks=True)
        raw = yaml.safe_load(yaml.safe_dump(original))
        for _ in range(rng.randint(1, 3)):
            raw = _mutate(raw, rng)
        (work / "scene.yaml").write_text(yaml.safe_dump(raw, allow_unicode=True))
        try:
            load_scene_config(work)
        except ConfigError as exc:
            assert exc.problems
            for line in exc.problems:
                assert_problem_line(line, work / "scene.yaml")
            if validated < 8:  # `simart validate` of the same file: the same lines, exit 1, no trace
                validated += 1
                assert main(["validate", str(work)]) == 1
                out = capsys.readouterr()
                assert "Traceback" not in out.out + out.err
                listed = [ln[4:] for ln in out.err.splitlines() if ln.startswith("  - ")]
                assert listed == exc.problems


def test_mutated_scenes_through_a_real_process_end_in_problem_lines(tmp_path):
    rng = random.Random(7)
    scene = next(p for p in SCENES if p.name == "tiny")
    original = yaml.safe_load((scene / "scene.yaml").read_text())
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for i in range(3):
        work = tmp_path / f"p{i}" / "tiny"
        shutil.copytree(scene, work)
        raw = yaml.safe_load(yaml.safe_dump(original))
        raw["clock"]["duration_s"] = [math.nan, "ten", -1.0][i]
        raw = _mutate(raw, rng)
        (work / "scene.yaml").write_text(yaml.safe_dump(raw, allow_unicode=True))
        res = subprocess.run([sys.executable, "-m", "simart_pipeline.cli", "validate", str(work)],
                             capture_output=True, text=True, env=env, timeout=300)
        assert res.returncode == 1 and "Traceback" not in res.stdout + res.stderr
        lines = [ln[4:] for ln in res.stderr.splitlines() if ln.startswith("  - ")]
        assert lines and any(ln.startswith(f"{work / 'scene.yaml'}: clock.duration_s: ") for ln in lines)
        for ln in lines:
            assert_problem_line(ln, work / "scene.yaml")


def _with_path(scene: Path, key: str, value: str) -> None:
    raw = yaml.safe_load((scene / "scene.yaml").read_text())
    if key == "source.path":
        raw["source"] = {"kind": "osm", "path": value}
    elif key == "platforms.0.trajectory.path":
        raw["platforms"][0]["trajectory"] = {"kind": "replay", "path": value}
    elif key == "sensor_imports.0.path":
        raw["sensor_imports"] = [{"path": value, "streams": [
            {"device": raw["platforms"][0]["name"], "sensor": "cam", "kind": "camera", "topic": "/image"}]}]
    elif key == "codebook.path":
        raw["codebook"] = {"path": value}
    (scene / "scene.yaml").write_text(yaml.safe_dump(raw))


PATH_KEYS = ["source.path", "platforms.0.trajectory.path", "sensor_imports.0.path", "codebook.path"]


@pytest.mark.parametrize("key", PATH_KEYS)
@pytest.mark.parametrize("how", ["dotdot", "absolute", "symlink_file", "symlink_dir"])
def test_paths_out_of_the_scene_folder_are_refused_by_key(key, how, tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "x.osm").write_text("<osm/>")
    (outside / "x.csv").write_text("time_ns,x_m,y_m,z_m\n0,0,0,0\n1,1,0,0\n")
    scene = tmp_path / "tiny"
    shutil.copytree(next(p for p in SCENES if p.name == "tiny"), scene)
    name = {"source.path": "x.osm", "platforms.0.trajectory.path": "x.csv", "sensor_imports.0.path": "x.bag",
            "codebook.path": "x.npy"}[key]
    (outside / name).write_bytes(b"0")
    if how == "dotdot":
        value = f"../outside/{name}"
    elif how == "absolute":
        value = str(outside / name)
    elif how == "symlink_file":
        (scene / name).symlink_to(outside / name)
        value = name
    else:
        (scene / "linked").symlink_to(outside, target_is_directory=True)
        value = f"linked/{name}"
    _with_path(scene, key, value)
    with pytest.raises(ConfigError) as exc:
        load_scene_config(scene)
    mine = [p for p in exc.value.problems if p.startswith(f"{scene / 'scene.yaml'}: {key}: ")]
    assert mine and any("inside the scene directory" in p or "points outside the scene directory" in p
                        for p in mine), exc.value.problems


@pytest.mark.parametrize("text", ["", "[1, 2]", "key: [unclosed", "\t- x: :"])
def test_non_mapping_or_broken_yaml_is_a_config_error(text, tmp_path):
    (tmp_path / "scene.yaml").write_text(text)
    with pytest.raises(ConfigError) as err:
        load_scene_config(tmp_path)
    assert all(line.startswith(f"{tmp_path / 'scene.yaml'}: ") for line in err.value.problems)


@pytest.mark.parametrize("text", ["", "[1, 2]", "key: [unclosed", "unknown_key: 1\n"])
def test_simart_validate_of_a_broken_scene_exits_non_zero_without_traceback(text, tmp_path, capsys):
    from simart_pipeline.cli import main

    (tmp_path / "scene.yaml").write_text(text)
    try:
        code = main(["validate", str(tmp_path)])
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    assert code not in (0, None)
    assert "Traceback" not in out.out + out.err
    assert str(tmp_path / "scene.yaml") in out.out + out.err


@pytest.mark.parametrize("content", [b"name: caf\xe9\n", b"\xff\xfe\x00", None])
def test_unreadable_scene_yaml_is_one_problem_line(content, tmp_path):
    if content is None:
        (tmp_path / "scene.yaml").mkdir()  # not a file at all
    else:
        (tmp_path / "scene.yaml").write_bytes(content)
    with pytest.raises(ConfigError) as err:
        load_scene_config(tmp_path)
    (line,) = err.value.problems
    assert_problem_line(line, tmp_path / "scene.yaml")


def test_broken_yaml_is_one_line_with_its_line_number(tmp_path):
    (tmp_path / "scene.yaml").write_text("a: 1\nkey: [unclosed\n")
    with pytest.raises(ConfigError) as err:
        load_scene_config(tmp_path)
    (line,) = err.value.problems
    assert "\n" not in line and line.startswith(f"{tmp_path / 'scene.yaml'}: line ")


@pytest.mark.parametrize("ckm, expected", [
    ({"size_m": [0.0, 10.0]}, "size_m: each side must be within (0, 100000] m"),
    ({"size_m": [-40.0, 30.0]}, "size_m: each side must be within (0, 100000] m"),
    ({"size_m": [1e5, 1e5], "cell_size_m": 0.5}, "the grid has 40,000,000,000 cells"),
])
def test_ckm_grids_no_machine_holds_are_refused_by_key(ckm, expected, tmp_path):
    scene = tmp_path / "tiny"
    shutil.copytree(next(p for p in SCENES if p.name == "tiny"), scene)
    raw = yaml.safe_load((scene / "scene.yaml").read_text())
    raw["ckm"].update(ckm)
    (scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError) as exc:
        load_scene_config(scene)
    (line,) = exc.value.problems
    assert_problem_line(line, scene / "scene.yaml")
    assert line.startswith(f"{scene / 'scene.yaml'}: ckm") and expected in line, line
