"""The CKM grid: cell centres at a fixed height, split into tiles (the tile partitions).

Cell (row i, col j) has its centre at
``x = center_x - size_x / 2 + (j + 0.5) * cell``, ``y = center_y - size_y / 2 + (i + 0.5) * cell``.
Tile ``r{a}c{b}`` holds rows ``row_edges[a]:row_edges[a+1]`` and cols ``col_edges[b]:col_edges[b+1]``
of an even split (``numpy.array_split``); tiles beyond the scene's ``ckm.tiles`` are empty.
"""

from __future__ import annotations

import re

import numpy as np

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


def tile_slices(ckm: Ckm, key: str) -> tuple[slice, slice] | None:
    """Row and column slices of tile ``key``; None when the scene's tiling has no such tile."""
    r, c = parse_tile_key(key)
    n_cols_tiles, n_rows_tiles = ckm.tiles  # (along x, along y)
    if r >= n_rows_tiles or c >= n_cols_tiles:
        return None
    rows, cols = ckm.shape
    re_ = np.linspace(0, rows, n_rows_tiles + 1).round().astype(int)
    ce = np.linspace(0, cols, n_cols_tiles + 1).round().astype(int)
    return slice(re_[r], re_[r + 1]), slice(ce[c], ce[c + 1])


def scene_tiles(ckm: Ckm) -> list[str]:
    n_cols_tiles, n_rows_tiles = ckm.tiles
    return [tile_key(r, c) for r in range(n_rows_tiles) for c in range(n_cols_tiles)]
