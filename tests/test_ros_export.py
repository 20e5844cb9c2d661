"""The session as a ROS bag, read back by readers the project did not write: MCAP with `mcap` and
`mcap-ros2-support` (custom types decoded from the schemas in the file), every format with rosbags'
AnyReader; counts against the Zarr stores, stamps, frame ids, bit-for-bit arrays, and round trips."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import TESTS

from simart_pipeline import stores
from simart_pipeline.cli import main
from simart_pipeline.ckm.maps import map_path
from simart_pipeline.export import bag

FORMATS = {"mcap": "session_mcap", "rosbag2-sqlite3": "session_sqlite3", "rosbag1": "session.bag"}


@pytest.fixture(scope="module")
def exported(tiny_run, tmp_path_factory):
    data, _, _, _, cfg = tiny_run
    out = tmp_path_factory.mktemp("bags")
    for fmt, name in FORMATS.items():
        assert main(["export", str(TESTS / "scenes" / "tiny"), "--weather", "sunny", "--format", fmt,
                     "--out", str(out / name), "--data", str(data)]) == 0
    return data, cfg, out


def _any_reader(path: Path):
    from rosbags.highlevel import AnyReader

    return AnyReader([path])  # the types come from the bag itself, not from simart_pipeline


def _messages(path: Path) -> dict[str, list]:
    """{topic: [(bag time ns, message)]} read with rosbags' AnyReader."""
    out: dict[str, list] = {}
    with _any_reader(path) as rd:
        for conn, t, raw in rd.messages():
            out.setdefault(conn.topic, []).append((t, rd.deserialize(raw, conn.msgtype)))
    return out


def _expected_counts(data: Path, cfg) -> dict[str, int]:
    session = stores.open_store(data / "session" / "tiny" / "sunny.zarr", tree=True)
    cirs, kpis = session["cirs"], session["kpis"]
    n_pose = session["trajectory"].sizes["time"]
    out = {"/clock": n_pose, "/tf": n_pose, "/tf_static": 1, "/simart/world_origin": 1,
           **{f"/{p.name}/odom": n_pose for p in cfg.platforms}}
    for node in session["sensors"].subtree:
        if not node.has_data:
            continue
        path, n = "/" + node.path.split("/sensors/", 1)[1], node.sizes["time"]
        if "rgb" in node.data_vars:
            out.update({f"{path}/{s}": n for s in ("image_raw", "depth", "semantic", "instance", "camera_info",
                                                   "actors")})
            out[f"{path}/instance_ids"] = 1
        elif "points_m" in node.data_vars:
            out[f"{path}/points"] = n
        else:
            out[path] = n
    for j in range(cirs.sizes["link"]):
        tx, rx = str(cirs["tx"].values[j]), str(cirs["rx"].values[j])
        out[f"/simart/cir/{tx}/{rx}"] = out[f"/simart/beams/{tx}/{rx}"] = cirs.sizes["time"]
    out.update({f"/simart/kpis/{p}": kpis.sizes["time"] for p in kpis["platform"].values})
    ckm = stores.open_store(map_path(data, "tiny", "sunny"))
    for layer in bag.ckm_layer_names(ckm):
        for bs in (ckm["bs"].values if "bs" in ckm[layer].dims else [None]):
            out[f"/simart/ckm/sunny/{layer}" + (f"/{bs}" if bs is not None else "")] = ckm.sizes["height"]
    radar = stores.open_store(data / "radar_frames" / "tiny" / "sunny.zarr", tree=True)
    for node in radar.children.values():
        out[f"/simart/radar/{node.name}/echoes"] = out[f"/simart/radar/{node.name}/range_doppler"] = node.sizes["time"]
    return out


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_every_format_reads_back_with_the_store_counts_stamps_and_frames(exported, fmt):
    data, cfg, out = exported
    msgs = _messages(out / FORMATS[fmt])
    assert {t: len(v) for t, v in msgs.items()} == _expected_counts(data, cfg)
    static = {(tf.header.frame_id, tf.child_frame_id) for _, m in msgs["/tf_static"] for tf in m.transforms}
    moving = {(tf.header.frame_id, tf.child_frame_id) for _, m in msgs["/tf"] for tf in m.transforms}
    known = {f for pair in static | moving for f in pair}
    assert {"world", "car0/base_link", "car0/cam_optical", "car0/lidar", "bs0/base_link", "parked0/body"} <= known
    for topic, items in msgs.items():
        times = np.array([t for t, _ in items])
        assert np.all(np.diff(times) >= 0), topic
        for t, m in items:
            h = getattr(m, "header", None)
            if h is None:
                continue
            assert h.stamp.sec * 10**9 + h.stamp.nanosec == t, topic  # header stamp = bag time = shared clock
            assert h.frame_id in known, (topic, h.frame_id)


