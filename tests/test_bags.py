"""Replay from ROS bags and the sensor plug-in contract, on real bags made by others and on bags
written here with known contents (docs/sensor-plugin.md)."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from simart_pipeline import frames, stores
from simart_pipeline.config import ConfigError, ReplayTrajectory, SceneConfig, load_scene_config
from simart_pipeline.mobility import bags, replay
from simart_pipeline.mobility.trajectory import build_trajectory
from simart_pipeline.sensing.bag_import import import_streams
from simart_pipeline.sensing.sensor_frames import build_sensor_frames

from conftest import SHARED_DATA

BAGS = SHARED_DATA / "bags"
ROTORS = "rotors_waypoint_example_gazebo.bag"
HUSKY = "robot_localization_test1_husky_real.bag"
LUMINAR = "embag_test_luminar_pointcloud.bag"
RASPICAM = "fiducials_aruco_images_raspicam.bag"
ORIGIN = {"latitude_deg": 42.3758, "longitude_deg": -71.1474, "altitude_m": 7.0}


@pytest.fixture(scope="module", autouse=True)
def _bags_present():
    missing = [f for f in (ROTORS, HUSKY, LUMINAR, RASPICAM) if not (BAGS / f).is_file()]
    if missing:
        pytest.fail(f"shared bags missing from {BAGS}: {', '.join(missing)}")


def raw_messages(path: Path, topic: str) -> list[tuple[int, object]]:
    """(record time, message) of one topic, read with rosbags directly: the reference."""
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as r:
        conns = [c for c in r.connections if c.topic == topic]
        return [(t, r.deserialize(raw, c.msgtype)) for c, t, raw in r.messages(connections=conns)]


def header_ns(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def scene(platform_trajectory, *, sensors=(), imports=(), duration=5.0, pose_rate=100.0) -> SceneConfig:
    return SceneConfig.model_validate({
        "name": "t", "source": {"kind": "procedural"}, "origin": ORIGIN,
        "base_stations": [{"name": "bs0", "position_m": [0.0, 0.0, 10.0]}],
        "platforms": [{"name": "p0", "kind": "uav", "trajectory": platform_trajectory, "sensors": list(sensors)}],
        "clock": {"duration_s": duration, "pose_rate_hz": pose_rate}, "sensor_imports": list(imports)})


# --- trajectory replay ------------------------------------------------------------------------------

def test_rotors_pose_replay_gives_the_messages_at_recorded_instants():
    msgs = raw_messages(BAGS / ROTORS, "/ground_truth/pose")
    t0 = header_ns(msgs[0][1])
    # The poses are stamped every 10 ms from 0.38 s: on the 100 Hz pose clock once the origin is the
    # first message, so every clock sample is a recorded instant.
    cfg = scene({"kind": "replay", "path": ROTORS, "topic": "/ground_truth/pose"}, duration=5.0)
    traj = build_trajectory(cfg, BAGS).sel(platform="p0")
    n = traj.sizes["time"]
    assert n == 501
    np.testing.assert_array_equal(np.array([header_ns(m) for _, m in msgs[:n]]) - t0, traj["time"].values)
    pos = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for _, m in msgs[:n]])
    quat = np.array([[m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w]
                     for _, m in msgs[:n]])
    np.testing.assert_array_equal(traj["position_m"].values, pos)
    np.testing.assert_array_equal(traj["orientation_xyzw"].values, quat)
    # PoseStamped has no velocity: the spline's derivative must match Gazebo's ground-truth twist
    # (world frame, recorded on its own topic) over the whole flight.
    rec = bags.read_bag_trajectory(BAGS / ROTORS, "/ground_truth/pose")
    v = replay.resample(rec, rec["time_ns"])["velocity_mps"]
    twist = np.array([[m.twist.linear.x, m.twist.linear.y, m.twist.linear.z]
                      for _, m in raw_messages(BAGS / ROTORS, "/ground_truth/twist")])
    err = np.linalg.norm(v - twist, axis=1)
    assert np.abs(twist).max() > 1.0 and np.median(err) < 2e-3 and np.percentile(err, 99) < 0.03


def test_rosbag2_sqlite3_and_mcap_conversions_give_identical_trajectories(tmp_path):
    from rosbags.convert import convert

    ros1 = bags.read_bag_trajectory(BAGS / ROTORS, "/ground_truth/pose")
    for storage, suffix in (("sqlite3", ".db3"), ("mcap", ".mcap")):
        out = tmp_path / f"rotors_{storage}"
        convert([BAGS / ROTORS], out, storage, 8, None, "file", None, None, [], ["/ground_truth/pose"], [], [])
        storage_file = next(out.glob(f"*{suffix}"))
        for path in (out, storage_file):  # the rosbag2 directory, and its storage file alone
            got = bags.read_bag_trajectory(path, "/ground_truth/pose")
            assert got.keys() == ros1.keys()
            for k in ros1:
                np.testing.assert_array_equal(got[k], ros1[k], err_msg=f"{path}: {k}")
        # through the config: a rosbag2 directory is a valid recording path
        (tmp_path / "scene.yaml").write_text(yaml.safe_dump(scene_yaml(
            tmp_path.name, {"kind": "replay", "path": out.name, "topic": "/ground_truth/pose"})))
        cfg = load_scene_config(tmp_path)
        traj = build_trajectory(cfg, tmp_path)
        np.testing.assert_array_equal(traj["position_m"].values[0], ros1["position_m"][:traj.sizes["time"]])


def scene_yaml(name, trajectory) -> dict:
    return {"name": name, "source": {"kind": "procedural"}, "origin": ORIGIN,
            "base_stations": [{"name": "bs0", "position_m": [0.0, 0.0, 10.0]}],
            "platforms": [{"name": "p0", "kind": "uav", "trajectory": trajectory}],
            "clock": {"duration_s": 2.0}}


def test_husky_odometry_replay_rotates_its_twist_into_world():
    msgs = raw_messages(BAGS / HUSKY, "/husky_velocity_controller/odom")
    rec = bags.read_bag_trajectory(BAGS / HUSKY, "/husky_velocity_controller/odom")
    assert len(rec["time_ns"]) == len(msgs) == 3952
    q = np.array([[m.pose.pose.orientation.x, m.pose.pose.orientation.y, m.pose.pose.orientation.z,
                   m.pose.pose.orientation.w] for _, m in msgs])
    twist = np.array([[m.twist.twist.linear.x, m.twist.twist.linear.y, m.twist.twist.linear.z] for _, m in msgs])
    # REP 105: the twist is in child_frame_id (base_link); the rotation matrix of each quaternion,
    # written out, takes it into the odom frame.
    x, y, z, w = q.T
    rot = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                    np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                    np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], 1)
    np.testing.assert_allclose(rec["velocity_mps"], np.einsum("nij,nj->ni", rot, twist), atol=1e-12)
    # ... and it points where the robot goes: the finite-difference heading of the recorded positions.
    dp = np.diff(rec["position_m"], axis=0)
    moving = np.linalg.norm(dp, axis=1) > 0.05
    v = rec["velocity_mps"][1:][moving]
    cos = np.sum(dp[moving] * v, axis=1) / np.linalg.norm(dp[moving], axis=1) / np.linalg.norm(v, axis=1)
    assert moving.sum() > 1000 and np.median(cos) > 0.9999
    speed_ratio = np.linalg.norm(dp[moving], axis=1) / np.diff(rec["time_ns"] / 1e9)[moving] \
        / np.linalg.norm(v, axis=1)
    assert abs(np.median(speed_ratio) - 1) < 0.05
    # Recorded instants give the recorded values, the angular rate (base_link) included.
    res = replay.resample(rec, rec["time_ns"][:200])
    np.testing.assert_array_equal(res["velocity_mps"], rec["velocity_mps"][:200])
    np.testing.assert_array_equal(res["angular_velocity_radps"],
                                  [[m.twist.twist.angular.x, m.twist.twist.angular.y, m.twist.twist.angular.z]
                                   for _, m in msgs[:200]])


# --- a bag written here: the /tf chain ---------------------------------------------------------------

def map_odom(t):  # moves linearly and yaws at a constant rate: tf2's interpolation is exact on it
    return np.array([10 + 0.5 * t, -5.0, 0.0]), Rotation.from_euler("z", 0.2 * t)


def odom_base(t):
    return np.array([2.0 * t, 1 + 0.3 * t, 0.0]), Rotation.from_euler("z", -0.5 * t) * Rotation.from_euler("x", 0.1)


BASE_LIDAR = (np.array([0.3, 0.0, 1.2]), Rotation.from_euler("xyz", [0.0, 0.2, np.pi / 2]))
BASE_IMU = (np.array([0.1, -0.2, 0.3]), Rotation.from_euler("x", np.pi))


def matrix(t_r) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = t_r[1].as_matrix(), t_r[0]
    return m


def write_tf_bag(path: Path) -> None:
    """rosbag2 MCAP: /tf (map->odom at 2 Hz, odom->base_link at 10 Hz), /tf_static, /imu at 10 Hz."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types

    def stamped(parent, child, t_ns, t_r):
        xyz, q = t_r[0], t_r[1].as_quat()
        return T["geometry_msgs/msg/TransformStamped"](
            header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9),
                                            frame_id=parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))

    tf_type, imu_type = "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/Imu"
    base = 1_700_000_000 * 10**9  # absolute stamps, as a real recording has
    msgs = []
    for k in range(9):  # map -> odom at 0, 0.5, ..., 4 s, with the ROS1-style leading slashes
        t = base + k * 500_000_000
        msgs.append(("/tf", t, T[tf_type](transforms=[stamped("/map", "/odom", t, map_odom(k * 0.5))])))
    for k in range(39):  # odom -> base_link at 0.05 + 0.1 k s
        t = base + 50_000_000 + k * 100_000_000
        msgs.append(("/tf", t, T[tf_type](transforms=[stamped("odom", "base_link", t, odom_base((t - base) / 1e9))])))
        v3 = T["geometry_msgs/msg/Vector3"]
        msgs.append(("/imu", t, T[imu_type](
            header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9),
                                            frame_id="imu_link"),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.array([-1.0] + [0.0] * 8),
            angular_velocity=v3(x=0.0, y=0.0, z=-0.5), angular_velocity_covariance=np.zeros(9),
            linear_acceleration=v3(x=0.0, y=0.0, z=-9.8 + k), linear_acceleration_covariance=np.zeros(9))))
    static = T[tf_type](transforms=[stamped("base_link", "lidar", base, BASE_LIDAR),
                                    stamped("base_link", "imu_link", base, BASE_IMU)])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {tp: w.add_connection(tp, ty, typestore=ts) for tp, ty in
                 (("/tf", tf_type), ("/tf_static", tf_type), ("/imu", imu_type))}
        w.write(conns["/tf_static"], base, ts.serialize_cdr(static, tf_type))
        for tp, t, m in sorted(msgs, key=lambda r: r[1]):
            w.write(conns[tp], t, ts.serialize_cdr(m, tf_type if tp == "/tf" else imu_type))


