"""Platform trajectories on the shared clock.

A waypoint trajectory respects its platform's dynamic limits (``config.DynamicLimits``; the model
and its defaults: ``docs/mobility.md``): the waypoints, or for ground vehicles the road route
through them (:mod:`.roads`), become a path of straight segments and continuous-curvature corner
blends within ``waypoint_tolerance_m`` of each waypoint (:mod:`.path`); the platform moves along it
from rest to rest with a jerk-limited speed profile that slows down in turns (:mod:`.dynamics`).
It waits at its first waypoint until ``start_offset_s`` and stays at its last one after arriving.
A UAV's attitude is a quadrotor's (body z along the thrust ``a + g``), ground vehicles and
pedestrians stay level; the heading follows the horizontal velocity (:mod:`.attitude`).

Dataset layout (``trajectory`` asset):

- dims ``platform``, ``time`` (int64 ns), ``axis`` (x, y, z), ``quaternion`` (x, y, z, w)
- ``position_m``, ``velocity_mps``, ``acceleration_mps2``: base_link origin in ``world`` (ENU)
- ``orientation_xyzw``: rotation of ``<platform>/base_link`` into ``world``
- ``angular_velocity_radps``: angular velocity of base_link, expressed in base_link
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.interpolate import CubicHermiteSpline
from scipy.spatial.transform import Rotation, Slerp

from simart_pipeline import clock, frames
from simart_pipeline.config import Platform, SceneConfig
from simart_pipeline.mobility import dynamics, path, roads
from simart_pipeline.vocabulary import AXES, QUATERNION_COMPONENTS, QUATERNION_ORDER

POSE_KEYS = ("position_m", "velocity_mps", "acceleration_mps2", "orientation_xyzw", "angular_velocity_radps")
CAR_MIN_ROAD_WIDTH_M = 3.0  # narrower centre lines are footways, cycleways and paths (osm_tags widths)


def _may_follow_roads(platform: Platform) -> bool:
    """Whether the platform follows roads wherever the scene has them (before looking at the scene)."""
    tr = platform.trajectory
    return tr.kind == "waypoints" and platform.kind != "uav" and (
        tr.follow_roads or (tr.follow_roads is None and platform.kind == "ground_vehicle"))


def follows_roads(platform: Platform, geom) -> bool:
    """Whether the platform's waypoints are joined along roads: ``follow_roads``, or by default for
    ground vehicles when ``geom`` (the source geometry) has road centre lines."""
    if not _may_follow_roads(platform):
        return False
    if platform.trajectory.follow_roads is None:
        return geom is not None and bool(roads.road_lines(geom)[0])
    return True


def waypoint_path(platform: Platform, geom=None) -> tuple[path.CornerPath, roads.Route | None]:
    """The corner-blended path of a waypoint platform, and its road route when it follows roads."""
    tr = platform.trajectory
    where = f"platform {platform.name}"
    wp = np.asarray(tr.waypoints_m, dtype=np.float64)  # consecutive ones apart: config check
    if not follows_roads(platform, geom):
        return path.corner_path(wp, np.full(len(wp), tr.waypoint_tolerance_m)), None
    if geom is None:
        raise ValueError(f"{where}: following roads needs the scene's source geometry")
    min_width = tr.min_road_width_m
    if min_width is None:
        min_width = CAR_MIN_ROAD_WIDTH_M if platform.kind == "ground_vehicle" else 0.0
    route = roads.route_through(geom, wp, min_width_m=min_width, max_snap_m=tr.max_road_snap_distance_m,
                                waypoint_tolerance_m=tr.waypoint_tolerance_m, where=where)
    if len(route.points_m) < 2:
        raise roads.RoadError(f"{where}: every waypoint snaps to the same point of the road")
    return path.corner_path(route.points_m, route.tolerance_m), route


def plan_platform(platform: Platform, geom=None) -> dynamics.MotionPlan:
    """The motion of a waypoint platform under its limits (:func:`dynamics.plan_motion`)."""
    tr = platform.trajectory
    cp, _ = waypoint_path(platform, geom)
    plan = dynamics.plan_motion(cp, platform.limits, tr.speed_mps,
                                "thrust" if platform.kind == "uav" else "level", tr.start_offset_s)
    lo, hi = platform.limits.min_height_above_ground_m, platform.limits.max_height_above_ground_m
    z = plan.segment_samples()["position_m"][:, 2]
    if (lo is not None and z.min() < lo - 1e-9) or (hi is not None and z.max() > hi + 1e-9):
        raise ValueError(f"platform {platform.name}: the path leaves the altitude band [{lo}, {hi}] m "
                         f"(z from {z.min():.2f} to {z.max():.2f} m)")
    return plan


def evaluate_waypoints(platform: Platform, t_s: np.ndarray, geom=None,
                       plan: dynamics.MotionPlan | None = None) -> dict[str, np.ndarray]:
    """Position, velocity, acceleration, orientation and body angular rate at times ``t_s`` [n] s
    (``plan``: the platform's :func:`plan_platform`, if the caller has it already)."""
    state = (plan or plan_platform(platform, geom)).evaluate(t_s)
    return {k: state[k] for k in POSE_KEYS}


def evaluate_platform(platform: Platform, t_ns: np.ndarray, scene_dir: Path | None,
                      geom=None, plan: dynamics.MotionPlan | None = None) -> dict[str, np.ndarray]:
    """A platform's poses at ``t_ns``: from its waypoints, or replayed from its recording."""
    if platform.trajectory.kind == "replay":
        if scene_dir is None:
            raise ValueError(f"platform {platform.name}: a replayed trajectory needs the scene directory")
        from simart_pipeline.mobility import replay

        return replay.replay_platform(platform, t_ns, scene_dir)  # CSV or bag, by file name
    return evaluate_waypoints(platform, clock.ns_to_seconds(t_ns), geom, plan)


def build_trajectory(cfg: SceneConfig, scene_dir: str | Path | None = None, geom=None) -> xr.Dataset:
    """Sample every platform's trajectory at the pose rate of the shared clock.

    :param scene_dir: the scene directory, for replayed recordings.
    :param geom: the scene's source geometry (the ``osm_extract`` stage), needed when a platform may
        follow roads; this stage never builds it itself.
    """
    if geom is None:
        needs = [p.name for p in cfg.platforms if _may_follow_roads(p)]
        if needs:
            raise ValueError(f"scene {cfg.name}: platform(s) {', '.join(needs)} follow roads: pass the scene's "
                             "source geometry (geom=, the osm_extract stage), or set follow_roads: false")
    t_ns = clock.sample_times_ns(cfg.clock.duration_s, cfg.clock.pose_rate_hz)
    plans = {p.name: plan_platform(p, geom) for p in cfg.platforms if p.trajectory.kind == "waypoints"}
    per = [evaluate_platform(p, t_ns, scene_dir, geom, plans.get(p.name)) for p in cfg.platforms]
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
            "quaternion": QUATERNION_COMPONENTS,
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
    ds.attrs.update(frame_id=frames.WORLD, quaternion_order=QUATERNION_ORDER,
                    pose_rate_hz=cfg.clock.pose_rate_hz,
                    model="; ".join(f"{p.name}: " + ("replayed from " + p.trajectory.path
                                                     if p.trajectory.kind == "replay" else
                                                     _waypoint_model(p, geom)) for p in cfg.platforms),
                    dynamics=json.dumps({p.name: _plan_summary(p, plans[p.name], geom) for p in cfg.platforms
                                         if p.name in plans}, sort_keys=True))
    return ds


def _waypoint_model(p: Platform, geom) -> str:
    route = "along roads through" if follows_roads(p, geom) else "through"
    att = "quadrotor attitude (body z along a + g)" if p.kind == "uav" else "level"
    return (f"jerk-limited motion from rest to rest {route} waypoints, clothoid corner blends, "
            f"{att}, heading along the horizontal velocity (docs/mobility.md)")


def _plan_summary(p: Platform, plan: dynamics.MotionPlan, geom) -> dict:
    """What the stored trajectory's provenance says about a waypoint platform's motion."""
    return {"motion_start_s": plan.start_s, "motion_end_s": round(plan.end_s, 9),
            "path_length_m": round(plan.path.total_length_m, 6), "time_scaling": plan.time_scaling,
            "follows_roads": follows_roads(p, geom), "limits": p.limits.model_dump(),
            "limit_ratios": {k: round(v, 9) for k, v in plan.limit_ratios().items()}}


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


def check_clear_of_buildings(traj: xr.Dataset, geom, where: str = "", replayed=()) -> None:
    """Raise if any platform's sampled position lies inside a building (``replayed``: the names of
    platforms replayed from a recording, whose message speaks of the recording, not of waypoints)."""
    from simart_pipeline.scene.geometry import inside_buildings

    for p in traj["platform"].values:
        xyz = traj["position_m"].sel(platform=p).values
        inside = inside_buildings(geom, xyz[:, 0], xyz[:, 1], xyz[:, 2])
        if inside.any():
            i = int(np.argmax(inside))
            t = int(traj["time"].values[i])
            what = ("check its recording and trajectory.recording_frame (where the recording's frame sits in "
                    "the scene)" if p in set(replayed) else "move its waypoints")
            raise ValueError(f"{where}: platform {p} is inside a building at t = {t} ns, "
                             f"position {np.round(xyz[i], 2).tolist()} m: {what}")
