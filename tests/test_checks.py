"""Asset checks: the quality functions catch broken data and pass the real tiny scene, Dagster runs
them with every materialisation, and a failed blocking check stops the downstream asset."""

import shutil

import numpy as np
import pytest
import xarray as xr

import dagster as dg

from simart_pipeline import clock, quality, stores
from simart_pipeline.assets import ALL_ASSETS, ALL_CHECKS
from simart_pipeline.ckm.maps import map_groups, map_path
from simart_pipeline.ckm.mosaic import open_map


WEATHERS = ("sunny", "night", "rainy")


def _store(data, asset, sub=None):
    return stores.open_store(stores.store_path(data, asset, "tiny", sub),
                             tree=asset in ("sensor_frames", "session")).load()


# -- through Dagster ---------------------------------------------------------------------------------

def _evaluations(instance):
    out = []
    for check in ALL_CHECKS:
        for key in check.check_keys:
            for rec in instance.event_log_storage.get_asset_check_execution_history(key, limit=100):
                out.append((key, rec.event.dagster_event.event_specific_data))
    return out


def test_every_check_of_the_tiny_scene_ran_and_passed(tiny_run):
    data, _, instance, _, _ = tiny_run
    evals = _evaluations(instance)
    failed = [(k.asset_key.to_user_string(), k.name, e.partition, e.description) for k, e in evals if not e.passed]
    assert not failed
    ran = {(k.asset_key.path[-1], k.name, str(e.partition)) for k, e in evals}
    for asset in ("trajectory", "osm_extract"):
        assert {(asset, "finite_values", "tiny"), (asset, "known_frame_ids", "tiny")} <= ran
    assert ("trajectory", "on_shared_clock", "tiny") in ran
    for asset, keys in (("sensor_frames", WEATHERS), ("kpis", WEATHERS), ("session", WEATHERS),
                        ("cirs", ("sunny", "rainy"))):  # cirs: one partition per weather group
        for w in keys:
            for name in ("finite_values", "known_frame_ids", "on_shared_clock"):
                assert (asset, name, f"tiny|{w}") in ran, (asset, name, w)
    for g in ("sunny", "rainy"):
        assert {("cirs", "passive_channel", f"tiny|{g}"), ("cirs", "cirs_sampling_converged", f"tiny|{g}")} <= ran
    for t in ("r0c0", "r0c1"):
        assert {("ckm_layers", "ckm_tile_complete", f"tiny|{t}"), ("ckm_layers", "ckm_passive", f"tiny|{t}")} <= ran
    assert ("ckm_map", "ckm_reference_converged", "tiny") in ran
    # the metadata carries the counts
    passive = [e for k, e in evals if k.name == "passive_channel"][0]
    assert passive.metadata["paths_checked"].value > 0 and passive.metadata["worst_margin_db"].value <= 0.1
    tile = [e for k, e in evals if k.name == "ckm_tile_complete"][0]
    assert 0 < tile.metadata["sunny_masked_fraction"].value < 1
    assert "sunny_empty_fraction" in tile.metadata
    blocking = {k.name: s.blocking for c in ALL_CHECKS for k, s in zip(c.check_keys, c.check_specs)}
    assert blocking == {"finite_values": True, "known_frame_ids": True, "on_shared_clock": True,
                        "passive_channel": True, "ckm_passive": True, "ckm_tile_complete": False,
                        "cirs_sampling_converged": False, "ckm_reference_converged": False,
                        "beam_study_sound": False}
    converged = [e for k, e in evals if k.name == "cirs_sampling_converged"][0]
    assert converged.metadata["links_compared"].value > 0
    assert converged.metadata["check_samples_per_src"].value == 10 * converged.metadata["samples_per_src"].value


def test_definitions_carry_the_checks():
    from simart_pipeline.definitions import defs

    keys = defs.resolve_asset_graph().asset_check_keys
    assert dg.AssetCheckKey(dg.AssetKey("cirs"), "passive_channel") in keys
    assert dg.AssetCheckKey(dg.AssetKey("radar_frames"), "on_shared_clock") in keys
    # three store checks per store asset (no clock check where there is no time), six others
    from simart_pipeline.assets.checks import STORE_ASSETS, TIMELESS

    assert len(keys) == sum(len(list(c.check_keys)) for c in ALL_CHECKS) == 3 * len(STORE_ASSETS) - len(TIMELESS) + 6


