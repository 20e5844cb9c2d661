"""Asset checks: the data contract asserted on every stage's partition as it is materialised.

The logic is in :mod:`simart_pipeline.quality`; each check here reads the partition's store, calls
one function and reports its result. Checks whose failure means wrong data are blocking: a failed
one stops the asset's downstream assets in the same run. docs/design.md, "Checks".
"""

import warnings

import dagster as dg
import numpy as np

from simart_pipeline import quality, stores
from simart_pipeline.partitions import scene_partitions, scene_tile, scene_weather, scene_weather_group, split_key
from simart_pipeline.resources import TREE_ASSETS, ProjectResource, RayTracerResource

# Store assets and their partitions; every one gets the finite-values, clock and frame-id checks
# (osm_extract has no time coordinate, so no clock check).
STORE_ASSETS = {"osm_extract": scene_partitions, "trajectory": scene_partitions,
                "sensor_frames": scene_weather, "cirs": scene_weather_group, "radar_frames": scene_weather_group,
                "kpis": scene_weather,
                "session": scene_weather}
TIMELESS = {"osm_extract"}

# Partitioned asset checks run per partition; Dagster 1.13 calls them a preview.
warnings.filterwarnings("ignore", message="Specifying a partitions_def on an AssetCheckSpec",
                        category=dg.PreviewWarning)


def _key(context: dg.AssetCheckExecutionContext, partitions_def) -> tuple[str, str | None]:
    key = context.partition_key
    if isinstance(partitions_def, dg.MultiPartitionsDefinition) and not isinstance(key, dg.MultiPartitionKey):
        key = partitions_def.get_partition_key_from_str(key)
    return split_key(key)


def _open(project: ProjectResource, asset: str, scene: str, sub: str | None):
    return stores.open_store(stores.store_path(project.data_root, asset, scene, sub), tree=asset in TREE_ASSETS)


def _result(r: quality.CheckResult, severity=dg.AssetCheckSeverity.ERROR, check_name: str | None = None,
            **extra) -> dg.AssetCheckResult:
    meta = {k: v for k, v in {**r.metadata, **extra}.items() if v is not None}
    if r.problems:
        meta["first_problems"] = dg.MetadataValue.md("\n".join(f"- {p}" for p in r.problems))
    return dg.AssetCheckResult(passed=r.passed, severity=severity, description=r.description, metadata=meta,
                               check_name=check_name)


_STORE_CHECKS = (  # name, description, the check on the opened store
    ("finite_values", "No inf anywhere; NaN only in float variables whose attrs carry nan_means "
     "(docs/data-contract.md, 'Missing means masked').", lambda obj, cfg, asset: quality.finite_values(obj)),
    ("known_frame_ids", "Every frame_id, parent_frame_id, sensor_frame_id attr (and frame ids in "
     "variables) is world or a frame of the scene config.", lambda obj, cfg, asset: quality.known_frame_ids(obj, cfg)),
    ("on_shared_clock", "Every stream's time is int64 ns, strictly increasing, within [0, duration]; "
     "streams sampled by the pipeline hold exactly the clock instants of their rate.",
     lambda obj, cfg, asset: quality.on_shared_clock(obj, cfg, asset)),
)


def _store_checks(asset: str, partitions_def) -> dg.AssetChecksDefinition:
    """The store checks of ``asset`` as one step: the store is opened once for all of them (each
    open costs 0.05-0.3 s, and a step its own events), each still its own check in the UI."""
    checks = [c for c in _STORE_CHECKS if not (c[0] == "on_shared_clock" and asset in TIMELESS)]

    @dg.multi_asset_check(name=f"{asset}_store_checks", specs=[
        dg.AssetCheckSpec(name, asset=asset, description=description, blocking=True,
                          partitions_def=partitions_def) for name, description, _ in checks])
    def _check(context: dg.AssetCheckExecutionContext, project: ProjectResource):
        scene, sub = _key(context, partitions_def)
        path = stores.store_path(project.data_root, asset, scene, sub)
        obj, cfg = _open(project, asset, scene, sub), project.config(scene)
        for name, _, run in checks:
            yield _result(run(obj, cfg, asset), check_name=name, store=str(path))
    return _check


