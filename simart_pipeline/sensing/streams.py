"""Poses and random streams of the sensors (the stage itself: :mod:`.sensor_frames`).

Poses: a platform's base_link pose at a sensor's instants comes from ``trajectory.poses_at``; a base
station's base_link is static (``position_m``, Sionna ``orientation_deg`` = yaw about z, pitch about
y, roll about x). A sensor frame is base_link composed with the sensor's mount
(``translation_m``, ``rpy_deg`` in base_link); a camera's optical frame is its sensor frame
composed with ``frames.OPTICAL_TO_BODY``.

Randomness: each stream draws from its own ``np.random.default_rng([seed, h])`` with ``h`` the first
8 bytes of SHA-256 of ``"<device>/<sensor>/<weather>"``, so streams are reproducible and
independent of each other and of the order in which they are rendered.
"""

from __future__ import annotations

import hashlib

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline import frames
from simart_pipeline.config import BaseStation, Platform
from simart_pipeline.mobility.trajectory import poses_at


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


def device_kind(device: Platform | BaseStation) -> str:
    return "platform" if isinstance(device, Platform) else "base_station"