@pytest.fixture(scope="module")
def tf_bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("tf") / "chain"
    write_tf_bag(path)
    return path


def test_tf_chain_composes_to_the_known_pose(tf_bag):
    rec = bags.read_bag_trajectory(tf_bag, "/tf", child_frame_id="lidar", parent_frame_id="map")
    t = rec["time_ns"] / 1e9 + 0.05  # the first instant where both moving links have data
    # every odom->base_link stamp and the map->odom stamps between them: 39 + 7
    assert len(t) == 46 and rec["time_ns"][0] == 0
    for i, ti in enumerate(t):
        want = matrix(map_odom(ti)) @ matrix(odom_base(ti)) @ matrix(BASE_LIDAR)
        np.testing.assert_allclose(rec["position_m"][i], want[:3, 3], atol=1e-9)
        np.testing.assert_allclose(Rotation.from_quat(rec["orientation_xyzw"][i]).as_matrix(), want[:3, :3],
                                   atol=1e-9)
    # The inverse lookup goes down from the common ancestor: the pose of map in the lidar frame.
    with bags.Bag(tf_bag) as bag:
        tree = bags.read_tf(bag)
    t_abs = np.array([1_700_000_000 * 10**9 + 1_234_567_890])
    pos, quat = tree.lookup("lidar", "/map", t_abs)
    want = np.linalg.inv(matrix(map_odom(1.23456789)) @ matrix(odom_base(1.23456789)) @ matrix(BASE_LIDAR))
    np.testing.assert_allclose(pos[0], want[:3, 3], atol=1e-9)
    np.testing.assert_allclose(Rotation.from_quat(quat[0]).as_matrix(), want[:3, :3], atol=1e-9)
    with pytest.raises(bags.BagError, match=r"chain.*no frame 'camera'.*base_link"):
        tree.lookup("map", "camera", t_abs)


