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
from simart_pipeline.scene.meshes import semantic_flag_attrs
from simart_pipeline.sensing.raycast import RayBundle, RayCaster
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
                 rotation: Rotation, wx: WeatherModel, rng: np.random.Generator) -> xr.Dataset:
    """Every sweep of one LiDAR; ``position_m`` [n, 3] and ``rotation`` (sensor into world) per sweep."""
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
        t, face = bundle.cast(position_m[i], mats[i])
        t, face = t.reshape(rings, n_az), face.reshape(rings, n_az)
        ret = (face >= 0) & (t <= lidar.max_range_m)
        r = t
        if noise_std > 0:
            r = t + rng.standard_normal(t.shape, dtype=np.float32) * np.float32(noise_std)
        if wx.lidar_dropout_probability > 0:
            ret &= rng.random(t.shape, dtype=np.float32) >= np.float32(wx.lidar_dropout_probability)
        rng_m[i] = np.where(ret, np.maximum(r, 0.0), np.nan)
        sem[i] = np.where(ret, caster.meshes.face_class[np.where(ret, face, 0)], 0)
    points = (rng_m[..., None] * d_s.reshape(rings, n_az, 3)[None].astype(np.float32)).astype(np.float32)
    el, az = beam_angles(lidar)
    ds = xr.Dataset(
        {
            "range_m": (("time", "ring", "azimuth"), rng_m,
                        dict(units="m", long_name="range of the beam's return (with range noise)",
                             nan_means="no return: nothing within max_range_m, or dropped by the weather")),
            "valid": (("time", "ring", "azimuth"), ~np.isnan(rng_m),
                      dict(units="1", long_name="the beam returned (range_m, points_m and semantic_class defined)")),
            "points_m": (("time", "ring", "azimuth", "axis"), points,
                         dict(units="m", long_name="return point in the sensor frame (x fwd, y left, z up)",
                              nan_means="no return (see range_m)")),
            "semantic_class": (("time", "ring", "azimuth"), sem,
                               dict(units="1", long_name="semantic class of the surface hit",
                                    **semantic_flag_attrs(),
                                    comment="0 (unlabeled) where there is no return")),
            "position_m": (("time", "axis"), position_m.astype(np.float64),
                           dict(units="m", long_name="sensor frame origin in world (ENU) at the sweep")),
            "orientation_xyzw": (("time", "quaternion"), rotation.as_quat().reshape(n_t, 4),
                                 dict(units="1", long_name="unit quaternion rotating the sensor frame into "
                                                           "world at the sweep, scalar last")),
        },
        coords={
            "elevation_rad": ("ring", el, dict(units="rad", long_name="beam elevation above the sensor's "
                                                                      "x-y plane")),
            "azimuth_rad": ("azimuth", az, dict(units="rad", long_name="beam azimuth from +x towards +y")),
        },
    )
    for name in ("range_m", "valid", "semantic_class"):
        ds[name].encoding["chunks"] = (1, rings, n_az)
    ds["points_m"].encoding["chunks"] = (1, rings, n_az, 3)
    ds.attrs.update(channels=rings, horizontal_samples=n_az,
                    vertical_fov_deg=list(lidar.vertical_fov_deg), max_range_m=lidar.max_range_m,
                    range_noise_std_m=lidar.range_noise_std_m, effective_range_noise_std_m=noise_std,
                    dropout_probability=wx.lidar_dropout_probability,
                    pose_model="whole sweep from the pose at the sweep's instant (no motion distortion "
                               "within a sweep in this version)",
                    beam_model="one ray per beam, first return, no divergence, no intensity")
    return ds
