"""The sensing stage: every sensor of every device of a scene, for one weather, as one tree.

:func:`render_sensor_frames` returns an ``xarray.DataTree`` with one group per sensor at
``/<device>/<sensor>`` (device = platform or base-station name). Each group has its own ``time``
coordinate (int64 ns, ``clock.sample_times_ns(duration, rate_hz)``), the sensor's variables (see
:mod:`.camera`, :mod:`.lidar`, :mod:`.inertial`) and attrs naming its frames, its mount, its kind and
rate, and the weather with the weather model's parameters (:mod:`.weather`).

Poses: a platform's base_link pose at a sensor's instants comes from ``trajectory.poses_at``; a base
station's base_link is static (``position_m``, Sionna ``orientation_deg`` = yaw about z, pitch about
y, roll about x). A sensor frame is base_link composed with the sensor's mount
(``translation_m``, ``rpy_deg`` in base_link); a camera's optical frame is its sensor frame
composed with ``frames.OPTICAL_TO_BODY``.

Randomness: each stream draws from its own ``np.random.default_rng([seed, h])`` with ``h`` the first
8 bytes of SHA-256 of ``"<device>/<sensor>/<weather>"``, so streams are reproducible and
independent of each other and of the order in which they are rendered.

The Mitsuba scene is built only when a camera or a LiDAR exists, once per call.
"""

from __future__ import annotations

import hashlib

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline import clock, frames
from simart_pipeline.config import BaseStation, Camera, Gps, Imu, Lidar, Platform, SceneConfig
from simart_pipeline.mobility.trajectory import poses_at
from simart_pipeline.vocabulary import AXES
from simart_pipeline.vocabulary import QUATERNION_COMPONENTS as QUAT
from simart_pipeline.scene.meshes import SceneMeshes
from simart_pipeline.sensing import camera, inertial, lidar, raycast
from simart_pipeline.sensing.weather import weather_model

SENSING_MODEL_VERSION = 1


def stream_seed(seed: int, device: str, sensor: str, weather: str) -> list[int]:
    """Entropy for ``np.random.default_rng`` of one stream (stable across processes)."""
    h = hashlib.sha256(f"{device}/{sensor}/{weather}".encode()).digest()
    return [int(seed) % (1 << 64), int.from_bytes(h[:8], "little")]


def stream_rng(seed: int, device: str, sensor: str, weather: str) -> np.random.Generator:
    return np.random.default_rng(stream_seed(seed, device, sensor, weather))


def base_station_rotation(bs: BaseStation) -> Rotation:
    """Rotation of a base station's base_link into world (Sionna yaw, pitch, roll)."""
    return frames.rotation_from_sionna_orientation(bs.orientation_deg, degrees=True)


def device_poses(device: Platform | BaseStation, traj: xr.Dataset | None, times_ns: np.ndarray
                 ) -> tuple[np.ndarray, Rotation, dict | None]:
    """base_link position [n, 3], rotation into world (n), and the full poses dict for a platform."""
    n = len(times_ns)
    if isinstance(device, Platform):
        p = poses_at(traj, device.name, times_ns)
        return p["position_m"], Rotation.from_quat(p["orientation_xyzw"]), p
    pos = np.tile(np.asarray(device.position_m, np.float64), (n, 1))
    q = base_station_rotation(device).as_quat()
    return pos, Rotation.from_quat(np.tile(q, (n, 1))), None


def mount_rotation(sensor) -> Rotation:
    return frames.rotation_from_rpy_deg(sensor.mount.rpy_deg)


def sensor_poses(pos_b: np.ndarray, rot_b: Rotation, sensor) -> tuple[np.ndarray, Rotation]:
    """Sensor frame origin [n, 3] and rotation into world from base_link poses and the mount."""
    pos = pos_b + rot_b.apply(np.asarray(sensor.mount.translation_m, np.float64))
    return pos.reshape(-1, 3), rot_b * mount_rotation(sensor)