def test_mcap_decodes_with_the_independent_mcap_reader_and_arrays_are_bit_for_bit(exported):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    data, cfg, out = exported
    session = stores.open_store(data / "session" / "tiny" / "sunny.zarr", tree=True)
    cirs = session["cirs"].to_dataset()
    mcap_file = next((out / FORMATS["mcap"]).glob("*.mcap"))
    decoded: dict[str, list] = {}
    with mcap_file.open("rb") as f:
        for _, channel, message, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append((message.log_time, msg))
    assert {t: len(v) for t, v in decoded.items()} == _expected_counts(data, cfg)

    # a CIR: every per-path array equal to the store's, bit for bit
    k = 2
    _, m = decoded["/simart/cir/bs0/car0"][k]
    link = int(np.flatnonzero((cirs["tx"].values == "bs0") & (cirs["rx"].values == "car0"))[0])
    ref = cirs.isel(time=k, link=link)
    a = ref["a"].values
    np.testing.assert_array_equal(np.asarray(m.a_real, np.float32).reshape(a.shape), a.real)
    np.testing.assert_array_equal(np.asarray(m.a_imag, np.float32).reshape(a.shape), a.imag)
    np.testing.assert_array_equal(np.asarray(m.tau_s), ref["tau_s"].values)
    for name in ("theta_t_rad", "phi_t_rad", "theta_r_rad", "phi_r_rad", "doppler_hz"):
        np.testing.assert_array_equal(np.asarray(getattr(m, name), np.float32), ref[name].values)
    np.testing.assert_array_equal(np.frombuffer(bytes(m.interaction), np.uint8).reshape(ref["interaction"].shape),
                                  ref["interaction"].values)
    np.testing.assert_array_equal(np.asarray(m.valid, bool), ref["valid"].values)
    assert list(m.actors) == [str(a) for a in cirs["actor"].values] == ["car0", "parked0"]

    # a depth image: the float32 z-depth, NaN where nothing is seen
    cam = session["sensors/car0/cam"].to_dataset()
    _, img = decoded["/car0/cam/depth"][1]
    assert img.encoding == "32FC1" and (img.height, img.width) == cam["depth_m"].shape[1:]
    depth = np.frombuffer(bytes(img.data), "<f4").reshape(img.height, img.width)
    np.testing.assert_array_equal(depth, cam["depth_m"].values[1])

    # a LiDAR cloud: x, y, z float32 of every beam (NaN: no return), organised ring x azimuth
    lid = session["sensors/car0/lidar"].to_dataset()
    _, cloud = decoded["/car0/lidar/points"][3]
    offsets = {f.name: f.offset for f in cloud.fields}
    raw = np.frombuffer(bytes(cloud.data), np.uint8).reshape(cloud.height, cloud.width, cloud.point_step)
    for axis, name in enumerate("xyz"):
        got = raw[..., offsets[name]:offsets[name] + 4].copy().view("<f4")[..., 0]
        np.testing.assert_array_equal(got, lid["points_m"].values[3][..., axis])

    # a CKM layer: the map's float32 values as float64, the grid's origin and resolution
    ckm = stores.open_store(map_path(data, "tiny", "sunny"))
    _, layer = decoded["/simart/ckm/sunny/path_gain_db/bs0"][0]
    grid = np.asarray(layer.data).reshape(layer.rows, layer.cols)
    np.testing.assert_array_equal(grid.astype(np.float32), ckm["path_gain_db"].sel(bs="bs0").isel(height=0).values)
    assert (layer.origin_x_m, layer.origin_y_m) == (ckm["x"].values[0], ckm["y"].values[0])
    assert layer.resolution_m == pytest.approx(cfg.ckm.cell_size_m)
    masked = ckm["cell_masked"].isel(height=0).values
    assert masked.any()
    valid = np.asarray(layer.valid, bool).reshape(layer.rows, layer.cols)
    np.testing.assert_array_equal(valid, np.isfinite(grid) & ~masked)
    _, mask_layer = decoded["/simart/ckm/sunny/cell_masked"][0]  # a mask describes every cell
    assert np.asarray(mask_layer.valid, bool).all()
    np.testing.assert_array_equal(np.asarray(mask_layer.data).reshape(layer.rows, layer.cols), masked)

    # the parked car in the car camera's ground truth, by name and class
    dets = [d for _, m in decoded["/car0/cam/actors"] for d in m.detections]
    assert dets and {d.id for d in dets} == {"parked0"}
    assert all(d.results[0].hypothesis.class_id == "vehicle" for d in dets)


