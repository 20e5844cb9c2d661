"""IMU and GPS of a platform, from its trajectory sampled at the sensor's clock instants.

IMU (frame ``<device>/<sensor>``, mounted in base_link with rotation ``R_bm`` = mount rpy):

    linear_acceleration = R_bm^T R_wb^T (a_world + [0, 0, g]) + accel_bias + N(0, accel_noise_std)
    angular_velocity    = R_bm^T omega_body                   + gyro_bias  + N(0, gyro_noise_std)

i.e. the specific force an accelerometer at rest reads as +g up (ROS ``sensor_msgs/Imu``
convention), with ``g = 9.80665 m s-2`` (standard gravity, no gravity model). First version: the
lever-arm terms of an IMU mounted off the base_link origin (``omega x (omega x r)`` and
``domega/dt x r``) are ignored, so the accelerations are those of the base_link origin; the noise
is white and Gaussian per sample with the configured standard deviation (no random walk); biases
are constant. ``orientation_xyzw`` is the true rotation of the IMU frame into world.

GPS: the antenna (base_link origin plus the mount translation, rotated into world) in ENU plus
Gaussian noise (``horizontal_noise_std_m`` per horizontal axis, east and north independently,
``vertical_noise_std_m`` up), converted to WGS84 latitude, longitude and ellipsoidal height about
the scene origin (``frames.enu_to_geodetic``). White noise per fix, no correlated error.
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline import frames
from simart_pipeline.config import Gps, Imu, WorldOrigin
from simart_pipeline.sensing import contract
from simart_pipeline.vocabulary import STANDARD_GRAVITY_MPS2



def render_imu(imu: Imu, times_ns: np.ndarray, poses: dict[str, np.ndarray],
               rng: np.random.Generator) -> xr.Dataset:
    """IMU samples from the platform's ``poses`` (``trajectory.poses_at`` output at ``times_ns``)."""
    n = len(times_ns)
    r_wb = Rotation.from_quat(poses["orientation_xyzw"])
    r_bm = frames.rotation_from_rpy_deg(imu.mount.rpy_deg)
    a_w = np.asarray(poses["acceleration_mps2"], np.float64)
    f_b = r_wb.inv().apply(a_w + np.array([0.0, 0.0, STANDARD_GRAVITY_MPS2]))
    f_i = r_bm.inv().apply(f_b).reshape(n, 3)
    w_i = r_bm.inv().apply(np.asarray(poses["angular_velocity_radps"], np.float64)).reshape(n, 3)
    acc = f_i + np.asarray(imu.accel_bias_mps2) + rng.normal(0.0, 1.0, (n, 3)) * imu.accel_noise_std_mps2
    gyr = w_i + np.asarray(imu.gyro_bias_radps) + rng.normal(0.0, 1.0, (n, 3)) * imu.gyro_noise_std_radps
    quat = (r_wb * r_bm).as_quat().reshape(n, 4)
    return contract.imu_stream(
        times_ns, acc, gyr, quat,
        linear_acceleration_covariance=contract.diagonal_covariance([imu.accel_noise_std_mps2] * 3, n),
        angular_velocity_covariance=contract.diagonal_covariance([imu.gyro_noise_std_radps] * 3, n),
        model=dict(gravity_mps2=STANDARD_GRAVITY_MPS2, accel_noise_std_mps2=imu.accel_noise_std_mps2,
                   gyro_noise_std_radps=imu.gyro_noise_std_radps, accel_bias_mps2=list(imu.accel_bias_mps2),
                   gyro_bias_radps=list(imu.gyro_bias_radps),
                   noise_model="constant bias + white Gaussian noise per sample (no random walk)",
                   lever_arm="ignored in this version: accelerations are those of the base_link origin"))


def render_gps(gps: Gps, times_ns: np.ndarray, poses: dict[str, np.ndarray], origin: WorldOrigin,
               rng: np.random.Generator) -> xr.Dataset:
    """GPS fixes from the platform's ``poses`` at ``times_ns``."""
    n = len(times_ns)
    r_wb = Rotation.from_quat(poses["orientation_xyzw"])
    true_enu = (np.asarray(poses["position_m"], np.float64)
                + r_wb.apply(np.asarray(gps.mount.translation_m, np.float64))).reshape(n, 3)
    std = np.array([gps.horizontal_noise_std_m, gps.horizontal_noise_std_m, gps.vertical_noise_std_m])
    noisy = true_enu + rng.normal(0.0, 1.0, (n, 3)) * std
    lla = frames.enu_to_geodetic(noisy, origin.latitude_deg, origin.longitude_deg, origin.altitude_m)
    return contract.gps_stream(
        times_ns, lla[:, 0], lla[:, 1], lla[:, 2], noisy, true_enu, origin, fix_valid=np.ones(n, bool),
        fix_status=np.zeros(n, np.int8), fix_service=np.ones(n, np.uint16),
        position_covariance_m2=contract.diagonal_covariance(std, n), position_covariance_type=np.full(n, 2, np.uint8),
        model=dict(horizontal_noise_std_m=gps.horizontal_noise_std_m, vertical_noise_std_m=gps.vertical_noise_std_m,
                   noise_model="white Gaussian per fix in ENU (per horizontal axis and vertical), "
                               "before the geodetic conversion"))
