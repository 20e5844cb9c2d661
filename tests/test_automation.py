"""Declarative automation over a test instance (no daemon): a new scene requests its first
materialisations, stage after stage, each partition the scene's config uses exactly once and no
other; a changed upstream requests exactly what depends on it."""

from __future__ import annotations

import warnings

import dagster as dg
import pytest

from conftest import TESTS

from simart_pipeline import registry, versions
from simart_pipeline.assets.config_sources import report_config_versions
from simart_pipeline.ckm.grid import scene_tiles
from simart_pipeline.definitions import build_definitions
from simart_pipeline.radio.materials import WEATHER_GROUP

TINY = TESTS / "scenes" / "tiny"


def _requested(result) -> set[tuple[str, str]]:
    return {(e.key.to_user_string(), str(p)) for e in result.results for p in result.get_requested_partitions(e.key)}


def _materialise(instance, graph, requested) -> None:
    """Record a materialisation of each requested partition, as the runs would."""
    for asset, part in requested:
        pd = graph.get(dg.AssetKey.from_user_string(asset)).partitions_def
        key = part
        if isinstance(pd, dg.MultiPartitionsDefinition):
            sub = next(d.name for d in pd.partitions_defs if d.name != "scene")
            key = dg.MultiPartitionKey(dict(zip(("scene", sub), part.split("|"))))
        instance.report_runless_asset_event(dg.AssetMaterialization(dg.AssetKey.from_user_string(asset), partition=key))


@pytest.fixture
def automated(tmp_path, monkeypatch):
    monkeypatch.setenv("SIMART_DATA", str(tmp_path))
    warnings.filterwarnings("ignore", category=dg.BetaWarning)
    defs = build_definitions(data_root=str(tmp_path))
    return defs, dg.DagsterInstance.ephemeral(), tmp_path


def test_a_new_scene_is_materialised_stage_by_stage_once_and_only_where_its_config_says(automated):
    defs, instance, data = automated
    graph = defs.resolve_asset_graph()
    first = dg.evaluate_automation_conditions(defs=defs, instance=instance)
    assert _requested(first) == set()
    cfg = registry.register(TINY, data)
    instance.add_dynamic_partitions("scene", [cfg.name])
    report_config_versions(instance, versions.VersionPlan(cfg, TINY))
    cursor, ticks, seen = first.cursor, [], []
    for _ in range(10):
        result = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=cursor)
        cursor, got = result.cursor, _requested(result)
        if not got:
            break
        ticks.append(got)
        seen += sorted(got)
        _materialise(instance, graph, got)
    assert ticks[0] == {("osm_extract", "tiny")}  # the root first, then what it feeds
    assert len(seen) == len(set(seen))  # nothing requested twice
    weathers, groups = set(cfg.weathers), {WEATHER_GROUP[w] for w in cfg.weathers}
    expected = {("osm_extract", "tiny"), ("paired_meshes", "tiny"), ("trajectory", "tiny"), ("ckm_map", "tiny")}
    expected |= {(a, f"tiny|{g}") for a in ("cirs", "radar_frames") for g in groups}
    expected |= {(a, f"tiny|{w}") for a in ("sensor_frames", "kpis", "session", "session_bag") for w in weathers}
    expected |= {("ckm_layers", f"tiny|{t}") for t in scene_tiles(cfg.ckm)}
    assert set(seen) == expected  # every partition the config uses, no tile or weather beyond them
    # each stage waits for its upstream: a session after its KPIs, a bag after its session
    tick_of = {k: i for i, t in enumerate(ticks) for k in t}
    assert tick_of[("session", "tiny|sunny")] > tick_of[("kpis", "tiny|sunny")] > tick_of[("cirs", "tiny|sunny")]
    assert tick_of[("session_bag", "tiny|sunny")] > tick_of[("ckm_map", "tiny")] > tick_of[("ckm_layers", "tiny|r0c0")]

    # a new trace of the rainy radio: exactly what reads it (transitively) is requested, once
    _materialise(instance, graph, {("cirs", "tiny|rainy")})
    result = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=cursor)
    assert _requested(result) == {("kpis", "tiny|rainy"), ("session", "tiny|rainy"), ("session_bag", "tiny|rainy")}
    again = dg.evaluate_automation_conditions(defs=defs, instance=instance, cursor=result.cursor)
    assert _requested(again) == set()