def _scene_with_the_bag(out: Path, tmp_path: Path, edit):
    """A copy of tests/scenes/tiny holding the exported MCAP bag as ``recorded/``, its config edited."""
    from simart_pipeline.config import load_scene_config

    scene = tmp_path / "tiny"
    shutil.copytree(TESTS / "scenes" / "tiny", scene)
    shutil.copytree(out / FORMATS["mcap"], scene / "recorded")
    raw = yaml.safe_load((scene / "scene.yaml").read_text())
    edit(raw)
    (scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    return scene, load_scene_config(scene)


def test_the_session_bag_asset_writes_an_mcap_bag_per_weather(exported):
    data, cfg, _ = exported
    for w in cfg.weathers:
        d = data / "session_bag" / "tiny" / w
        meta = yaml.safe_load((d / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert meta["storage_identifier"] == "mcap" and list(d.glob("*.mcap"))


def test_replaying_the_exported_odometry_reproduces_the_cirs_bit_for_bit(exported, tmp_path):
    from simart_pipeline.mobility.trajectory import build_trajectory
    from simart_pipeline.radio import cirs as radio_cirs
    from simart_pipeline.radio.tracer import RadioScene
    from simart_pipeline.scene import geometry, meshes
    from simart_pipeline.scene.actors import scene_actors

    data, cfg, out = exported
    scene, replayed_cfg = _scene_with_the_bag(out, tmp_path, lambda raw: raw["platforms"][0].update(
        trajectory={"kind": "replay", "path": "recorded", "topic": "/car0/odom"}))
    geom = geometry.from_dataset(stores.open_store(data / "osm_extract" / "tiny.zarr").load())
    traj = build_trajectory(replayed_cfg, scene, geom=geom)
    stored = stores.open_store(data / "trajectory" / "tiny.zarr").load()
    np.testing.assert_array_equal(traj["position_m"].values, stored["position_m"].values)
    np.testing.assert_array_equal(traj["orientation_xyzw"].values, stored["orientation_xyzw"].values)
    radio = RadioScene.from_config(meshes.radio_scene_file(data / "paired_meshes" / "tiny"), replayed_cfg, "sunny")
    radio.add_actors(scene_actors(replayed_cfg, scene))
    again = radio_cirs.trace_trajectory(radio, replayed_cfg, traj, geom)
    ref = stores.open_store(data / "cirs" / "tiny" / "sunny.zarr").load()
    for name in ("a", "tau_s", "doppler_hz", "valid", "interaction", "interaction_actor"):
        np.testing.assert_array_equal(again[name].values, ref[name].values, err_msg=name)


def test_export_refuses_a_path_that_is_not_a_bag(exported, tmp_path, capsys):
    data, _, _ = exported
    precious = tmp_path / "notes"
    precious.mkdir()
    (precious / "keep.txt").write_text("mine")
    args = ["export", str(TESTS / "scenes" / "tiny"), "--data", str(data), "--out"]
    assert main(args + [str(precious)]) == 1
    assert "exists and is not a bag" in capsys.readouterr().err
    assert (precious / "keep.txt").read_text() == "mine"
    assert main(args + [str(tmp_path / "x.bag")]) == 1  # rosbag2 is a directory
    assert main(args + [str(tmp_path / "x"), "--format", "rosbag1"]) == 1  # ROS 1 is a .bag file


def test_importing_the_exported_sensor_streams_reproduces_the_stored_ones(exported, tmp_path):
    from simart_pipeline.scene import meshes
    from simart_pipeline.sensing.sensor_frames import build_sensor_frames

    data, cfg, out = exported
    scene, imported_cfg = _scene_with_the_bag(out, tmp_path, lambda raw: raw.update(sensor_imports=[{
        "path": "recorded", "streams": [
        {"device": "car0", "sensor": "cam", "kind": "camera", "topic": "/car0/cam/image_raw",
         "camera_info_topic": "/car0/cam/camera_info"},
        {"device": "car0", "sensor": "lidar", "kind": "lidar", "topic": "/car0/lidar/points"},
        {"device": "car0", "sensor": "imu", "kind": "imu", "topic": "/car0/imu"},
        {"device": "car0", "sensor": "gps", "kind": "gps", "topic": "/car0/gps"}]}]))
    traj = stores.open_store(data / "trajectory" / "tiny.zarr").load()
    tree = build_sensor_frames(meshes.load(data / "paired_meshes" / "tiny"), traj, imported_cfg, "sunny", scene)
    stored = stores.open_store(data / "sensor_frames" / "tiny" / "sunny.zarr", tree=True)
    for path, names in {"car0/cam": ("rgb", "camera_matrix", "position_m", "orientation_xyzw"),
                        "car0/lidar": ("range_m", "points_m", "valid"),
                        "car0/imu": ("linear_acceleration_mps2", "angular_velocity_radps",
                                     "linear_acceleration_covariance"),
                        "car0/gps": ("latitude_deg", "longitude_deg", "altitude_m", "position_covariance_m2")}.items():
        got, ref = tree[path].to_dataset(), stored[path].to_dataset()
        np.testing.assert_array_equal(got["time"].values, ref["time"].values, err_msg=path)
        for name in names:
            np.testing.assert_array_equal(got[name].values, ref[name].values, err_msg=f"{path}:{name}")


def test_the_zarr_session_opens_with_xarray_without_a_warning(exported):
    import warnings

    import xarray as xr

    data, _, _ = exported
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # consolidated metadata: no fallback warning
        tree = xr.open_datatree(data / "session" / "tiny" / "sunny.zarr", engine="zarr")
    assert {"trajectory", "sensors", "cirs", "kpis"} <= set(tree.children)
