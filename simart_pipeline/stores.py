"""The one Zarr writer: every asset partition is one Zarr v3 store under the data root.

Layout: ``<data_root>/<asset>/<scene>.zarr`` for scene partitions and
``<data_root>/<asset>/<scene>/<weather or tile>.zarr`` for two-dimensional ones.

A store is written aside (``.<name>.tmp-<host>-<pid>-<id>``) and swapped into place in one step, so
a failed or killed run never leaves a half-written store, and a rerun replaces the last good version
completely or not at all (see :func:`_replace_atomically`; what a killed writer leaves aside is
cleaned up by the next write, :func:`recover`). Before a store is written, it is checked: no inf
anywhere, and NaN only in variables whose attrs say what NaN means (``nan_means``).

A store filled region by region (the CKM mosaic: one region per tile, from concurrent runs) is
created empty by :func:`create_chunked_store`, written aside and renamed like every other store, and
filled by :func:`write_region`, which checks each region as above and refuses one that does not
cover whole chunks (writers sharing a chunk corrupt it silently). Absent chunks read as the fill
values of :func:`fill_value`: NaN in float variables (which must say what NaN means), -1 in integer
ones, false in booleans.
"""

from __future__ import annotations

import ctypes
import errno
import hashlib
import json
import os
import re
import shutil
import socket
import uuid
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import xarray as xr

SAFE_KEY = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


class StoreError(ValueError):
    """A store that must not be written (non-finite values, unsafe path)."""


def _safe(part: str, what: str) -> str:
    if not SAFE_KEY.match(part) or part in (".", ".."):
        raise StoreError(f"unsafe {what} {part!r}: only letters, digits, '_', '-', '.' are allowed")
    return part


def store_path(data_root: str | Path, asset: str, scene: str, sub: str | None = None,
               suffix: str = ".zarr") -> Path:
    """Where the store of one asset partition lives; every part is checked to stay under the root."""
    root = Path(data_root).resolve()
    parts = [_safe(asset, "asset name"), _safe(scene, "scene name")]
    if sub is not None:
        parts.append(_safe(sub, "partition key"))
    path = root.joinpath(*parts[:-1], parts[-1] + suffix)
    if root not in path.resolve().parents:
        raise StoreError(f"store path {path} escapes the data root {root}")
    return path


def check_finite(obj: xr.Dataset | xr.DataTree, where: str = "") -> None:
    """No inf anywhere; NaN only in float variables that declare ``nan_means`` in their attrs."""
    nodes = obj.subtree if isinstance(obj, xr.DataTree) else [obj]
    for node in nodes:
        ds = node.to_dataset() if isinstance(node, xr.DataTree) else node
        group = getattr(node, "path", "/")
        for name, var in ds.variables.items():
            if not np.issubdtype(var.dtype, np.inexact):
                continue
            values = np.asarray(var.values)
            if np.isinf(values).any():
                raise StoreError(f"{where}{group}:{name} holds inf")
            if "nan_means" not in var.attrs and np.isnan(values).any():
                raise StoreError(f"{where}{group}:{name} holds NaN but its attrs do not say what NaN "
                                 "means (attr 'nan_means')")


def _portable_strings(ds: xr.Dataset) -> xr.Dataset:
    # Fixed-width numpy unicode has no Zarr v3 spec; variable-length strings do (zarr-extensions).
    fixed = {k for k, v in ds.variables.items() if v.dtype.kind == "U"}
    coords = {k: (ds[k].dims, ds[k].values.astype(object), ds[k].attrs) for k in fixed & set(ds.coords)}
    data = {k: ds[k].variable.astype(object) for k in fixed - set(ds.coords)}
    return ds.assign_coords(coords).assign(data)


def _plain_strings(ds: xr.Dataset) -> xr.Dataset:
    # zarr reads variable-length strings as numpy StringDType, which many numpy paths (astype(str),
    # pandas) do not take yet; hand callers ordinary object arrays of str.
    names = [k for k, v in ds.variables.items() if v.dtype.kind == "T"]
    if not names:
        return ds
    coords = {k: (ds[k].dims, ds[k].values.astype(object), ds[k].attrs) for k in names if k in ds.coords}
    data = {k: ds[k].variable.astype(object) for k in names if k not in ds.coords}
    return ds.assign_coords(coords).assign(data)