def test_the_automation_sensor_is_declared_and_on_by_default(automated):
    defs, _, _ = automated
    sensor = defs.resolve_sensor_def("keep_scenes_fresh")
    assert sensor.default_status == dg.DefaultSensorStatus.RUNNING
    graph = defs.resolve_asset_graph()
    for key in graph.materializable_asset_keys:
        assert graph.get(key).automation_condition is not None, key


def test_the_new_scenes_sensor_adds_valid_scenes_and_reports_invalid_ones(tmp_path, monkeypatch):
    import shutil

    from simart_pipeline.assets.automation import new_scenes, scan_scenes

    scenes, data = tmp_path / "scenes", tmp_path / "data"
    shutil.copytree(TINY, scenes / "tiny")
    (scenes / "broken").mkdir(parents=True)
    (scenes / "broken" / "scene.yaml").write_text("name: broken\nclock: {duration_s: -1}\n")
    monkeypatch.setenv("SIMART_SCENES", str(scenes))
    monkeypatch.setenv("SIMART_DATA", str(data))
    instance = dg.DagsterInstance.ephemeral()
    added, problems, _ = scan_scenes(instance, None)
    assert added == ["tiny"]
    assert any(p.startswith(f"{scenes / 'broken' / 'scene.yaml'}: clock.duration_s:") for p in problems), problems
    context = dg.build_sensor_context(instance=instance)
    result = new_scenes(context)
    assert [r.partition_keys for r in result.dynamic_partitions_requests] == [["tiny"]]
    assert registry.scene_dir("tiny", data, tmp_path / "elsewhere") == (scenes / "tiny").resolve()
    # config versions reported: Dagster knows the scene's config before anything runs
    assert instance.fetch_observations(dg.AssetKey(["scene_config", "cirs"]), limit=1).records
    # nothing new: skipped; an edited scene is seen again, the broken one is not reported twice
    again = new_scenes(dg.build_sensor_context(instance=instance, cursor=context.cursor))
    assert isinstance(again, dg.SkipReason) and "no new or changed scene" in again.skip_message
    (scenes / "broken" / "scene.yaml").write_text("name: broken\nclock: {duration_s: 1, bogus: 3}\n")
    edited = new_scenes(dg.build_sensor_context(instance=instance, cursor=context.cursor))
    assert isinstance(edited, dg.SkipReason) and "clock.bogus" in edited.skip_message


def test_a_partition_is_in_use_by_its_own_dimension(tmp_path, monkeypatch):
    """``sunny`` is a weather and a weather group: a scene that lists only night uses the dry group
    ``sunny`` for its radio, but not the weather ``sunny`` for its sensors."""
    import shutil

    import yaml

    from simart_pipeline.assets.automation import partition_in_use

    monkeypatch.setenv("SIMART_DATA", str(tmp_path / "data"))
    scene = tmp_path / "tiny"
    shutil.copytree(TINY, scene)
    raw = yaml.safe_load((scene / "scene.yaml").read_text())
    raw["weathers"] = ["night"]
    (scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    registry.register(scene, tmp_path / "data")
    assert partition_in_use("tiny|sunny", "weather_group") and partition_in_use("tiny|night", "weather")
    assert not partition_in_use("tiny|sunny", "weather") and not partition_in_use("tiny|rainy", "weather_group")
    assert partition_in_use("tiny|r0c1", "tile") and not partition_in_use("tiny|r1c0", "tile")
    assert partition_in_use("tiny", None) and not partition_in_use("elsewhere", None)
