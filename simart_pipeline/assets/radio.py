"""Radio assets: channel impulse responses along the trajectories."""

import time

import dagster as dg
import xarray as xr

from simart_pipeline import provenance, stores
from simart_pipeline.assets.versioning import code_version, versioned
from simart_pipeline.partitions import from_scene, scene_weather, split_key
from simart_pipeline.radio import cirs as radio_cirs
from simart_pipeline.radio.materials import weathers_sharing_materials
from simart_pipeline.radio.pictures import traced_paths_markdown
from simart_pipeline.resources import ProjectResource, RayTracerResource
from simart_pipeline.scene import geometry
from simart_pipeline.scene.meshes import SceneMeshes


def _same_content_store(project: ProjectResource, scene: str, weather: str, key: str):
    """Another weather's CIR store of this scene with the same radio materials (one policy with the
    CKM maps: ``weathers_sharing_materials``) and the same content hash, if one exists."""
    cfg = project.config(scene)
    group = next(g for g in weathers_sharing_materials(cfg.weathers, cfg.materials.weather_table()).values()
                 if weather in g)
    for other in sorted(group):
        path = stores.store_path(project.data_root, "cirs", scene, other, suffix=".zarr")
        if other == weather or not path.exists():
            continue
        try:
            ds = stores.open_store(path)
        except Exception:  # an unreadable store is simply not reused
            continue
        # Only a traced original is reused, so a rerun of the original traces again.
        if ds.attrs.get("cir_content_sha256") == key and not ds.attrs.get("reused_from_weather"):
            return ds
    return None


@dg.asset(partitions_def=scene_weather, code_version=code_version("cirs"), group_name="radio", pool="raytracing",
          ins={"paired_meshes": dg.AssetIn(partition_mapping=from_scene),
               "trajectory": dg.AssetIn(partition_mapping=from_scene),
               "osm_extract": dg.AssetIn(partition_mapping=from_scene)})
def cirs(context: dg.AssetExecutionContext, project: ProjectResource, ray_tracer: RayTracerResource,
         paired_meshes: SceneMeshes, trajectory: xr.Dataset, osm_extract: xr.Dataset) -> dg.Output[xr.Dataset]:
    """Sionna RT PathSolver from every base station to every platform at every radio-clock instant.

    A weather whose radio materials equal another weather's (sunny and night) reuses that weather's
    CIRs when they exist, by content hash of scene, materials, trajectory and solver settings."""
    scene, weather = split_key(context.partition_key)
    cfg = project.config(scene)
    t0 = time.perf_counter()
    radio = ray_tracer.load(paired_meshes, cfg, weather)
    traj = trajectory.load()
    geom = geometry.from_dataset(osm_extract.load())
    lg = radio_cirs.link_geometry(cfg, traj)
    key = radio_cirs.cir_content_sha256(radio, cfg, lg)
    same = _same_content_store(project, scene, weather, key)
    if same is not None:
        ds = radio_cirs.reuse_for_weather(same.load(), weather)
        context.log.info(f"{scene}/{weather}: radio materials equal {ds.attrs['reused_from_weather']}'s: "
                         "reusing its CIRs instead of tracing")
    else:
        ds = radio_cirs.trace_trajectory(radio, cfg, traj, geom)
    elapsed = time.perf_counter() - t0
    ds.attrs.update(provenance.attrs(cfg, "cirs", mitsuba_variant=ray_tracer.variant()))
    n_rx = ds.sizes["time"] * ds.sizes["link"]
    meta = {
        "time_steps": ds.sizes["time"], "links": ds.sizes["link"], "max_paths": ds.sizes["path"],
        "links_without_path": int(ds["link_no_path"].sum()),
        "links_not_usable": int((~ds["link_usable"]).sum()),
        "los_fraction": float(ds["los"].any("path").mean()),
        "reused_from_weather": ds.attrs["reused_from_weather"] or "(traced)",
        "cir_content_sha256": key, "compute_s": round(elapsed, 2),
        "weather_material_overrides": ds.attrs["weather_material_overrides"]}
    if not ds.attrs["reused_from_weather"]:
        meta["ms_per_link_step"] = round(1e3 * elapsed / max(n_rx, 1), 2)
    meta["paths_picture"] = dg.MetadataValue.md(traced_paths_markdown(
        radio, cfg, lg, geom, ds.sizes["time"] // 2, title=f"{scene}/{weather}"))
    return versioned(context, project, "cirs", ds, meta)
