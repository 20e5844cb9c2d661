"""A failure inside any asset ends `simart run` with one line naming the partition and the
project's own message, exit status 1, and no stack trace unless --verbose."""

import shutil

import pytest

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
