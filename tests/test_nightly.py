"""The nightly regeneration (assets/nightly.py) over a test instance, at chosen evaluation times:
before the hour nothing is requested; at the hour, with a materialised scene unchanged, nothing;
after a CKM cell-size edit, one backfill of exactly the partitions that edit stales; nothing is
requested twice (the same night again, or the next night while that backfill is unfinished); a
registered scene never materialised is requested whole."""

from __future__ import annotations

import datetime
import os
import shutil
import warnings
from zoneinfo import ZoneInfo

import dagster as dg
import pytest
import yaml
from dagster._core.execution.backfill import BulkActionStatus, PartitionBackfill
from dagster._core.test_utils import freeze_time

from conftest import TESTS

from simart_pipeline.assets.nightly import nightly_regeneration_sensor
from simart_pipeline.assets.staleness import BACKFILL_TAG, scene_partitions_of
from simart_pipeline.cli import materialize_scene
from simart_pipeline.config import load_scene_config
from simart_pipeline.definitions import build_definitions

TZ = ZoneInfo("Europe/Berlin")  # not the machine's zone (UTC): the sensor must honour its own


def at(day: int, hour: int, minute: int = 0) -> datetime.datetime:
    return datetime.datetime(2026, 11, day, hour, minute, 30, tzinfo=TZ)