def test_imu_import_takes_its_extrinsics_from_tf_static(tf_bag):
    traj_cfg = {"kind": "replay", "path": tf_bag.name, "topic": "/tf", "child_frame_id": "base_link",
                "parent_frame_id": "map"}
    cfg = scene(traj_cfg, sensors=[{"kind": "imu", "name": "imu"}], duration=3.0, imports=[
        {"path": tf_bag.name, "streams": [{"device": "p0", "sensor": "imu", "kind": "imu", "topic": "/imu",
                                           "extrinsics": "tf"}]}])
    traj = build_trajectory(cfg, tf_bag.parent)
    ds = import_streams(cfg.sensor_imports[0], cfg, traj, tf_bag.parent)["/p0/imu"]
    np.testing.assert_allclose(ds.attrs["mount_translation_m"], BASE_IMU[0], atol=1e-12)
    assert Rotation.from_quat(ds.attrs["mount_quaternion_xyzw"]).approx_equal(BASE_IMU[1], atol=1e-12)
    assert "tf: pose of 'imu_link' in 'base_link'" in ds.attrs["extrinsics_source"]
    # times: header stamps minus the first, within the 3 s session (0, 0.1, ..., 3.0 s)
    np.testing.assert_array_equal(ds["time"].values, np.arange(31) * 100_000_000)
    np.testing.assert_array_equal(ds["linear_acceleration_mps2"].values[:, 2], -9.8 + np.arange(31))
    assert ds.attrs["num_messages_outside_session"] == 8
    # the IMU's pose is the replayed trajectory (same origin: the first stamps coincide) with the mount
    for i in (0, 7, 30):
        ti = 0.05 + 0.1 * i
        want = (matrix(map_odom(ti)) @ matrix(odom_base(ti)))[:3, :3] @ BASE_IMU[1].as_matrix()
        np.testing.assert_allclose(Rotation.from_quat(ds["orientation_xyzw"].values[i]).as_matrix(), want,
                                   atol=1e-9)
    assert np.isnan(ds["reported_orientation_xyzw"].values).all()  # covariance[0] = -1: none reported


