"""Devices: antenna arrays, sensors (one shared sensor base), base stations, platforms and their
dynamic limits."""

from __future__ import annotations

import math
from typing import Annotated, Literal, Union

from pydantic import Field, field_validator, model_validator

from simart_pipeline.config.actors import ActorKind, Body
from simart_pipeline.config.base import Vec2, Vec3, _Model, _rate_has_exact_clock
from simart_pipeline.config.trajectories import TrajectorySource
from simart_pipeline.vocabulary import STANDARD_GRAVITY_MPS2


class Array(_Model):
    """A uniform planar array in the y-z plane of its device, boresight +x (Sionna PlanarArray)."""

    rows: int = Field(1, ge=1)
    cols: int = Field(1, ge=1)
    spacing_wavelengths: float = Field(0.5, gt=0)
    pattern: Literal["iso", "dipole", "hw_dipole", "tr38901"] = "iso"
    polarization: Literal["V", "H"] = "V"

    @property
    def num_antennas(self) -> int:
        return self.rows * self.cols


class Mount(_Model):
    """Pose of a sensor in its parent's base_link: translation and roll/pitch/yaw (deg)."""

    translation_m: Vec3 = (0.0, 0.0, 0.0)
    rpy_deg: Vec3 = (0.0, 0.0, 0.0)
    sees_own_body: bool = Field(False, description="the sensor sees its own platform's body "
                                "(off: a camera under a drone does not film its own arms)")


class SensorBase(_Model):
    """What every sensor has: a name unique on its device, a rate on the shared clock (Hz; each
    kind sets its default) and its mount in the device's base_link."""

    name: str
    rate_hz: float
    mount: Mount = Mount()
    _rate = field_validator("rate_hz")(classmethod(lambda cls, v: _rate_has_exact_clock(v)))


class Camera(SensorBase):
    kind: Literal["camera"]
    rate_hz: float = 2.0
    width_px: int = Field(320, ge=8, le=8192)
    height_px: int = Field(240, ge=8, le=8192)
    horizontal_fov_deg: float = Field(90.0, gt=1, lt=179)
    max_depth_m: float = Field(500.0, gt=0)


class Lidar(SensorBase):
    kind: Literal["lidar"]
    rate_hz: float = 5.0
    channels: int = Field(16, ge=1, le=256)
    vertical_fov_deg: Vec2 = (-15.0, 15.0)
    horizontal_samples: int = Field(512, ge=8, le=8192)
    max_range_m: float = Field(120.0, gt=0)
    range_noise_std_m: float = Field(0.02, ge=0)


class Imu(SensorBase):
    kind: Literal["imu"]
    rate_hz: float = 100.0
    accel_noise_std_mps2: float = Field(0.02, ge=0)
    gyro_noise_std_radps: float = Field(0.002, ge=0)
    accel_bias_mps2: Vec3 = (0.0, 0.0, 0.0)
    gyro_bias_radps: Vec3 = (0.0, 0.0, 0.0)


class Gps(SensorBase):
    kind: Literal["gps"]
    rate_hz: float = 1.0
    horizontal_noise_std_m: float = Field(1.5, ge=0)
    vertical_noise_std_m: float = Field(3.0, ge=0)


Sensor = Annotated[Union[Camera, Lidar, Imu, Gps], Field(discriminator="kind")]


class Radar(_Model):
    """A monostatic OFDM radar at a base station: it transmits the scene's OFDM numerology from the
    base station's position and listens there (``receive_offset_m`` in the base station's frame
    moves the receive antenna: 0 is co-located). One frame of ``num_symbols`` OFDM symbols every
    ``1 / rate_hz`` s on the shared clock; processing: ``sensing/radar.py``, ``docs/actors.md``."""

    rate_hz: float = 2.0
    num_symbols: int = Field(256, ge=8, le=8192)
    window: Literal["hann", "rect"] = "hann"
    diffuse_reflection: bool = Field(
        True, description="trace diffuse scattering for the echoes (a small or curved body rarely "
        "has a face normal to the radar: without it most actors return no echo)")
    array: Array = Field(Array(rows=1, cols=1, pattern="iso"),
                         description="the radar's transmit and receive array (one antenna by default)")
    receive_offset_m: Vec3 = (0.0, 0.0, 0.0)
    _rate = field_validator("rate_hz")(classmethod(lambda cls, v: _rate_has_exact_clock(v)))


class BaseStation(_Model):
    name: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$")
    position_m: Vec3
    # Sionna orientation (alpha, beta, gamma) = yaw about z, pitch about y, roll about x; deg.
    orientation_deg: Vec3 = (0.0, 0.0, 0.0)
    array: Array = Array(rows=8, cols=8, pattern="tr38901")
    power_dbm: float = 30.0
    sensors: tuple[Camera, ...] = ()
    radar: Radar | None = None