def _edit(scene_dir, edit) -> None:
    raw = yaml.safe_load((scene_dir / "scene.yaml").read_text())
    edit(raw)
    (scene_dir / "scene.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))


def _requested(result) -> set[tuple[str, str]]:
    """The asset partitions of the result's backfill requests (there is at most one)."""
    assert len(result.run_requests) <= 1
    assert all(r.requires_backfill_daemon() for r in result.run_requests)  # a backfill, not a run
    return {(k.asset_key.to_user_string(), str(k.partition_key))
            for r in result.run_requests for k in r.asset_graph_subset.iterate_asset_partitions()}


@pytest.fixture(scope="module")
def nightly(tmp_path_factory):
    """A copy of tiny (one weather, to keep it short) materialised through ``simart run``'s path."""
    mp = pytest.MonkeyPatch()
    warnings.filterwarnings("ignore", category=dg.BetaWarning)
    root = tmp_path_factory.mktemp("nightly")
    scenes, data = root / "scenes", root / "data"
    shutil.copytree(TESTS / "scenes" / "tiny", scenes / "tiny")
    _edit(scenes / "tiny", lambda raw: raw.update(weathers=["sunny"]))
    mp.setenv("SIMART_DATA", str(data))
    mp.setenv("SIMART_SCENES", str(scenes))
    instance = dg.DagsterInstance.ephemeral()
    materialize_scene(scenes / "tiny", data, instance=instance, progress=lambda _: None)
    defs = build_definitions(data_root=str(data), scenes_root=str(scenes))
    sensor = nightly_regeneration_sensor("0 2 * * *", "Europe/Berlin")

    def evaluate(when: datetime.datetime, cursor: str | None):
        with freeze_time(when):
            return sensor(dg.build_sensor_context(instance=instance, cursor=cursor, definitions=defs,
                                                  resources={"project": defs.resources["project"]}))

    yield scenes / "tiny", data, instance, defs, evaluate
    mp.undo()


def test_the_nightly_backfill_requests_exactly_what_is_stale_once(nightly):
    scene, data, instance, defs, evaluate = nightly
    # a new sensor, before the hour: nothing, and it remembers the last tick (not a regeneration)
    first = evaluate(at(20, 1, 59), None)
    assert _requested(first) == set() and "first regeneration is at 2026-11-20T02:00:00+01:00" in first.skip_reason.skip_message
    # still before the hour (01:59:30 Berlin is 00:59:30 UTC): nothing
    assert _requested(evaluate(at(20, 1, 59), first.cursor)) == set()
    # at the hour, the scene unchanged since it was materialised: nothing is stale
    night1 = evaluate(at(20, 2, 0), first.cursor)
    assert _requested(night1) == set() and "nothing is stale or missing" in night1.skip_reason.skip_message
    assert night1.cursor != first.cursor

    # the CKM cell size changes: the CKM tiles, the map and the bag that carries the map are stale
    _edit(scene, lambda raw: raw["ckm"].update(cell_size_m=10.0))
    assert _requested(evaluate(at(20, 3, 0), night1.cursor)) == set()  # tonight's tick is handled
    night2 = evaluate(at(21, 2, 1), night1.cursor)
    expected = {("ckm_layers", "tiny|r0c0"), ("ckm_layers", "tiny|r0c1"), ("ckm_map", "tiny"),
                ("session_bag", "tiny|sunny")}
    assert _requested(night2) == expected
    assert night2.run_requests[0].tags[BACKFILL_TAG] == "nightly"
    # the request is one backfill across three partition definitions (scene, scene x tile, scene x weather)
    pds = {str(defs.resolve_asset_graph().get(dg.AssetKey(a)).partitions_def) for a, _ in expected}
    assert len(pds) == 3
    # nothing requested twice: the same night again
    assert _requested(evaluate(at(21, 2, 30), night2.cursor)) == set()

    # the sensor daemon records the request as a backfill; while it is unfinished, the next night
    # leaves its partitions alone
    backfill = PartitionBackfill.from_asset_graph_subset(
        backfill_id="nightly1", backfill_timestamp=at(21, 2, 1).timestamp(), tags=night2.run_requests[0].tags,
        dynamic_partitions_store=instance, asset_graph_subset=night2.run_requests[0].asset_graph_subset,
        title=None, description=None, run_config=None)
    instance.add_backfill(backfill)
    night3 = evaluate(at(22, 2, 1), night2.cursor)
    assert _requested(night3) == set() and "nothing is stale or missing" in night3.skip_reason.skip_message

    # the backfill done (simart run's path computes exactly the stale partitions): nothing on the next night
    lines = []
    materialize_scene(scene, data, instance=instance, progress=lines.append)
    assert {line.split("] ")[1].split(":")[0] for line in lines if ": computing (" in line} == \
        {f"{a} ({p})" for a, p in expected}
    instance.update_backfill(backfill.with_status(BulkActionStatus.COMPLETED_SUCCESS))
    assert _requested(evaluate(at(23, 2, 1), night3.cursor)) == set()


def test_a_registered_scene_never_materialised_is_requested_whole_and_a_broken_one_is_skipped(nightly):
    scene, data, instance, defs, evaluate = nightly
    other = scene.parent / "other"
    shutil.copytree(TESTS / "scenes" / "tiny", other)
    _edit(other, lambda raw: raw.update(name="other"))
    from simart_pipeline import registry

    registry.register(other, data)
    instance.add_dynamic_partitions("scene", ["other", "vanished"])  # "vanished": no folder, no config
    try:
        start = evaluate(at(24, 1, 0), None)
        got = _requested(evaluate(at(24, 2, 0), start.cursor))
        want = {(a, str(k)) for a, k in scene_partitions_of(load_scene_config(other))}
        assert got == want and len(want) == 22  # every partition its config uses (three weathers, two tiles)
    finally:
        instance.delete_dynamic_partition("scene", "other")
        instance.delete_dynamic_partition("scene", "vanished")


def test_the_nightly_cron_and_zone_are_one_setting(monkeypatch):
    import importlib

    import simart_pipeline.assets.nightly as nightly_module

    with pytest.raises(ValueError, match="SIMART_NIGHTLY_CRON"):
        nightly_regeneration_sensor("at two", "UTC")
    monkeypatch.setenv("SIMART_NIGHTLY_CRON", "30 3 * * 1-5")
    monkeypatch.setenv("SIMART_NIGHTLY_TZ", "America/New_York")
    try:
        importlib.reload(nightly_module)
        assert "'30 3 * * 1-5' (America/New_York" in nightly_module.NIGHTLY_SENSOR.description
    finally:
        monkeypatch.undo()
        importlib.reload(nightly_module)
    assert nightly_module.NIGHTLY_CRON == os.environ.get("SIMART_NIGHTLY_CRON", "0 2 * * *")
