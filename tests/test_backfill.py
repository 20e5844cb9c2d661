"""``simart backfill``: a Dagster backfill of a scene's stale partitions, submitted to the instance
and run by Dagster's own backfill daemon logic (``execute_backfill_iteration`` over an in-process
code location, runs launched synchronously). A CKM backfill of four tiles is interrupted (two tiles
fail), then resubmitted: the finished tiles are not redone (no file of theirs is rewritten, the new
backfill's runs are exactly the two remaining tiles) and the map is complete."""

from __future__ import annotations

import logging
import shutil
import warnings
from pathlib import Path

import dagster as dg
import pytest
import yaml
from dagster._core.execution.backfill import BulkActionStatus
from dagster._core.remote_origin import InProcessCodeLocationOrigin
from dagster._core.test_utils import create_test_daemon_workspace_context, instance_for_test
from dagster._core.types.loadable_target_origin import LoadableTargetOrigin
from dagster._core.workspace.load_target import InProcessWorkspaceLoadTarget
from dagster._daemon.backfill import execute_backfill_iteration

from conftest import TESTS

from simart_pipeline.assets.staleness import BACKFILL_TAG
from simart_pipeline.cli import main, scene_backfill

TILES = ["r0c0", "r0c1", "r1c0", "r1c1"]
FAILING = {"r1c0", "r1c1"}

LOCATION = """
import dagster as dg
from simart_pipeline.definitions import build_definitions

# the project's Definitions, steps in the run's own process (the test's fault stays in effect)
defs = dg.Definitions.merge(build_definitions(data_root={data!r}, scenes_root={scenes!r}),
                            dg.Definitions(executor=dg.in_process_executor))
"""


def _files(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*")
            if p.is_file() and p.name != "scene_registry.json"}


@pytest.fixture
def four_tiles(tmp_path, monkeypatch):
    """A copy of tiny whose CKM grid has 2 x 2 tiles; SIMART_DATA and SIMART_SCENES point at it."""
    warnings.filterwarnings("ignore", category=dg.BetaWarning)
    scenes, data = tmp_path / "scenes", tmp_path / "data"
    shutil.copytree(TESTS / "scenes" / "tiny", scenes / "tiny")
    path = scenes / "tiny" / "scene.yaml"
    raw = yaml.safe_load(path.read_text())
    raw["ckm"]["tiles"] = [2, 2]
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    monkeypatch.setenv("SIMART_DATA", str(data))
    monkeypatch.setenv("SIMART_SCENES", str(scenes))
    location = tmp_path / "backfill_location.py"
    location.write_text(LOCATION.format(data=str(data), scenes=str(scenes)))
    return scenes / "tiny", data, location


def _run_backfill(context, backfill_id: str, max_iterations: int = 12) -> BulkActionStatus:
    """Dagster's backfill daemon, iteration after iteration, until the backfill is done."""
    instance = context.instance
    for _ in range(max_iterations):
        list(execute_backfill_iteration(context, logging.getLogger("backfill-daemon")))
        status = instance.get_backfill(backfill_id).status
        if status not in (BulkActionStatus.REQUESTED, BulkActionStatus.CANCELING, BulkActionStatus.FAILING):
            return status
    raise AssertionError(f"backfill {backfill_id} still {status} after {max_iterations} iterations")


def _runs(instance, backfill_id: str) -> dict[str, dg.DagsterRunStatus]:
    return {f"{','.join(sorted(k.to_user_string() for k in r.asset_selection))} ({r.tags['dagster/partition']})": r.status
            for r in instance.get_runs(filters=dg.RunsFilter(tags={"dagster/backfill": backfill_id}))}


