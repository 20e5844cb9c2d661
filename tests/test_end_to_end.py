"""Materialise a tiny scene end to end through Dagster: every asset, two weathers, two tiles."""

import numpy as np
import pytest
import xarray as xr

import dagster as dg

from simart_pipeline import stores
from simart_pipeline.cli import materialize_scene
from simart_pipeline.config import load_scene_config

WEATHERS = ["sunny", "rainy"]
TILES = ["r0c0", "r0c1"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from conftest import TESTS

    data = tmp_path_factory.mktemp("data")
    instance = dg.DagsterInstance.ephemeral()
    lines = []
    out = materialize_scene(TESTS / "scenes" / "tiny", data, WEATHERS, TILES, instance=instance,
                            progress=lines.append)
    return data, out, instance, lines, load_scene_config(TESTS / "scenes" / "tiny")


def _all_finite_where_valid(ds: xr.Dataset):
    for name, v in ds.variables.items():
        if np.issubdtype(v.dtype, np.inexact):
            vals = np.asarray(v.values)
            assert not np.isinf(vals).any(), name
            if "nan_means" not in v.attrs:
                assert not np.isnan(vals).any(), name


def test_one_store_per_asset_partition(run):
    data, out, instance, lines, cfg = run
    expected = {"osm_extract": 1, "paired_meshes": 1, "trajectory": 1, "sensor_frames": 2, "cirs": 2,
                "kpis": 2, "session": 2, "ckm_layers": 2}
    assert {k: len(v) for k, v in out.items()} == expected
    assert (data / "paired_meshes" / "tiny" / "radio" / "scene.xml").is_file()
    assert any("materialised" in line for line in lines)
    # the instance recorded every materialisation
    for key in ("cirs", "kpis", "session", "ckm_layers"):
        assert len(instance.get_materialized_partitions(dg.AssetKey(key))) == 2


def test_units_and_time_alignment_across_streams(run):
    data, _, _, _, cfg = run
    for weather in WEATHERS:
        tree = stores.open_store(data / "session" / "tiny" / f"{weather}.zarr", tree=True)
        assert {"trajectory", "cirs", "kpis", "sensors"} <= set(tree.children)
        assert tree.attrs["config_sha256"] == cfg.digest()
        radio_t = tree["cirs"]["time"].values
        assert radio_t.dtype == np.int64
        np.testing.assert_array_equal(tree["kpis"]["time"].values, radio_t)
        pose_t = tree["trajectory"]["time"].values
        assert set(radio_t) <= set(pose_t)  # 5 Hz radio instants are 50 Hz pose instants exactly
        sensors = [n for n in tree["sensors"].subtree if n.has_data]
        assert {n.path.split("/sensors/")[1] for n in sensors} == {"car0/cam", "car0/lidar", "car0/imu", "car0/gps"}
        for node in sensors:
            t = node["time"].values
            assert t.dtype == np.int64 and t[0] == 0 and t[-1] <= 10**9
        for node in tree.subtree:
            ds = node.to_dataset().load()
            _all_finite_where_valid(ds)
            for name, v in ds.data_vars.items():
                assert "long_name" in v.attrs, (node.path, name)
                if np.issubdtype(v.dtype, np.number) and v.dtype != bool:
                    assert "units" in v.attrs or "flag_values" in v.attrs or "valid_where" in v.attrs \
                        or name.endswith("_id"), (node.path, name)


def test_channels_and_kpis_are_computed(run):
    data, _, _, _, cfg = run
    cirs = stores.open_store(data / "cirs" / "tiny" / "sunny.zarr").load()
    kpis = stores.open_store(data / "kpis" / "tiny" / "sunny.zarr").load()
    assert cirs.sizes["link"] == 2 and cirs.sizes["tx_ant"] == 4
    assert cirs["num_valid_paths"].values.max() >= 2 and cirs["los"].any()
    # a valid path has a positive delay, an invalid one is masked
    valid = cirs["valid"].values
    assert (cirs["tau_s"].values[valid] > 0).all() and np.isnan(cirs["tau_s"].values[~valid]).all()
    served = kpis["rx_served"].values
    assert served.any()
    assert np.isfinite(kpis["sinr_db"].values[served]).all()
    assert (kpis["sinr_db"].values[served] <= kpis["snr_db"].values[served] + 1e-9).all()
    rainy = stores.open_store(data / "cirs" / "tiny" / "rainy.zarr")
    assert "wet_ground" in rainy.attrs["weather_material_overrides"]


def test_ckm_tiles_hold_path_gain(run):
    data, _, _, _, cfg = run
    a = stores.open_store(data / "ckm_layers" / "tiny" / "r0c0.zarr").load()
    b = stores.open_store(data / "ckm_layers" / "tiny" / "r0c1.zarr").load()
    mosaic = xr.concat([a, b], dim="x")
    rows, cols = cfg.ckm.shape
    assert mosaic.sizes["y"] == rows and mosaic.sizes["x"] == cols
    gain = mosaic["path_gain_db"].values
    assert np.isfinite(gain[mosaic["has_path"].values]).all()
    assert (gain[np.isfinite(gain)] < 0).all()  # passive channel: gain below 0 dB
    outdoor = ~mosaic["cell_inside_building"].values
    covered = mosaic["has_path"].any("bs").values
    assert not covered[~outdoor].any()  # indoor cells are masked, never traced
    assert covered[outdoor].mean() > 0.8, covered[outdoor].mean()


def test_rerun_is_idempotent_and_reproducible(run):
    data, _, instance, _, _ = run
    from conftest import TESTS

    before = stores.open_store(data / "cirs" / "tiny" / "sunny.zarr").load()
    materialize_scene(TESTS / "scenes" / "tiny", data, ["sunny"], ["r0c0"], instance=instance, progress=lambda s: None)
    after = stores.open_store(data / "cirs" / "tiny" / "sunny.zarr").load()
    xr.testing.assert_identical(before.drop_attrs(), after.drop_attrs())
