"""Radio assets: channel impulse responses along the trajectories, and the base stations' radars."""

import time

import dagster as dg
import xarray as xr

from simart_pipeline import previews, provenance
from simart_pipeline.assets.versioning import code_version, config_dep, versioned
from simart_pipeline.partitions import from_scene, scene_weather_group, split_key
from simart_pipeline.radio import cirs as radio_cirs
from simart_pipeline.radio import radar_echoes
from simart_pipeline.radio.materials import weathers_sharing_materials
from simart_pipeline.radio.pictures import traced_paths_markdown
from simart_pipeline.resources import ProjectResource, RayTracerResource
from simart_pipeline.scene import geometry
from simart_pipeline.scene.actors import scene_actors
from simart_pipeline.scene.meshes import SceneMeshes
from simart_pipeline.scene.meshes import radio_scene_file as scene_meshes_file


@dg.asset(partitions_def=scene_weather_group, code_version=code_version("cirs"),
          deps=[config_dep("cirs")], group_name="radio", pool="raytracing",
          ins={"paired_meshes": dg.AssetIn(partition_mapping=from_scene),
               "trajectory": dg.AssetIn(partition_mapping=from_scene),
               "osm_extract": dg.AssetIn(partition_mapping=from_scene)})
def cirs(context: dg.AssetExecutionContext, project: ProjectResource, ray_tracer: RayTracerResource,
         paired_meshes: SceneMeshes, trajectory: xr.Dataset, osm_extract: xr.Dataset) -> dg.Output[xr.Dataset]:
    """Sionna RT PathSolver from every base station to every platform at every radio-clock instant,
    once per weather group: the weathers that share radio materials (sunny and night) share one
    trace, and their ``kpis`` and ``session`` partitions read it through the partition mapping."""
    scene, group = split_key(context.partition_key)
    cfg = project.config(scene)
    t0 = time.perf_counter()
    radio = ray_tracer.load(paired_meshes, cfg, group, actors_from=project.scene_dir(scene))
    traj = trajectory.load()
    geom = geometry.from_dataset(osm_extract.load())
    lg = radio_cirs.link_geometry(cfg, traj)
    ds = radio_cirs.trace_trajectory(radio, cfg, traj, geom)
    elapsed = time.perf_counter() - t0
    weathers = weathers_sharing_materials(cfg.weathers).get(group, [])  # the scene's weathers this trace serves
    ds.attrs.update(provenance.attrs(cfg, "cirs", mitsuba_variant=ray_tracer.variant(), weather_group=group,
                                     weathers=",".join(weathers)))
    n_rx = ds.sizes["time"] * ds.sizes["link"]
    meta = {
        "time_steps": ds.sizes["time"], "links": ds.sizes["link"], "max_paths": ds.sizes["path"],
        "links_without_path": int(ds["link_no_path"].sum()),
        "links_not_usable": int((~ds["link_usable"]).sum()),
        "los_fraction": float(ds["los"].any("path").mean()),
        "actors": ", ".join(ds["actor"].values.tolist()) or "none",
        "solver_calls": int(ds.attrs.get("trace_calls", 1)),
        "weathers": ", ".join(weathers), "compute_s": round(elapsed, 2),
        "ms_per_link_step": round(1e3 * elapsed / max(n_rx, 1), 2),
        "weather_material_overrides": ds.attrs["weather_material_overrides"]}
    meta["paths_picture"] = dg.MetadataValue.md(traced_paths_markdown(
        radio, cfg, lg, geom, ds.sizes["time"] // 2, title=f"{scene}/{group}"))
    return versioned(context, project, "cirs", ds, meta)


@dg.asset(partitions_def=scene_weather_group, code_version=code_version("radar_frames"),
          deps=[config_dep("radar_frames")], group_name="radio", pool="raytracing",
          ins={"paired_meshes": dg.AssetIn(partition_mapping=from_scene),
               "trajectory": dg.AssetIn(partition_mapping=from_scene)})
def radar_frames(context: dg.AssetExecutionContext, project: ProjectResource, paired_meshes: SceneMeshes,
                 trajectory: xr.Dataset) -> dg.Output[xr.DataTree]:
    """Each base station's radar (``base_stations.N.radar``): sensing CIRs of the echoes from the
    scene and the actors, a range-Doppler map per radar frame, and the actors' true range, radial
    velocity and angles. A scene without radar traces nothing and stores an empty tree."""
    scene, group = split_key(context.partition_key)
    cfg = project.config(scene)
    t0 = time.perf_counter()
    radio = None
    if radar_echoes.radar_base_stations(cfg):
        radio = radar_echoes.radar_scene(scene_meshes_file(paired_meshes.root), cfg, group)
        radio.add_actors(scene_actors(cfg, project.scene_dir(scene)))
    tree = radar_echoes.radar_frames(radio, cfg, trajectory.load() if radio is not None else None)
    tree.attrs.update(provenance.attrs(cfg, "radar_frames", weather_group=group))
    meta = {"radars": tree.attrs["radars"], "compute_s": round(time.perf_counter() - t0, 2)}
    for node in tree.children.values():
        i = node.sizes["time"] // 2
        truth = [(str(a), node["actor_range_m"].values[i, k], node["actor_radial_velocity_mps"].values[i, k])
                 for k, a in enumerate(node["actor"].values)]
        far = max([r for _, r, _ in truth] + [100.0]) * 1.5
        meta[f"range_doppler_{node.name}"] = dg.MetadataValue.md(previews.range_doppler(
            node["range_doppler_power_db"].values[i], node["range_m"].values, node["radial_velocity_mps"].values,
            truth, title=f"{scene}/{group} {node.name} t={node['time'].values[i] / 1e9:g} s", max_range_m=far))
        meta[f"echo_paths_{node.name}"] = int(node["valid"].sum())
    return versioned(context, project, "radar_frames", tree, meta)