def _group_attrs(device, sensor, weather_attrs: dict) -> dict:
    optical = isinstance(sensor, Camera)
    attrs = {
        "device": device.name,
        "device_kind": "platform" if isinstance(device, Platform) else "base_station",
        "sensor": sensor.name,
        "sensor_kind": sensor.kind,
        "rate_hz": sensor.rate_hz,
        "frame_id": frames.sensor_frame(device.name, sensor.name, optical=optical),
        "parent_frame_id": frames.base_link(device.name),
        "sensor_frame_id": frames.sensor_frame(device.name, sensor.name),
        "mount_translation_m": list(sensor.mount.translation_m),
        "mount_rpy_deg": list(sensor.mount.rpy_deg),
        "mount_quaternion_xyzw": mount_rotation(sensor).as_quat().tolist(),
        "mount_comment": "pose of sensor_frame_id in parent_frame_id: translation (m) and roll about x, "
                         "pitch about y, yaw about z (deg, extrinsic xyz)",
        "quaternion_order": frames.QUATERNION_ORDER,
    }
    if optical:
        attrs["optical_to_sensor_quaternion_xyzw"] = frames.OPTICAL_TO_BODY.as_quat().tolist()
        attrs["optical_comment"] = ("frame_id is the optical frame (z forward, x right, y down), "
                                    "rotated from sensor_frame_id by optical_to_sensor_quaternion_xyzw")
    attrs.update(weather_attrs)
    return attrs


def render_sensor_frames(meshes: SceneMeshes, traj: xr.Dataset, cfg: SceneConfig,
                         weather: str) -> xr.DataTree:
    """Render every sensor of ``cfg`` in ``weather``: a tree with a group per ``/<device>/<sensor>``."""
    wx = weather_model(weather)
    wx_attrs = wx.attrs()
    caster: raycast.RayCaster | None = None

    def get_caster() -> raycast.RayCaster:
        nonlocal caster
        if caster is None:
            caster = raycast.RayCaster(meshes)
        return caster

    groups: dict[str, xr.Dataset] = {}
    for device in (*cfg.platforms, *cfg.base_stations):
        for sensor in device.sensors:
            t_ns = clock.sample_times_ns(cfg.clock.duration_s, sensor.rate_hz)
            rng = stream_rng(cfg.seed, device.name, sensor.name, weather)
            pos_b, rot_b, poses = device_poses(device, traj, t_ns)
            if isinstance(sensor, Camera):
                pos_s, rot_s = sensor_poses(pos_b, rot_b, sensor)
                ds = camera.render_camera(get_caster(), sensor, t_ns, pos_s, rot_s * frames.OPTICAL_TO_BODY,
                                          wx, rng)
            elif isinstance(sensor, Lidar):
                pos_s, rot_s = sensor_poses(pos_b, rot_b, sensor)
                ds = lidar.render_lidar(get_caster(), sensor, t_ns, pos_s, rot_s, wx, rng)
            elif isinstance(sensor, Imu):
                ds = inertial.render_imu(sensor, t_ns, poses, rng)
            elif isinstance(sensor, Gps):
                ds = inertial.render_gps(sensor, t_ns, poses, cfg.origin, rng)
            else:  # pragma: no cover - the config schema admits no other kind
                raise TypeError(f"unknown sensor kind {type(sensor).__name__}")
            coords = {"time": ("time", t_ns.astype(np.int64),
                               dict(units="ns", long_name="simulated time since session start"))}
            if "axis" in ds.dims:
                coords["axis"] = AXES
            if "quaternion" in ds.dims:
                coords["quaternion"] = QUAT
            ds = ds.assign_coords(coords)
            ds.attrs.update(_group_attrs(device, sensor, wx_attrs))
            groups[f"/{device.name}/{sensor.name}"] = ds
    tree = xr.DataTree.from_dict(groups) if groups else xr.DataTree()
    tree.attrs.update(weather=weather, weather_description=wx.description, world_frame_id=frames.WORLD,
                      sensing_model_version=SENSING_MODEL_VERSION, scene=cfg.name, seed=cfg.seed)
    return tree
