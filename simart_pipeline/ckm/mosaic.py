"""One mosaic Zarr store per (scene, set of radio materials): a template written once, then every
tile written into its own chunk-aligned region.

- The template holds every layer at full grid size with chunks equal to the tiles (no chunk is
  written: absent chunks read as the fill value), the coordinates, and ``tile_complete``
  (tile_row, tile_col) with one chunk per tile. It is written aside and renamed into place. A
  template whose ``template_sha256`` (grid, layers, config) differs from the wanted one is
  replaced, since its tiles belong to another config.
- A tile first marks itself incomplete, writes its region (whole chunks only: asserted, since
  concurrent writers sharing a chunk corrupt it silently), then marks itself complete. A failed
  tile leaves the other tiles' chunks untouched and is simply rerun; any subset of tiles in any
  order gives the same map.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import uuid
from pathlib import Path

import numpy as np
import xarray as xr
import zarr

from simart_pipeline.ckm.grid import chunk_shape, parse_tile_key, tile_slices
from simart_pipeline.config import Ckm

GRID_DIMS = ("height", "y", "x")


def template_sha256(spec: dict, coords: dict, attrs: dict) -> str:
    blob = json.dumps({"spec": {k: [list(v[0]), str(np.dtype(v[1]))] for k, v in sorted(spec.items())},
                       "coords": {k: np.asarray(v[1]).tolist() for k, v in sorted(coords.items())},
                       "attrs": attrs}, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()


def _fill(dtype) -> object:
    dt = np.dtype(dtype)
    if dt == bool:
        return False
    if np.issubdtype(dt, np.floating):
        return np.nan
    return -1


def ensure_template(path: Path, ckm: Ckm, spec: dict[str, tuple[tuple[str, ...], object, dict]],
                    coords: dict[str, tuple[tuple[str, ...], np.ndarray, dict]], attrs: dict) -> str:
    """Write the mosaic template at ``path`` unless an identical one is there; returns its hash.

    :param spec: layer name -> (dims, dtype, attrs); dims end with ``GRID_DIMS`` (plus ``beam``)
    :param coords: name -> (dims, values, attrs) for every coordinate
    """
    path = Path(path)
    key = template_sha256(spec, coords, attrs)
    if path.exists():
        try:
            if zarr.open_group(path, mode="r").attrs.get("template_sha256") == key:
                return key
        except Exception:  # an unreadable store is replaced below
            pass
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        g = zarr.open_group(tmp, mode="w", zarr_format=3)
        sizes = {d: len(v[1]) for d, v in coords.items() if v[0] == (d,)}
        cy, cx = chunk_shape(ckm)
        for name, (dims, dtype, var_attrs) in spec.items():
            shape = tuple(sizes[d] for d in dims)
            chunks = tuple({"y": cy, "x": cx}.get(d, sizes[d]) for d in dims)
            g.create_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=_fill(dtype),
                           dimension_names=dims, attributes=var_attrs)
        n_cols_tiles, n_rows_tiles = ckm.tiles
        g.create_array("tile_complete", shape=(n_rows_tiles, n_cols_tiles), chunks=(1, 1), dtype=bool,
                       fill_value=False, dimension_names=("tile_row", "tile_col"),
                       attributes={"long_name": "the tile's cells are all written (false: missing or "
                                   "being written)"})
        for name, (dims, values, var_attrs) in coords.items():
            values = np.asarray(values)
            dtype = str if values.dtype.kind in "OUS" else values.dtype
            arr = g.create_array(name, shape=values.shape, dtype=dtype, dimension_names=dims,
                                 attributes=var_attrs)
            arr[...] = values
        g.attrs.update({**attrs, "template_sha256": key})
        try:
            os.rename(tmp, path)
        except OSError:
            # Another tile won the race with the same template, or a stale template is in the way.
            if zarr.open_group(path, mode="r").attrs.get("template_sha256") == key:
                return key
            stale = path.with_name(f".{path.name}.{uuid.uuid4().hex}.stale")
            os.rename(path, stale)
            os.rename(tmp, path)
            shutil.rmtree(stale, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return key


def write_tile(path: Path, ckm: Ckm, tile: str, ds: xr.Dataset) -> None:
    """Write tile ``tile``'s layers (dims ``... height, y, x``) into their chunk-aligned region."""
    sl = tile_slices(ckm, tile)
    if sl is None:
        return
    r, c = parse_tile_key(tile)
    cy, cx = chunk_shape(ckm)
    rows, cols = ckm.shape
    if sl[0].start % cy or sl[1].start % cx or not (sl[0].stop % cy == 0 or sl[0].stop == rows) \
            or not (sl[1].stop % cx == 0 or sl[1].stop == cols):
        raise AssertionError(f"tile {tile} region {sl} is not aligned to chunks ({cy}, {cx})")
    done = zarr.open_array(Path(path) / "tile_complete", mode="r+")
    done[r, c] = False
    data = ds.drop_vars([k for k in ds.coords])
    for v in data.data_vars.values():
        v.attrs.clear()
        v.encoding.clear()
    data.attrs = {}
    data.to_zarr(path, region={"y": sl[0], "x": sl[1]}, mode="r+", consolidated=False, zarr_format=3)
    done[r, c] = True


def open_map(path: Path) -> xr.Dataset:
    """The mosaic as an xarray dataset (absent tiles read as fills; see ``tile_complete``)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no channel knowledge map at {path}: materialise ckm_layers first")
    return xr.open_zarr(path, consolidated=False)