def test_a_failed_blocking_check_stops_the_downstream_asset(tiny_run, tmp_path, monkeypatch):
    from conftest import TESTS
    from simart_pipeline import registry
    from simart_pipeline.definitions import build_definitions

    data = tmp_path / "data"
    shutil.copytree(tiny_run[0], data)
    broken = quality.CheckResult(False, "a stream off the clock (broken on purpose)", {"streams_checked": 1})
    on_clock = quality.on_shared_clock
    monkeypatch.setattr(quality, "on_shared_clock", lambda ds, cfg, asset, *a, **kw:
                        broken if asset == "sensor_frames" else on_clock(ds, cfg, asset, *a, **kw))
    instance = dg.DagsterInstance.ephemeral()
    registry.register(TESTS / "scenes" / "tiny", data)
    instance.add_dynamic_partitions("scene", ["tiny"])
    result = dg.materialize([*ALL_ASSETS, *ALL_CHECKS], selection=["sensor_frames", "kpis", "session"],
                            partition_key=dg.MultiPartitionKey({"scene": "tiny", "weather": "sunny"}),
                            instance=instance, resources=build_definitions(data_root=str(data)).resources,
                            raise_on_error=False)
    assert not result.success
    done = {e.asset_key.path[-1] for e in result.get_asset_materialization_events()}
    assert done == {"sensor_frames", "kpis"}  # session, downstream of the failed check, never ran
    evals = {(e.asset_check_key.asset_key.path[-1], e.asset_check_key.name): e.passed
             for e in result.get_asset_check_evaluations()}
    assert evals[("sensor_frames", "on_shared_clock")] is False and evals[("sensor_frames", "finite_values")] is True
    assert evals[("kpis", "on_shared_clock")] is True
    assert not instance.get_materialized_partitions(dg.AssetKey("session"))


# -- the functions on real and broken data ----------------------------------------------------------

@pytest.fixture(scope="module")
def real(tiny_run):
    data, _, _, _, cfg = tiny_run
    return data, cfg


def test_finite_values(real):
    data, _ = real
    ds = _store(data, "kpis", "sunny")
    assert quality.finite_values(ds).passed
    bad = ds.copy()
    bad["snr_db"] = bad["snr_db"].copy(data=np.where(np.arange(bad["snr_db"].size).reshape(bad["snr_db"].shape) == 0,
                                                     np.inf, bad["snr_db"].values))
    r = quality.finite_values(bad)
    assert not r.passed and "snr_db holds 1 inf" in r.description
    cirs = _store(data, "cirs", "sunny")
    nan = cirs.copy()
    nan["tau_s"] = nan["tau_s"].where(nan["valid"])  # NaN for invalid paths, but no nan_means
    r = quality.finite_values(nan)
    assert not r.passed and "tau_s" in r.description and "nan_means" in r.description
    nan["tau_s"].attrs["nan_means"] = "no path"
    assert quality.finite_values(nan).passed
    tree = _store(data, "session", "sunny")
    assert quality.finite_values(tree).passed
    imu = tree["sensors/car0/imu"].to_dataset()
    name = next(k for k, v in imu.data_vars.items() if v.dtype.kind == "f" and "nan_means" not in v.attrs)
    tree["sensors/car0/imu"] = xr.DataTree(imu.assign({name: imu[name] * np.nan}))
    r = quality.finite_values(tree)
    assert not r.passed and f"/sensors/car0/imu:{name}" in r.description


