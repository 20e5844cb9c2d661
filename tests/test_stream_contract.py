"""One stream contract per sensor kind (simart_pipeline/sensing/contract.py, docs/sensor-plugin.md):
a stream rendered by the embedded sensors and one imported from a bag have the same variables, the
same dims per variable and the same attrs keys, with documented absent values where a source
cannot know a value."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from simart_pipeline import stores
from simart_pipeline.mobility.trajectory import build_trajectory
from simart_pipeline.sensing.bag_import import import_streams
from simart_pipeline.sensing.sensor_frames import render_sensor_frames

from conftest import SHARED_DATA
from test_sensing import CAM, GROUND, WALL, make_config, scene_of

BAGS = SHARED_DATA / "bags"
HUSKY = "robot_localization_test1_husky_real.bag"
LUMINAR = "embag_test_luminar_pointcloud.bag"
RASPICAM = "fiducials_aruco_images_raspicam.bag"


def signature(ds: xr.Dataset) -> dict:
    """What the contract fixes: variables (data and coords), dims per variable, attrs keys.
    ``field_<name>`` (extra PointCloud2 fields kept as recorded) is outside the contract."""
    return {"variables": {k: v.dims for k, v in ds.variables.items() if not k.startswith("field_")},
            "variable_attrs": {k: sorted(v.attrs) for k, v in ds.variables.items() if not k.startswith("field_")},
            "group_attrs": sorted(ds.attrs)}


@pytest.fixture(scope="module")
def rendered() -> dict[str, xr.Dataset]:
    sensors = [dict(CAM, rate_hz=2.0),
               {"kind": "lidar", "name": "lidar", "rate_hz": 5.0, "channels": 4, "horizontal_samples": 32},
               {"kind": "imu", "name": "imu", "rate_hz": 20.0}, {"kind": "gps", "name": "gps", "rate_hz": 2.0}]
    cfg = make_config([], sensors, duration=1.0)
    tree = render_sensor_frames(scene_of(GROUND, WALL), build_trajectory(cfg), cfg, "sunny")
    return {kind: tree[f"p0/{name}"].to_dataset() for kind, name in
            (("camera", "cam"), ("lidar", "lidar"), ("imu", "imu"), ("gps", "gps"))}


def import_config(imports, duration=30.0):
    from test_bags import scene

    return scene({"kind": "replay", "path": HUSKY, "topic": "/husky_velocity_controller/odom"},
                 duration=duration, imports=imports)


@pytest.fixture(scope="module")
def imported() -> dict[str, xr.Dataset]:
    cfg = import_config([
        {"path": HUSKY, "streams": [{"device": "p0", "sensor": "imu", "kind": "imu", "topic": "/imu/data"},
                                    {"device": "p0", "sensor": "gps", "kind": "gps", "topic": "/fix"}]},
        {"path": LUMINAR, "streams": [{"device": "p0", "sensor": "lidar", "kind": "lidar",
                                       "topic": "/luminar_pointcloud"}]},
        {"path": RASPICAM, "streams": [{"device": "p0", "sensor": "cam", "kind": "camera",
                                        "topic": "/raspicam_node/image/compressed",
                                        "camera_info_topic": "/raspicam_node/camera_info"}]}])
    traj = build_trajectory(cfg, BAGS)
    out = {}
    for imp in cfg.sensor_imports:
        for path, ds in import_streams(imp, cfg, traj, BAGS, "sunny").items():
            out[ds.attrs["sensor_kind"]] = ds
    return out


@pytest.mark.parametrize("kind", ["camera", "lidar", "imu", "gps"])
def test_rendered_and_imported_streams_have_one_contract(rendered, imported, kind):
    r, i = signature(rendered[kind]), signature(imported[kind])
    assert r["variables"] == i["variables"]
    assert r["variable_attrs"] == i["variable_attrs"]
    assert r["group_attrs"] == i["group_attrs"]
    for ds in (rendered[kind], imported[kind]):
        stores.check_finite(ds)  # every NaN says what it means
        for name, var in ds.data_vars.items():
            assert "units" in var.attrs and "long_name" in var.attrs, (kind, name)
    assert rendered[kind].attrs["source"].startswith("rendered")
    assert imported[kind].attrs["source"].startswith("imported")
    assert rendered[kind].attrs["weather_model"].startswith("applied")
    assert imported[kind].attrs["weather_model"].startswith("none")


def test_absent_values_are_the_documented_ones(rendered, imported):
    cam_r, cam_i = rendered["camera"], imported["camera"]
    assert np.isnan(cam_i["depth_m"].values).all() and not cam_i["depth_valid"].values.any()
    assert (cam_i["semantic_class"].values == 0).all() and (cam_i["instance_id"].values == 0).all()
    assert "not recorded" in cam_i["depth_m"].attrs["nan_means"]
    np.testing.assert_array_equal(cam_r["distortion_coefficients"].values, np.zeros(5))
    assert cam_r["distortion_coefficients"].attrs["distortion_model"] == "plumb_bob"
    assert cam_i["distortion_coefficients"].attrs["distortion_model"] == "plumb_bob"  # the raspicam's CameraInfo
    for ds in rendered.values():  # a rendered stream's stamps are its sample instants
        np.testing.assert_array_equal(ds["header_stamp_ns"].values, ds["time"].values)
        np.testing.assert_array_equal(ds["record_time_ns"].values, ds["time"].values)
        assert ds.attrs["mean_rate_hz"] > 0 and ds.attrs["rate_hz"] > 0
        assert ds.attrs["source_topic"] == "none" and ds.attrs["num_messages_in_bag"] == 0
    for ds in imported.values():
        assert np.isnan(ds.attrs["rate_hz"]) and ds.attrs["mean_rate_hz"] >= 0  # 0: one message (raspicam)
    assert imported["imu"].attrs["mean_rate_hz"] > 0
    # LiDAR: the unorganised Luminar cloud is one ring, the points along azimuth
    lid_r, lid_i = rendered["lidar"], imported["lidar"]
    assert lid_i.sizes["ring"] == 1 and lid_i.sizes["azimuth"] == lid_i["point_count"].values.max()
    assert np.isnan(lid_i["elevation_rad"].values).all() and np.isnan(lid_i["azimuth_rad"].values).all()
    assert (lid_i["semantic_class"].values == 0).all() and "field_laser_id" in lid_i
    assert np.isnan(lid_r["intensity"].values).all() and "no intensity" in lid_r["intensity"].attrs["nan_means"]
    assert (lid_r["point_count"].values == 4 * 32).all()
    # IMU: the simulator's noise as covariance, no orientation estimate
    imu_r = rendered["imu"]
    np.testing.assert_array_equal(imu_r["linear_acceleration_covariance"].values[0],
                                  np.diag([imu_r.attrs["accel_noise_std_mps2"] ** 2] * 3))
    np.testing.assert_array_equal(imu_r["angular_velocity_covariance"].values[-1],
                                  np.diag([imu_r.attrs["gyro_noise_std_radps"] ** 2] * 3))
    assert np.isnan(imu_r["reported_orientation_xyzw"].values).all()
    assert (imu_r["reported_orientation_covariance"].values[:, 0, 0] == -1).all()
    assert np.isnan(imported["imu"].attrs["accel_noise_std_mps2"])
    # GPS: the noisy fix in ENU, a valid diagonal-known fix
    gps_r = rendered["gps"]
    from simart_pipeline import frames

    lla = frames.enu_to_geodetic(gps_r["fix_enu_m"].values, *make_config().origin.model_dump().values())
    np.testing.assert_allclose(lla[:, 0], gps_r["latitude_deg"].values, rtol=0, atol=1e-12)
    assert gps_r["fix_valid"].all() and (gps_r["fix_status"] == 0).all() and (gps_r["fix_service"] == 1).all()
    assert (gps_r["position_covariance_type"] == 2).all()
    h, v = gps_r.attrs["horizontal_noise_std_m"], gps_r.attrs["vertical_noise_std_m"]
    np.testing.assert_array_equal(gps_r["position_covariance_m2"].values[0], np.diag([h * h, h * h, v * v]))


def write_organised_cloud_bag(path: Path) -> np.ndarray:
    """A ROS1 bag with two PointCloud2 of 2 rows x 3 columns (x y z intensity float32, ring uint16),
    the second 1 x 2: returns the xyz written [2, 2, 3, 3] (NaN where the second has no point)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2")])
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=dtype.fields[n][1], datatype=d, count=1)
              for n, d in (("x", 7), ("y", 7), ("z", 7), ("intensity", 7), ("ring", 4))]
    want = np.full((2, 2, 3, 3), np.nan, np.float32)
    with Writer(path) as w:
        c = w.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        for k, (h, wd) in enumerate(((2, 3), (1, 2))):
            pts = np.zeros((h, wd), dtype)
            for r in range(h):
                for col in range(wd):
                    pts[r, col] = (r + 1, col + 10 * k, 0.5, 100 * r + col, r)
            want[k, :h, :wd] = np.stack([pts["x"], pts["y"], pts["z"]], -1)
            hdr = T["std_msgs/msg/Header"](seq=k, stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=k * 10**8),
                                           frame_id="lidar")
            msg = T["sensor_msgs/msg/PointCloud2"](header=hdr, height=h, width=wd, fields=fields, is_bigendian=False,
                                                   point_step=dtype.itemsize, row_step=dtype.itemsize * wd,
                                                   data=np.frombuffer(pts.tobytes(), np.uint8), is_dense=True)
            w.write(c, 10**9 + k * 10**8, ts.serialize_ros1(msg, "sensor_msgs/msg/PointCloud2"))
    return want


