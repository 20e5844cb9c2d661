"""Materialise a tiny scene end to end through Dagster: every asset, three weathers, two tiles."""

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import dagster as dg

from simart_pipeline import stores
from simart_pipeline.cli import materialize_scene

WEATHERS = ["sunny", "night", "rainy"]


@pytest.fixture(scope="module")
def run(tiny_run):
    return tiny_run  # conftest: materialised once per session, shared with test_checks.py


def _all_finite_where_valid(ds: xr.Dataset):
    for name, v in ds.variables.items():
        if np.issubdtype(v.dtype, np.inexact):
            vals = np.asarray(v.values)
            assert not np.isinf(vals).any(), name
            if "nan_means" not in v.attrs:
                assert not np.isnan(vals).any(), name


def test_one_store_per_asset_partition(run):
    data, out, instance, lines, cfg = run
    expected = {"osm_extract": 1, "paired_meshes": 1, "trajectory": 1, "sensor_frames": 3, "cirs": 2, "radar_frames": 2,
                "kpis": 3, "session": 3, "ckm": 2, "session_bag": 3}
    assert {k: len(v) for k, v in out.items()} == expected
    assert (data / "paired_meshes" / "tiny" / "radio" / "scene.xml").is_file()
    assert any("materialised" in line for line in lines)
    # the instance recorded every materialisation
    for key in ("kpis", "session"):
        assert len(instance.get_materialized_partitions(dg.AssetKey(key))) == 3
    assert len(instance.get_materialized_partitions(dg.AssetKey("cirs"))) == 2  # one per weather group
    assert len(instance.get_materialized_partitions(dg.AssetKey("ckm_layers"))) == 2
    assert len(instance.get_materialized_partitions(dg.AssetKey("ckm_map"))) == 1


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
    assert (cirs["tau_s"].values[valid] > 0).all() and (cirs["tau_s"].values[~valid] == -1).all()
    served = kpis["rx_served"].values
    assert served.any()
    assert np.isfinite(kpis["sinr_db"].values[served]).all()
    assert (kpis["sinr_db"].values[served] <= kpis["snr_db"].values[served] + 1e-9).all()
    rainy = stores.open_store(data / "cirs" / "tiny" / "rainy.zarr").load()
    assert "wet_ground" in rainy.attrs["weather_material_overrides"]
    assert "wet_concrete" in rainy.attrs["weather_material_overrides"]


def test_dry_weathers_trace_once_and_rain_traces_again(run):
    """Night has sunny's radio materials: one trace serves both, through the weather-group partition
    mapping that Dagster's lineage shows (no asset reads another partition's store on its own)."""
    data, _, instance, _, _ = run
    assert not (data / "cirs" / "tiny" / "night.zarr").exists()
    sunny, rainy = (stores.open_store(data / "cirs" / "tiny" / f"{g}.zarr").load() for g in ("sunny", "rainy"))
    assert sunny.attrs["weathers"] == "sunny,night" and rainy.attrs["weathers"] == "rainy"
    assert sunny.attrs["cir_content_sha256"] != rainy.attrs["cir_content_sha256"]
    los = sunny["los"].values
    assert not np.array_equal(sunny["a"].values[..., 1:], rainy["a"].values[..., 1:]) or not los.any()
    kpis = {w: stores.open_store(data / "kpis" / "tiny" / f"{w}.zarr").load() for w in WEATHERS}
    xr.testing.assert_identical(kpis["sunny"].drop_attrs(), kpis["night"].drop_attrs())
    night_session = stores.open_store(data / "session" / "tiny" / "night.zarr", tree=True)
    np.testing.assert_array_equal(night_session["cirs"]["a"].values, sunny["a"].values)

    def upstream(asset, weather):
        key = str(dg.MultiPartitionKey({"scene": "tiny", "weather": weather}))
        rec = instance.fetch_materializations(
            dg.AssetRecordsFilter(asset_key=dg.AssetKey(asset), asset_partitions=[key]), limit=1).records[0]
        return set(rec.event_log_entry.asset_materialization.metadata["data_version_inputs"].value["upstream"])

    assert "cirs[sunny]" in upstream("kpis", "night") and "cirs[rainy]" in upstream("kpis", "rainy")
    assert "cirs[sunny]" in upstream("session", "night")
    events = instance.fetch_materializations(dg.AssetKey("cirs"), limit=10).records
    assert "data:image/png;base64," in events[0].asset_materialization.metadata["paths_picture"].value


