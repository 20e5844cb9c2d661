"""CKM layers of one tile, traced at the cell centres with PathSolver (reference mode).

First version: per (base station, cell) the incoherent path gain, line of sight, time of arrival
and number of paths. Cells inside buildings are masked and never traced; a tile with no cell to
trace returns at once. Results do not depend on the tile: every cell is traced from the same
scene, seed and settings, and a cell's value depends only on its own centre.

Path gain (incoherent) of a cell: ``sum_p mean_{tx_ant, rx_ant} |a_p|^2``, the power gain from one
antenna element to one antenna element summed over paths without phases.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from simart_pipeline.ckm.grid import cell_centres, tile_slices
from simart_pipeline.config import SceneConfig
from simart_pipeline.radio.tracer import RadioScene
from simart_pipeline.scene.geometry import SourceGeometry, inside_buildings

NO_PATH = "no valid path from this base station to the cell centre, or the cell is masked"


def tile_layers(radio: RadioScene | None, cfg: SceneConfig, geom: SourceGeometry, tile: str) -> xr.Dataset:
    """All layers of tile ``tile`` as a dataset over (bs, y, x); ``radio`` may be None if empty."""
    ckm = cfg.ckm
    sl = tile_slices(ckm, tile)
    y_all, x_all = cell_centres(ckm)
    y = y_all[sl[0]] if sl else y_all[:0]
    x = x_all[sl[1]] if sl else x_all[:0]
    yy, xx = np.meshgrid(y, x, indexing="ij")
    zz = np.full_like(xx, ckm.height_m)
    indoor = inside_buildings(geom, xx, yy, zz)
    traced = ~indoor
    B = len(cfg.base_stations)
    shape = (B, *xx.shape)
    gain = np.zeros(shape)
    los = np.zeros(shape, bool)
    toa = np.full(shape, np.nan)
    npaths = np.zeros(shape, np.int32)
    cells = np.flatnonzero(traced.ravel())
    if len(cells) and radio is not None:
        rx = np.column_stack([xx.ravel()[cells], yy.ravel()[cells], zz.ravel()[cells]])
        tx = np.array([b.position_m for b in cfg.base_stations], np.float64)
        tx_ori = np.deg2rad(np.array([b.orientation_deg for b in cfg.base_stations], np.float64))
        p = radio.trace(tx, tx_ori, rx)
        g = (np.abs(p.a) ** 2).mean(axis=(1, 3)).sum(-1)           # [rx, tx]
        flat = (slice(None), cells)
        gain.reshape(B, -1)[flat] = g.T
        los.reshape(B, -1)[flat] = p.los.any(-1).T
        npaths.reshape(B, -1)[flat] = p.valid.sum(-1).T
        # initial=inf: a batch in which no cell has any path has zero paths along the last axis.
        first = np.min(np.where(p.valid, p.tau_s, np.inf), axis=-1, initial=np.inf)
        first = np.where(np.isfinite(first), first, np.nan)
        toa.reshape(B, -1)[flat] = first.T
    has_path = gain > 0
    with np.errstate(divide="ignore"):
        gain_db = np.where(has_path, 10 * np.log10(np.where(has_path, gain, 1.0)), np.nan)
    toa = np.where(has_path, toa, np.nan)
    dims = ("bs", "y", "x")
    ds = xr.Dataset(
        {
            "path_gain_db": (dims, gain_db, dict(
                units="dB", long_name="path gain, incoherent sum over paths, element to element",
                nan_means=NO_PATH)),
            "path_loss_db": (dims, -gain_db, dict(units="dB", long_name="path loss (= -path gain)",
                                                  nan_means=NO_PATH)),
            "los": (dims, los, dict(long_name="a line-of-sight path exists")),
            "num_paths": (dims, npaths, dict(units="1", long_name="number of valid paths")),
            "toa_s": (dims, toa, dict(units="s", long_name="time of arrival (delay of the first path)",
                                      nan_means=NO_PATH)),
            "has_path": (dims, has_path, dict(long_name="at least one valid path")),
            "cell_inside_building": (("y", "x"), indoor, dict(long_name="cell centre inside a building: "
                                                               "masked, not traced")),
        },
        coords={
            "bs": [b.name for b in cfg.base_stations],
            "y": ("y", y, dict(units="m", long_name="cell centre north (ENU)")),
            "x": ("x", x, dict(units="m", long_name="cell centre east (ENU)")),
            "row": ("y", np.arange(len(y_all))[sl[0]] if sl else np.arange(0), dict(long_name="grid row")),
            "col": ("x", np.arange(len(x_all))[sl[1]] if sl else np.arange(0), dict(long_name="grid col")),
        },
        attrs=dict(tile=tile, height_m=ckm.height_m, cell_size_m=ckm.cell_size_m,
                   grid_shape=list(ckm.shape), mode="reference (PathSolver at cell centres)",
                   cells_traced=int(len(cells)), in_scene_tiling=int(sl is not None),
                   radio_materials="dry (the materials of sunny and night weather)"),
    )
    return ds
