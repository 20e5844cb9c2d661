"""Channel-knowledge-map assets: each tile writes its region of the scene's mosaic store; the
scene's map gathers pictures of every layer."""

import time

import dagster as dg
import xarray as xr

from simart_pipeline import previews, provenance
from simart_pipeline.ckm import mosaic
from simart_pipeline.ckm.grid import parse_tile_key, scene_tiles, tile_slices
from simart_pipeline.ckm.maps import map_groups, map_path, map_template, picture_layers
from simart_pipeline.assets.versioning import FORCE_TAG, code_version, config_dep, versioned_result
from simart_pipeline.partitions import from_scene, scene_partitions, scene_tile, split_key
from simart_pipeline.resources import ProjectResource, RayTracerResource
from simart_pipeline.scene import geometry
from simart_pipeline.scene.meshes import SceneMeshes


@dg.asset(partitions_def=scene_tile, code_version=code_version("ckm_layers"),
          deps=[config_dep("ckm_layers")], group_name="ckm", pool="raytracing",
          ins={"paired_meshes": dg.AssetIn(partition_mapping=from_scene),
               "osm_extract": dg.AssetIn(partition_mapping=from_scene)})
def ckm_layers(context: dg.AssetExecutionContext, project: ProjectResource, ray_tracer: RayTracerResource,
               paired_meshes: SceneMeshes, osm_extract: xr.Dataset) -> dg.MaterializeResult:
    """Every CKM layer of one tile, for each set of radio materials, written into its chunk-aligned
    region of the scene's mosaic store (``ckm/<scene>/<materials>.zarr``)."""
    from simart_pipeline.ckm.layers import tile_grid, tile_layers
    from simart_pipeline.ckm.outdoor import mesh_solids_of

    scene, tile = split_key(context.partition_key)
    cfg = project.config(scene)
    t0 = time.perf_counter()
    if tile_slices(cfg.ckm, tile) is None:  # a static tile this scene's grid does not use
        return versioned_result(context, project, "ckm_layers", {"in_scene_tiling": False, "cells_traced": 0})
    geom = geometry.from_dataset(osm_extract.load())
    meta = {"in_scene_tiling": True, "mode": cfg.ckm.mode, "cells_traced": 0}
    grid = tile_grid(cfg, geom, tile, mesh_solids_of(paired_meshes))
    plan = project.version_plan(scene)
    force = context.run.tags.get(FORCE_TAG) == "true"
    for name, weathers in map_groups(cfg).items():
        path = map_path(project.data_root, scene, name)
        map_version, tile_version = plan.map_version(name), plan.map_tile_version(name, tile)
        meta[f"{name}_store"] = dg.MetadataValue.path(str(path))
        meta[f"{name}_weathers"] = ", ".join(weathers)
        if not force and mosaic.tile_is_current(path, tile, map_version, tile_version):
            meta[f"{name}_tile"] = "up to date (its map's inputs did not change)"
            continue
        # A tile whose cells are all masked loads no scene.
        radio = ray_tracer.load(paired_meshes, cfg, name) if grid.traced.any() else None
        ds = tile_layers(radio, cfg, geom, tile, project.scene_dir(scene), grid)
        spec, coords, attrs = map_template(cfg, ds, weathers,
                                           provenance.attrs(cfg, "ckm_layers", weathers=",".join(weathers)))
        mosaic.ensure_template(path, cfg.ckm, spec, coords, attrs, map_version)
        mosaic.write_tile(path, cfg.ckm, tile, ds, tile_version)
        meta[f"{name}_tile"] = "computed"
        meta["cells_traced"] = int(ds.attrs["cells_traced"])
        if "rays_per_bs" in ds.attrs:
            meta[f"{name}_rays_per_bs"] = ", ".join(f"{n:.0e}" for n in ds.attrs["rays_per_bs"])
        if "second_pass_per_bs" in ds.attrs:
            meta[f"{name}_second_pass"] = "; ".join(
                f"bs {i}: {p['undersampled_cells']} undersampled cells, {p['new_samples']} new samples" if p else f"bs {i}: none"
                for i, p in enumerate(ds.attrs["second_pass_per_bs"]))
        if "lattice_second_pass_per_bs" in ds.attrs:
            meta[f"{name}_lattice_second_pass"] = "; ".join(
                f"bs {i}: {p['cells_swapped']} of {p['undersampled_cells']} undersampled cells swapped, "
                f"{p['new_rays']} new rays" if p else f"bs {i}: none"
                for i, p in enumerate(ds.attrs["lattice_second_pass_per_bs"]))
        if "diffuse_gather_per_bs" in ds.attrs:
            meta[f"{name}_diffuse_gather"] = "; ".join(
                f"bs {i}: {p['cells']} few-hit cells gathered, {p['photons']} photons, {p['pairs']} pairs"
                if p and p["cells"] else
                f"bs {i}: not gathered ({p.get('auto_share', 0):.0%} few-hit cells at 1e7 rays)" if p
                else f"bs {i}: none" for i, p in enumerate(ds.attrs["diffuse_gather_per_bs"]))
    meta["compute_s"] = round(time.perf_counter() - t0, 2)
    meta["cells"] = int(grid.traced.size)
    if meta["cells_traced"]:
        meta["cells_per_s"] = round(meta["cells_traced"] / max(meta["compute_s"], 1e-9), 1)
    return versioned_result(context, project, "ckm_layers", meta)


@dg.asset(partitions_def=scene_partitions, code_version=code_version("ckm_map"), group_name="ckm",
          deps=[config_dep("ckm_map"), dg.AssetDep("ckm_layers", partition_mapping=from_scene)],
          ins={"osm_extract": dg.AssetIn()})
def ckm_map(context: dg.AssetExecutionContext, project: ProjectResource, osm_extract: xr.Dataset) -> dg.MaterializeResult:
    """The scene's channel knowledge maps: which tiles are complete, and one picture per map of its
    key layers (first height; per-station layers shown for the serving station) over the buildings."""
    scene = context.partition_key
    cfg = project.config(scene)
    geom = geometry.from_dataset(osm_extract.load())
    meta = {}
    wanted = scene_tiles(cfg.ckm)
    for name, weathers in map_groups(cfg).items():
        path = map_path(project.data_root, scene, name)
        ds = mosaic.open_map(path).load()
        done = ds["tile_complete"].values
        complete = [t for t in wanted if done[parse_tile_key(t)]]
        meta[f"{name}_store"] = dg.MetadataValue.path(str(path))
        meta[f"{name}_tiles_complete"] = f"{len(complete)}/{len(wanted)}"
        meta[f"{name}_tiles_digest"] = mosaic.tiles_digest(path)  # what was pictured (simart run's staleness)
        meta[f"{name}_cells"] = int(ds.sizes["y"] * ds.sizes["x"] * ds.sizes["height"])
        meta[f"{name}_map"] = dg.MetadataValue.md(previews.heatmaps(
            list(picture_layers(ds)), ds["x"].values, ds["y"].values, geom,
            title=f"{scene}: {name} map ({', '.join(weathers)}), h = {float(ds['height'][0]):g} m"))
    return versioned_result(context, project, "ckm_map", meta)