@dg.asset_check(asset="cirs", blocking=True, partitions_def=scene_weather_group,
                description="Passive channel: no valid path gains more than free space at the tx-rx "
                            "distance times the arrays' largest element gains (+0.1 dB), nor arrives "
                            "before the line of sight.")
def passive_channel(context: dg.AssetCheckExecutionContext, project: ProjectResource) -> dg.AssetCheckResult:
    scene, group = _key(context, scene_weather_group)
    return _result(quality.passive_channel(_open(project, "cirs", scene, group)))


def _tile_maps(context: dg.AssetCheckExecutionContext, project: ProjectResource):
    """(tile, config, the tile's region or None when outside the scene's tiling, maps or {})."""
    from simart_pipeline.ckm.grid import tile_slices
    from simart_pipeline.ckm.maps import map_groups, map_path
    from simart_pipeline.ckm.mosaic import open_map

    scene, tile = _key(context, scene_tile)
    cfg = project.config(scene)
    sl = tile_slices(cfg.ckm, tile)
    if sl is None:
        return tile, cfg, None, {}
    return tile, cfg, sl, {name: open_map(map_path(project.data_root, scene, name)) for name in map_groups(cfg)}


@dg.asset_check(asset="ckm_layers", partitions_def=scene_tile,
                description="The tile is marked complete in every map of the scene; fractions of its "
                            "cells masked (inside a building or outside the region) and empty (traced, "
                            "no path from any station). A warning, not blocking.")
def ckm_tile_complete(context: dg.AssetCheckExecutionContext, project: ProjectResource) -> dg.AssetCheckResult:
    tile, cfg, _, maps = _tile_maps(context, project)
    return _result(quality.ckm_tile(maps, cfg, tile), dg.AssetCheckSeverity.WARN)


@dg.asset_check(asset="ckm_layers", blocking=True, partitions_def=scene_tile,
                description="Passive map: per station and traced cell of the tile, path_gain_db is at "
                            "most count x free space x the station's largest element gain (+0.1 dB), "
                            "and toa_s is not before the line of sight.")
def ckm_passive(context: dg.AssetCheckExecutionContext, project: ProjectResource) -> dg.AssetCheckResult:
    tile, cfg, sl, maps = _tile_maps(context, project)
    if sl is None:
        return dg.AssetCheckResult(passed=True, description=f"tile {tile} is outside the scene's tiling",
                                   metadata={"cells_checked": 0})
    results = {name: quality.ckm_passive(ds, cfg, *sl) for name, ds in maps.items()}
    problems = [f"map {n}: {p}" for n, r in results.items() for p in r.problems]
    checked = sum(r.metadata["cells_checked"] for r in results.values())
    margins = [r.metadata["worst_margin_db"] for r in results.values() if r.metadata.get("worst_margin_db") is not None]
    meta = {"cells_checked": checked, "worst_margin_db": max(margins) if margins else None,
            "tolerance_db": quality.GAIN_TOLERANCE_DB}
    return _result(quality.CheckResult.of(problems, f"{checked} station-cell pairs in {len(maps)} map(s) "
                                          "passive", meta))


_CONVERGENCE = ("PathSolver's sampling: {what} traced again from every station with 10x "
                "ray_tracing.samples_per_src (the static scene, Sionna's default candidate generator, the "
                "solver's other settings); a warning where a link's path gain moves more than 1 dB or its RMS "
                "delay spread more than max(10 ns, 20 %): paths the configured samples miss "
                "(docs/ray-tracing.md, 'Sampling convergence').")


@dg.asset_check(asset="cirs", partitions_def=scene_weather_group,
                description=_CONVERGENCE.format(what="8 receivers spread over the session"))
def cirs_sampling_converged(context: dg.AssetCheckExecutionContext, project: ProjectResource,
                            ray_tracer: RayTracerResource) -> dg.AssetCheckResult:
    from simart_pipeline.radio.cirs import link_geometry
    from simart_pipeline.radio.convergence import sampling_convergence, spread_receivers

    scene, group = _key(context, scene_weather_group)
    cfg = project.config(scene)
    lg = link_geometry(cfg, _open(project, "trajectory", scene, None))
    rx = lg.rx_position_m.reshape(-1, 3)
    radio = ray_tracer.load(stores.store_path(project.data_root, "paired_meshes", scene, suffix=""), cfg, group)
    # the default generator finds the CIRs' paths at a third of the deterministic one's time
    conv = sampling_convergence(radio, lg.tx_position_m, lg.tx_orientation_rad, rx[spread_receivers(rx)],
                                deterministic=False)
    return _result(conv.result("platform"), dg.AssetCheckSeverity.WARN)


