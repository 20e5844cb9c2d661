"""Platform trajectories on the shared clock.

First version: a waypoint trajectory is a C2 cubic spline through the waypoints, with knots at the
times a platform flying at ``speed_mps`` along the straight segments would reach them; before the
first knot and after the last the platform holds still. Heading follows the horizontal velocity,
roll and pitch stay zero (a level platform; the mobility issue adds attitude dynamics).

Dataset layout (``trajectory`` asset):

- dims ``platform``, ``time`` (int64 ns), ``axis`` (x, y, z), ``quaternion`` (x, y, z, w)
- ``position_m``, ``velocity_mps``, ``acceleration_mps2``: base_link origin in ``world`` (ENU)
- ``orientation_xyzw``: rotation of ``<platform>/base_link`` into ``world``
- ``angular_velocity_radps``: angular velocity of base_link, expressed in base_link
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr
from scipy.interpolate import CubicHermiteSpline, CubicSpline
from scipy.spatial.transform import Rotation, Slerp

from simart_pipeline import clock, frames
from simart_pipeline.config import Platform, SceneConfig

AXES = ["x", "y", "z"]
QUAT = ["x", "y", "z", "w"]
_EPS_SPEED = 1e-6


def waypoint_knots_s(platform: Platform) -> np.ndarray:
    """Knot times (s): start offset plus cumulative straight-line distance over speed."""
    wp = np.asarray(platform.trajectory.waypoints_m, dtype=np.float64)
    seg = np.linalg.norm(np.diff(wp, axis=0), axis=1)
    if np.any(seg <= 0):
        raise ValueError(f"platform {platform.name}: two consecutive waypoints coincide")
    return platform.trajectory.start_offset_s + np.concatenate([[0.0], np.cumsum(seg)]) \
        / platform.trajectory.speed_mps


def evaluate_waypoints(platform: Platform, t_s: np.ndarray) -> dict[str, np.ndarray]:
    """Position, velocity, acceleration, orientation and body angular rate at times ``t_s`` [n] s."""
    wp = np.asarray(platform.trajectory.waypoints_m, dtype=np.float64)
    knots = waypoint_knots_s(platform)
    spline = CubicSpline(knots, wp, axis=0, bc_type="natural")
    t = np.asarray(t_s, dtype=np.float64)
    moving = (t >= knots[0]) & (t <= knots[-1])
    tc = np.clip(t, knots[0], knots[-1])
    pos = spline(tc)
    vel = np.where(moving[:, None], spline(tc, 1), 0.0)
    acc = np.where(moving[:, None], spline(tc, 2), 0.0)
    # Heading from the horizontal velocity; where the platform stands still it keeps the heading
    # it had (at the start: the heading it is about to take).
    v_edge = spline(tc, 1)
    yaw = np.arctan2(v_edge[:, 1], v_edge[:, 0])
    vh2 = vel[:, 0] ** 2 + vel[:, 1] ** 2
    yaw_rate = np.where(vh2 > _EPS_SPEED,
                        (vel[:, 0] * acc[:, 1] - vel[:, 1] * acc[:, 0]) / np.maximum(vh2, _EPS_SPEED), 0.0)
    quat = Rotation.from_euler("z", yaw[:, None]).as_quat()  # scalar-last x, y, z, w
    ang = np.zeros_like(pos)
    ang[:, 2] = yaw_rate  # level platform: body z is world z
    return {"position_m": pos, "velocity_mps": vel, "acceleration_mps2": acc,
            "orientation_xyzw": quat, "angular_velocity_radps": ang}


def evaluate_platform(platform: Platform, t_ns: np.ndarray, scene_dir: Path | None) -> dict[str, np.ndarray]:
    """A platform's poses at ``t_ns``: from its waypoints, or replayed from its recording."""
    if platform.trajectory.kind == "replay":
        if scene_dir is None:
            raise ValueError(f"platform {platform.name}: a replayed trajectory needs the scene directory")
        from simart_pipeline.mobility import replay

        rec = replay.read_csv(Path(scene_dir) / platform.trajectory.path)
        return replay.resample(rec, t_ns, platform.trajectory.time_offset_s)
    return evaluate_waypoints(platform, clock.ns_to_seconds(t_ns))


