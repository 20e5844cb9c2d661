"""Clock, frames and the one Zarr writer."""

import os

import numpy as np
import pytest
import xarray as xr

from simart_pipeline import clock, frames, stores


def test_streams_share_instants_exactly():
    t10 = clock.sample_times_ns(5.0, 10.0)
    t2 = clock.sample_times_ns(5.0, 2.0)
    assert t10.dtype == np.int64 and len(t10) == 51 and len(t2) == 11
    assert set(t2) <= set(t10)
    assert t10[-1] == 5 * clock.NS_PER_S


def test_rate_without_integer_period_has_no_drift():
    t = clock.sample_times_ns(100.0, 30.0)
    # sample i at floor(i * 1e9 / 30): every 30th sample on a whole second, never more than 1 ns off
    assert np.all(t[::30] == np.arange(0, 101) * clock.NS_PER_S)
    ideal = np.arange(len(t)) * (1e9 / 30)
    assert np.max(np.abs(t - ideal)) < 1.0
    assert np.all(np.diff(t) > 0)


def test_enu_geodetic_round_trip_below_a_millimetre():
    rng = np.random.default_rng(0)
    enu = rng.uniform(-5000, 5000, size=(100, 3))
    lla = frames.enu_to_geodetic(enu, 48.1372, 11.5755, 519.0)
    back = frames.geodetic_to_enu(lla, 48.1372, 11.5755, 519.0)
    assert np.max(np.abs(back - enu)) < 1e-3