# --- sensor import from real bags ----------------------------------------------------------------------

def test_husky_imu_and_gps_import(tmp_path):
    cfg = scene({"kind": "replay", "path": HUSKY, "topic": "/husky_velocity_controller/odom"}, duration=30.0,
                imports=[{"path": HUSKY, "streams": [
                    {"device": "p0", "sensor": "imu", "kind": "imu", "topic": "/imu/data"},
                    {"device": "p0", "sensor": "gps", "kind": "gps", "topic": "/fix"}]}])
    traj = build_trajectory(cfg, BAGS)
    got = import_streams(cfg.sensor_imports[0], cfg, traj, BAGS, "sunny")
    imu, gps = got["/p0/imu"], got["/p0/gps"]
    raw_imu, raw_fix = raw_messages(BAGS / HUSKY, "/imu/data"), raw_messages(BAGS / HUSKY, "/fix")
    origin = min(header_ns(raw_imu[0][1]), header_ns(raw_fix[0][1]))
    assert imu.attrs["time_origin_ns"] == origin
    n = imu.sizes["time"]
    assert n == sum(0 <= header_ns(m) - origin <= 30 * 10**9 for _, m in raw_imu) > 800
    np.testing.assert_array_equal(imu["time"].values, [header_ns(m) - origin for _, m in raw_imu[:n]])
    acc = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
                    for _, m in raw_imu[:n]])
    np.testing.assert_array_equal(imu["linear_acceleration_mps2"].values, acc)
    # the quirk: the IMU is mounted rotated, gravity's reaction (+g) is on its +y axis
    mean = acc.mean(axis=0)
    assert abs(np.linalg.norm(mean) - 9.81) < 0.3 and mean[1] > 9.0
    assert imu["linear_acceleration_mps2"].attrs["units"] == "m s-2"
    # GPS: lat/lon/alt as recorded, and round trip through the scene's ENU frame
    m = gps.sizes["time"]
    lla = np.array([[f.latitude, f.longitude, f.altitude] for _, f in raw_fix[:m]])
    np.testing.assert_array_equal(np.stack([gps["latitude_deg"], gps["longitude_deg"], gps["altitude_m"]], -1), lla)
    back = frames.enu_to_geodetic(gps["fix_enu_m"].values, ORIGIN["latitude_deg"], ORIGIN["longitude_deg"],
                                  ORIGIN["altitude_m"])
    np.testing.assert_allclose(back[:, :2], lla[:, :2], rtol=0, atol=1e-10)
    np.testing.assert_allclose(back[:, 2], lla[:, 2], atol=1e-6)
    assert gps["fix_valid"].all() and (gps["fix_status"] == 1).all()  # SBAS fixes
    assert gps.attrs["source_frame_id"] == "gps"  # '/gps' in the bag: the leading slash is dropped
    assert gps.attrs["time_sampling"].startswith("recorded")
    stores.check_finite(gps)
    stores.check_finite(imu)


