"""Sensing assets: camera, LiDAR, IMU and GPS streams on the shared clock, per weather."""

import time

import dagster as dg
import xarray as xr

from simart_pipeline import previews, provenance
from simart_pipeline.assets.versioning import code_version, config_dep, versioned
from simart_pipeline.partitions import from_scene, scene_weather, split_key
from simart_pipeline.resources import ProjectResource
from simart_pipeline.scene.meshes import SceneMeshes
from simart_pipeline.sensing.sensor_frames import build_sensor_frames


@dg.asset(partitions_def=scene_weather, code_version=code_version("sensor_frames"),
          deps=[config_dep("sensor_frames")], group_name="sensing", pool="rendering",
          ins={"paired_meshes": dg.AssetIn(partition_mapping=from_scene),
               "trajectory": dg.AssetIn(partition_mapping=from_scene)})
def sensor_frames(context: dg.AssetExecutionContext, project: ProjectResource,
                  paired_meshes: SceneMeshes, trajectory: xr.Dataset) -> dg.Output[xr.DataTree]:
    """Every configured sensor's stream, one group per ``<device>/<sensor>``: rendered, or imported
    from a bag (``sensor_imports``, docs/sensor-plugin.md)."""
    scene, weather = split_key(context.partition_key)
    cfg = project.config(scene)
    t0 = time.perf_counter()
    tree = build_sensor_frames(paired_meshes, trajectory.load(), cfg, weather, project.scene_dir(scene))
    tree.attrs.update(provenance.attrs(cfg, "sensor_frames", weather=weather))
    meta = {"streams": ", ".join(node.path for node in tree.subtree if node.has_data) or "none",
            "render_s": round(time.perf_counter() - t0, 2)}
    cams = [node for node in tree.subtree if "rgb" in node.data_vars]
    # The camera and frame that see the most actors (the first camera's first frame without any).
    best = max(((n, i) for n in cams for i in range(n.sizes["time"])),
               key=lambda c: int((c[0]["actor_pixel_count"].values[c[1]] > 0).sum()), default=None)
    if best is not None:
        node, i = best
        boxes = [(str(name), box) for name, box, n in zip(
            node["actor"].values, node["actor_visible_box_px"].values[i], node["actor_pixel_count"].values[i]) if n]
        meta["preview"] = dg.MetadataValue.md(previews.image(
            node["rgb"].values[i], title=f"{node.path} {weather} t={node['time'].values[i] / 1e9:g} s", boxes=boxes))
        meta["actor_pixels_per_frame"] = {
            n.path: int(n["actor_pixel_count"].values.sum() // max(n.sizes["time"], 1)) for n in cams}
    return versioned(context, project, "sensor_frames", tree, meta)
