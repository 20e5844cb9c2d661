"""The session assets: one (scene, weather) gathered into one store, and the same as one ROS bag."""

import time

import dagster as dg
import xarray as xr

from simart_pipeline import provenance, stores
from simart_pipeline.assets.versioning import code_version, config_dep, versioned, versioned_result
from simart_pipeline.export.pictures import bag_picture
from simart_pipeline.partitions import from_scene, from_weather_group, scene_weather, split_key
from simart_pipeline.resources import ProjectResource


@dg.asset(partitions_def=scene_weather, code_version=code_version("session"),
          deps=[config_dep("session")], group_name="session",
          ins={"trajectory": dg.AssetIn(partition_mapping=from_scene),
               "cirs": dg.AssetIn(partition_mapping=from_weather_group)})
def session(context: dg.AssetExecutionContext, project: ProjectResource, trajectory: xr.Dataset,
            sensor_frames: xr.DataTree, cirs: xr.Dataset, kpis: xr.Dataset) -> dg.Output[xr.DataTree]:
    """Groups ``/trajectory``, ``/sensors/<device>/<sensor>``, ``/cirs`` and ``/kpis`` on one clock."""
    scene, weather = split_key(context.partition_key)
    cfg = project.config(scene)
    groups = {"/trajectory": trajectory.load(), "/cirs": cirs.load(), "/kpis": kpis.load()}
    for node in sensor_frames.subtree:
        if node.has_data:
            groups[f"/sensors{node.path}"] = node.to_dataset().load()
    root = xr.Dataset(attrs=provenance.attrs(cfg, "session", weather=weather))
    tree = xr.DataTree.from_dict({"/": root, **groups})
    return versioned(context, project, "session", tree, {"groups": ", ".join(sorted(groups)),
                                                        "duration_s": cfg.clock.duration_s})


@dg.asset(partitions_def=scene_weather, code_version=code_version("session_bag"),
          deps=[config_dep("session_bag"), dg.AssetDep("ckm_map", partition_mapping=from_scene)],
          group_name="session",
          ins={"radar_frames": dg.AssetIn(partition_mapping=from_weather_group)})
def session_bag(context: dg.AssetExecutionContext, project: ProjectResource, session: xr.DataTree,
                radar_frames: xr.DataTree) -> dg.MaterializeResult:
    """The session as one rosbag2 (MCAP) file for ROS tools: sensors, poses and frames, channels,
    KPIs, beams, the CKM layers of the weather's radio materials and the radars' frames, on the
    shared clock (docs/ros-export.md). ``simart export`` writes other formats and places."""
    from simart_pipeline.ckm.maps import map_path
    from simart_pipeline.ckm.mosaic import open_map
    from simart_pipeline.export import bag
    from simart_pipeline.radio.materials import WEATHER_GROUP
    from simart_pipeline.scene.actors import scene_actors

    scene, weather = split_key(context.partition_key)
    cfg = project.config(scene)
    group = WEATHER_GROUP[weather]
    ckm_path = map_path(project.data_root, scene, group)
    out = stores.store_path(project.data_root, "session_bag", scene, weather, suffix="")
    t0 = time.perf_counter()
    counts = bag.export_session(out, "mcap", session, cfg, actors=scene_actors(cfg, project.scene_dir(scene)),
                                ckm=open_map(ckm_path) if ckm_path.exists() else None, ckm_materials=group,
                                radar=radar_frames)
    meta = {"path": str(out), "format": "rosbag2 MCAP", "topics": len(counts), "messages": sum(counts.values()),
            "bytes": sum(f.stat().st_size for f in out.rglob("*") if f.is_file()),
            "write_s": round(time.perf_counter() - t0, 2),
            "picture": dg.MetadataValue.md(bag_picture(session, title=f"{scene}/{weather}"))}
    return versioned_result(context, project, "session_bag", meta)