def test_luminar_pointcloud_import_equals_the_raw_fields():
    cfg = scene({"waypoints_m": [[0, 0, 5], [5, 0, 5]], "speed_mps": 1.0}, duration=1.0, imports=[
        {"path": LUMINAR, "streams": [{"device": "p0", "sensor": "luminar", "kind": "lidar",
                                       "topic": "/luminar_pointcloud"}]}])
    ds = import_streams(cfg.sensor_imports[0], cfg, build_trajectory(cfg), BAGS)["/p0/luminar"]
    raw = raw_messages(BAGS / LUMINAR, "/luminar_pointcloud")
    assert ds.sizes["time"] == len(raw) == 5
    assert ds.sizes["ring"] == 1  # an unorganised cloud (height 1) is one ring, its points along azimuth
    for i, (t_rec, msg) in enumerate(raw):
        n = msg.width * msg.height
        assert ds["point_count"].values[i] == n
        off = {f.name: f.offset for f in msg.fields}
        buf, step = bytes(msg.data), msg.point_step
        assert not msg.is_bigendian and all(f.datatype == 7 for f in msg.fields[:4])  # float32 x y z intensity
        for c, name in enumerate(("x", "y", "z")):
            ref = [struct.unpack_from("<f", buf, k * step + off[name])[0] for k in range(n)]
            np.testing.assert_array_equal(ds["points_m"].values[i, 0, :n, c], ref)
        ref = [struct.unpack_from("<f", buf, k * step + off["intensity"])[0] for k in range(n)]
        np.testing.assert_array_equal(ds["intensity"].values[i, 0, :n], ref)
        ref = [struct.unpack_from("<H", buf, k * step + off["laser_id"])[0] for k in range(n)]
        np.testing.assert_array_equal(ds["field_laser_id"].values[i, 0, :n], ref)
        assert ds["valid"].values[i, 0, :n].all() and not ds["valid"].values[i, 0, n:].any()
    # the quirk: header stamps are months older than the record times; each gives its own clock
    assert ds.attrs["source_stamp"] == "message header stamps" and ds["time"].values[-1] < 0.5e9
    assert (ds["record_time_ns"] - ds["header_stamp_ns"]).min() > 200 * 86400 * 10**9
    imp = cfg.sensor_imports[0].model_copy(update={"stamp": "record"})
    rec = import_streams(imp, cfg, build_trajectory(cfg), BAGS)["/p0/luminar"]
    np.testing.assert_array_equal(rec["time"].values, [t - raw[0][0] for t, _ in raw])
    assert ds["points_m"].attrs["units"] == "m" and ds["points_m"].dtype == np.float32


def test_raspicam_jpeg_is_decoded_with_its_intrinsics():
    import io

    from PIL import Image

    cfg = scene({"waypoints_m": [[0, 0, 5], [5, 0, 5]], "speed_mps": 1.0}, duration=1.0, imports=[
        {"path": RASPICAM, "streams": [{"device": "bs0", "sensor": "raspicam", "kind": "camera",
                                        "topic": "/raspicam_node/image/compressed",
                                        "camera_info_topic": "/raspicam_node/camera_info"}]}])
    ds = import_streams(cfg.sensor_imports[0], cfg, None, BAGS)["/bs0/raspicam"]
    assert ds["rgb"].shape == (1, 960, 1280, 3) and ds["rgb"].dtype == np.uint8
    assert ds["rgb"].dims == ("time", "y", "x", "channel")
    _, msg = raw_messages(BAGS / RASPICAM, "/raspicam_node/image/compressed")[0]
    ref = np.asarray(Image.open(io.BytesIO(bytes(msg.data))).convert("RGB"), np.int16)  # another decoder
    diff = np.abs(ds["rgb"].values[0].astype(np.int16) - ref)
    assert diff.mean() < 1.0 and np.percentile(diff, 99) <= 3
    info = raw_messages(BAGS / RASPICAM, "/raspicam_node/camera_info")[0][1]
    np.testing.assert_array_equal(ds["camera_matrix"].values, np.reshape(info.K, (3, 3)))
    assert ds.attrs["frame_id"] == "bs0/raspicam_optical" and ds.attrs["source_frame_id"] == "raspicam"
    assert ds.attrs["source_message_type"] == "sensor_msgs/msg/CompressedImage"
    # base station camera: the optical frame in world, from the static pose (identity mount)
    np.testing.assert_array_equal(ds["position_m"].values[0], [0.0, 0.0, 10.0])


