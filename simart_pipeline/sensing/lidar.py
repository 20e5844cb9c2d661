"""Spinning LiDAR: one sweep of ``channels`` rings x ``horizontal_samples`` azimuths per frame.

Sensor frame ``<device>/<sensor>``: x forward, y left, z up. Ring ``k`` points at elevation
``vertical_fov_deg[0] + k * (vertical_fov_deg[1] - vertical_fov_deg[0]) / (channels - 1)`` (one ring:
the middle of the field of view); azimuth ``j`` at ``2 pi j / horizontal_samples`` counter-clockwise
from +x (towards +y). A beam's unit direction is
``(cos el cos az, cos el sin az, sin el)``.

First version: the whole sweep is taken from the pose at the sweep's instant (no motion distortion
within a sweep), one ray per beam (no beam divergence), no intensity. A beam returns the first
surface within ``max_range_m``; its range gets Gaussian noise (``range_noise_std_m`` times the
weather's ``lidar_range_noise_factor``) and the weather may drop it (``lidar_dropout_probability``).
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline.config import Lidar
from simart_pipeline.sensing import contract
from simart_pipeline.sensing.raycast import ActorView, RayBundle, RayCaster
from simart_pipeline.sensing.weather import WeatherModel


def beam_angles(lidar: Lidar) -> tuple[np.ndarray, np.ndarray]:
    """(elevation [channels], azimuth [horizontal_samples]) in rad."""
    lo, hi = lidar.vertical_fov_deg
    if lidar.channels == 1:
        el = np.array([(lo + hi) / 2])
    else:
        el = np.linspace(lo, hi, lidar.channels)
    az = 2 * np.pi * np.arange(lidar.horizontal_samples) / lidar.horizontal_samples
    return np.deg2rad(el), az


def beam_directions(lidar: Lidar) -> np.ndarray:
    """[channels, horizontal_samples, 3] unit beam directions in the sensor frame."""
    el, az = beam_angles(lidar)
    ce = np.cos(el)[:, None]
    return np.stack([ce * np.cos(az)[None, :], ce * np.sin(az)[None, :],
                     np.broadcast_to(np.sin(el)[:, None], (len(el), len(az)))], axis=-1)


def render_lidar(caster: RayCaster, lidar: Lidar, times_ns: np.ndarray, position_m: np.ndarray,
                 rotation: Rotation, wx: WeatherModel, rng: np.random.Generator,
                 actors: ActorView | None = None) -> xr.Dataset:
    """Every sweep of one LiDAR; ``position_m`` [n, 3] and ``rotation`` (sensor into world) per sweep;
    ``actors``: the actors at the sweep instants (``caster.actors`` holds their layer)."""
    n_t = len(times_ns)
    rings, n_az = lidar.channels, lidar.horizontal_samples
    d_s = beam_directions(lidar).reshape(-1, 3)
    mats = rotation.as_matrix().reshape(n_t, 3, 3)
    rng_m = np.full((n_t, rings, n_az), np.nan, np.float32)
    sem = np.zeros((n_t, rings, n_az), np.uint8)
    noise_std = lidar.range_noise_std_m * wx.lidar_range_noise_factor
    bundle = RayBundle(caster, d_s)
    position_m = np.asarray(position_m, np.float64).reshape(n_t, 3)
    for i in range(n_t):  # in time order: the noise draws are the same however sweeps are split
        if actors is not None:
            actors.place(caster.actors, i, position_m[i], lidar.max_range_m)
        t, face = bundle.cast(position_m[i], mats[i])
        t, face = t.reshape(rings, n_az), face.reshape(rings, n_az)
        ret = (face >= 0) & (t <= lidar.max_range_m)
        r = t
        if noise_std > 0:
            r = t + rng.standard_normal(t.shape, dtype=np.float32) * np.float32(noise_std)
        if wx.lidar_dropout_probability > 0:
            ret &= rng.random(t.shape, dtype=np.float32) >= np.float32(wx.lidar_dropout_probability)
        rng_m[i] = np.where(ret, np.maximum(r, 0.0), np.nan)
        sem[i] = np.where(ret, caster.face_labels(face)[0], 0)
    points = (rng_m[..., None] * d_s.reshape(rings, n_az, 3)[None].astype(np.float32)).astype(np.float32)
    el, az = beam_angles(lidar)
    return contract.lidar_stream(
        times_ns, rng_m, points, ~np.isnan(rng_m), position_m, rotation.as_quat().reshape(n_t, 4),
        point_count=np.full(n_t, rings * n_az, np.int64), elevation_rad=el, azimuth_rad=az, semantic_class=sem,
        model=dict(channels=rings, horizontal_samples=n_az, vertical_fov_deg=list(lidar.vertical_fov_deg),
                   max_range_m=lidar.max_range_m, range_noise_std_m=lidar.range_noise_std_m,
                   effective_range_noise_std_m=noise_std, dropout_probability=wx.lidar_dropout_probability,
                   pose_model="whole sweep from the pose at the sweep's instant (no motion distortion "
                              "within a sweep in this version)",
                   beam_model="one ray per beam, first return, no divergence, no intensity",
                   layout="organised: ring x azimuth grid of the beams (elevation_rad, azimuth_rad)"))