def test_ckm_maps_hold_every_layer_for_dry_and_wet_materials(run, capsys):
    data, _, instance, _, cfg = run
    from simart_pipeline.cli import main

    dry = stores.open_store(data / "ckm" / "tiny" / "sunny.zarr").load()
    wet = stores.open_store(data / "ckm" / "tiny" / "rainy.zarr").load()
    assert dry.attrs["map_weathers"] == "sunny,night" and wet.attrs["map_weathers"] == "rainy"
    rows, cols = cfg.ckm.shape
    assert dry.sizes["y"] == rows and dry.sizes["x"] == cols and dry["tile_complete"].all()
    for layer in ("path_gain_db", "path_loss_db", "path_gain_coherent_db", "rx_power_dbm", "toa_s",
                  "rms_delay_spread_s", "asa_deg", "asd_deg", "zsa_deg", "zsd_deg", "los", "count",
                  "best_bs", "sinr_db", "effective_sinr_db", "mcs_index", "bler", "rate_bps",
                  "best_beam", "best_beam_gain_db", "beam_gain_db"):
        assert layer in dry and "long_name" in dry[layer].attrs, layer
    gain = dry["path_gain_db"].values
    has = dry["has_path"].values
    assert np.isfinite(gain[has]).all() and (gain[has] < 0).all()  # passive channel
    indoor = dry["cell_inside_building"].values
    assert indoor.any() and not has[:, indoor].any()  # indoor cells are masked, never traced
    assert has.any(axis=0)[~indoor].mean() > 0.8
    # rain changes the reflections, so the wet map differs where paths bounce
    assert not np.allclose(np.nan_to_num(dry["path_gain_db"].values), np.nan_to_num(wet["path_gain_db"].values))
    events = instance.fetch_materializations(dg.AssetKey("ckm_map"), limit=1).records
    meta = events[0].asset_materialization.metadata
    assert meta["sunny_tiles_complete"].value == "2/2"
    assert "data:image/png;base64," in meta["sunny_map"].value  # one picture of the key layers per map
    assert not [k for k in meta if k.startswith("sunny_") and k.endswith("_db")]
    assert main(["ckm", "tiny", "--data", str(data), "--weather", "night", "--layer", "sinr_db"]) == 0
    assert "sinr_db" in capsys.readouterr().out


def test_rerun_is_idempotent_and_reproducible(run):
    data, _, instance, _, _ = run
    from conftest import TESTS

    before = stores.open_store(data / "cirs" / "tiny" / "sunny.zarr").load()
    # forced: an unforced rerun would find everything up to date and recompute nothing
    materialize_scene(TESTS / "scenes" / "tiny", data, ["sunny"], ["r0c0"], instance=instance, progress=lambda s: None,
                      force=True)
    after = stores.open_store(data / "cirs" / "tiny" / "sunny.zarr").load()
    assert after.attrs["data_version"] == before.attrs["data_version"]
    xr.testing.assert_identical(before.drop_attrs(), after.drop_attrs())


def test_no_runs_outputs_outlive_its_step(tmp_path, monkeypatch):
    """`simart run` materialises step after step in one process; each run's result holds its
    outputs (a weather's rendered frames: gigabytes for a long session). Before the next step
    starts, the previous run's result must be gone, cycles included, or the peak memory grows
    by a weather's frames per weather."""
    import gc
    import weakref

    results = []
    real = dg.materialize

    def recording(*args, **kwargs):
        res = real(*args, **kwargs)
        results.append(weakref.ref(res))
        return res

    monkeypatch.setattr(dg, "materialize", recording)
    alive_at_next_step = []

    def progress(line):
        if ": computing" in line and results:
            alive_at_next_step.append(results[-1]() is not None)

    gc.disable()  # no collection by chance between steps: the run must free its results itself
    try:
        materialize_scene(Path(__file__).parent / "scenes" / "tiny", tmp_path / "data", ["sunny"], ["r0c0"],
                          instance=dg.DagsterInstance.ephemeral(), progress=progress)
    finally:
        gc.enable()
    assert len(results) >= 3 and alive_at_next_step and not any(alive_at_next_step)