def test_raw_bgr_and_png_images_decode_to_the_pixels_written(tmp_path):
    """A ROS1 bag written here: a raw bgr8 Image with padded rows, and the same pixels as a PNG."""
    import cv2
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    rgb = np.random.default_rng(3).integers(0, 256, (3, 2, 5, 3), dtype=np.uint8)  # 2 frames, 5 x 3 px
    path = tmp_path / "images.bag"
    with Writer(path) as w:
        raw_c = w.add_connection("/cam/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        png_c = w.add_connection("/cam/image/compressed", "sensor_msgs/msg/CompressedImage", typestore=ts)
        for k in range(2):
            t = 10**9 + k * 50_000_000
            hdr = T["std_msgs/msg/Header"](seq=k, stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=k * 50_000_000),
                                           frame_id="cam_optical")
            bgr = rgb[:, k, :, ::-1]
            padded = np.zeros((3, 5 * 3 + 4), np.uint8)  # step 19: 4 bytes of padding per row
            padded[:, :15] = bgr.reshape(3, 15)
            img = T["sensor_msgs/msg/Image"](header=hdr, height=3, width=5, encoding="bgr8", is_bigendian=0,
                                             step=19, data=padded.ravel())
            w.write(raw_c, t, ts.serialize_ros1(img, "sensor_msgs/msg/Image"))
            ok, png = cv2.imencode(".png", np.ascontiguousarray(bgr))
            assert ok
            comp = T["sensor_msgs/msg/CompressedImage"](header=hdr, format="png", data=png.ravel())
            w.write(png_c, t, ts.serialize_ros1(comp, "sensor_msgs/msg/CompressedImage"))
    cfg = scene({"waypoints_m": [[0, 0, 5], [5, 0, 5]], "speed_mps": 1.0}, duration=1.0, imports=[
        {"path": path.name, "streams": [
            {"device": "bs0", "sensor": "raw", "kind": "camera", "topic": "/cam/image_raw"},
            {"device": "bs0", "sensor": "png", "kind": "camera", "topic": "/cam/image/compressed"}]}])
    got = import_streams(cfg.sensor_imports[0], cfg, None, tmp_path)
    for name in ("raw", "png"):
        ds = got[f"/bs0/{name}"]
        np.testing.assert_array_equal(ds["rgb"].values, np.moveaxis(rgb, 1, 0), err_msg=name)
        np.testing.assert_array_equal(ds["time"].values, [0, 50_000_000])
        assert ds.attrs["source_format"] == "ROS1" and ds.attrs["projection"].startswith("unknown")
    assert got["/bs0/raw"]["rgb"].attrs["source_encoding"] == "bgr8"


# --- errors ------------------------------------------------------------------------------------------------

def test_a_missing_topic_names_the_file_and_its_topics():
    with pytest.raises(bags.BagError, match=rf"{HUSKY}: no topic '/odom'; the bag has: /fix \(sensor_msgs/msg/"
                                            r"NavSatFix\), /husky_velocity_controller/odom"):
        bags.read_bag_trajectory(BAGS / HUSKY, "/odom")
    with pytest.raises(bags.BagError, match=rf"{HUSKY}: topic /fix holds sensor_msgs/msg/NavSatFix"):
        bags.read_bag_trajectory(BAGS / HUSKY, "/fix")
    cfg = scene({"waypoints_m": [[0, 0, 5], [5, 0, 5]], "speed_mps": 1.0}, imports=[
        {"path": HUSKY, "streams": [{"device": "p0", "sensor": "cam", "kind": "camera", "topic": "/imu/data"}]}])
    with pytest.raises(bags.BagError, match=rf"{HUSKY}: topic /imu/data holds sensor_msgs/msg/Imu; expected "
                                            r"sensor_msgs/msg/Image or sensor_msgs/msg/CompressedImage"):
        import_streams(cfg.sensor_imports[0], cfg, None, BAGS)


@pytest.mark.parametrize("fraction", [0.001, 0.5, 0.999])
def test_a_truncated_bag_names_the_file(tmp_path, fraction):
    data = (BAGS / ROTORS).read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[:int(len(data) * fraction)])
    with pytest.raises(bags.BagError, match=r"cut\.bag: cannot read the ROS1 bag \(truncated or corrupt\?\)"):
        bags.read_bag_trajectory(cut, "/ground_truth/pose")