def test_an_organised_cloud_maps_rows_to_rings_and_columns_to_azimuths(tmp_path, rendered):
    want = write_organised_cloud_bag(tmp_path / "cloud.bag")
    from test_bags import scene

    cfg = scene({"waypoints_m": [[0, 0, 5], [5, 0, 5]], "speed_mps": 1.0}, duration=1.0, imports=[
        {"path": "cloud.bag", "streams": [{"device": "p0", "sensor": "lidar", "kind": "lidar", "topic": "/points"}]}])
    ds = import_streams(cfg.sensor_imports[0], cfg, build_trajectory(cfg), tmp_path)["/p0/lidar"]
    assert ds.sizes == {**ds.sizes, "time": 2, "ring": 2, "azimuth": 3}
    np.testing.assert_array_equal(ds["points_m"].values, want)
    np.testing.assert_array_equal(ds["valid"].values, ~np.isnan(want[..., 0]))
    np.testing.assert_array_equal(ds["point_count"].values, [6, 2])
    np.testing.assert_array_equal(ds["intensity"].values[0], [[0, 1, 2], [100, 101, 102]])
    np.testing.assert_array_equal(ds["field_ring"].values[0], [[0, 0, 0], [1, 1, 1]])
    assert signature(ds)["variables"] == signature(rendered["lidar"])["variables"]
    assert signature(ds)["group_attrs"] == signature(rendered["lidar"])["group_attrs"]
    stores.write_store(xr.DataTree.from_dict({"/p0/lidar": ds}), tmp_path / "out.zarr")  # the writer's checks
