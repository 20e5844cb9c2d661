"""Reruns recompute only what changed: known answers on the tiny scene. An unchanged rerun writes no
store; a sensor-rate edit rewrites exactly the sensing stores (and the sessions that hold them); a
rain-material edit rewrites exactly the rainy radio stores; data versions depend on inputs alone."""

from pathlib import Path

import dagster as dg
import pytest
import yaml

from simart_pipeline import versions
from simart_pipeline.assets.config_sources import report_config_versions
from simart_pipeline.cli import materialize_scene
from simart_pipeline.config import load_scene_config

TILES = ["r0c0", "r0c1"]


def _files(root: Path) -> dict[str, int]:
    """Every file under the data root with its modification time (ns); the scene registry aside."""
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*")
            if p.is_file() and p.name != "scene_registry.json"}


def _rewritten(before: dict, after: dict) -> set[str]:
    """The stores (e.g. ``cirs/tiny/rainy.zarr``, ``paired_meshes/tiny/radio``) with a file written or removed."""
    changed = {p for p in set(before) | set(after) if before.get(p) != after.get(p)}

    def store(p):
        parts = Path(p).parts
        n = next((i + 1 for i, part in enumerate(parts) if part.endswith(".zarr")), 3)
        return "/".join(parts[:n])

    return {store(p) for p in changed}


def _edit(scene_dir: Path, edit) -> None:
    path = scene_dir / "scene.yaml"
    raw = yaml.safe_load(path.read_text())
    edit(raw)
    path.write_text(yaml.safe_dump(raw, sort_keys=False))


@pytest.fixture(scope="module")
def reruns(tmp_path_factory):
    """Materialise a copy of tiny, then rerun it unchanged, after a sensor-rate edit and after a
    rain-material edit; the files and progress lines of each step."""
    import shutil

    from conftest import TESTS

    root = tmp_path_factory.mktemp("reruns")
    scene = root / "tiny"
    shutil.copytree(TESTS / "scenes" / "tiny", scene)
    data = root / "data"
    instance = dg.DagsterInstance.ephemeral()
    steps = {}

    def run(name, tiles=TILES, **kw):
        lines = []
        materialize_scene(scene, data, None, tiles, instance=instance, progress=lines.append, **kw)
        steps[name] = (_files(data), lines)

    def dagster_stale(name):
        """What Dagster itself calls stale after an edit, once it has read the config sources."""
        report_config_versions(instance, versions.VersionPlan(load_scene_config(scene), scene))
        steps[name + "_stale"] = stale_in_dagster(instance, data)

    run("first")
    steps["first_stale"] = stale_in_dagster(instance, data)
    run("unchanged")
    _edit(scene, lambda raw: raw["platforms"][0]["sensors"][0].update(rate_hz=4.0))
    dagster_stale("sensor_rate")
    run("sensor_rate")
    _edit(scene, lambda raw: raw.setdefault("materials", {}).update(
        rain={"concrete": "wet_brick", "medium_dry_ground": "wet_ground"}))
    dagster_stale("rain_materials")
    run("rain_materials")
    run("forced", force=True)
    shutil.rmtree(data / "ckm")  # the maps deleted (as with the data root): the first tile recreates them
    run("maps_deleted", tiles=TILES[:1])
    run("maps_refilled")
    return data, scene, instance, steps


def stale_in_dagster(instance, data) -> dict[str, str]:
    """``{"asset (partition)": root cause}`` of every stale materialised partition, as Dagster's own
    staleness (what the UI shows) reports it."""
    from dagster._core.definitions.data_version import CachingStaleStatusResolver, StaleStatus
    from dagster._core.loader import LoadingContextForTest

    from simart_pipeline.definitions import build_definitions

    graph = build_definitions(data_root=str(data)).resolve_asset_graph()
    resolver = CachingStaleStatusResolver(instance, graph, LoadingContextForTest(instance))
    out = {}
    for key in graph.materializable_asset_keys:
        for part in instance.get_materialized_partitions(key):
            if resolver.get_status(key, part) == StaleStatus.STALE:
                roots = resolver.get_stale_root_causes(key, part)
                out[f"{key.to_user_string()} ({part})"] = "; ".join(
                    f"{c.key.asset_key.to_user_string()} {c.reason}" for c in roots)
    return out


def _computed(lines) -> set[str]:
    return {line.split("] ")[1].split(":")[0] for line in lines if ": computing (" in line}


def test_an_unchanged_rerun_computes_nothing_and_writes_no_store(reruns):
    _, _, _, steps = reruns
    first, unchanged = steps["first"], steps["unchanged"]
    # every partition (cirs and radar_frames: 2 weather groups; session_bag: 3 weathers)
    assert len(_computed(first[1])) == 3 + 2 + 2 + 3 * 3 + len(TILES) + 1 + 3
    assert _computed(unchanged[1]) == set()
    assert unchanged[0] == first[0]  # not one file written, not one modification time changed
    assert any("0 of 22 asset partitions computed, 22 up to date" in line for line in unchanged[1])


def test_a_sensor_rate_edit_rewrites_exactly_the_sensing_stores(reruns):
    _, _, _, steps = reruns
    rewritten = _rewritten(steps["unchanged"][0], steps["sensor_rate"][0])
    weathers = ("sunny", "night", "rainy")
    assert rewritten == ({f"{a}/tiny/{w}.zarr" for a in ("sensor_frames", "session") for w in weathers}
                         | {f"session_bag/tiny/{w}" for w in weathers})
    assert _computed(steps["sensor_rate"][1]) == {f"{a} (tiny|{w})" for a in ("sensor_frames", "session", "session_bag")
                                                   for w in weathers}
    why = [line for line in steps["sensor_rate"][1] if "] sensor_frames (" in line]
    assert len(why) == 3
    assert all("its config changed" in line for line in why)


