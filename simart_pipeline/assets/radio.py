"""Radio assets: channel impulse responses along the trajectories."""

import time

import dagster as dg
import xarray as xr

from simart_pipeline import provenance
from simart_pipeline.partitions import from_scene, scene_weather, split_key
from simart_pipeline.radio.cirs import trace_trajectory
from simart_pipeline.resources import ProjectResource, RayTracerResource
from simart_pipeline.scene import geometry
from simart_pipeline.scene.meshes import SceneMeshes


@dg.asset(partitions_def=scene_weather, code_version="1", group_name="radio", pool="raytracing",
          ins={"paired_meshes": dg.AssetIn(partition_mapping=from_scene),
               "trajectory": dg.AssetIn(partition_mapping=from_scene),
               "osm_extract": dg.AssetIn(partition_mapping=from_scene)})
def cirs(context: dg.AssetExecutionContext, project: ProjectResource, ray_tracer: RayTracerResource,
         paired_meshes: SceneMeshes, trajectory: xr.Dataset, osm_extract: xr.Dataset) -> dg.Output[xr.Dataset]:
    """Sionna RT PathSolver from every base station to every platform at every radio-clock instant."""
    scene, weather = split_key(context.partition_key)
    cfg = project.config(scene)
    t0 = time.perf_counter()
    radio = ray_tracer.load(paired_meshes, cfg, weather)
    ds = trace_trajectory(radio, cfg, trajectory.load(), geometry.from_dataset(osm_extract.load()))
    elapsed = time.perf_counter() - t0
    ds.attrs.update(provenance.attrs(cfg, "cirs", mitsuba_variant=ray_tracer.variant()))
    n_rx = ds.sizes["time"] * ds.sizes["link"]
    return dg.Output(ds, metadata={
        "time_steps": ds.sizes["time"], "links": ds.sizes["link"], "max_paths": ds.sizes["path"],
        "links_without_path": int(ds["link_no_path"].sum()), "los_fraction": float(ds["los"].any("path").mean()),
        "trace_s": round(elapsed, 2), "ms_per_link_step": round(1e3 * elapsed / max(n_rx, 1), 2),
        "weather_material_overrides": ds.attrs["weather_material_overrides"]})
