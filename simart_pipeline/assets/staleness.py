"""What is stale, and submitting backfills of it: one answer for ``simart run``, ``simart backfill``
and the nightly regeneration (:mod:`simart_pipeline.assets.nightly`).

An asset partition is **stale** when it was never materialised (under this data root), its stores
are gone, or the data version its inputs give now (``versions.VersionPlan``: code version, config
slice, source files, upstream data versions) differs from the one its last materialisation
recorded. Data versions are computed from the inputs alone, so an edit that stales a partition also
stales everything downstream of it at once, before anything runs.
"""

from __future__ import annotations

from pathlib import Path

import dagster as dg
from dagster._core.definitions.assets.graph.asset_graph_subset import AssetGraphSubset
from dagster._core.definitions.events import AssetKeyPartitionKey
from dagster._core.execution.backfill import PartitionBackfill
from dagster._core.utils import make_new_backfill_id
from dagster._time import get_current_timestamp

from simart_pipeline import versions
from simart_pipeline.ckm.grid import scene_tiles, tile_slices
from simart_pipeline.partitions import split_key
from simart_pipeline.radio.materials import WEATHER_GROUP

BACKFILL_TAG = "simart/backfill"  # run and backfill tag: who asked ("cli" or "nightly")


def partition_status(instance, plan, asset: str, key, data_root: Path, paths: list[Path]) -> tuple[bool, str]:
    """(up to date, why not): up to date when the last materialisation recorded in ``instance`` has
    the data version the inputs give now, was written under ``data_root``, and its stores exist."""
    _, sub = split_key(key)
    expected = plan.data_version(asset, sub)
    records = instance.fetch_materializations(
        dg.AssetRecordsFilter(asset_key=dg.AssetKey(asset), asset_partitions=[str(key)]), limit=1).records
    if not records:
        return False, "never materialised"
    md = records[0].event_log_entry.asset_materialization.metadata
    recorded = md["data_version"].value if "data_version" in md else None
    if "data_root" not in md or md["data_root"].value != str(data_root):
        return False, "not materialised under this data root"
    if not all(p.exists() for p in paths):
        return False, "its store is missing"
    if recorded == expected:
        return _map_content_status(plan, asset, sub, data_root, md)
    old = md["data_version_inputs"].value if "data_version_inputs" in md else None
    return False, versions.why_different(old, plan.inputs(asset, sub))


def _map_content_status(plan, asset: str, sub, data_root: Path, md) -> tuple[bool, str]:
    """The CKM assets share the scene's mosaic maps, so a map that exists is not enough: a tile is up
    to date only if its region of every map is complete at its version, and the map's picture only if
    the map's tiles are what it pictured (a deleted and recreated map, e.g. after the data root was
    removed, holds only the tiles rerun since)."""
    from simart_pipeline.ckm import mosaic
    from simart_pipeline.ckm.maps import map_groups, map_path

    cfg = plan.cfg
    if asset == "ckm_layers" and tile_slices(cfg.ckm, sub) is not None:
        for name in map_groups(cfg):
            if not mosaic.tile_is_current(map_path(data_root, cfg.name, name), sub, plan.map_version(name),
                                          plan.map_tile_version(name, sub)):
                return False, f"its region of the {name} map is missing or out of date"
    if asset == "ckm_map":
        for name in map_groups(cfg):
            key = f"{name}_tiles_digest"
            if key not in md or md[key].value != mosaic.tiles_digest(map_path(data_root, cfg.name, name)):
                return False, f"the {name} map changed since its picture"
    return True, ""


def scene_steps(cfg, weathers, tiles) -> list[tuple[list[str], object]]:
    """A scene's asset partitions in an order where every upstream comes first: ``[(asset names,
    partition key)]``, one step a Dagster run of ``simart run``."""
    steps = [(["osm_extract", "paired_meshes", "trajectory"], cfg.name)]
    # one trace per weather group (sunny and night share the dry one), then each weather's stages
    steps += [(["cirs", "radar_frames"], dg.MultiPartitionKey({"scene": cfg.name, "weather_group": g}))
              for g in dict.fromkeys(WEATHER_GROUP[w] for w in weathers)]
    steps += [(["sensor_frames", "kpis", "session"], dg.MultiPartitionKey({"scene": cfg.name, "weather": w}))
              for w in weathers]
    steps += [(["ckm_layers"], dg.MultiPartitionKey({"scene": cfg.name, "tile": t})) for t in tiles]
    steps += [(["ckm_map"], cfg.name)]
    steps += [(["session_bag"], dg.MultiPartitionKey({"scene": cfg.name, "weather": w})) for w in weathers]
    if cfg.beam_study is not None and set(weathers) == set(cfg.weathers):  # the study reads every weather
        steps += [(["beam_prediction"], cfg.name)]
    return steps