def test_a_corrupt_rosbag2_names_the_file(tmp_path):
    from rosbags.convert import convert

    out = tmp_path / "r2"
    convert([BAGS / ROTORS], out, "mcap", 8, None, "file", None, None, [], ["/ground_truth/pose"], [], [])
    mcap = next(out.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:len(mcap.read_bytes()) // 2])
    with pytest.raises(bags.BagError, match=r"r2.*(truncated or corrupt)"):
        bags.read_bag_trajectory(out, "/ground_truth/pose")


def test_config_refuses_paths_outside_the_scene_and_unknown_formats(tiny_scene):
    raw = yaml.safe_load((tiny_scene / "scene.yaml").read_text())
    raw["platforms"][0]["trajectory"] = {"kind": "replay", "path": "../x.bag", "topic": "/odom"}
    raw["sensor_imports"] = [{"path": "/data/other.bag", "streams": [
        {"device": "car0", "sensor": "cam", "kind": "camera", "topic": "/image"}]}]
    (tiny_scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError) as exc:
        load_scene_config(tiny_scene)
    assert any("platforms.0.trajectory.path" in p and "inside the scene directory" in p for p in exc.value.problems)
    assert any("sensor_imports.0.path" in p and "inside the scene directory" in p for p in exc.value.problems)
    for bad, message in [({"kind": "replay", "path": "rec.txt", "topic": "/odom"}, "unknown recording format"),
                         ({"kind": "replay", "path": "rec.bag"}, "topic: a bag needs the topic"),
                         ({"kind": "replay", "path": "rec.csv", "topic": "/odom"}, "topic: only for bags")]:
        with pytest.raises(ValueError, match=message):
            ReplayTrajectory.model_validate(bad)
    # an imported stream must name a device, and may replace only a sensor of its own kind
    raw["platforms"][0]["trajectory"] = {"kind": "replay", "path": "link.bag", "topic": "/fix"}
    raw["sensor_imports"] = [{"path": "link.bag", "streams": [
        {"device": "car0", "sensor": "cam", "kind": "lidar", "topic": "/image"}]}]
    (tiny_scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match=r"sensor_imports\.0\.streams\.0\.kind: 'lidar' cannot replace "
                                          r"car0/cam, a camera"):
        load_scene_config(tiny_scene)
    # a symlink inside the scene directory that leads out of it is refused too
    (tiny_scene / "link.bag").symlink_to(BAGS / HUSKY)
    raw["sensor_imports"][0]["streams"][0]["kind"] = "camera"
    (tiny_scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError) as exc:
        load_scene_config(tiny_scene)
    assert any("platforms.0.trajectory.path: 'link.bag' points outside" in p for p in exc.value.problems)
    assert any("sensor_imports.0.path: 'link.bag' points outside" in p for p in exc.value.problems)


# --- end to end --------------------------------------------------------------------------------------------

def test_sensing_stage_with_an_imported_and_a_rendered_stream(tiny_scene):
    """The function the sensor_frames asset calls, on a scene whose IMU comes from the Husky bag
    while its GPS is rendered from the replayed odometry; written and read back as a store."""
    shutil.copy(BAGS / HUSKY, tiny_scene / "husky.bag")  # a scene owns its recordings
    raw = yaml.safe_load((tiny_scene / "scene.yaml").read_text())
    car = raw["platforms"][0]
    car["trajectory"] = {"kind": "replay", "path": "husky.bag", "topic": "/husky_velocity_controller/odom",
                         "stamp": "record", "time_origin": "bag_start",
                         "recording_frame": {"translation_m": [-38.0, -18.0, 0.0]}}
    car["sensors"] = [s for s in car["sensors"] if s["kind"] in ("imu", "gps")]
    raw["clock"] = {"duration_s": 2.0, "radio_rate_hz": 5.0, "pose_rate_hz": 50.0}
    raw["sensor_imports"] = [{"path": "husky.bag", "stamp": "record", "time_origin": "bag_start",
                              "streams": [{"device": "car0", "sensor": "imu", "kind": "imu", "topic": "/imu/data"}]}]
    (tiny_scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    cfg = load_scene_config(tiny_scene)
    traj = build_trajectory(cfg, tiny_scene)
    odom = raw_messages(tiny_scene / "husky.bag", "/husky_velocity_controller/odom")
    start = raw_messages(tiny_scene / "husky.bag", "/imu/data")[0][0]  # the bag's first record
    first = odom[0][1].pose.pose.position
    t0 = (odom[0][0] - start)  # the first odometry record, on the session clock
    i0 = int(np.searchsorted(traj["time"].values, t0))
    np.testing.assert_allclose(traj["position_m"].values[0, i0], [first.x - 38.0, first.y - 18.0, first.z], atol=0.05)
    tree = build_sensor_frames(None, traj, cfg, "rainy", tiny_scene)  # no camera or LiDAR: no meshes needed
    assert sorted(n.path for n in tree.subtree if n.has_data) == ["/car0/gps", "/car0/imu"]
    path = stores.write_store(tree, tiny_scene / "out.zarr")
    back = stores.open_store(path, tree=True)
    imu, gps = back["car0/imu"].to_dataset(), back["car0/gps"].to_dataset()
    assert imu.attrs["source_topic"] == "/imu/data" and imu.attrs["weather"] == "rainy"
    assert imu["time"].dtype == np.int64 and imu["time"].values[0] == 0  # the bag's first record is an IMU one
    np.testing.assert_array_equal(imu["record_time_ns"].values - start, imu["time"].values)
    assert gps.attrs["rate_hz"] == 2.0 and gps.attrs["source"].startswith("rendered")  # rendered as before
    assert gps.attrs["source_topic"] == "none" and imu.attrs["weather_model"].startswith("none")
    np.testing.assert_array_equal(gps["time"].values, [0, 500_000_000, 1_000_000_000, 1_500_000_000, 2_000_000_000])
    # the rendered GPS antenna follows the replayed, shifted odometry
    np.testing.assert_allclose(gps["position_enu_m"].values[0], [first.x - 38.0, first.y - 18.0, first.z], atol=1e-9)


def test_validate_opens_every_input_the_config_names(tiny_scene):
    """`simart validate` reads the replay recording and its topic, the sensor-import bags, topics and
    message types and the codebook file before any work, one `file: key.path: message` line each;
    a replay inside a building is told about its recording, not about waypoints it does not have."""
    from simart_pipeline.validation import scene_problems

    shutil.copy(BAGS / HUSKY, tiny_scene / "husky.bag")
    path = tiny_scene / "scene.yaml"
    raw = yaml.safe_load(path.read_text())
    car = raw["platforms"][0]
    car["trajectory"] = {"kind": "replay", "path": "husky.bag", "topic": "/husky_velocity_controller/odm",
                         "stamp": "record"}
    raw["sensor_imports"] = [{"path": "husky.bag", "stamp": "record", "streams": [
        {"device": "car0", "sensor": "imu", "kind": "imu", "topic": "/fix"},
        {"device": "car0", "sensor": "gps", "kind": "gps", "topic": "/gps_fix"}]}]
    np.save(tiny_scene / "beams.npy", np.ones((4, 3), np.complex128))  # 3 antennas, unit norm not met
    raw["codebook"] = {"path": "beams.npy"}
    path.write_text(yaml.safe_dump(raw))
    _, problems = scene_problems(tiny_scene)
    by_key = {p.split(": ")[1]: p for p in problems}
    assert all(p.startswith(f"{path}: ") for p in problems) and len(problems) == 4, problems
    assert "no topic '/husky_velocity_controller/odm'" in by_key["platforms.0.trajectory"]
    assert "/husky_velocity_controller/odom (nav_msgs/msg/Odometry)" in by_key["platforms.0.trajectory"]
    assert "holds sensor_msgs/msg/NavSatFix; expected sensor_msgs/msg/Imu" in by_key["sensor_imports.0.streams.0.topic"]
    assert "no topic '/gps_fix'" in by_key["sensor_imports.0.streams.1.topic"]
    assert "codebook must be [num_beams, " in by_key["codebook.path"]

    car["trajectory"]["topic"] = "/husky_velocity_controller/odom"
    first = raw_messages(BAGS / HUSKY, "/husky_velocity_controller/odom")[0][1].pose.pose.position
    from simart_pipeline.scene.source import build_source_geometry

    geom = build_source_geometry(load_scene_config(tiny_scene), tiny_scene)
    centre = geom.of_class("building")[0].geometry.representative_point()
    car["trajectory"]["recording_frame"] = {"translation_m": [centre.x - first.x, centre.y - first.y, 1.0 - first.z]}
    raw.pop("sensor_imports")
    raw.pop("codebook")
    path.write_text(yaml.safe_dump(raw))
    _, problems = scene_problems(tiny_scene)
    assert len(problems) == 1 and "platforms.0.trajectory: " in problems[0], problems
    assert "recorded poses of car0 lie inside a building" in problems[0] and "recording_frame" in problems[0]
    assert "waypoints" not in problems[0]