def build_trajectory(cfg: SceneConfig, scene_dir: str | Path | None = None) -> xr.Dataset:
    """Sample every platform's trajectory at the pose rate of the shared clock."""
    t_ns = clock.sample_times_ns(cfg.clock.duration_s, cfg.clock.pose_rate_hz)
    per = [evaluate_platform(p, t_ns, scene_dir) for p in cfg.platforms]
    names = [p.name for p in cfg.platforms]

    def stack(key, comp):
        return (("platform", "time", comp), np.stack([d[key] for d in per]))

    ds = xr.Dataset(
        {
            "position_m": stack("position_m", "axis"),
            "velocity_mps": stack("velocity_mps", "axis"),
            "acceleration_mps2": stack("acceleration_mps2", "axis"),
            "orientation_xyzw": stack("orientation_xyzw", "quaternion"),
            "angular_velocity_radps": stack("angular_velocity_radps", "axis"),
        },
        coords={
            "platform": names,
            "time": ("time", t_ns, {"units": "ns", "long_name": "simulated time since session start"}),
            "axis": AXES,
            "quaternion": QUAT,
            "child_frame_id": ("platform", [frames.base_link(n) for n in names]),
        },
    )
    attrs = {
        "position_m": ("m", "base_link origin in world (ENU)"),
        "velocity_mps": ("m s-1", "base_link linear velocity in world"),
        "acceleration_mps2": ("m s-2", "base_link linear acceleration in world (gravity excluded)"),
        "orientation_xyzw": ("1", "unit quaternion rotating base_link into world, scalar last"),
        "angular_velocity_radps": ("rad s-1", "angular velocity of base_link, expressed in base_link"),
    }
    for k, (units, long_name) in attrs.items():
        ds[k].attrs.update(units=units, long_name=long_name, frame_id=frames.WORLD)
    ds["angular_velocity_radps"].attrs["frame_id"] = "<platform>/base_link"
    ds.attrs.update(frame_id=frames.WORLD, quaternion_order=frames.QUATERNION_ORDER,
                    pose_rate_hz=cfg.clock.pose_rate_hz,
                    model="; ".join(f"{p.name}: " + ("replayed from " + p.trajectory.path
                                                     if p.trajectory.kind == "replay" else
                                                     "cubic spline through waypoints, level, heading "
                                                     "along velocity") for p in cfg.platforms))
    return ds


def poses_at(traj: xr.Dataset, platform: str, times_ns: np.ndarray) -> dict[str, np.ndarray]:
    """Poses of ``platform`` at arbitrary clock instants, interpolated from the stored samples.

    Position by cubic Hermite interpolation with the stored velocities, velocity, acceleration and
    angular rate linearly, orientation by slerp; instants outside the stored span are clamped.
    :returns: the trajectory's variables as ``[n, 3]`` / ``[n, 4]`` float64 arrays.
    """
    p = traj.sel(platform=platform)
    t = clock.ns_to_seconds(p["time"].values)
    q = clock.ns_to_seconds(np.asarray(times_ns)).clip(t[0], t[-1])
    pos = p["position_m"].values
    out = {"position_m": CubicHermiteSpline(t, pos, p["velocity_mps"].values, axis=0)(q)}
    for k in ("velocity_mps", "acceleration_mps2", "angular_velocity_radps"):
        v = p[k].values
        out[k] = np.stack([np.interp(q, t, v[:, i]) for i in range(3)], axis=-1)
    out["orientation_xyzw"] = Slerp(t, Rotation.from_quat(p["orientation_xyzw"].values))(q).as_quat()
    return out


def check_clear_of_buildings(traj: xr.Dataset, geom, where: str = "") -> None:
    """Raise if any platform's sampled position lies inside a building."""
    from simart_pipeline.scene.geometry import inside_buildings

    for p in traj["platform"].values:
        xyz = traj["position_m"].sel(platform=p).values
        inside = inside_buildings(geom, xyz[:, 0], xyz[:, 1], xyz[:, 2])
        if inside.any():
            i = int(np.argmax(inside))
            t = int(traj["time"].values[i])
            raise ValueError(f"{where}: platform {p} is inside a building at t = {t} ns, "
                             f"position {np.round(xyz[i], 2).tolist()} m: move its waypoints")