def stores_of(asset: str, key, data_root: Path, cfg) -> list[Path]:
    """The stores an asset partition writes (the CKM assets: the scene's mosaic maps)."""
    if asset in ("ckm_layers", "ckm_map"):
        from simart_pipeline.ckm.maps import map_groups, map_path

        return [map_path(data_root, cfg.name, name) for name in map_groups(cfg)]
    return [store_of(asset, key, data_root)]


def store_of(asset: str, key, data_root: Path) -> Path:
    from simart_pipeline import stores
    from simart_pipeline.resources import DIRECTORY_ASSETS

    scene, sub = split_key(key)
    return stores.store_path(data_root, asset, scene, sub, suffix="" if asset in DIRECTORY_ASSETS else ".zarr")


def scene_partitions_of(cfg, assets=None, weathers=None, tiles=None) -> list[tuple[str, object]]:
    """``[(asset, partition key)]`` of the scene that its config uses (its weathers, their groups,
    its tiles), upstream first; narrowed to ``assets``, ``weathers`` and ``tiles`` when given."""
    ws = list(weathers or cfg.weathers)
    ts = list(tiles or scene_tiles(cfg.ckm))
    return [(name, key) for names, key in scene_steps(cfg, ws, ts) for name in names
            if not assets or name in assets]


def stale_partitions(instance, project, scene: str, assets=None, weathers=None, tiles=None) -> dict[tuple[str, object], str]:
    """``{(asset, partition key): why}`` of the scene's partitions (narrowed as in
    :func:`scene_partitions_of`) that are missing or stale, upstream first (``project``: a
    ``ProjectResource``, whose data root and scenes root say where)."""
    cfg = project.config(scene)
    plan = project.version_plan(scene)
    data_root = Path(project.data_root)
    out = {}
    for name, key in scene_partitions_of(cfg, assets, weathers, tiles):
        ok, why = partition_status(instance, plan, name, key, data_root, stores_of(name, key, data_root, cfg))
        if not ok:
            out[(name, key)] = why
    return out


def asset_graph_subset(asset_graph, partitions) -> AssetGraphSubset:
    """The asset partitions ``[(asset, partition key)]`` as Dagster's AssetGraphSubset (what a
    backfill targets)."""
    return AssetGraphSubset.from_asset_partition_set(
        {AssetKeyPartitionKey(dg.AssetKey(a), str(k)) for a, k in partitions}, asset_graph)


def backfill_request(asset_graph, partitions, tags: dict[str, str]) -> dg.RunRequest:
    """A sensor's answer that launches one backfill of ``partitions`` (Dagster 1.13: only sensors,
    not schedules, may answer with a backfill; the backfill daemon runs it in dependency order)."""
    return dg.RunRequest.for_asset_graph_subset(asset_graph_subset(asset_graph, partitions), tags=tags)


def submit_backfill(instance, asset_graph, partitions, tags: dict[str, str], title: str | None = None,
                    description: str | None = None) -> str:
    """Record a backfill of ``partitions`` on ``instance`` (what a sensor's backfill request and
    the UI's "Materialize" do): the daemon of ``simart dev`` or ``dagster-daemon`` launches its runs,
    through the instance's run coordinator and pools. Returns the backfill id."""
    backfill_id = make_new_backfill_id()
    instance.add_backfill(PartitionBackfill.from_asset_graph_subset(
        backfill_id=backfill_id, backfill_timestamp=get_current_timestamp(), tags=tags,
        dynamic_partitions_store=instance, asset_graph_subset=asset_graph_subset(asset_graph, partitions),
        title=title, description=description, run_config=None))
    return backfill_id