# Temporaries of a target ``NAME`` are ``.NAME.tmp-<host>-<pid>-<id>`` (the new version being written,
# or after the swap the old one being deleted) and ``.NAME.old-<host>-<pid>-<id>`` (the old version
# moved aside, fallback swap only). Host and pid tell whether their writer still lives, so that the
# next writer (or reader) on the same host can restore or delete what a killed one left behind.
_HOST = hashlib.sha256(socket.gethostname().encode()).hexdigest()[:6]
_TEMP = re.compile(r"^\.(?P<name>.+)\.(?P<kind>tmp|old)-(?P<host>[0-9a-f]{6})-(?P<pid>\d+)-[0-9a-f]{8}$")


def _temp_name(path: Path, kind: str) -> Path:
    return path.with_name(f".{path.name}.{kind}-{_HOST}-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` of this host still runs (this process counts as alive): the
    writer of a temporary, or the process of a run (``cli.release_dead_runs``)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def _dead_temporaries(path: Path) -> list[tuple[str, Path]]:
    """(kind, dir) of the temporaries of ``path`` left by dead writers on this host; a pid reused by
    a live process keeps its temporaries (left behind, never wrongly deleted)."""
    out = []
    try:
        entries = list(path.parent.iterdir())
    except FileNotFoundError:
        return out
    for p in entries:
        m = _TEMP.match(p.name)
        if m and m["name"] == path.name and m["host"] == _HOST and not process_alive(int(m["pid"])):
            out.append((m["kind"], p))
    return out


def recover(path: str | Path) -> None:
    """Undo what a writer of ``path`` killed mid-swap left: a missing ``path`` with its old version
    moved aside (``.old-``) gets that version back; every other temporary of a dead writer is deleted.
    Called before every write and every :func:`open_store`."""
    path = Path(path)
    dead = _dead_temporaries(path)
    for kind, p in dead:
        if kind == "old" and not path.exists():
            try:
                os.rename(p, path)  # fails harmlessly if another process put a store there first
                continue
            except OSError:
                pass
        shutil.rmtree(p, ignore_errors=True)


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100
try:
    _renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
except (AttributeError, OSError):  # not Linux, or a libc older than glibc 2.28
    _renameat2 = None


def _exchange(a: Path, b: Path) -> bool:
    """Swap the directories at ``a`` and ``b`` in one step (Linux renameat2 RENAME_EXCHANGE): true
    when done, false where the system or file system cannot (then :func:`_replace_atomically` falls
    back to two renames); OSError when ``b`` is missing (ENOENT) or another error."""
    if _renameat2 is None:
        return False
    if _renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _replace_atomically(tmp: Path, path: Path, keep_existing: Callable[[Path], bool] | None = None) -> None:
    """Swap ``tmp`` into ``path``; at every instant ``path`` is either the old or the new version.

    The swap is one renameat2(RENAME_EXCHANGE): afterwards ``tmp`` holds the old version, which the
    caller deletes. Where that is not available, the old version is renamed aside (``.old-``) and
    ``tmp`` renamed in; a writer killed between the two leaves no store at ``path``, which
    :func:`recover` (run by the next write or :func:`open_store`) undoes by renaming ``.old-`` back.

    With ``keep_existing``, a store already at ``path`` (or one that another process renames there
    first) for which it returns true is kept, and ``tmp`` is discarded by the caller."""
    if keep_existing is not None:
        try:
            os.rename(tmp, path)  # fails where a non-empty directory is in the way
            return
        except OSError:
            if not path.exists():
                raise
            if keep_existing(path):  # another writer won the race with an equal store
                return
    for _ in range(8):  # each retry means another writer created or swapped ``path`` meanwhile
        try:
            if _exchange(tmp, path):
                return  # the old version is now at ``tmp``: the caller deletes it
            break
        except FileNotFoundError:
            try:
                os.rename(tmp, path)  # nothing there: a plain rename (fails on a non-empty dir)
                return
            except OSError as exc:
                if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                    raise
    old = None
    if path.exists():
        old = _temp_name(path, "old")
        os.replace(path, old)
    try:
        os.replace(tmp, path)
    except BaseException:
        if old is not None:
            os.replace(old, path)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def write_named(path: Path, fill: Callable[[Path], None]) -> Path:
    """Create ``path`` (a directory or a file) by calling ``fill(p)`` with a path ``p`` of the same
    name that does not exist yet (for writers that create it themselves and name what is inside
    after it, as rosbag2 does), then move it into place atomically; what dead writers left behind is
    restored or deleted first (:func:`recover`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    recover(path)
    tmp = _temp_name(path, "tmp")
    try:
        tmp.mkdir()
        inner = tmp / path.name
        fill(inner)
        if inner.is_dir():
            _replace_atomically(inner, path)
        else:
            os.replace(inner, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # a failed write, or the old version after the exchange
    return path


def write_directory(path: Path, fill: Callable[[Path], None],
                    keep_existing: Callable[[Path], bool] | None = None) -> Path:
    """Create a directory by calling ``fill(tmp_dir)``, then rename it into place atomically;
    ``keep_existing(path)`` true keeps what is already there (see :func:`_replace_atomically`).
    What dead writers of ``path`` left behind is restored or deleted first (:func:`recover`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    recover(path)
    if keep_existing is not None and path.exists() and keep_existing(path):
        return path
    tmp = _temp_name(path, "tmp")
    try:
        tmp.mkdir()
        fill(tmp)
        _replace_atomically(tmp, path, keep_existing)
    finally:
        if tmp.exists():  # a failed write, or the old version after the exchange
            shutil.rmtree(tmp, ignore_errors=True)
    return path


# write_store builds a store this size or smaller in memory and writes its files in one pass:
# every zarr call goes through zarr's event-loop thread, and on disk each also waits for a file
# thread (a session store: 558 objects, 1.4 s through the disk, 1.0 s through memory). Larger
# stores are written straight to disk, so that a big one is never held twice.
IN_MEMORY_WRITE_MAX_BYTES = 512 * 2**20


def write_store(obj: xr.Dataset | xr.DataTree, path: str | Path) -> Path:
    """Write a dataset or a tree of datasets as one Zarr v3 store at ``path``, atomically, with
    consolidated metadata (written once, whole: the consolidated copy cannot go stale), so that
    ``xr.open_zarr`` / ``xr.open_datatree`` open it in one read and without a warning."""
    path = Path(path)
    check_finite(obj, where=f"{path}: ")

    def fill(tmp: Path) -> None:
        import zarr
        from zarr.storage import MemoryStore

        in_memory: dict | None = {} if obj.nbytes <= IN_MEMORY_WRITE_MAX_BYTES else None
        target = tmp if in_memory is None else MemoryStore(store_dict=in_memory)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*Consolidated metadata.*")
            if isinstance(obj, xr.DataTree):
                obj.map_over_datasets(_portable_strings).to_zarr(
                    target, mode="w", zarr_format=3, consolidated=False)
            else:
                _portable_strings(obj).to_zarr(target, mode="w", zarr_format=3, consolidated=False)
            # Once, at the root, when everything is written: DataTree.to_zarr consolidates after
            # every group, each time over the whole store (12 passes, half of a session store's
            # 3 s write). The root's copy covers the nested groups.
            zarr.consolidate_metadata(target, zarr_format=3)
        if in_memory is not None:
            for key in sorted(in_memory):
                f = tmp / key
                f.parent.mkdir(parents=True, exist_ok=True)
                f.write_bytes(in_memory[key].to_bytes())

    return write_directory(path, fill)


def fill_value(dtype) -> object:
    """What an absent chunk of a variable of ``dtype`` reads as: NaN, -1 or false."""
    dt = np.dtype(dtype)
    if dt == bool:
        return False
    if np.issubdtype(dt, np.floating):
        return np.nan
    return -1


def create_chunked_store(path: str | Path,
                         variables: dict[str, tuple[tuple[str, ...], tuple[int, ...], object, dict, tuple[int, ...]]],
                         coords: dict[str, tuple[tuple[str, ...], np.ndarray, dict]], attrs: dict,
                         keep_existing: Callable[[Path], bool] | None = None) -> Path:
    """An empty Zarr v3 store to be filled by :func:`write_region`: written aside, renamed into place,
    with consolidated metadata. Region writes add chunks and never touch metadata, so the
    consolidated copy stays exact and ``xr.open_zarr`` opens the store in one read, without a warning.

    :param variables: name -> (dims, shape, dtype, attrs, chunks); no chunk is written, so every value
        reads as :func:`fill_value` until a region is written. A float variable must say what NaN means.
    :param coords: name -> (dims, values, attrs), written in full.
    :param keep_existing: called with an existing store at ``path``: true keeps it as it is.
    """
    for name, (dims, _, dtype, var_attrs, _) in variables.items():
        if np.issubdtype(np.dtype(dtype), np.floating) and "nan_means" not in var_attrs:
            raise StoreError(f"{path}: {name} reads as NaN until written but its attrs do not say what "
                             "NaN means (attr 'nan_means')")

    def fill(tmp: Path) -> None:
        import zarr

        g = zarr.open_group(tmp, mode="w", zarr_format=3)
        for name, (dims, shape, dtype, var_attrs, chunks) in variables.items():
            g.create_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=fill_value(dtype),
                           dimension_names=dims, attributes=var_attrs)
        for name, (dims, values, var_attrs) in coords.items():
            values = np.asarray(values)
            check_finite(xr.Dataset({name: (dims, values, var_attrs)}), where=f"{path}: ")
            dtype = str if values.dtype.kind in "OUS" else values.dtype
            arr = g.create_array(name, shape=values.shape, dtype=dtype, dimension_names=dims,
                                 attributes=var_attrs)
            arr[...] = values
        g.attrs.update(attrs)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*Consolidated metadata.*")
            zarr.consolidate_metadata(tmp, zarr_format=3)

    return write_directory(Path(path), fill, keep_existing)


def write_region(ds: xr.Dataset, path: str | Path, region: dict[str, slice], chunks: dict[str, int],
                 sizes: dict[str, int]) -> None:
    """Write ``ds`` (its data variables, no coordinates) into ``region`` of a store made by
    :func:`create_chunked_store`, after the checks of :func:`check_finite`.

    :param chunks: the store's chunk length per region dim; ``sizes``: the store's size per dim. A
        region must start on a chunk boundary and end on one or at the end of its dim.
    """
    for dim, sl in region.items():
        c, n = chunks[dim], sizes[dim]
        if sl.start % c or not (sl.stop % c == 0 or sl.stop == n):
            raise StoreError(f"{path}: region {dim}={sl} is not aligned to chunks of {c} (writers sharing "
                             "a chunk corrupt it)")
    check_finite(ds, where=f"{path}: ")
    data = ds.drop_vars(list(ds.coords))
    data = xr.Dataset({k: xr.Variable(v.dims, v.data) for k, v in data.data_vars.items()})
    data.to_zarr(path, region=region, mode="r+", consolidated=False, zarr_format=3)


def open_store(path: str | Path, tree: bool = False) -> xr.Dataset | xr.DataTree:
    """Open a store written by :func:`write_store` (lazily)."""
    path = Path(path)
    if not path.exists():
        recover(path)  # a writer killed mid-swap may have left the last good version aside
    if not path.exists():
        raise FileNotFoundError(f"no store at {path}: materialise the upstream asset first")
    # Stores carry consolidated metadata (never stale: write_store's are written whole and replaced
    # whole, a chunked store's regions write no metadata), read in one request instead of one per
    # array: 2-4x faster opens, which every asset check and downstream input pays. Older stores
    # filled region by region have none.
    consolidated = has_consolidated_metadata(path)
    if tree:
        return xr.open_datatree(path, engine="zarr", consolidated=consolidated).map_over_datasets(_plain_strings)
    return _plain_strings(xr.open_zarr(path, consolidated=consolidated))


def has_consolidated_metadata(path: Path) -> bool:
    """Whether the Zarr v3 store at ``path`` holds consolidated metadata at its root."""
    try:
        return bool(json.loads((path / "zarr.json").read_bytes()).get("consolidated_metadata"))
    except (OSError, ValueError):
        return False