@dg.asset_check(asset="ckm_map", partitions_def=scene_partitions,
                description=_CONVERGENCE.format(what="reference mode: 8 traced cells spread over each map") +
                " Fast mode: the map is not PathSolver's; passes.")
def ckm_reference_converged(context: dg.AssetCheckExecutionContext, project: ProjectResource,
                            ray_tracer: RayTracerResource) -> dg.AssetCheckResult:
    from simart_pipeline.ckm.maps import map_groups, map_path, masked_cells
    from simart_pipeline.ckm.mosaic import open_map
    from simart_pipeline.radio.convergence import sampling_convergence, spread_receivers

    scene = context.partition_key
    cfg = project.config(scene)
    if cfg.ckm.mode != "reference":
        return dg.AssetCheckResult(passed=True, description="fast mode: the map is not PathSolver's",
                                   metadata={"links_compared": 0})
    tx = np.array([b.position_m for b in cfg.base_stations], np.float64)
    tx_ori = np.deg2rad(np.array([b.orientation_deg for b in cfg.base_stations], np.float64))
    root = stores.store_path(project.data_root, "paired_meshes", scene, suffix="")
    results = {}
    for name in map_groups(cfg):
        ds = open_map(map_path(project.data_root, scene, name))
        traced = ~masked_cells(ds)
        hh, yy, xx = np.meshgrid(ds["height"].values, ds["y"].values, ds["x"].values, indexing="ij")
        pts = np.column_stack([xx[traced], yy[traced], hh[traced]])
        if len(pts):
            conv = sampling_convergence(ray_tracer.load(root, cfg, name), tx, tx_ori, pts[spread_receivers(pts)],
                                        deterministic=cfg.ckm.deterministic_solver)
            results[name] = conv.result("cell")
    if not results:
        return dg.AssetCheckResult(passed=True, description="no traced cell", metadata={"links_compared": 0})
    failed = {n: res for n, res in results.items() if not res.passed}
    first = next(iter(failed.values() or results.values()))
    desc = "; ".join(f"map {n}: {res.description}" for n, res in failed.items()) or first.description
    meta = {**first.metadata, "links_compared": sum(res.metadata["links_compared"] for res in results.values()),
            "problems": sum(res.metadata["problems"] for res in results.values())}
    problems = [f"map {n}: {p}" for n, res in results.items() for p in res.problems]
    return _result(quality.CheckResult(not failed, desc, meta, problems), dg.AssetCheckSeverity.WARN)


@dg.asset_check(asset="beam_prediction", partitions_def=scene_partitions,
                description="The study is sound: no flight in both the training and the test set and "
                            "every flight in one, top-1 <= top-3 <= top-5 in every row, detections + "
                            "misses = frames with the UAV visible.")
def beam_study_sound(context: dg.AssetCheckExecutionContext, project: ProjectResource) -> dg.AssetCheckResult:
    import json

    from simart_pipeline.study.beam_prediction import num_flights, study_problems

    scene = context.partition_key
    cfg = project.config(scene)
    if cfg.beam_study is None:
        return dg.AssetCheckResult(passed=True, description=f"{scene} has no beam study")
    out = stores.store_path(project.data_root, "beam_prediction", scene, suffix="")
    results = json.loads((out / "results.json").read_text())
    problems = study_problems(results, num_flights(cfg))
    return _result(quality.CheckResult.of(problems, f"{len(results['train_flights'])} training and "
                                          f"{len(results['test_flights'])} test flights, disjoint",
                                          {"path": str(out)}))


STORE_CHECKS = [_store_checks(asset, pd) for asset, pd in STORE_ASSETS.items()]
ALL_CHECKS = [*STORE_CHECKS, passive_channel, cirs_sampling_converged, ckm_tile_complete, ckm_passive,
              ckm_reference_converged, beam_study_sound]
