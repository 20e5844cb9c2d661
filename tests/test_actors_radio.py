"""Actors in the radio scene: a parked car removes the line of sight, a moving metal plate gives
the closed-form Doppler of a moving reflector, and the CIR marks which actor each bounce meets."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.constants as const
import trimesh

from conftest import LOS_SPECULAR
from simart_pipeline.config import SceneConfig
from simart_pipeline.mobility.trajectory import build_trajectory, poses_at
from simart_pipeline.radio import cirs as radio_cirs
from simart_pipeline.radio.tracer import NO_ACTOR, RadioScene
from simart_pipeline.scene import actors
from simart_pipeline.vocabulary import InteractionKind

FC = 3.5e9
ORIGIN = {"latitude_deg": 48.1372, "longitude_deg": 11.5755, "altitude_m": 519.0}
ISO = {"rows": 1, "cols": 1, "pattern": "iso", "polarization": "V"}


def config(platforms, static_actors=(), bs_at=(0.0, 0.0, 1.0), **rt) -> SceneConfig:
    return SceneConfig.model_validate({
        "name": "t", "source": {"kind": "procedural"}, "origin": ORIGIN,
        "base_stations": [{"name": "bs0", "position_m": list(bs_at), "array": ISO}],
        "platforms": [dict(p, array=ISO) for p in platforms], "static_actors": list(static_actors),
        "clock": {"duration_s": 1.0, "radio_rate_hz": 4.0},
        "ray_tracing": {"max_depth": 1, "samples_per_src": 100_000, **LOS_SPECULAR, **rt}})


def trace(cfg, scene_dir=None):
    radio = RadioScene.from_config(None, cfg)
    radio.add_actors(actors.scene_actors(cfg, scene_dir))
    traj = build_trajectory(cfg)
    return radio_cirs.trace_trajectory(radio, cfg, traj), traj


WALKER = {"name": "p0", "kind": "pedestrian",
          "trajectory": {"waypoints_m": [[20.0, 0.0, 1.0], [20.0, 0.2, 1.0]], "speed_mps": 0.05}}


def test_a_parked_car_across_the_line_of_sight_removes_it():
    car = {"name": "parked", "kind": "ground_vehicle", "position_m": [10.0, 0.0, 0.0], "yaw_deg": 90.0}
    blocked, _ = trace(config([WALKER], [car]))
    clear, _ = trace(config([WALKER], [dict(car, body={"mesh": "none"})]))
    assert clear["los"].any("path").all()
    assert not blocked["los"].any()
    # The walker's own body is never in its own link: with no other actor, one call of the static
    # scene; with the car, one call per instant.
    assert clear.attrs["trace_calls"] == 1 and blocked.attrs["trace_calls"] == blocked.sizes["time"]
    d = np.linalg.norm(clear["rx_position_m"] - clear["tx_position_m"], axis=-1)
    gain = (np.abs(clear["a"]) ** 2).sum(("rx_ant", "tx_ant", "path"))
    np.testing.assert_allclose(gain, (const.c / FC / (4 * np.pi * d)) ** 2, rtol=1e-3)


def test_moving_metal_plate_gives_the_closed_form_doppler(tmp_path):
    # A 6 m x 6 m plate whose normal is the carrier's x axis (a ground vehicle: it does not pitch as it
    # accelerates, a multirotor would), moving away from tx and rx along +x.
    plate = trimesh.Trimesh([[0, -3, -3], [0, 3, -3], [0, 3, 3], [0, -3, 3]], [[0, 1, 2], [0, 2, 3]], process=False)
    plate.export(tmp_path / "plate.ply")
    flyer = {"name": "plate", "kind": "ground_vehicle", "body": {"mesh": "plate.ply", "material": "metal",
                                                       "antenna_point_m": [0.0, 0.0, 0.0]},
             "trajectory": {"waypoints_m": [[0.0, 0.0, 10.0], [40.0, 0.0, 10.0]], "speed_mps": 5.0,
                            "follow_roads": False},
             "limits": {"max_acceleration_mps2": 9.0, "max_tangential_acceleration_mps2": 9.0,
                        "max_jerk_mps3": 500.0}}
    still = {"name": "rx", "kind": "pedestrian", "body": {"mesh": "none"},
             "trajectory": {"waypoints_m": [[-20.0, 5.0, 10.0], [-20.0, 5.0, 10.001]], "speed_mps": 0.001}}
    cfg = config([flyer, still], bs_at=(-20.0, -5.0, 10.0))
    ds, traj = trace(cfg, tmp_path)
    link = int(np.flatnonzero(ds["rx"].values == "rx")[0])
    wavelength = const.c / FC
    tx = np.array([-20.0, -5.0, 10.0])
    checked = 0
    for i, t in enumerate(ds["time"].values):
        pose = poses_at(traj, "plate", np.array([t]))
        x_p, v = pose["position_m"][0, 0], pose["velocity_mps"][0]
        rx = ds["rx_position_m"].values[i, link]
        via_plate = (ds["interaction_actor"].values[i, link, 0] == 0) & ds["valid"].values[i, link]
        assert via_plate.sum() == 1
        k = int(np.flatnonzero(via_plate)[0])
        assert ds["interaction"].values[i, link, 0, k] == InteractionKind.SPECULAR
        image = tx * [-1, 1, 1] + [2 * x_p, 0, 0]
        s = (x_p - image[0]) / (rx[0] - image[0])
        hit = image + s * (rx - image)
        ki = (hit - tx) / np.linalg.norm(hit - tx)
        ko = (rx - hit) / np.linalg.norm(rx - hit)
        expected = (ko - ki) @ v / wavelength
        assert ds["doppler_hz"].values[i, link, k] == pytest.approx(expected, abs=0.05)
        assert ds["tau_s"].values[i, link, k] == pytest.approx(
            (np.linalg.norm(hit - tx) + np.linalg.norm(rx - hit)) / const.c, rel=1e-6)
        checked += abs(expected) > 50  # the plate is moving, not at rest
        los = ds["los"].values[i, link]
        assert np.all(ds["interaction_actor"].values[i, link][:, los] == NO_ACTOR)
    assert checked >= 2
