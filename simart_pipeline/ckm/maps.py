"""The scene's channel knowledge maps: one per set of radio materials, where they live, their
template, and what to picture."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr

from simart_pipeline import stores
from simart_pipeline.ckm.grid import cell_centres
from simart_pipeline.config import SceneConfig
from simart_pipeline.radio.materials import weathers_sharing_materials


def map_groups(cfg: SceneConfig) -> dict[str, list[str]]:
    """Weathers with the same radio materials share one map, named after the first of them
    (:func:`~simart_pipeline.radio.materials.weathers_sharing_materials`)."""
    return weathers_sharing_materials(cfg.ckm.weathers or cfg.weathers)


def map_name_for_weather(cfg: SceneConfig, weather: str) -> str:
    for name, weathers in map_groups(cfg).items():
        if weather in weathers:
            return name
    raise ValueError(f"weather {weather!r} has no map in scene {cfg.name!r}: ckm.weathers is "
                     f"{list(cfg.ckm.weathers or cfg.weathers)}")


def masked_cells(ds: xr.Dataset) -> np.ndarray:
    """``[height, y, x]`` bool: the cells a map (or a tile of it) masked, ``cell_masked``; for maps
    written before that layer, the centre masks it is made of."""
    if "cell_masked" in ds:
        return ds["cell_masked"].values.astype(bool)
    masked = ds["cell_inside_building"].values.astype(bool)
    if "cell_outside_region" in ds:
        masked = masked | ds["cell_outside_region"].values.astype(bool)[None]
    return masked


def map_path(data_root, scene: str, name: str) -> Path:
    return stores.store_path(data_root, "ckm", scene, name, suffix=".zarr")


def map_template(cfg: SceneConfig, tile_ds: xr.Dataset, weathers: list[str], attrs: dict):
    """(spec, coords, attrs) of the full-grid mosaic whose tiles look like ``tile_ds``."""
    y, x = cell_centres(cfg.ckm)
    coords = {}
    for name, c in tile_ds.coords.items():
        values = {"y": y, "x": x, "row": np.arange(len(y)), "col": np.arange(len(x))}.get(name, c.values)
        if name in ("row", "col"):
            coords[name] = (("y",) if name == "row" else ("x",), values, dict(c.attrs))
        else:
            coords[name] = ((name,), np.asarray(values).astype(str) if c.dtype.kind in "OUT" else values,
                            dict(c.attrs))
    spec = {name: (v.dims, v.dtype, dict(v.attrs)) for name, v in tile_ds.data_vars.items()}
    ck = cfg.ckm
    full = dict(attrs, map_weathers=",".join(weathers), mode=ck.mode, cell_size_m=ck.cell_size_m,
                grid_shape=list(ck.shape), tiles=list(ck.tiles), heights_m=list(ck.heights),
                layer_definitions="docs/ckm.md")
    full = {k: v for k, v in full.items() if k not in ("tile", "cells_traced", "in_scene_tiling")}
    return spec, coords, full


# The layers of the one picture of a map: propagation, then link level.
KEY_LAYERS = ("path_gain_db", "toa_s", "rms_delay_spread_s", "asa_deg", "los_power_fraction", "best_bs",
              "sinr_db", "mcs_index", "rate_bps")


def picture_layers(ds: xr.Dataset, names=KEY_LAYERS):
    """(layer, 2D values at the first height, label) for the layers ``names`` (in that order) that
    the map has; per-station layers show the serving station's value."""
    h0 = ds.isel(height=0)
    serving = h0["best_bs"].values if "best_bs" in h0 else None
    for name in names:
        if name not in h0.data_vars:
            continue
        v = h0[name]
        if v.dims[-2:] != ("y", "x") or "beam" in v.dims or (v.dtype == bool and name != "los"):
            continue
        vals = v.values
        if "bs" in v.dims:
            if serving is None:
                continue
            vals = np.take_along_axis(vals, np.maximum(serving, 0)[None], axis=0)[0]
            vals = np.where(serving >= 0, vals, np.nan)
        vals = vals.astype(np.float64)
        if name in ("best_bs", "mcs_index", "best_beam"):
            vals = np.where(vals >= 0, vals, np.nan)
        units = v.attrs.get("units", "")
        yield name, vals, f"{name} ({units})" if units and units != "1" else name


def open_scene_map(data_root, cfg: SceneConfig, weather: str | None = None) -> xr.Dataset:
    """The channel knowledge map of ``weather`` (default the first mapped weather) as xarray."""
    from simart_pipeline.ckm.mosaic import open_map

    name = map_name_for_weather(cfg, weather) if weather else next(iter(map_groups(cfg)))
    return open_map(map_path(data_root, cfg.name, name))