def test_clock(real):
    data, cfg = real
    traj = _store(data, "trajectory")
    assert quality.on_shared_clock(traj, cfg, "trajectory").passed
    t = traj["time"].values.copy()
    t[1:-1] += 1  # one nanosecond off, still increasing and within the session
    r = quality.on_shared_clock(traj.assign_coords(time=t), cfg, "trajectory")
    assert not r.passed and r.description.startswith("1 problem(s): /:time is off the 50 Hz clock by up to 1 ns")
    late = traj.assign_coords(time=traj["time"].values + 10**6)
    assert "outside [0, 1000000000] ns" in quality.on_shared_clock(late, cfg, "trajectory").description
    as_float = traj.assign_coords(time=traj["time"].values.astype(np.float64))
    assert "not int64" in quality.on_shared_clock(as_float, cfg, "trajectory").description
    tree = _store(data, "sensor_frames", "sunny")
    assert quality.on_shared_clock(tree, cfg, "sensor_frames").passed
    # a stream imported from a bag keeps its own instants: only the general rule applies
    gps = tree["car0/gps"].to_dataset()
    t = gps["time"].values.copy()
    t[1:-1] += 7
    jitter = gps.assign_coords(time=t)
    tree["car0/gps"] = xr.DataTree(jitter)
    assert not quality.on_shared_clock(tree, cfg, "sensor_frames").passed
    jitter.attrs.update(source="imported from a bag (docs/sensor-plugin.md)", source_file="rec.bag")
    tree["car0/gps"] = xr.DataTree(jitter)
    assert quality.on_shared_clock(tree, cfg, "sensor_frames").passed
    backwards = jitter.assign_coords(time=jitter["time"].values[::-1].copy())
    tree["car0/gps"] = xr.DataTree(backwards)
    assert "not strictly increasing" in quality.on_shared_clock(tree, cfg, "sensor_frames").description
    session = _store(data, "session", "sunny")
    r = quality.on_shared_clock(session, cfg, "session")
    assert r.passed and r.metadata["streams_at_exact_instants"] == 7
    kpis = _store(data, "kpis", "sunny")
    want = clock.sample_times_ns(cfg.clock.duration_s, cfg.clock.radio_rate_hz)
    assert np.array_equal(kpis["time"].values, want)
    assert not quality.on_shared_clock(kpis.isel(time=slice(1, None)), cfg, "kpis").passed


def test_frame_ids(real):
    data, cfg = real
    assert quality.config_frames(cfg) >= {"world", "car0/base_link", "bs0/base_link", "car0/cam",
                                          "car0/cam_optical", "car0/lidar"}
    tree = _store(data, "sensor_frames", "sunny")
    assert quality.known_frame_ids(tree, cfg).passed
    lidar = tree["car0/lidar"].to_dataset()
    lidar.attrs["parent_frame_id"] = "car1/base_link"
    tree["car0/lidar"] = xr.DataTree(lidar)
    r = quality.known_frame_ids(tree, cfg)
    assert not r.passed and "'car1/base_link' is not a frame of the config" in r.description
    cirs = _store(data, "cirs", "sunny")
    assert quality.known_frame_ids(cirs, cfg).passed
    cirs["rx_position_m"].attrs["frame_id"] = "map"
    assert not quality.known_frame_ids(cirs, cfg).passed
    traj = _store(data, "trajectory")
    r = quality.known_frame_ids(traj, cfg)  # "<platform>/base_link": one per platform
    assert r.passed and r.metadata["per_element_templates"] == 1
    traj["angular_velocity_radps"].attrs["frame_id"] = "<robot>/base_link"
    assert "no such coordinate" in quality.known_frame_ids(traj, cfg).description


def test_passive_channel(real):
    data, _ = real
    cirs = _store(data, "cirs", "sunny")
    r = quality.passive_channel(cirs)
    assert r.passed and r.metadata["paths_checked"] == int(cirs["valid"].sum())
    assert r.metadata["element_gains_db"] == 8.0  # tr38901 stations, isotropic receiver
    # the strongest path, made stronger than free space allows
    p = (np.abs(cirs["a"].values) ** 2).max(axis=(2, 3))
    margin = r.metadata["worst_margin_db"]
    loud = cirs.copy()
    loud["a"] = loud["a"] * np.float32(10 ** ((0.5 - margin) / 20))
    r2 = quality.passive_channel(loud)
    assert not r2.passed and "gains more than free space by" in r2.description
    assert r2.metadata["worst_margin_db"] == pytest.approx(0.5, abs=1e-3)
    assert p.max() > 0
    # a path earlier than the line of sight
    early = cirs.copy()
    tau = early["tau_s"].values.copy()
    t, li, pi = np.argwhere(early["valid"].values)[0]
    d = np.linalg.norm(cirs["tx_position_m"].values[t, li] - cirs["rx_position_m"].values[t, li])
    tau[t, li, pi] = d / 299792458.0 - 1e-9
    early["tau_s"] = early["tau_s"].copy(data=tau)
    r3 = quality.passive_channel(early)
    assert not r3.passed and "before the line of sight by 1.0000 ns" in r3.description
    # with an isotropic station the real data's tr38901 gain would be above free space: the bound
    # needs the element gains
    iso = cirs.copy()
    iso.attrs["tx_array_pattern"] = "iso"
    assert quality.passive_channel(iso).metadata["worst_margin_db"] > margin


