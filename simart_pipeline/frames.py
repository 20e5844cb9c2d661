"""The one frame convention: a local ENU world frame per scene, REP 105/103 frame names.

- ``world``: x east, y north, z up (m), origin at the scene's WGS84 origin.
- ``<device>/base_link``: x forward, y left, z up (REP 103), pose given as a transform to world.
- ``<device>/<sensor>``: the sensor body frame, x forward; ``<device>/<sensor>_optical``: camera
  optical frame, z forward, x right, y down (REP 103 ``_optical`` suffix).
Quaternions are stored scalar-last ``(x, y, z, w)`` as in ROS ``geometry_msgs/Quaternion``
(``vocabulary.QUATERNION_ORDER``).
"""

from __future__ import annotations

import numpy as np
import pymap3d
from scipy.spatial.transform import Rotation

WORLD = "world"

# Rotation from a camera optical frame (z fwd, x right, y down) to its body frame (x fwd, y left, z up).
OPTICAL_TO_BODY = Rotation.from_matrix(np.array([[0.0, 0.0, 1.0],
                                                  [-1.0, 0.0, 0.0],
                                                  [0.0, -1.0, 0.0]]))


def base_link(device: str) -> str:
    return f"{device}/base_link"


def sensor_frame(device: str, sensor: str, optical: bool = False) -> str:
    return f"{device}/{sensor}_optical" if optical else f"{device}/{sensor}"


def rotation_from_rpy_deg(rpy_deg) -> Rotation:
    """Roll about x, pitch about y, yaw about z (extrinsic xyz = intrinsic ZYX), degrees."""
    return Rotation.from_euler("xyz", np.asarray(rpy_deg, dtype=float), degrees=True)


def rotation_from_sionna_orientation(yaw_pitch_roll, degrees: bool = False) -> Rotation:
    """Sionna RT orientation ``[..., 3] = (yaw about z, pitch about y, roll about x)`` as the
    rotation of the device's own frame into world, ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    return Rotation.from_euler("ZYX", np.asarray(yaw_pitch_roll, dtype=np.float64), degrees=degrees)


def sionna_orientation(rotation: Rotation) -> np.ndarray:
    """Inverse of :func:`rotation_from_sionna_orientation`: ``[..., 3]`` (yaw, pitch, roll), rad."""
    return rotation.as_euler("ZYX")


def enu_to_geodetic(enu_m: np.ndarray, lat0_deg: float, lon0_deg: float, alt0_m: float) -> np.ndarray:
    """``[..., 3]`` ENU (m) around the origin to ``[..., 3]`` (lat deg, lon deg, alt m) on WGS84."""
    e, n, u = np.moveaxis(np.asarray(enu_m, dtype=np.float64), -1, 0)
    lat, lon, alt = pymap3d.enu2geodetic(e, n, u, lat0_deg, lon0_deg, alt0_m)
    return np.stack([lat, lon, alt], axis=-1)


def geodetic_to_enu(lla: np.ndarray, lat0_deg: float, lon0_deg: float, alt0_m: float) -> np.ndarray:
    """Inverse of :func:`enu_to_geodetic`."""
    lat, lon, alt = np.moveaxis(np.asarray(lla, dtype=np.float64), -1, 0)
    e, n, u = pymap3d.geodetic2enu(lat, lon, alt, lat0_deg, lon0_deg, alt0_m)
    return np.stack([e, n, u], axis=-1)