def test_optical_frame_convention():
    # optical z (forward) is body x; optical x (right) is body -y; optical y (down) is body -z
    m = frames.OPTICAL_TO_BODY.as_matrix()
    assert np.allclose(m @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(m @ [1, 0, 0], [0, -1, 0])
    assert np.allclose(m @ [0, 1, 0], [0, 0, -1])


def _ds(value=1.0):
    return xr.Dataset({"v": (("time", "name"), np.full((3, 2), value), {"units": "m"})},
                      coords={"time": np.arange(3, dtype=np.int64), "name": ["a", "b"]})


def test_store_round_trip_and_overwrite(tmp_path):
    path = stores.store_path(tmp_path, "cirs", "demo", "sunny")
    assert path == tmp_path.resolve() / "cirs" / "demo" / "sunny.zarr"
    stores.write_store(_ds(1.0), path)
    stores.write_store(_ds(2.0), path)
    back = stores.open_store(path).load()
    assert np.all(back["v"].values == 2.0) and list(back["name"].values) == ["a", "b"]
    assert back["time"].dtype == np.int64
    assert [p.name for p in path.parent.iterdir()] == ["sunny.zarr"]  # no leftovers


def test_a_store_built_in_memory_equals_one_written_to_disk(tmp_path, monkeypatch):
    """write_store builds small stores in memory and writes their files in one pass: the same
    files, bytes and tree as a store written straight to disk, nested groups and strings
    included, and one consolidated copy at the root that opens every group."""
    import json

    tree = xr.DataTree.from_dict({
        "/": xr.Dataset(attrs={"scene": "demo"}),
        "/uav0/cam": _ds(1.5).assign(label=("name", np.array(["road", "wall"]))),
        "/uav0/imu": xr.Dataset({"acc_mps2": (("time", "axis"), np.arange(9.0).reshape(3, 3), {"units": "m/s^2"})},
                                coords={"time": np.arange(3, dtype=np.int64)}),
    })
    stores.write_store(tree, tmp_path / "memory.zarr")
    monkeypatch.setattr(stores, "IN_MEMORY_WRITE_MAX_BYTES", -1)
    stores.write_store(tree, tmp_path / "disk.zarr")

    def files(root):
        return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    mem, disk = files(tmp_path / "memory.zarr"), files(tmp_path / "disk.zarr")
    assert mem.keys() == disk.keys() and "uav0/cam/v/c/0/0" in mem
    assert all(mem[k] == disk[k] for k in mem)
    back = stores.open_store(tmp_path / "memory.zarr", tree=True).load()
    assert back.identical(tree)
    nested = json.loads(mem["zarr.json"])["consolidated_metadata"]["metadata"]
    assert {"uav0", "uav0/cam", "uav0/cam/v", "uav0/imu/acc_mps2"} <= set(nested)
    assert not json.loads(mem["uav0/zarr.json"]).get("consolidated_metadata")  # the root's only


def test_failed_write_leaves_last_good_version(tmp_path, monkeypatch):
    path = tmp_path / "s.zarr"
    stores.write_store(_ds(1.0), path)

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(xr.Dataset, "to_zarr", boom)
    with pytest.raises(OSError, match="disk full"):
        stores.write_store(_ds(5.0), path)
    monkeypatch.undo()
    assert np.all(stores.open_store(path).load()["v"].values == 1.0)
    assert sorted(os.listdir(tmp_path)) == ["s.zarr"]


def test_non_finite_values_are_refused(tmp_path):
    with pytest.raises(stores.StoreError, match="inf"):
        stores.write_store(_ds(np.inf), tmp_path / "a.zarr")
    with pytest.raises(stores.StoreError, match="nan_means"):
        stores.write_store(_ds(np.nan), tmp_path / "b.zarr")
    ok = _ds(np.nan)
    ok["v"].attrs["nan_means"] = "no path"
    stores.write_store(ok, tmp_path / "c.zarr")
    assert not (tmp_path / "a.zarr").exists() and not (tmp_path / "b.zarr").exists()


@pytest.mark.parametrize("bad", ["../x", "a/b", "..", "", ".hidden"])
def test_unsafe_partition_keys_are_refused(tmp_path, bad):
    with pytest.raises(stores.StoreError, match="unsafe"):
        stores.store_path(tmp_path, "cirs", "demo", bad)


def _region_store(path, keep_existing=None, tag="a"):
    """A 4 x 6 float map in chunks of 2 x 3 and an int flag per chunk, nothing written yet."""
    variables = {"gain_db": (("y", "x"), (4, 6), np.float32, {"units": "dB", "nan_means": "not written"}, (2, 3)),
                 "count": (("y", "x"), (4, 6), np.int16, {"units": "1"}, (2, 3)),
                 "done": (("y", "x"), (4, 6), bool, {}, (2, 3))}
    coords = {"y": (("y",), np.arange(4.0), {"units": "m"}), "x": (("x",), np.arange(6.0), {"units": "m"})}
    return stores.create_chunked_store(path, variables, coords, {"tag": tag}, keep_existing=keep_existing)


def test_region_writes_are_checked_like_every_store(tmp_path):
    path = _region_store(tmp_path / "m.zarr")
    empty = xr.open_zarr(path, consolidated=False).load()
    assert np.isnan(empty["gain_db"]).all() and (empty["count"] == -1).all() and not empty["done"].any()
    part = xr.Dataset({"gain_db": (("y", "x"), np.full((2, 3), 1.5, np.float32), {"nan_means": "x"}),
                       "count": (("y", "x"), np.full((2, 3), 7, np.int16)),
                       "done": (("y", "x"), np.ones((2, 3), bool))})
    aligned = {"y": slice(2, 4), "x": slice(3, 6)}
    stores.write_region(part, path, aligned, chunks={"y": 2, "x": 3}, sizes={"y": 4, "x": 6})
    with pytest.raises(stores.StoreError, match="not aligned"):
        stores.write_region(part, path, {"y": slice(1, 3), "x": slice(0, 3)}, chunks={"y": 2, "x": 3},
                            sizes={"y": 4, "x": 6})
    bad = part.assign(gain_db=part["gain_db"].where(part["count"] < 0, np.inf))
    with pytest.raises(stores.StoreError, match="inf"):
        stores.write_region(bad, path, {"y": slice(0, 2), "x": slice(0, 3)}, chunks={"y": 2, "x": 3},
                            sizes={"y": 4, "x": 6})
    after = xr.open_zarr(path, consolidated=False).load()
    written = np.zeros((4, 6), bool)
    written[2:, 3:] = True
    assert (after["gain_db"].values[written] == 1.5).all() and np.isnan(after["gain_db"].values[~written]).all()
    assert (after["count"].values[written] == 7).all() and (after["count"].values[~written] == -1).all()


def test_chunked_store_metadata_is_consolidated_and_region_writes_keep_it_exact(tmp_path):
    import json
    import warnings

    path = _region_store(tmp_path / "m.zarr")
    part = xr.Dataset({"gain_db": (("y", "x"), np.full((2, 3), 2.5, np.float32), {"nan_means": "x", "extra": 1}),
                       "count": (("y", "x"), np.full((2, 3), 3, np.int16)), "done": (("y", "x"), np.ones((2, 3), bool))})
    stores.write_region(part, path, {"y": slice(0, 2), "x": slice(3, 6)}, chunks={"y": 2, "x": 3},
                        sizes={"y": 4, "x": 6})
    # every array's own metadata, after the write, is what the root's consolidated copy says
    consolidated = json.loads((path / "zarr.json").read_text())["consolidated_metadata"]["metadata"]
    names = sorted(p.parent.name for p in path.glob("*/zarr.json"))
    assert sorted(consolidated) == names == ["count", "done", "gain_db", "x", "y"]
    for name in names:
        assert json.loads((path / name / "zarr.json").read_text()) == consolidated[name], name
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # xarray warns when it falls back to reading array by array
        fast = xr.open_zarr(path).load()
    assert fast.identical(xr.open_zarr(path, consolidated=False).load())
    assert (fast["gain_db"].values[:2, 3:] == 2.5).all() and np.isnan(fast["gain_db"].values[2:]).all()
    assert fast["gain_db"].attrs == {"units": "dB", "nan_means": "not written"}  # the region's attrs not written


def test_chunked_store_needs_nan_meanings_and_keeps_an_equal_template(tmp_path):
    with pytest.raises(stores.StoreError, match="nan_means"):
        stores.create_chunked_store(tmp_path / "n.zarr", {"v": (("x",), (4,), np.float64, {}, (2,))},
                                    {"x": (("x",), np.arange(4), {})}, {})
    assert not (tmp_path / "n.zarr").exists()
    path = _region_store(tmp_path / "m.zarr")
    part = xr.Dataset({"gain_db": (("y", "x"), np.zeros((2, 3), np.float32), {"nan_means": "x"}),
                       "count": (("y", "x"), np.zeros((2, 3), np.int16)), "done": (("y", "x"), np.ones((2, 3), bool))})
    stores.write_region(part, path, {"y": slice(0, 2), "x": slice(0, 3)}, chunks={"y": 2, "x": 3},
                        sizes={"y": 4, "x": 6})

    def equal_to(tag):
        return lambda p: xr.open_zarr(p, consolidated=False).attrs["tag"] == tag

    _region_store(path, keep_existing=equal_to("a"), tag="a")  # an equal template: its tiles stay
    assert bool(xr.open_zarr(path, consolidated=False)["done"][0, 0])
    _region_store(path, keep_existing=equal_to("b"), tag="b")  # another template: replaced, empty again
    again = xr.open_zarr(path, consolidated=False)
    assert again.attrs["tag"] == "b" and not bool(again["done"][0, 0])
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
