"""The base station as a radar: a large metal plate at normal incidence, range R and radial speed
v, shows up in the range-Doppler map at (R, v) and its echo follows the radar equation."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.constants as const
import trimesh

from conftest import LOS_SPECULAR
from simart_pipeline import clock
from simart_pipeline.config import SceneConfig
from simart_pipeline.mobility.trajectory import build_trajectory, poses_at
from simart_pipeline.radio import radar_echoes
from simart_pipeline.scene import actors
from simart_pipeline.vocabulary import InteractionKind

FC = 3.5e9
ORIGIN = {"latitude_deg": 48.1372, "longitude_deg": 11.5755, "altitude_m": 519.0}
ISO = {"rows": 1, "cols": 1, "pattern": "iso", "polarization": "V"}


def test_plate_echo_at_range_and_speed_with_radar_equation_power(tmp_path):
    # A 20 m x 20 m plate facing the radar (its normal is the carrier's x axis), 60 m away and
    # receding along +x: its first Fresnel zone (radius sqrt(lambda R / 2) = 1.6 m) is well inside.
    plate = trimesh.Trimesh([[0, -10, -10], [0, 10, -10], [0, 10, 10], [0, -10, 10]], [[0, 1, 2], [0, 2, 3]],
                            process=False)
    plate.export(tmp_path / "plate.ply")
    cfg = SceneConfig.model_validate({
        "name": "t", "source": {"kind": "procedural"}, "origin": ORIGIN,
        "base_stations": [{"name": "bs0", "position_m": [0.0, 0.0, 20.0], "array": ISO,
                           "radar": {"rate_hz": 2.0, "num_symbols": 512}}],
        "platforms": [{"name": "plate", "kind": "ground_vehicle", "array": ISO,
                       "body": {"mesh": "plate.ply", "material": "metal", "antenna_point_m": [0.0, 0.0, 0.0],
                                "scattering_coefficient": 0.0},
                       "trajectory": {"waypoints_m": [[60.0, 0.0, 20.0], [200.0, 0.0, 20.0]], "speed_mps": 12.0,
                                      "follow_roads": False}}],
        "clock": {"duration_s": 1.5}, "ray_tracing": {"max_depth": 1, "samples_per_src": 100_000, **LOS_SPECULAR}})
    radio = radar_echoes.radar_scene(None, cfg, "sunny")
    radio.add_actors(actors.scene_actors(cfg, tmp_path))
    traj = build_trajectory(cfg)
    ds = radar_echoes.radar_frames(radio, cfg, traj)["bs0"].to_dataset()
    wavelength = const.c / FC
    rd = ds["range_doppler_power_db"]
    assert ds.sizes["time"] == len(clock.sample_times_ns(1.5, 2.0))
    for i, t in enumerate(ds["time"].values):
        pose = poses_at(traj, "plate", np.array([t]))
        r, v = pose["position_m"][0, 0], pose["velocity_mps"][0, 0]
        assert ds["actor_range_m"].values[i, 0] == pytest.approx(r, abs=1e-9)
        assert ds["actor_radial_velocity_mps"].values[i, 0] == pytest.approx(v, abs=1e-9)
        echo = ds["valid"].values[i] & (ds["interaction_actor"].values[i, 0] == 0)
        assert echo.sum() == 1
        k = int(np.flatnonzero(echo)[0])
        assert ds["tau_s"].values[i, k] == pytest.approx(2 * r / const.c, rel=1e-6)
        assert ds["doppler_hz"].values[i, k] == pytest.approx(-2 * v / wavelength, abs=0.05)
        # Radar equation, isotropic antennas: P_r / P_t = lambda^2 sigma / ((4 pi)^3 R^4), with the
        # plate acting as a mirror: sigma = pi R^2, i.e. (lambda / (8 pi R))^2 (|Gamma| ~ 1 for metal).
        gain_db = 10 * np.log10(np.abs(ds["a"].values[i, 0, 0, k]) ** 2)
        radar_eq_db = 10 * np.log10(wavelength ** 2 * np.pi * r ** 2 / ((4 * np.pi) ** 3 * r ** 4))
        assert gain_db == pytest.approx(radar_eq_db, abs=0.1)
        # The map's peak: within one bin of (R, v); its power at most the echo's gain and no lower
        # than the worst off-bin loss of a Hann window in both dimensions (2 x 1.42 dB).
        cell = np.unravel_index(int(np.argmax(rd.values[i])), rd.shape[1:])
        assert abs(ds["range_m"].values[cell[0]] - r) <= rd.attrs["range_resolution_m"]
        assert abs(ds["radial_velocity_mps"].values[cell[1]] - v) <= rd.attrs["velocity_resolution_mps"]
        assert gain_db - 2.9 <= float(rd.values[i][cell]) <= gain_db + 0.01


def test_a_scene_without_radar_traces_nothing():
    cfg = SceneConfig.model_validate({
        "name": "t", "source": {"kind": "procedural"}, "origin": ORIGIN,
        "base_stations": [{"name": "bs0", "position_m": [0.0, 0.0, 20.0]}],
        "platforms": [{"name": "p", "kind": "uav", "trajectory": {"waypoints_m": [[0, 0, 5], [5, 0, 5]], "speed_mps": 1.0}}],
        "clock": {"duration_s": 1.0}})
    assert radar_echoes.radar_base_stations(cfg) == []
    tree = radar_echoes.radar_frames(None, cfg, None)
    assert not tree.children and tree.attrs["radars"] == "none"


def test_a_car_echoes_by_diffuse_scattering_at_its_range_and_radial_velocity():
    """A car has no face normal to the radar, so it echoes by scattering: every echo via it lies
    within the car's extent of its true range, with the Doppler of its true radial velocity (a
    translating body: every point moves alike, the projection changes by the angle it spans)."""
    cfg = SceneConfig.model_validate({
        "name": "t", "source": {"kind": "procedural"}, "origin": ORIGIN,
        "base_stations": [{"name": "bs0", "position_m": [0.0, 0.0, 20.0], "array": ISO, "radar": {"rate_hz": 2.0}}],
        "platforms": [{"name": "car", "kind": "ground_vehicle", "array": ISO,
                       "trajectory": {"waypoints_m": [[60.0, 0.0, 1.5], [200.0, 0.0, 1.5]], "speed_mps": 12.0,
                                      "follow_roads": False}}],
        "clock": {"duration_s": 1.5}, "ray_tracing": {"max_depth": 1, "samples_per_src": 1_000_000, **LOS_SPECULAR}})
    radio = radar_echoes.radar_scene(None, cfg, "sunny")
    car = actors.scene_actors(cfg, None)
    radio.add_actors(car)
    ds = radar_echoes.radar_frames(radio, cfg, build_trajectory(cfg))["bs0"].to_dataset()
    wavelength = const.c / FC
    half_extent = car[0].bounding_radius_m
    for i in range(ds.sizes["time"]):
        echo = ds["valid"].values[i] & (ds["interaction_actor"].values[i, 0] == 0)
        assert echo.sum() >= 1
        r, v = ds["actor_range_m"].values[i, 0], ds["actor_radial_velocity_mps"].values[i, 0]
        ranges = ds["tau_s"].values[i][echo] * const.c / 2
        assert np.all(np.abs(ranges - r) <= half_extent)
        speeds = -ds["doppler_hz"].values[i][echo] * wavelength / 2
        np.testing.assert_allclose(speeds, v, atol=0.01 + 0.02 * abs(v))
        assert np.all(ds["interaction"].values[i, 0][echo] == InteractionKind.DIFFUSE)
