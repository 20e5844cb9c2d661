"""Actors in the sensors: a UAV seen by a base-station camera, a parked car hit by a LiDAR, the
own-body rule, and the per-frame ground truth against the analytic projection."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from simart_pipeline.config import SceneConfig
from simart_pipeline.mobility.trajectory import build_trajectory, poses_at
from simart_pipeline.scene import actors
from simart_pipeline.sensing.sensor_frames import render_sensor_frames
from simart_pipeline.vocabulary import ACTOR_INSTANCE_ID_BASE, SemanticClass
from tests.test_sensing import GROUND, ORIGIN, scene_of

UAV_AT = (20.0, 1.0, 4.0)


def config(plat_sensors=(), bs_sensors=(), static_actors=(), waypoints=(UAV_AT, (20.5, 1.0, 4.0)),
           kind="uav") -> SceneConfig:
    return SceneConfig.model_validate({
        "name": "t", "source": {"kind": "procedural"}, "origin": ORIGIN,
        "base_stations": [{"name": "bs0", "position_m": [0.0, 0.0, 10.0], "sensors": list(bs_sensors)}],
        "platforms": [{"name": "p0", "kind": kind, "sensors": list(plat_sensors),
                       "trajectory": {"waypoints_m": [list(w) for w in waypoints], "speed_mps": 0.2}}],
        "static_actors": list(static_actors), "clock": {"duration_s": 1.0}})


# Looking down at the UAV 6 m below and 20 m ahead.
BS_CAM = {"kind": "camera", "name": "cam", "rate_hz": 1.0, "width_px": 160, "height_px": 120,
          "horizontal_fov_deg": 8.0, "mount": {"rpy_deg": [0.0, float(np.degrees(np.arctan2(6.0, 20.0))), 0.0]}}


def test_base_station_camera_sees_the_uav_with_its_class_box_and_depth():
    cfg = config(bs_sensors=[BS_CAM])
    traj = build_trajectory(cfg)
    ds = render_sensor_frames(scene_of(GROUND), traj, cfg, "sunny")["bs0/cam"].to_dataset()
    uav = actors.scene_actors(cfg, None)[0]
    assert uav.instance_id == ACTOR_INSTANCE_ID_BASE
    for i, t in enumerate(ds["time"].values):
        inst = ds["instance_id"].values[i]
        mine = inst == uav.instance_id
        assert mine.sum() > 20
        assert np.all(ds["semantic_class"].values[i][mine] == SemanticClass.UAV)
        assert int(ds["actor_pixel_count"].values[i, 0]) == int(mine.sum())
        # Unoccluded and inside the image: the visible pixels' box is the projection of the mesh's
        # vertices, rounded to the pixel centres they cover (within one pixel).
        vis, proj = ds["actor_visible_box_px"].values[i, 0], ds["actor_projected_box_px"].values[i, 0]
        np.testing.assert_allclose(vis, proj, atol=1.0)
        # Depth: the z-depth of every UAV pixel lies within the body's bounding radius of the
        # z-depth of the body centre (the antenna point sits 8 cm straight above the centre).
        pose = poses_at(traj, "p0", np.array([t]))
        centre = pose["position_m"][0] - [0.0, 0.0, 0.08]
        eye = ds["position_m"].values[i]
        axis = Rotation.from_quat(ds["orientation_xyzw"].values[i]).apply([0.0, 0.0, 1.0])
        depth = ds["depth_m"].values[i][mine]
        assert np.all(np.abs(depth - (centre - eye) @ axis) <= uav.bounding_radius_m)
        assert depth.min() < (centre - eye) @ axis  # the near side is seen
        box_centre = centre + [0.0, 0.0, 0.015]  # the body's bounds span z -0.03 .. 0.06
        assert ds["actor_distance_m"].values[i, 0] == pytest.approx(np.linalg.norm(box_centre - eye), abs=1e-6)


def test_own_sensors_do_not_see_their_own_body_unless_the_mount_says_so():
    down = {"kind": "camera", "name": "down", "rate_hz": 1.0, "width_px": 32, "height_px": 32,
            "horizontal_fov_deg": 120.0, "mount": {"translation_m": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 90.0, 0.0]}}
    seeing = dict(down, name="down_self", mount=dict(down["mount"], sees_own_body=True))
    cfg = config(plat_sensors=[down, seeing])
    tree = render_sensor_frames(scene_of(GROUND), build_trajectory(cfg), cfg, "sunny")
    blind, self_seen = tree["p0/down"].to_dataset(), tree["p0/down_self"].to_dataset()
    assert not np.any(blind["semantic_class"].values == SemanticClass.UAV)
    assert np.all(blind["semantic_class"].values == SemanticClass.GROUND)
    centre = self_seen["semantic_class"].values[:, 16, 16]
    assert np.all(centre == SemanticClass.UAV)
    # The body box's top is 5 cm below the antenna point the camera sits on.
    np.testing.assert_allclose(self_seen["depth_m"].values[:, 16, 16], 0.05, atol=1e-4)


def test_lidar_returns_hit_a_parked_car_at_the_analytic_range():
    lidar = {"kind": "lidar", "name": "lidar", "rate_hz": 1.0, "channels": 1, "vertical_fov_deg": [-15.0, -15.0],
             "horizontal_samples": 360, "range_noise_std_m": 0.0}
    car = {"name": "parked", "kind": "ground_vehicle", "position_m": [10.0, 0.0, 0.0], "yaw_deg": 0.0}
    cfg = config(plat_sensors=[lidar], static_actors=[car], waypoints=((0.0, 0.0, 3.0), (0.5, 0.0, 3.0)))
    traj = build_trajectory(cfg)
    ds = render_sensor_frames(scene_of(GROUND), traj, cfg, "sunny")["p0/lidar"].to_dataset()
    for i, t in enumerate(ds["time"].values):
        pos = ds["position_m"].values[i]
        ahead = int(np.argmin(np.abs(ds["azimuth_rad"].values)))
        assert ds["semantic_class"].values[i, 0, ahead] == SemanticClass.VEHICLE
        # The beam at -15 deg meets the car's rear face, x = 10 - 4.5 / 2, at z = 3 - 2.25 tan 15.
        expected = (7.75 - pos[0]) / np.cos(np.deg2rad(15.0))
        assert ds["range_m"].values[i, 0, ahead] == pytest.approx(expected, abs=1e-3)
        behind = int(np.argmin(np.abs(ds["azimuth_rad"].values - np.pi)))
        assert ds["semantic_class"].values[i, 0, behind] == SemanticClass.GROUND


def test_actor_out_of_range_is_skipped_exactly():
    cam = dict(BS_CAM, max_depth_m=15.0)  # the UAV at 20 m lies beyond the far plane
    cfg = config(bs_sensors=[cam])
    ds = render_sensor_frames(scene_of(GROUND), build_trajectory(cfg), cfg, "sunny")["bs0/cam"].to_dataset()
    assert int(ds["actor_pixel_count"].sum()) == 0
    no_body = cfg.model_copy(update={"platforms": (cfg.platforms[0].model_copy(
        update={"body": cfg.platforms[0].body.model_copy(update={"mesh": "none"})}),)})
    ref = render_sensor_frames(scene_of(GROUND), build_trajectory(no_body), no_body, "sunny")["bs0/cam"].to_dataset()
    np.testing.assert_array_equal(ds["rgb"].values, ref["rgb"].values)


def test_validate_names_a_broken_body_file_and_an_actor_in_a_building(tiny_scene):
    import yaml

    from simart_pipeline.validation import scene_problems

    raw = yaml.safe_load((tiny_scene / "scene.yaml").read_text())
    (tiny_scene / "broken.ply").write_bytes(b"ply\nformat nonsense\n")
    raw["platforms"][0]["body"] = {"mesh": "broken.ply"}
    raw["static_actors"] = [{"name": "inside", "kind": "pedestrian", "position_m": [-15.0, 0.0, 0.0]}]
    (tiny_scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    _, problems = scene_problems(tiny_scene)
    assert any("platforms.0.body.mesh" in p and "broken.ply" in p for p in problems), problems
    assert any("static_actors.0.position_m" in p and "inside a building" in p for p in problems), problems


def test_aircraft_lights_add_their_radiance_to_the_uav_pixels_only(monkeypatch):
    """Night: the lights of an aircraft actor add ``aircraft_light_radiance_rgb`` (attenuated by the
    haze over the pixel's distance) to the linear value of its pixels, and nothing elsewhere."""
    import dataclasses

    from simart_pipeline.sensing import weather

    cfg = config(bs_sensors=[BS_CAM])
    traj = build_trajectory(cfg)
    quiet = dataclasses.replace(weather.NIGHT, pixel_noise_std_dn=0.0)
    frames = {}
    for lit in (True, False):
        wx = quiet if lit else dataclasses.replace(quiet, aircraft_light_radiance_rgb=(0.0, 0.0, 0.0))
        monkeypatch.setitem(weather.WEATHER_MODELS, "night", wx)
        frames[lit] = render_sensor_frames(scene_of(GROUND), traj, cfg, "night")["bs0/cam"].to_dataset()
    assert max(quiet.aircraft_light_radiance_rgb) > 0
    uav = frames[True]["semantic_class"].values == SemanticClass.UAV
    assert uav.sum() > 20
    lit, dark = (frames[k]["rgb"].values for k in (True, False))
    np.testing.assert_array_equal(lit[~uav], dark[~uav])

    def linear(dn):  # inverse sRGB of 8-bit values
        c = dn.astype(float) / 255.0
        return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)

    fog = np.exp(-frames[True]["depth_m"].values[uav] / quiet.visibility_m)[:, None]
    expected = linear(dark[uav]) + np.asarray(quiet.aircraft_light_radiance_rgb) * fog * quiet.exposure
    # One 8-bit step of sRGB at these levels is < 0.004 in linear units.
    np.testing.assert_allclose(linear(lit[uav]), np.minimum(expected, 1.0), atol=0.004)
