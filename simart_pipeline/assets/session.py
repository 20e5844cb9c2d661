"""The session asset: one (scene, weather) gathered into one store, like one rosbag per session."""

import dagster as dg
import xarray as xr

from simart_pipeline import provenance
from simart_pipeline.assets.versioning import code_version, config_dep, versioned
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
