"""One mosaic Zarr store per (scene, set of radio materials): a template written once, then every
tile written into its own chunk-aligned region.

- The template holds every layer at full grid size with chunks equal to the tiles (no chunk is
  written: absent chunks read as the fill value, ``stores.fill_value``), the coordinates, and
  ``tile_complete`` (tile_row, tile_col) with one chunk per tile. ``stores.create_chunked_store``
  writes it aside and renames it into place. A template whose ``template_sha256`` (grid, layers,
  config) differs from the wanted one is replaced, since its tiles belong to another config.
- A tile first marks itself incomplete (``tile_complete`` false, ``tile_data_version`` -1), writes
  its region through ``stores.write_region`` (whole chunks only, and the finite/NaN checks of every
  store), records its version in ``tile_data_version`` and then marks itself complete; a tile whose
  recorded version equals the wanted one and which is complete is up to date
  (:func:`tile_is_current`) and is not written again. A failed or killed tile leaves the other
  tiles' chunks untouched and is simply rerun; any subset of tiles in any order gives the same map.
- Every chunk file is written aside and renamed into place by zarr's LocalStore (zarr 3.1:
  ``_atomic_write``), so a kill leaves each chunk old or new, never torn; a tile killed mid-write
  may mix old and new chunks, which is why its marks are cleared first. The marks are one chunk
  per tile, so marking one tile never rewrites another's.
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
                    coords: dict[str, tuple[tuple[str, ...], np.ndarray, dict]], attrs: dict,
                    map_version: str = "") -> str:
    """Write the mosaic template at ``path`` unless an identical one is there; returns its hash.

    :param spec: layer name -> (dims, dtype, attrs); dims end with ``GRID_DIMS`` (plus ``beam``)
    :param coords: name -> (dims, values, attrs) for every coordinate
    :param map_version: what the map's content depends on (``versions.VersionPlan.map_version``);
        the template's identity is its layout and this, not its provenance attrs, so that an edit
        of the config that the map does not read leaves the map and its tiles in place.
    """
    path = Path(path)
    key = template_sha256(spec, coords, {"map_version": map_version})
    sizes = {d: len(v[1]) for d, v in coords.items() if v[0] == (d,)}
    cy, cx = chunk_shape(ckm)
    variables = {}
    for name, (dims, dtype, var_attrs) in spec.items():
        variables[name] = (dims, tuple(sizes[d] for d in dims), dtype, var_attrs,
                           tuple({"y": cy, "x": cx}.get(d, sizes[d]) for d in dims))
    n_cols_tiles, n_rows_tiles = ckm.tiles
    variables["tile_complete"] = (("tile_row", "tile_col"), (n_rows_tiles, n_cols_tiles), bool, {
        "long_name": "the tile's cells are all written (false: missing or being written)"}, (1, 1))
    variables["tile_data_version"] = (("tile_row", "tile_col"), (n_rows_tiles, n_cols_tiles), np.int64, {
        "long_name": "version of the inputs the tile was computed from (first 60 bits of a SHA-256); "
                     "-1: not written"}, (1, 1))
    stores.create_chunked_store(path, variables, coords,
                                {**attrs, "template_sha256": key, "map_version": map_version},
                                keep_existing=lambda p: _has_template(p, key))
    return key


def tile_is_current(path: Path, tile: str, map_version: str, tile_version: int) -> bool:
    """Whether the mosaic at ``path`` is the template of ``map_version`` and holds tile ``tile``
    complete at ``tile_version``."""
    path = Path(path)
    try:
        g = zarr.open_group(path, mode="r")
        r, c = parse_tile_key(tile)
        return (g.attrs.get("map_version") == map_version and bool(g["tile_complete"][r, c])
                and int(g["tile_data_version"][r, c]) == tile_version)
    except Exception:  # absent or unreadable: not current
        return False


def tiles_digest(path: Path) -> str:
    """Digest of the mosaic's template and per-tile versions (``tile_data_version``): it changes
    whenever a tile is written or the map is recreated, so a picture of the map can tell whether the
    map changed since ("" when the map is absent or unreadable)."""
    try:
        g = zarr.open_group(Path(path), mode="r")
        versions = np.asarray(g["tile_data_version"][...], dtype=np.int64)
        return hashlib.sha256(str(g.attrs.get("template_sha256")).encode() + versions.tobytes()).hexdigest()[:16]
    except Exception:
        return ""


def _remove_partial_chunks(path: Path, r: int, c: int) -> None:
    """Delete the half-written chunk files (``<chunk>.<uuid>.partial``, zarr's LocalStore) that a run
    killed while writing tile (r, c) left: readers ignore them, but they would pile up. The chunk key
    of each array is built from its own dimension names (tile (r, c) is chunk r along ``y`` and
    ``tile_row``, chunk c along ``x`` and ``tile_col``; other dims are one chunk), so a live writer's
    files of another tile are never touched."""
    import zarr

    index = {"y": str(r), "x": str(c), "tile_row": str(r), "tile_col": str(c)}
    for name, arr in zarr.open_group(path, mode="r").arrays():
        dims = arr.metadata.dimension_names or ()
        if not {"y", "x"} <= set(dims) and not {"tile_row", "tile_col"} <= set(dims):
            continue
        key = "/".join(index.get(d, "*") for d in dims)
        for f in path.glob(f"{name}/c/{key}.*.partial"):
            f.unlink(missing_ok=True)


def write_tile(path: Path, ckm: Ckm, tile: str, ds: xr.Dataset, tile_version: int = -1) -> None:
    """Write tile ``tile``'s layers (dims ``... height, y, x``) into their chunk-aligned region."""
    sl = tile_slices(ckm, tile)
    if sl is None:
        return
    r, c = parse_tile_key(tile)
    cy, cx = chunk_shape(ckm)
    rows, cols = ckm.shape
    done = zarr.open_array(Path(path) / "tile_complete", mode="r+")
    version = zarr.open_array(Path(path) / "tile_data_version", mode="r+")
    # Both marks are cleared before any of the tile's chunks changes and set only after all of them
    # are written: a run killed in between leaves a tile that is not current, so it is recomputed,
    # and a previously current tile being rewritten is from then on treated as never written.
    done[r, c] = False
    version[r, c] = -1
    _remove_partial_chunks(Path(path), r, c)
    stores.write_region(ds, path, {"y": sl[0], "x": sl[1]}, chunks={"y": cy, "x": cx},
                        sizes={"y": rows, "x": cols})
    version[r, c] = tile_version
    done[r, c] = True


def open_map(path: Path) -> xr.Dataset:
    """The mosaic as an xarray dataset (absent tiles read as fills; see ``tile_complete``)."""
    path = Path(path)
    if not path.exists():
        stores.recover(path)  # a template swap killed half way may have left the map aside
    if not path.exists():
        raise FileNotFoundError(f"no channel knowledge map at {path}: materialise ckm_layers first")
    return xr.open_zarr(path, consolidated=stores.has_consolidated_metadata(path))