class DynamicLimits(_Model):
    """Bounds a waypoint trajectory never exceeds (``docs/mobility.md``); defaults per platform kind
    in :data:`DEFAULT_LIMITS`, which a platform's ``limits`` overrides key by key.

    Accelerations exclude gravity. Tangential (along the path) and lateral (across it) are each
    capped by ``max_acceleration_mps2`` as well. The yaw limits shape turns in place (at stops);
    while moving, the heading follows the velocity. Heights are above the ground plane z = 0.
    """

    max_speed_mps: float = Field(gt=0, le=100)
    max_acceleration_mps2: float = Field(gt=0, le=100)
    max_tangential_acceleration_mps2: float = Field(gt=0, le=100)
    max_lateral_acceleration_mps2: float = Field(gt=0, le=100)
    max_jerk_mps3: float = Field(gt=0, le=1000)
    max_yaw_rate_radps: float = Field(gt=0, le=50)
    max_yaw_acceleration_radps2: float = Field(gt=0, le=500)
    min_height_above_ground_m: float | None = Field(None, description="UAV altitude band: lower bound")
    max_height_above_ground_m: float | None = Field(None, description="UAV altitude band: upper bound")


# Defaults per platform kind; where the numbers come from: docs/mobility.md, "Limits".
DEFAULT_LIMITS: dict[str, dict[str, float | None]] = {
    # PX4 multicopter auto mode: MPC_ACC_HOR 3 m s-2, MPC_ACC_HOR_MAX 5 m s-2, MPC_JERK_AUTO 4 m s-3,
    # MPC_YAWRAUTO_MAX 45 deg/s; top speed of small multirotors ~20 m s-1; EU 2019/947 open
    # category: at most 120 m above the ground.
    "uav": {"max_speed_mps": 20.0, "max_acceleration_mps2": 5.0, "max_tangential_acceleration_mps2": 3.0,
            "max_lateral_acceleration_mps2": 5.0, "max_jerk_mps3": 4.0, "max_yaw_rate_radps": 0.785,
            "max_yaw_acceleration_radps2": 1.57, "min_height_above_ground_m": 2.0,
            "max_height_above_ground_m": 120.0},
    # Urban car: 50 km/h; ISO 15622 (ACC) 2 m s-2 and 2.5 m s-3; ISO 11270 (lane keeping) 3 m s-2 lateral.
    "ground_vehicle": {"max_speed_mps": 13.9, "max_acceleration_mps2": 3.0,
                       "max_tangential_acceleration_mps2": 2.0, "max_lateral_acceleration_mps2": 3.0,
                       "max_jerk_mps3": 2.5, "max_yaw_rate_radps": 0.5, "max_yaw_acceleration_radps2": 0.5},
    # Walking: free speed ~1.34 m s-1 (Weidmann 1993), brisk walk up to 2.5 m s-1; gait starts and
    # turns of about 1 m s-2.
    "pedestrian": {"max_speed_mps": 2.5, "max_acceleration_mps2": 1.5, "max_tangential_acceleration_mps2": 1.0,
                   "max_lateral_acceleration_mps2": 1.0, "max_jerk_mps3": 2.0, "max_yaw_rate_radps": 1.5,
                   "max_yaw_acceleration_radps2": 3.0},
}


class Platform(_Model):
    name: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$")
    kind: ActorKind
    array: Array = Array()
    body: Body = Body()
    trajectory: TrajectorySource
    limits: DynamicLimits | None = Field(None, description="overrides of the kind's DEFAULT_LIMITS; "
                                         "always filled in after validation")
    sensors: tuple[Sensor, ...] = ()

    @model_validator(mode="before")
    @classmethod
    def _kind_defaults(cls, data):
        # The kind's defaults under whatever the config gives, key by key.
        if isinstance(data, dict) and data.get("kind") in DEFAULT_LIMITS:
            given = data.get("limits")
            if given is None or isinstance(given, dict):
                data = {**data, "limits": {**DEFAULT_LIMITS[data["kind"]], **(given or {})}}
        return data

    @model_validator(mode="after")
    def _within_limits(self):
        lim, tr = self.limits, self.trajectory
        if lim is None:  # only for a kind without defaults, which the schema refuses already
            return self
        band = (lim.min_height_above_ground_m, lim.max_height_above_ground_m)
        if self.kind != "uav":
            if band != (None, None):
                raise ValueError(f"platform {self.name}: limits: an altitude band applies to UAVs only")
        else:
            # A multirotor cannot accelerate downward faster than g without turning over.
            if lim.max_acceleration_mps2 >= STANDARD_GRAVITY_MPS2:
                raise ValueError(f"platform {self.name}: limits.max_acceleration_mps2 must stay below "
                                 f"g = {STANDARD_GRAVITY_MPS2} m/s2 for a multirotor")
            if None not in band and band[0] >= band[1]:
                raise ValueError(f"platform {self.name}: limits: min_height_above_ground_m must be below "
                                 "max_height_above_ground_m")
        if tr.kind != "waypoints":
            return self
        if tr.speed_mps > lim.max_speed_mps:
            raise ValueError(f"platform {self.name}: trajectory.speed_mps {tr.speed_mps} exceeds "
                             f"limits.max_speed_mps {lim.max_speed_mps} of a {self.kind}")
        if self.kind == "uav" and tr.follow_roads:
            raise ValueError(f"platform {self.name}: trajectory.follow_roads is for ground vehicles and pedestrians")
        lo = -math.inf if band[0] is None else band[0]
        hi = math.inf if band[1] is None else band[1]
        for k, w in enumerate(tr.waypoints_m):
            if not lo <= w[2] <= hi:
                raise ValueError(f"platform {self.name}: trajectory.waypoints_m.{k} {list(w)} is {w[2]} m "
                                 f"above the ground, outside its altitude band [{band[0]}, {band[1]}] m "
                                 "(limits.min/max_height_above_ground_m)")
        return self
