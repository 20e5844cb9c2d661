"""Channel-knowledge-map assets: the layers of one grid tile."""

import time

import dagster as dg
import numpy as np
import xarray as xr

from simart_pipeline import previews, provenance
from simart_pipeline.ckm.grid import tile_slices
from simart_pipeline.ckm.layers import tile_layers
from simart_pipeline.partitions import from_scene, scene_tile, split_key
from simart_pipeline.resources import ProjectResource, RayTracerResource
from simart_pipeline.scene import geometry
from simart_pipeline.scene.meshes import SceneMeshes


@dg.asset(partitions_def=scene_tile, code_version="1", group_name="ckm", pool="raytracing",
          ins={"paired_meshes": dg.AssetIn(partition_mapping=from_scene),
               "osm_extract": dg.AssetIn(partition_mapping=from_scene)})
def ckm_layers(context: dg.AssetExecutionContext, project: ProjectResource, ray_tracer: RayTracerResource,
               paired_meshes: SceneMeshes, osm_extract: xr.Dataset) -> dg.Output[xr.Dataset]:
    """Path gain, path loss, LoS, ToA and path count per cell of one tile and base station."""
    scene, tile = split_key(context.partition_key)
    cfg = project.config(scene)
    geom = geometry.from_dataset(osm_extract.load())
    t0 = time.perf_counter()
    # A tile outside the scene's tiling, or with every cell indoors, needs no scene loaded.
    needs_radio = tile_slices(cfg.ckm, tile) is not None
    radio = ray_tracer.load(paired_meshes, cfg, "sunny") if needs_radio else None
    ds = tile_layers(radio, cfg, geom, tile)
    elapsed = time.perf_counter() - t0
    ds.attrs.update(provenance.attrs(cfg, "ckm_layers"))
    meta = {"cells": int(ds.sizes["y"] * ds.sizes["x"]), "cells_traced": ds.attrs["cells_traced"],
            "in_scene_tiling": bool(ds.attrs["in_scene_tiling"]), "compute_s": round(elapsed, 2)}
    if ds.attrs["cells_traced"]:
        best = ds["path_gain_db"].max("bs", skipna=True).values
        meta["preview"] = dg.MetadataValue.md(previews.heatmap(
            np.nan_to_num(best, nan=np.nanmin(best) if np.isfinite(best).any() else 0.0),
            ds["x"].values, ds["y"].values, geom, "best path gain (dB)", title=f"{scene} {tile}"))
    return dg.Output(ds, metadata=meta)
