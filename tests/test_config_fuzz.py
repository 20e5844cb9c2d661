"""Config fuzzing (part of issue 16): randomly mutated bundled scene.yaml files either load or
raise ConfigError with one ``file: key.path: message`` line per problem; never a traceback."""

import math
import random
import shutil
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


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.name)
def test_mutated_scene_yaml_loads_or_lists_problems(scene, tmp_path):
    rng = random.Random(16)
    original = yaml.safe_load((scene / "scene.yaml").read_text())
    for i in range(40):
        work = tmp_path / f"m{i}"
        shutil.copytree(scene, work, symlinks=True)
        raw = _mutate(yaml.safe_load(yaml.safe_dump(original)), rng)
        (work / "scene.yaml").write_text(yaml.safe_dump(raw, allow_unicode=True))
        try:
            load_scene_config(work)
        except ConfigError as exc:
            assert exc.problems
            for line in exc.problems:
                assert line.startswith(f"{work / 'scene.yaml'}: "), line


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


def test_broken_yaml_is_one_line_with_its_line_number(tmp_path):
    (tmp_path / "scene.yaml").write_text("a: 1\nkey: [unclosed\n")
    with pytest.raises(ConfigError) as err:
        load_scene_config(tmp_path)
    (line,) = err.value.problems
    assert "\n" not in line and line.startswith(f"{tmp_path / 'scene.yaml'}: line ")
