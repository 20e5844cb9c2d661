"""Sensing stage: cameras, LiDAR, IMU and GPS against analytic answers."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import trimesh
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline import clock, frames, stores
from simart_pipeline.config import SceneConfig
from simart_pipeline.mobility.trajectory import build_trajectory, poses_at
from simart_pipeline.scene.meshes import SceneMeshes
from simart_pipeline.vocabulary import SemanticClass
from simart_pipeline.sensing import raycast
from simart_pipeline.vocabulary import STANDARD_GRAVITY_MPS2
from simart_pipeline.sensing.lidar import beam_angles
from simart_pipeline.sensing.sensor_frames import render_sensor_frames

WALL_ID = 42
GROUND_ID = 7
ORIGIN = {"latitude_deg": 48.1372, "longitude_deg": 11.5755, "altitude_m": 519.0}


def make_config(bs_sensors=(), plat_sensors=(), *, bs_position=(0.0, 0.0, 0.0), bs_orientation=(0.0, 0.0, 0.0),
                waypoints=((0.0, 0.0, 5.0), (10.0, 0.0, 5.0)), speed=2.0, start_offset=0.0, duration=1.0,
                seed=0, kind="uav") -> SceneConfig:
    return SceneConfig.model_validate({
        "name": "t", "source": {"kind": "procedural"}, "origin": ORIGIN,
        "base_stations": [{"name": "bs0", "position_m": list(bs_position),
                           "orientation_deg": list(bs_orientation), "sensors": list(bs_sensors)}],
        "platforms": [{"name": "p0", "kind": kind, "sensors": list(plat_sensors),
                       "trajectory": {"waypoints_m": [list(w) for w in waypoints], "speed_mps": speed,
                                      "start_offset_s": start_offset}}],
        "clock": {"duration_s": duration}, "seed": seed,
    })


def quad(corners, cls, inst) -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray]:
    mesh = trimesh.Trimesh(np.asarray(corners, float), [[0, 1, 2], [0, 2, 3]], process=False)
    return mesh, np.full(2, cls, np.uint8), np.full(2, inst, np.int64)


def scene_of(*parts) -> SceneMeshes:
    return SceneMeshes(trimesh.util.concatenate([p[0] for p in parts]),
                       np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts]), {})


# A wall in the plane x = 10 m, y in [-2, 5], z in [-1, 3] (asymmetric, to catch flipped axes).
WALL = quad([(10, -2, -1), (10, 5, -1), (10, 5, 3), (10, -2, 3)], SemanticClass.BUILDING, WALL_ID)
GROUND = quad([(-1000, -1000, 0), (1000, -1000, 0), (1000, 1000, 0), (-1000, 1000, 0)],
              SemanticClass.GROUND, GROUND_ID)
CAM = {"kind": "camera", "name": "cam", "rate_hz": 1.0, "width_px": 64, "height_px": 48,
       "horizontal_fov_deg": 90.0}


def wall_mask(ds: xr.Dataset) -> np.ndarray:
    """Pixels whose ray from the origin along +x meets the wall, from the intrinsics alone."""
    k = ds["camera_matrix"].values
    v, u = np.meshgrid(np.arange(ds.sizes["y"]), np.arange(ds.sizes["x"]), indexing="ij")
    world_y = -10.0 * (u - k[0, 2]) / k[0, 0]  # optical x right = world -y for a camera facing +x
    world_z = -10.0 * (v - k[1, 2]) / k[1, 1]  # optical y down = world -z
    return (world_y > -2) & (world_y < 5) & (world_z > -1) & (world_z < 3)


@pytest.mark.parametrize("bs_position, bs_yaw", [((0.0, 0.0, 0.0), 0.0), ((20.0, 0.0, 0.0), 180.0)])
def test_camera_depth_of_wall_is_z_depth(bs_position, bs_yaw):
    # Facing +x from the origin, or facing -x (Sionna yaw 180 deg) from x = 20: the wall is 10 m away.
    cfg = make_config([CAM], bs_position=bs_position, bs_orientation=(bs_yaw, 0.0, 0.0))
    tree = render_sensor_frames(scene_of(WALL), build_trajectory(cfg), cfg, "sunny")
    ds = tree["bs0/cam"].to_dataset()
    depth = ds["depth_m"].values[0]
    expect = wall_mask(ds) if bs_yaw == 0 else wall_mask(ds)[:, ::-1]  # turned round: y mirrors
    hit = ~np.isnan(depth)
    np.testing.assert_array_equal(hit, expect)
    assert hit.sum() > 200 and not hit.all()
    # Every pixel that meets the wall, the off-centre ones (rays up to ~30 deg off axis) included.
    np.testing.assert_allclose(depth[hit], 10.0, atol=1e-3)
    np.testing.assert_array_equal(ds["depth_valid"].values[0], hit)
    np.testing.assert_allclose(ds["position_m"].values[0], bs_position)


def test_camera_labels_of_wall():
    cfg = make_config([CAM])
    tree = render_sensor_frames(scene_of(WALL), build_trajectory(cfg), cfg, "sunny")
    ds = tree["bs0/cam"].to_dataset()
    mask = wall_mask(ds)
    sem, inst = ds["semantic_class"].values[0], ds["instance_id"].values[0]
    assert (sem[mask] == SemanticClass.BUILDING).all() and (inst[mask] == WALL_ID).all()
    assert (sem[~mask] == SemanticClass.UNLABELED).all() and (inst[~mask] == 0).all()
    assert sem.dtype == np.uint8 and inst.dtype == np.int64
    assert list(ds["semantic_class"].attrs["flag_values"]) == [int(c) for c in SemanticClass]
    assert ds["rgb"].dtype == np.uint8 and ds["rgb"].shape == (2, 48, 64, 3)


def test_camera_on_platform_follows_the_pose_chain():
    # Platform at 5 m flying east, camera mounted 1 m forward, pitched down 45 deg: the optical axis
    # meets the ground 5 m ahead of the camera, at a z-depth of 5 * sqrt(2) m.
    cam = dict(CAM, width_px=65, mount={"translation_m": [1.0, 0.0, 0.0], "rpy_deg": [0.0, 45.0, 0.0]})
    cfg = make_config(plat_sensors=[cam], kind="pedestrian")  # level (a UAV tilts as it accelerates)
    tree = render_sensor_frames(scene_of(GROUND), build_trajectory(cfg), cfg, "sunny")
    ds = tree["p0/cam"].to_dataset()
    k = ds["camera_matrix"].values
    f = k[0, 0]
    assert k[0, 2] == 32  # column 32 is the centre column
    v = np.arange(48)
    # Row v looks down by 45 deg + atan((v - cy) / f); the ground is 5 m below: z-depth is
    # 5 / sin(angle) * cos(atan((v - cy) / f)).
    off = np.arctan((v - k[1, 2]) / f)
    expect = 5.0 / np.sin(np.pi / 4 + off) * np.cos(off)
    np.testing.assert_allclose(ds["depth_m"].values[:, :, 32], np.broadcast_to(expect, (2, 48)), rtol=1e-4)
    pos = poses_at(build_trajectory(cfg), "p0", ds["time"].values)["position_m"]
    np.testing.assert_allclose(ds["position_m"].values, pos + [1.0, 0.0, 0.0], atol=1e-9)
    assert ds.attrs["frame_id"] == "p0/cam_optical" and ds.attrs["parent_frame_id"] == "p0/base_link"


def test_raycaster_hits_faces_by_index():
    caster = raycast.RayCaster(scene_of(GROUND, WALL))
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 1.0] / np.sqrt(2)])
    hits = caster.intersect([0.0, 0.0, 1.0], dirs)
    np.testing.assert_allclose(hits.t[:2], [10.0, 1.0], rtol=1e-6)
    assert hits.t[2] == np.inf and hits.face[2] == -1 and not hits.hit[2:].any()  # up, and over the wall
    assert set(hits.face[:2]) <= {0, 1, 2, 3} and hits.face[0] >= 2 and hits.face[1] < 2  # wall, ground
    np.testing.assert_allclose(np.abs(hits.normal[:2]), [[1, 0, 0], [0, 0, 1]], atol=1e-12)
    assert caster.occluded([0.0, 0.0, 1.0], dirs[:1]).all()
    assert not caster.occluded([0.0, 0.0, 1.0], dirs[:1], max_t=9.0).any()


def test_lidar_ranges_over_flat_ground():
    h = 5.0 - 0.2  # platform at 5 m, LiDAR mounted 0.2 m below base_link
    lidar = {"kind": "lidar", "name": "lidar", "rate_hz": 5.0, "channels": 5, "vertical_fov_deg": [-30.0, -10.0],
             "horizontal_samples": 64, "max_range_m": 120.0, "range_noise_std_m": 0.0,
             "mount": {"translation_m": [0.0, 0.0, -0.2]}}
    cfg = make_config(plat_sensors=[lidar], kind="pedestrian")  # level
    tree = render_sensor_frames(scene_of(GROUND), build_trajectory(cfg), cfg, "sunny")
    ds = tree["p0/lidar"].to_dataset()
    el, _ = beam_angles(cfg.platforms[0].sensors[0])
    np.testing.assert_allclose(np.rad2deg(el), [-30, -25, -20, -15, -10])
    expect = h / np.sin(-el)
    rng_m = ds["range_m"].values
    assert rng_m.shape == (6, 5, 64)
    np.testing.assert_allclose(rng_m, np.broadcast_to(expect[None, :, None], rng_m.shape), rtol=1e-5)
    np.testing.assert_allclose(ds["points_m"].values[..., 2], -h, atol=1e-3)
    assert (ds["semantic_class"].values == SemanticClass.GROUND).all() and ds["valid"].values.all()


def test_lidar_rain_drops_returns_and_adds_noise():
    lidar = {"kind": "lidar", "name": "lidar", "rate_hz": 5.0, "channels": 8, "vertical_fov_deg": [-30.0, -10.0],
             "horizontal_samples": 512, "range_noise_std_m": 0.02}
    cfg = make_config(plat_sensors=[lidar], kind="pedestrian")  # level
    meshes, traj = scene_of(GROUND), build_trajectory(cfg)
    out = {w: render_sensor_frames(meshes, traj, cfg, w)["p0/lidar"].to_dataset() for w in ("sunny", "rainy")}
    el, _ = beam_angles(cfg.platforms[0].sensors[0])
    truth = (5.0 / np.sin(-el))[None, :, None]
    for w, ds in out.items():
        wx_drop = ds.attrs["weather_lidar_dropout_probability"]
        valid = ds["valid"].values
        assert abs((1 - valid.mean()) - wx_drop) < 0.01
        err = (ds["range_m"].values - truth)[valid]
        std = 0.02 * ds.attrs["weather_lidar_range_noise_factor"]
        assert abs(err.std() / std - 1) < 0.05 and abs(err.mean()) < 0.1 * std
        assert np.isnan(ds["points_m"].values[~valid]).all()
    assert out["rainy"]["valid"].values.mean() < out["sunny"]["valid"].values.mean()


def test_imu_integrates_back_to_the_trajectory():
    imu = {"kind": "imu", "name": "imu", "rate_hz": 100.0, "accel_noise_std_mps2": 0.0,
           "gyro_noise_std_radps": 0.0, "mount": {"rpy_deg": [10.0, -5.0, 90.0]}}
    cfg = make_config(plat_sensors=[imu], waypoints=((0, 0, 10), (40, 0, 15), (40, 40, 12), (0, 40, 10)),
                      speed=8.0, duration=12.0)
    traj = build_trajectory(cfg)
    ds = render_sensor_frames(scene_of(GROUND), traj, cfg, "rainy")["p0/imu"].to_dataset()
    t = clock.ns_to_seconds(ds["time"].values)
    truth = poses_at(traj, "p0", ds["time"].values)
    r_wi = Rotation.from_quat(ds["orientation_xyzw"].values)
    a_w = r_wi.apply(ds["linear_acceleration_mps2"].values) - [0.0, 0.0, STANDARD_GRAVITY_MPS2]
    dt = np.diff(t)[:, None]
    vel = truth["velocity_mps"][0] + np.vstack([[0, 0, 0], np.cumsum(dt * (a_w[1:] + a_w[:-1]) / 2, axis=0)])
    pos = truth["position_m"][0] + np.vstack([[0, 0, 0], np.cumsum(dt * (vel[1:] + vel[:-1]) / 2, axis=0)])
    # Trapezoidal integration at 100 Hz of a piecewise-linear acceleration: errors of order
    # duration * dt**2 * jerk / 12, a fraction of a millimetre over 12 s (measured: 0.07 mm).
    assert len(t) == 1201
    assert np.abs(vel - truth["velocity_mps"]).max() < 2e-4
    assert np.abs(pos - truth["position_m"]).max() < 1e-3
    # The gyro reads the body yaw rate in the (rotated) IMU frame.
    r_bm = frames.rotation_from_rpy_deg([10.0, -5.0, 90.0])
    np.testing.assert_allclose(r_bm.apply(ds["angular_velocity_radps"].values), truth["angular_velocity_radps"],
                               atol=1e-12)


def test_imu_at_rest_reads_plus_g_with_bias_and_noise():
    imu = {"kind": "imu", "name": "imu", "rate_hz": 200.0, "accel_noise_std_mps2": 0.05,
           "gyro_noise_std_radps": 0.01, "accel_bias_mps2": [0.1, 0.0, 0.0], "gyro_bias_radps": [0.0, 0.0, 0.02]}
    cfg = make_config(plat_sensors=[imu], duration=10.0, start_offset=100.0)  # standing still, level
    ds = render_sensor_frames(scene_of(GROUND), build_trajectory(cfg), cfg, "sunny")["p0/imu"].to_dataset()
    acc, gyr = ds["linear_acceleration_mps2"].values, ds["angular_velocity_radps"].values
    np.testing.assert_allclose(acc.mean(0), [0.1, 0.0, STANDARD_GRAVITY_MPS2], atol=0.01)
    np.testing.assert_allclose(acc.std(0), 0.05, rtol=0.1)
    np.testing.assert_allclose(gyr.mean(0), [0.0, 0.0, 0.02], atol=0.002)
    np.testing.assert_allclose(gyr.std(0), 0.01, rtol=0.1)


def test_gps_round_trips_to_enu():
    gps = {"kind": "gps", "name": "gps", "rate_hz": 2.0, "horizontal_noise_std_m": 0.0,
           "vertical_noise_std_m": 0.0, "mount": {"translation_m": [0.3, 0.1, 0.5]}}
    cfg = make_config(plat_sensors=[gps], waypoints=((0, 0, 10), (300, 200, 60)), speed=20.0, duration=10.0)
    traj = build_trajectory(cfg)
    ds = render_sensor_frames(scene_of(GROUND), traj, cfg, "night")["p0/gps"].to_dataset()
    lla = np.stack([ds["latitude_deg"].values, ds["longitude_deg"].values, ds["altitude_m"].values], -1)
    enu = frames.geodetic_to_enu(lla, ORIGIN["latitude_deg"], ORIGIN["longitude_deg"], ORIGIN["altitude_m"])
    np.testing.assert_allclose(enu, ds["position_enu_m"].values, atol=1e-3)
    p = poses_at(traj, "p0", ds["time"].values)
    lever = Rotation.from_quat(p["orientation_xyzw"]).apply([0.3, 0.1, 0.5])
    np.testing.assert_allclose(ds["position_enu_m"].values, p["position_m"] + lever, atol=1e-9)
    assert ds["latitude_deg"].attrs["units"] == "degrees_north"
    assert ds["longitude_deg"].attrs["units"] == "degrees_east"


def test_no_camera_or_lidar_builds_no_scene(monkeypatch):
    def no_scene(meshes):
        raise AssertionError("the Mitsuba scene must not be built without a camera or LiDAR")

    monkeypatch.setattr(raycast, "build_scene", no_scene)
    cfg = make_config()
    tree = render_sensor_frames(scene_of(GROUND), build_trajectory(cfg), cfg, "sunny")
    assert len(list(tree.subtree)) == 1 and not tree.children and not tree.has_data
    cfg = make_config(plat_sensors=[{"kind": "imu", "name": "imu"}, {"kind": "gps", "name": "gps"}])
    tree = render_sensor_frames(scene_of(GROUND), build_trajectory(cfg), cfg, "rainy")
    assert sorted(n.path for n in tree.subtree if n.has_data) == ["/p0/gps", "/p0/imu"]


def test_weathers_differ_measurably():
    box = trimesh.creation.box(extents=(10.0, 10.0, 12.0))
    box.apply_translation((25.0, 0.0, 6.0))
    parts = [GROUND, (box, np.full(len(box.faces), SemanticClass.BUILDING, np.uint8),
                      np.full(len(box.faces), WALL_ID, np.int64))]
    cam = dict(CAM, width_px=160, height_px=120, mount={"rpy_deg": [0.0, 15.0, 0.0]})
    cfg = make_config([cam], bs_position=(0.0, -3.0, 6.0))
    meshes, traj = scene_of(*parts), build_trajectory(cfg)
    out = {w: render_sensor_frames(meshes, traj, cfg, w)["bs0/cam"].to_dataset() for w in ("sunny", "rainy", "night")}
    mean = {w: float(ds["rgb"].values[0].mean()) for w, ds in out.items()}
    assert mean["sunny"] > mean["rainy"] + 10 > mean["night"] + 20, mean
    # Weather changes the picture, never the geometry or the labels.
    for w in ("rainy", "night"):
        np.testing.assert_array_equal(out[w]["depth_m"].values, out["sunny"]["depth_m"].values)
        np.testing.assert_array_equal(out[w]["semantic_class"].values, out["sunny"]["semantic_class"].values)
    # Sunny: the box casts a shadow (sun from the south-east): shadowed ground is darker than lit ground.
    sem = out["sunny"]["semantic_class"].values[0]
    assert (sem == SemanticClass.GROUND).any() and (sem == SemanticClass.BUILDING).any()
    ground = out["sunny"]["rgb"].values[0][sem == SemanticClass.GROUND].mean(-1)
    assert ground.min() < 0.6 * np.median(ground)
    # Rainy streaks and noise are deterministic: a rerun is identical.
    again = render_sensor_frames(meshes, traj, cfg, "rainy")["bs0/cam"].to_dataset()
    np.testing.assert_array_equal(again["rgb"].values, out["rainy"]["rgb"].values)


def test_time_grids_units_and_store(tmp_path):
    sensors = [dict(CAM, rate_hz=3.0),
               {"kind": "lidar", "name": "lidar", "rate_hz": 7.0, "channels": 4, "horizontal_samples": 32},
               {"kind": "imu", "name": "imu", "rate_hz": 30.0}, {"kind": "gps", "name": "gps", "rate_hz": 1.5}]
    cfg = make_config([dict(CAM, name="mast", rate_hz=0.5)], sensors, duration=2.0)
    tree = render_sensor_frames(scene_of(GROUND, WALL), build_trajectory(cfg), cfg, "rainy")
    groups = {n.path: n.to_dataset() for n in tree.subtree if n.has_data}
    assert sorted(groups) == ["/bs0/mast", "/p0/cam", "/p0/gps", "/p0/imu", "/p0/lidar"]
    for path, ds in groups.items():
        rate = Fraction(str(ds.attrs["rate_hz"]))
        t = ds["time"].values
        assert t.dtype == np.int64 and ds["time"].attrs["units"] == "ns"
        expect = [int(i * 10**9 / rate) for i in range(len(t))]  # floor(i * 1e9 / rate), exact
        assert t.tolist() == expect and t[-1] <= 2 * 10**9 < t[-1] + 10**9 / rate, path
        for name, var in ds.data_vars.items():
            assert "units" in var.attrs and "long_name" in var.attrs, (path, name)
        for key in ("frame_id", "parent_frame_id", "sensor_kind", "weather", "mount_translation_m",
                    "mount_rpy_deg", "weather_visibility_m", "weather_lidar_dropout_probability"):
            assert key in ds.attrs, (path, key)
    assert groups["/p0/cam"]["rgb"].encoding["chunks"] == (1, 48, 64, 3)
    stores.write_store(tree, tmp_path / "rainy.zarr")
    back = stores.open_store(tmp_path / "rainy.zarr", tree=True)
    assert back["p0/cam"]["rgb"].encoding["chunks"] == (1, 48, 64, 3)
    assert back["p0/lidar"]["time"].dtype == np.int64
    np.testing.assert_array_equal(back["p0/cam"]["depth_m"].values, groups["/p0/cam"]["depth_m"].values)


def test_street_lamps_over_the_road_light_it_by_inverse_square():
    import dataclasses

    from simart_pipeline.config import Camera
    from simart_pipeline.sensing import camera
    from simart_pipeline.sensing.weather import NIGHT

    road = quad([(0, -3, 0.01), (60, -3, 0.01), (60, 3, 0.01), (0, 3, 0.01)], SemanticClass.ROAD, 5)
    meshes = scene_of(GROUND, road)
    lamps = camera.street_lamps(meshes, 30.0, 6.0)
    on = lamps.position_m[lamps.present]
    # Lattice from (0, -30): the road touches four 30 m cells, each gets the road point nearest its
    # centre ((15 | 45, -15 | 15)), i.e. on the road's edges, 6 m up.
    assert len(on) == 4 and lamps.present.sum() == 4
    np.testing.assert_allclose(np.sort(on[:, 0]), [15, 15, 45, 45], atol=3.0)
    assert np.all(np.abs(np.abs(on[:, 1]) - 3.0) < 1.0)
    np.testing.assert_allclose(on[:, 2], 6.01, atol=1e-6)
    assert camera.street_lamps(scene_of(GROUND), 30.0, 6.0) is None  # no road, no lamp

    # Only the street lamps light the scene: the road point under a camera looking straight down
    # shows albedo * sum_k I cos_k / r_k^2 over the four lamps (sRGB-encoded, 8 bit).
    wx = dataclasses.replace(NIGHT, ambient_rgb=(0.0, 0.0, 0.0), lamp_intensity_rgb=(0.0, 0.0, 0.0),
                             pixel_noise_std_dn=0.0, visibility_m=1e12)
    cam = Camera(kind="camera", name="cam", width_px=9, height_px=9, horizontal_fov_deg=10.0)
    caster = raycast.RayCaster(meshes)
    eye = np.array([20.0, -1.0, 30.0])
    down = Rotation.from_euler("y", 90.0, degrees=True) * frames.OPTICAL_TO_BODY
    ds = camera.render_camera(caster, cam, np.array([0]), eye[None], down, wx, np.random.default_rng(0))
    p = np.array([eye[0], eye[1], 0.01])
    hit = caster.intersect(eye[None], np.array([[0.0, 0.0, -1.0]]))
    assert hit.face[0] >= 0 and meshes.face_class[hit.face[0]] == SemanticClass.ROAD
    v = on - p
    r2 = (v ** 2).sum(1)
    cos = v[:, 2] / np.sqrt(r2)
    irradiance = np.asarray(wx.street_lamp_intensity_rgb)[None] * (cos / np.maximum(r2, 1.0))[:, None]
    linear = camera.face_albedo(meshes)[hit.face[0]] * irradiance.sum(0)
    expected = np.rint(255 * camera.srgb_encode(linear))
    np.testing.assert_allclose(ds["rgb"].values[0, 4, 4].astype(float), expected, atol=1.0)
    # A wide slab at 2.5-3.5 m between the road point and every lamp (6 m up) puts it in shadow.
    box = trimesh.creation.box(extents=(40.0, 40.0, 1.0))
    box.apply_translation((p[0], p[1], 3.0))
    roofed = scene_of(GROUND, road, (box, np.full(len(box.faces), SemanticClass.BUILDING, np.uint8),
                                     np.full(len(box.faces), WALL_ID, np.int64)))
    low = np.array([p[0], p[1], 1.0])
    dark = camera.render_camera(raycast.RayCaster(roofed), cam, np.array([0]), low[None], down, wx,
                                np.random.default_rng(0))
    np.testing.assert_array_equal(dark["rgb"].values[0, 4, 4], 0)
