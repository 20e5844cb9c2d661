"""The CKM grid: cell centres on horizontal planes, split into chunk-aligned tiles (the partitions).

Cell (row i, col j) has its centre at
``x = center_x - size_x / 2 + (j + 0.5) * cell``, ``y = center_y - size_y / 2 + (i + 0.5) * cell``,
at every height of ``ckm.heights``. Tiles are Zarr chunks: along each axis a tile spans
``chunk = ceil(n / tiles)`` cells, tile ``r{a}c{b}`` holds rows ``a*chunk_y : (a+1)*chunk_y`` and
cols ``b*chunk_x : (b+1)*chunk_x`` (the last ones may be shorter). So every tile writes whole chunks
of the mosaic store and parallel tiles never share a chunk. Tiles beyond the scene's ``ckm.tiles``
(or past the grid's end) are empty.
"""

from __future__ import annotations

import math
import re

import numpy as np
import shapely

from simart_pipeline.config import Ckm

_TILE = re.compile(r"^r(\d+)c(\d+)$")


def tile_key(row: int, col: int) -> str:
    return f"r{row}c{col}"


def parse_tile_key(key: str) -> tuple[int, int]:
    m = _TILE.match(key)
    if not m:
        raise ValueError(f"not a tile key: {key!r} (expected r<row>c<col>)")
    return int(m.group(1)), int(m.group(2))


def cell_centres(ckm: Ckm) -> tuple[np.ndarray, np.ndarray]:
    """(y [rows], x [cols]) cell-centre coordinates, m."""
    rows, cols = ckm.shape
    x = ckm.center_m[0] - ckm.size_m[0] / 2 + (np.arange(cols) + 0.5) * ckm.cell_size_m
    y = ckm.center_m[1] - ckm.size_m[1] / 2 + (np.arange(rows) + 0.5) * ckm.cell_size_m
    return y, x


def chunk_shape(ckm: Ckm) -> tuple[int, int]:
    """(rows, cols) of one tile: the mosaic store's chunk shape along y and x."""
    rows, cols = ckm.shape
    n_cols_tiles, n_rows_tiles = ckm.tiles
    return math.ceil(rows / n_rows_tiles), math.ceil(cols / n_cols_tiles)


def tile_slices(ckm: Ckm, key: str) -> tuple[slice, slice] | None:
    """Row and column slices of tile ``key``; None when the scene's tiling has no such tile."""
    r, c = parse_tile_key(key)
    n_cols_tiles, n_rows_tiles = ckm.tiles  # (along x, along y)
    if r >= n_rows_tiles or c >= n_cols_tiles:
        return None
    rows, cols = ckm.shape
    cr, cc = chunk_shape(ckm)
    if r * cr >= rows or c * cc >= cols:
        return None  # a tile past the grid's end (more tiles than cells)
    return slice(r * cr, min((r + 1) * cr, rows)), slice(c * cc, min((c + 1) * cc, cols))


def scene_tiles(ckm: Ckm) -> list[str]:
    n_cols_tiles, n_rows_tiles = ckm.tiles
    return [tile_key(r, c) for r in range(n_rows_tiles) for c in range(n_cols_tiles)
            if tile_slices(ckm, tile_key(r, c)) is not None]


def outside_region(ckm: Ckm, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Cells whose centre lies outside the region of interest (all False without a region)."""
    xx, yy = np.meshgrid(x, y)
    if ckm.region_m is None:
        return np.zeros(xx.shape, bool)
    region = shapely.Polygon(ckm.region_m)
    return ~shapely.contains_xy(region, xx, yy)
