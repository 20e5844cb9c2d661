"""The Definitions object loads, `dagster definitions validate` accepts it, the CLI explains itself."""

import os
import subprocess
import sys

import dagster as dg
import pytest

from simart_pipeline.cli import main
from simart_pipeline.definitions import defs

EXPECTED = {"osm_extract", "paired_meshes", "trajectory", "sensor_frames", "cirs", "radar_frames", "kpis", "ckm_layers",
            "ckm_map", "session", "session_bag", "beam_prediction"}


def test_definitions_load_with_every_asset_and_partitioning():
    graph = defs.resolve_asset_graph()
    keys = {k.to_user_string() for k in graph.get_all_asset_keys()}
    assert keys == EXPECTED | {f"scene_config/{n}" for n in EXPECTED}  # each stage's part of scene.yaml
    by_name = {k.to_user_string(): graph.get(k) for k in graph.get_all_asset_keys()}
    scene_only = {"osm_extract", "paired_meshes", "trajectory", "ckm_map", "beam_prediction"}
    for name, node in by_name.items():
        if name.startswith("scene_config/"):  # partitioned like the stage that reads it
            assert node.partitions_def == by_name[name.split("/")[1]].partitions_def
            continue
        pd = node.partitions_def
        if name in scene_only:
            assert isinstance(pd, dg.DynamicPartitionsDefinition) and pd.name == "scene"
        else:
            assert isinstance(pd, dg.MultiPartitionsDefinition)
            dims = {d.name for d in pd.partitions_defs}
            assert dims == ({"scene", "tile"} if name == "ckm_layers" else
                            {"scene", "weather_group"} if name in ("cirs", "radar_frames") else {"scene", "weather"})
    # lineage: session gathers sensors, channels and KPIs; ckm depends on the meshes
    def parents(n):
        return {k.to_user_string() for k in by_name[n].parent_keys} - {f"scene_config/{n}"}

    assert all(f"scene_config/{n}" in {k.to_user_string() for k in by_name[n].parent_keys} for n in EXPECTED)
    assert parents("session") == {"trajectory", "sensor_frames", "cirs", "kpis"}
    assert parents("cirs") == {"paired_meshes", "trajectory", "osm_extract"}
    assert parents("ckm_layers") == {"paired_meshes", "osm_extract"}
    assert parents("kpis") == {"cirs"}
    assert parents("ckm_map") == {"ckm_layers", "osm_extract"}
    assert parents("beam_prediction") == {"trajectory", "sensor_frames", "kpis"}


def test_dagster_definitions_validate(tmp_path):
    env = dict(os.environ, DAGSTER_HOME=str(tmp_path))
    r = subprocess.run([sys.executable, "-m", "dagster", "definitions", "validate",
                        "-m", "simart_pipeline.definitions"], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.parametrize("argv", [["--help"], ["run", "--help"], ["validate", "--help"], ["scenes", "--help"]])
def test_help_explains_itself(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "usage: simart" in out and len(out) > 200


def test_validate_reports_problems_and_exit_status(tiny_scene, capsys):
    assert main(["validate", str(tiny_scene)]) == 0
    text = (tiny_scene / "scene.yaml").read_text().replace("max_depth: 2", "max_depth: 2, max_dept: 1")
    (tiny_scene / "scene.yaml").write_text(text)
    assert main(["validate", str(tiny_scene)]) == 1
    err = capsys.readouterr().err
    assert f"{tiny_scene / 'scene.yaml'}: ray_tracing.max_dept: Extra inputs are not permitted" in err


def test_scenes_lists_the_demo(capsys):
    assert main(["scenes"]) == 0
    assert "demo" in capsys.readouterr().out


def test_run_refuses_an_invalid_scene_before_any_work(tiny_scene, tmp_path, capsys):
    (tiny_scene / "scene.yaml").write_text((tiny_scene / "scene.yaml").read_text().replace("speed_mps: 10.0", "speed_mps: -1"))
    data = tmp_path / "data"
    assert main(["run", str(tiny_scene), "--data", str(data)]) == 1
    assert "platforms.0.trajectory.speed_mps" in capsys.readouterr().err
    assert not data.exists()


def test_preflight_names_the_fix_when_llvm_is_too_old(monkeypatch):
    from simart_pipeline import engine

    monkeypatch.setattr(engine, "cuda_available", lambda: False)
    monkeypatch.setattr(engine, "_llvm_candidates", lambda: [(15, "/usr/lib/libLLVM-15.so")])
    with pytest.raises(engine.PreflightError, match="libllvm19"):
        engine.preflight()


def test_config_observations_use_dagsters_data_version_tag():
    from dagster._core.definitions.data_version import DATA_VERSION_TAG

    from simart_pipeline.assets import config_sources

    assert config_sources.DATA_VERSION_TAG == DATA_VERSION_TAG