def test_an_interrupted_ckm_backfill_resumes_without_redoing_finished_tiles(four_tiles, monkeypatch):
    scene, data, location = four_tiles
    origin = InProcessCodeLocationOrigin(LoadableTargetOrigin(python_file=str(location), attribute="defs",
                                                              working_directory=str(location.parent)))
    with instance_for_test(synchronous_run_coordinator=True, synchronous_run_launcher=True) as instance, \
            create_test_daemon_workspace_context(InProcessWorkspaceLoadTarget(origin), instance) as context:
        # first backfill: the scene's meshes and its four CKM tiles; tiles r1c* fail (a fault, where a
        # machine going down would leave them unfinished too), r0c* are written
        from simart_pipeline.ckm import layers

        real = layers.tile_layers

        def faulty(radio, cfg, geom, tile, *args, **kwargs):
            if tile in FAILING:
                raise RuntimeError(f"injected fault in tile {tile}")
            return real(radio, cfg, geom, tile, *args, **kwargs)

        monkeypatch.setattr(layers, "tile_layers", faulty)
        lines = []
        first = scene_backfill(str(scene), ["osm_extract", "paired_meshes", "ckm_layers"], instance=instance,
                               progress=lines.append)
        assert first and any(f"backfill {first}: 6 of 6 asset partitions" in line for line in lines)
        assert instance.get_backfill(first).tags[BACKFILL_TAG] == "cli"
        assert _run_backfill(context, first) in (BulkActionStatus.COMPLETED_FAILED, BulkActionStatus.FAILED)
        runs = _runs(instance, first)
        ok = {k for k, s in runs.items() if s == dg.DagsterRunStatus.SUCCESS}
        # the scene's two assets share a run (same partition), each tile has its own, after them
        assert ok == {"osm_extract,paired_meshes (tiny)", "ckm_layers (tiny|r0c0)", "ckm_layers (tiny|r0c1)"}
        assert {k for k, s in runs.items() if s == dg.DagsterRunStatus.FAILURE} == \
            {f"ckm_layers (tiny|{t})" for t in sorted(FAILING)}
        before = _files(data)
        assert any(p.startswith("ckm/tiny/") for p in before)

        # resume: the same command again; only the two unfinished tiles are submitted
        monkeypatch.setattr(layers, "tile_layers", real)
        lines = []
        second = scene_backfill("tiny", instance=instance, progress=lines.append)
        target = {(k.asset_key.to_user_string(), str(k.partition_key))
                  for k in instance.get_backfill(second).asset_backfill_data.target_subset.iterate_asset_partitions()}
        assert target == {("ckm_layers", f"tiny|{t}") for t in FAILING}
        assert any(f"backfill {second}: 2 of 4 asset partitions of scene 'tiny' (2 up to date)" in line for line in lines)
        assert _run_backfill(context, second) == BulkActionStatus.COMPLETED_SUCCESS
        assert _runs(instance, second) == {f"ckm_layers (tiny|{t})": dg.DagsterRunStatus.SUCCESS for t in sorted(FAILING)}

        # the finished tiles (and the meshes) were not redone: not one file written before is rewritten
        after = _files(data)
        assert {p: after.get(p) for p in before} == before
        new = set(after) - set(before)
        assert new and all(p.startswith("ckm/tiny/") for p in new)
        from simart_pipeline.ckm import mosaic
        from simart_pipeline.ckm.maps import map_groups, map_path
        from simart_pipeline.config import load_scene_config

        cfg = load_scene_config(scene)
        for name in map_groups(cfg):
            assert mosaic.open_map(map_path(data, "tiny", name))["tile_complete"].values.all()

        # and once more: nothing left to do, nothing submitted
        lines = []
        assert scene_backfill("tiny", instance=instance, progress=lines.append) is None
        assert any("nothing to backfill, all 4 asset partitions of ckm_layers are up to date" in line for line in lines)


def test_simart_backfill_submits_to_the_project_instance(four_tiles, tmp_path, monkeypatch, capsys):
    """The command on a DAGSTER_HOME with the repository's dagster.yaml: a backfill of every CKM
    tile is recorded (for the daemon to run), its id and where to watch it printed; wrong
    arguments are one error line."""
    scene, _, _ = four_tiles
    monkeypatch.setenv("DAGSTER_HOME", str(tmp_path / "home"))
    assert main(["backfill", str(scene), "--tile", "r0c1", "r1c1"]) == 0
    out = capsys.readouterr().out
    backfill_id = out.split("backfill ", 1)[1].split(":")[0]
    assert f"/runs/b/{backfill_id}" in out and "simart dev" in out
    instance = dg.DagsterInstance.get()
    try:
        backfill = instance.get_backfill(backfill_id)
        assert backfill.status == BulkActionStatus.REQUESTED
        target = {(k.asset_key.to_user_string(), str(k.partition_key))
                  for k in backfill.asset_backfill_data.target_subset.iterate_asset_partitions()}
        assert target == {("ckm_layers", "tiny|r0c1"), ("ckm_layers", "tiny|r1c1")}
        assert "QueuedRunCoordinator" in type(instance.run_coordinator).__name__  # dagster.yaml's queue and pools
    finally:
        instance.dispose()
    assert main(["backfill", "tiny", "--tile", "r9c9"]) == 1
    assert "--tile r9c9: not among the tiles of scene 'tiny'" in capsys.readouterr().err
    assert main(["backfill", "tiny", "--asset", "ckm"]) == 1
    assert "--asset ckm: no such asset" in capsys.readouterr().err