def test_ckm_tile_and_passivity(real):
    data, cfg = real
    maps = {n: open_map(map_path(data, "tiny", n)).load() for n in map_groups(cfg)}
    r = quality.ckm_tile(maps, cfg, "r0c0")
    assert r.passed and r.metadata["sunny_masked_fraction"] > 0 and r.metadata["sunny_cells"] == 24
    assert quality.ckm_tile(maps, cfg, "r3c3").passed  # not in the scene's tiling
    broken = {n: ds.copy(deep=True) for n, ds in maps.items()}
    broken["rainy"]["tile_complete"].values[0, 1] = False
    r = quality.ckm_tile(broken, cfg, "r0c1")
    assert not r.passed and "map rainy: tile r0c1 is not complete" in r.description
    assert quality.ckm_tile(broken, cfg, "r0c0").passed
    from simart_pipeline.ckm.grid import tile_slices

    sl = tile_slices(cfg.ckm, "r0c0")
    dry = maps["sunny"]
    assert quality.ckm_passive(dry, cfg, *sl).passed
    loud = dry.copy(deep=True)
    loud["path_gain_db"] = loud["path_gain_db"] + 20
    assert not quality.ckm_passive(loud, cfg, *sl).passed
    early = dry.copy(deep=True)
    early["toa_s"] = early["toa_s"] * 0.5
    r = quality.ckm_passive(early, cfg, *sl)
    assert not r.passed and "toa_s before the line of sight" in r.description
    # of the tile's traced cells, those where some station holds a path gain / a delay spread:
    # one cell's spread taken from every station drops the fraction by exactly one cell
    r = quality.ckm_tile(maps, cfg, "r0c0")
    held, gain = r.metadata["sunny_with_delay_spread_fraction"], r.metadata["sunny_with_path_gain_fraction"]
    assert 0 < held <= gain <= 1
    traced = round((1 - r.metadata["sunny_masked_fraction"]) * r.metadata["sunny_cells"])
    spread = dry["rms_delay_spread_s"].values  # bs, height, y, x
    h, y, x = np.argwhere(np.isfinite(spread[:, :, sl[0], sl[1]]).any(axis=0))[0]
    fewer = {n: ds.copy(deep=True) for n, ds in maps.items()}
    fewer["sunny"]["rms_delay_spread_s"].values[:, h, sl[0].start + y, sl[1].start + x] = np.nan
    r2 = quality.ckm_tile(fewer, cfg, "r0c0")
    assert r2.metadata["sunny_with_delay_spread_fraction"] == pytest.approx(held - 1 / traced, abs=1e-4)
    assert r2.metadata["sunny_with_path_gain_fraction"] == gain


def test_a_failed_warning_is_printed_under_its_step_and_the_run_goes_on(tmp_path, monkeypatch):
    # every link fails the sampling check with a negative tolerance: a warning, not a stop
    from conftest import TESTS
    from simart_pipeline.cli import materialize_scene
    from simart_pipeline.radio import convergence

    monkeypatch.setattr(convergence, "GAIN_TOLERANCE_DB", -1.0)
    lines = []
    out = materialize_scene(TESTS / "scenes" / "tiny", tmp_path / "data", ["sunny"], ["r0c0"],
                            instance=dg.DagsterInstance.ephemeral(), progress=lines.append)
    warned = [s for s in lines if s.lstrip().startswith("check ")]
    assert any(s.lstrip().startswith("check cirs_sampling_converged (warn): ") for s in warned), lines
    assert any(s.lstrip().startswith("check ckm_reference_converged (warn): map sunny: ") for s in warned), lines
    assert all("raise ray_tracing.samples_per_src" in s for s in warned)
    # the run went on past both: every store downstream of them was written
    assert all(p.exists() for paths in out.values() for p in paths)
    assert "session_bag" in out and "ckm" in out
