"""Scene assets: source geometry, paired meshes, trajectories (partitioned by scene)."""

import json
import time

import dagster as dg
import xarray as xr

from simart_pipeline import previews, provenance
from simart_pipeline.mobility.trajectory import build_trajectory, check_clear_of_buildings
from simart_pipeline.partitions import scene_partitions
from simart_pipeline.resources import ProjectResource
from simart_pipeline.scene import build, geometry, meshes, source
from simart_pipeline.assets.versioning import code_version, config_dep, versioned


@dg.asset(partitions_def=scene_partitions, code_version=code_version("osm_extract"),
          deps=[config_dep("osm_extract")], group_name="scene")
def osm_extract(context: dg.AssetExecutionContext, project: ProjectResource) -> dg.Output[xr.Dataset]:
    """Source geometry in the local ENU frame: buildings and parts, roads, land cover, ground; heights, roofs, materials."""
    scene = context.partition_key
    cfg = project.config(scene)
    geom = source.build_source_geometry(cfg, project.scene_dir(scene))
    ds = geometry.to_dataset(geom)
    ds.attrs.update(provenance.attrs(cfg, "osm_extract", source_kind=cfg.source.kind))
    counts = {c: len(geom.of_class(c)) for c in geometry.FEATURE_CLASSES}
    return versioned(context, project, "osm_extract", ds, {
        **{f"num_{k}": v for k, v in counts.items()}, "num_warnings": len(geom.warnings),
        "preview": dg.MetadataValue.md(previews.top_view(geom, cfg, title=scene))})


@dg.asset(partitions_def=scene_partitions, code_version=code_version("paired_meshes"),
          deps=[config_dep("paired_meshes")], group_name="scene")
def paired_meshes(context: dg.AssetExecutionContext, project: ProjectResource,
                  osm_extract: xr.Dataset) -> dg.Output[meshes.PairedMeshesOutput]:
    """Visual mesh (per-face class and instance, facade detail) and radio mesh (Mitsuba XML + PLY)."""
    scene = context.partition_key
    cfg = project.config(scene)
    t0 = time.perf_counter()
    out = build.paired_meshes_for_scene(cfg, project.scene_dir(scene), geometry.from_dataset(osm_extract.load()),
                                        provenance.attrs(cfg, "paired_meshes"))
    counts = out.meshes.counts()
    report = out.scene_info.get("mesh_import") or out.scene_info.get("sionna_xml") or {}
    return versioned(context, project, "paired_meshes", out, {
        **{k: v for k, v in counts.items() if k not in ("radio_materials", "radio_triangles_per_mesh")},
        "radio_materials": ", ".join(counts["radio_materials"]),
        "radio_triangles_per_mesh": dg.MetadataValue.json(counts["radio_triangles_per_mesh"]),
        **{k: report[k] for k in ("triangle_reduction", "hausdorff_p95_m", "hausdorff_max_m") if k in report},
        "build_s": round(time.perf_counter() - t0, 3)})


@dg.asset(partitions_def=scene_partitions, code_version=code_version("trajectory"),
          deps=[config_dep("trajectory")], group_name="scene")
def trajectory(context: dg.AssetExecutionContext, project: ProjectResource,
               osm_extract: xr.Dataset) -> dg.Output[xr.Dataset]:
    """Platform poses, velocities and accelerations on the shared clock under each platform's dynamic
    limits (ground vehicles along the roads of ``osm_extract``), checked clear of buildings."""
    scene = context.partition_key
    cfg = project.config(scene)
    geom = geometry.from_dataset(osm_extract.load())
    ds = build_trajectory(cfg, project.scene_dir(scene), geom=geom)
    check_clear_of_buildings(ds, geom, where=f"scene {scene}",
                             replayed=[p.name for p in cfg.platforms if p.trajectory.kind == "replay"])
    ds.attrs.update(provenance.attrs(cfg, "trajectory"))
    motion = json.loads(ds.attrs["dynamics"])
    return versioned(context, project, "trajectory", ds, {
        "num_platforms": ds.sizes["platform"], "num_samples": ds.sizes["time"],
        "motion_end_s": dg.MetadataValue.json({k: v["motion_end_s"] for k, v in motion.items()}),
        "preview": dg.MetadataValue.md(previews.top_view(geom, cfg, ds, title=scene))})
