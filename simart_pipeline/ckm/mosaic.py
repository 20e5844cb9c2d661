"""One mosaic Zarr store per (scene, set of radio materials): a template written once, then every
tile written into its own chunk-aligned region.

- The template holds every layer at full grid size with chunks equal to the tiles (no chunk is
  written: absent chunks read as the fill value, ``stores.fill_value``), the coordinates, and
  ``tile_complete`` (tile_row, tile_col) with one chunk per tile. ``stores.create_chunked_store``
  writes it aside and renames it into place. A template whose ``template_sha256`` (grid, layers,
  config) differs from the wanted one is replaced, since its tiles belong to another config.
- A tile first marks itself incomplete, writes its region through ``stores.write_region`` (whole
  chunks only, and the finite/NaN checks of every store), then marks itself complete. A failed
  tile leaves the other tiles' chunks untouched and is simply rerun; any subset of tiles in any
  order gives the same map.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import xarray as xr
import zarr

from simart_pipeline import stores
from simart_pipeline.ckm.grid import chunk_shape, parse_tile_key, tile_slices
from simart_pipeline.config import Ckm

GRID_DIMS = ("height", "y", "x")


def template_sha256(spec: dict, coords: dict, attrs: dict) -> str:
    blob = json.dumps({"spec": {k: [list(v[0]), str(np.dtype(v[1]))] for k, v in sorted(spec.items())},
                       "coords": {k: np.asarray(v[1]).tolist() for k, v in sorted(coords.items())},
                       "attrs": attrs}, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()


def _has_template(path: Path, key: str) -> bool:
    try:
        return zarr.open_group(path, mode="r").attrs.get("template_sha256") == key
    except Exception:  # an unreadable store is replaced
        return False


def ensure_template(path: Path, ckm: Ckm, spec: dict[str, tuple[tuple[str, ...], object, dict]],
                    coords: dict[str, tuple[tuple[str, ...], np.ndarray, dict]], attrs: dict) -> str:
    """Write the mosaic template at ``path`` unless an identical one is there; returns its hash.

    :param spec: layer name -> (dims, dtype, attrs); dims end with ``GRID_DIMS`` (plus ``beam``)
    :param coords: name -> (dims, values, attrs) for every coordinate
    """
    path = Path(path)
    key = template_sha256(spec, coords, attrs)
    sizes = {d: len(v[1]) for d, v in coords.items() if v[0] == (d,)}
    cy, cx = chunk_shape(ckm)
    variables = {}
    for name, (dims, dtype, var_attrs) in spec.items():
        variables[name] = (dims, tuple(sizes[d] for d in dims), dtype, var_attrs,
                           tuple({"y": cy, "x": cx}.get(d, sizes[d]) for d in dims))
    n_cols_tiles, n_rows_tiles = ckm.tiles
    variables["tile_complete"] = (("tile_row", "tile_col"), (n_rows_tiles, n_cols_tiles), bool, {
        "long_name": "the tile's cells are all written (false: missing or being written)"}, (1, 1))
    stores.create_chunked_store(path, variables, coords, {**attrs, "template_sha256": key},
                                keep_existing=lambda p: _has_template(p, key))
    return key


def write_tile(path: Path, ckm: Ckm, tile: str, ds: xr.Dataset) -> None:
    """Write tile ``tile``'s layers (dims ``... height, y, x``) into their chunk-aligned region."""
    sl = tile_slices(ckm, tile)
    if sl is None:
        return
    r, c = parse_tile_key(tile)
    cy, cx = chunk_shape(ckm)
    rows, cols = ckm.shape
    done = zarr.open_array(Path(path) / "tile_complete", mode="r+")
    done[r, c] = False
    stores.write_region(ds, path, {"y": sl[0], "x": sl[1]}, chunks={"y": cy, "x": cx},
                        sizes={"y": rows, "x": cols})
    done[r, c] = True


def open_map(path: Path) -> xr.Dataset:
    """The mosaic as an xarray dataset (absent tiles read as fills; see ``tile_complete``)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no channel knowledge map at {path}: materialise ckm_layers first")
    return xr.open_zarr(path, consolidated=False)