def test_dagster_calls_stale_exactly_what_each_edit_concerns(reruns):
    _, _, _, steps = reruns
    assert steps["first_stale"] == {}
    # Dagster marks the partitions whose own inputs changed; what reads them (session) turns stale
    # when they are rematerialised with a new data version, which simart run does in the same go.
    sensors = steps["sensor_rate_stale"]
    assert set(sensors) == {f"sensor_frames (tiny|{w})" for w in ("sunny", "rainy", "night")}
    assert all("scene_config/sensor_frames" in cause for cause in sensors.values())  # the cause, as the UI says
    rain = steps["rain_materials_stale"]
    assert set(rain) == {"cirs (tiny|rainy)", "radar_frames (tiny|rainy)"} | {f"ckm_layers (tiny|{t})" for t in TILES}
    assert "scene_config/cirs" in rain["cirs (tiny|rainy)"]


def test_a_rain_material_edit_rewrites_exactly_the_rainy_radio_stores(reruns):
    _, _, _, steps = reruns
    rewritten = _rewritten(steps["sensor_rate"][0], steps["rain_materials"][0])
    assert rewritten == {"cirs/tiny/rainy.zarr", "radar_frames/tiny/rainy.zarr", "kpis/tiny/rainy.zarr",
                         "session/tiny/rainy.zarr", "ckm/tiny/rainy.zarr", "session_bag/tiny/rainy"}
    computed = _computed(steps["rain_materials"][1])
    assert {"cirs (tiny|rainy)", "kpis (tiny|rainy)", "session (tiny|rainy)"} <= computed
    assert not any("sunny" in c or "night" in c for c in computed)
    assert "sensor_frames (tiny|rainy)" not in computed and "trajectory (tiny)" not in computed


def test_force_recomputes_everything(reruns):
    _, _, _, steps = reruns
    assert len(_computed(steps["forced"][1])) == 22
    rewritten = _rewritten(steps["rain_materials"][0], steps["forced"][0])
    assert {"ckm/tiny/sunny.zarr", "cirs/tiny/sunny.zarr", "osm_extract/tiny.zarr"} <= rewritten


def test_deleted_maps_are_refilled_by_every_tile_and_pictured_again(reruns):
    """A tile is up to date only if its region of each map is; the first tile rerun recreates the
    maps, and the other tiles must not take the recreated (empty) regions for theirs."""
    from simart_pipeline.ckm.maps import map_groups, map_path
    from simart_pipeline.ckm.mosaic import open_map

    data, scene, _, steps = reruns
    assert _computed(steps["maps_deleted"][1]) == {f"ckm_layers (tiny|{TILES[0]})", "ckm_map (tiny)"}
    refilled = steps["maps_refilled"][1]
    assert _computed(refilled) == {f"ckm_layers (tiny|{TILES[1]})", "ckm_map (tiny)"}
    assert any(f"ckm_layers (tiny|{TILES[1]}): computing (its region of the sunny map is missing" in line
               for line in refilled)
    assert any("ckm_map (tiny): computing (the sunny map changed since its picture)" in line for line in refilled)
    cfg = load_scene_config(scene)
    for name in map_groups(cfg):
        done = open_map(map_path(data, cfg.name, name))["tile_complete"].values
        assert done[0, 0] and done[0, 1], name


def test_data_versions_depend_on_inputs_alone(reruns, tmp_path):
    """The version Dagster records equals the one computed from the inputs before anything ran, and
    another process (another hash seed, another working directory, no instance) computes the same."""
    import json
    import subprocess
    import sys

    data, scene, instance, _ = reruns
    cfg = load_scene_config(scene)
    plan = versions.VersionPlan(cfg, scene)
    parts = [("osm_extract", None), ("trajectory", None), ("cirs", "rainy"), ("session", "night"),
             ("ckm_layers", "r0c1"), ("ckm_map", None)]
    code = ("import json, sys; from simart_pipeline import versions; from simart_pipeline.config import "
            "load_scene_config as L; p = versions.VersionPlan(L(sys.argv[1]), sys.argv[1]); "
            "print(json.dumps([p.data_version(a, s) for a, s in json.loads(sys.argv[2])]))")
    res = subprocess.run([sys.executable, "-c", code, str(scene), json.dumps(parts)], capture_output=True,
                         text=True, cwd=tmp_path, env={**__import__("os").environ, "PYTHONHASHSEED": "12345"},
                         check=True)
    elsewhere = dict(zip(parts, json.loads(res.stdout)))
    for asset, sub in parts:
        key = str(dg.MultiPartitionKey({"scene": "tiny", "weather" if sub in ("sunny", "rainy", "night")
                                        else "tile": sub})) if sub else "tiny"
        record = instance.fetch_materializations(
            dg.AssetRecordsFilter(asset_key=dg.AssetKey(asset), asset_partitions=[key]), limit=1).records[0]
        tags = record.event_log_entry.asset_materialization.tags
        assert tags["dagster/data_version"] == plan.data_version(asset, sub) == elsewhere[(asset, sub)]
        assert tags["dagster/code_version"] == versions.code_version(asset)
    # sunny's and night's KPIs read the one dry trace; rain's the wet one
    assert plan.inputs("kpis", "sunny")["upstream"] == plan.inputs("kpis", "night")["upstream"] \
        == {"cirs[sunny]": plan.data_version("cirs", "sunny")} != plan.inputs("kpis", "rainy")["upstream"]
    assert plan.data_version("sensor_frames", "sunny") != plan.data_version("sensor_frames", "night")
