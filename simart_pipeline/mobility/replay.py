"""Offline replay: a recorded trajectory (CSV or ROS bag) resampled onto the shared clock.

:func:`read_recording` reads what a platform's ``trajectory: {kind: replay}`` names, by file name:
a CSV (:func:`read_csv`), or a ROS1 bag, rosbag2 storage file or directory
(:func:`simart_pipeline.mobility.bags.read_bag_trajectory`), and moves it from the recording's
frame into the scene's world frame (``recording_frame``; identity by default, which leaves every
value untouched).

CSV layout (header required, one row per recorded pose, times strictly increasing):

- ``time_ns`` (int64) or ``time_s``; ``x_m, y_m, z_m``: base_link origin in the world frame (ENU);
- optional ``qx, qy, qz, qw``: rotation of base_link into world (scalar last); without it the
  heading follows the horizontal velocity and the platform stays level;
- optional ``vx_mps, vy_mps, vz_mps``: velocity in world; without it, the derivative of a cubic
  spline through the positions.

A bag's recording may also carry ``angular_velocity_radps`` (Odometry: base_link's, in base_link);
without it the angular rate comes from consecutive orientations.

Resampling: an instant that equals a recorded one takes the recorded values exactly (so a
trajectory exported at the pose rate and replayed gives the very same poses, and the very same
CIRs); between records, positions are cubic Hermite (with the velocities), velocities,
accelerations and recorded angular rates linear, orientations slerp; before the first and after
the last record the platform holds still at the end pose.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr
from scipy.interpolate import CubicHermiteSpline, CubicSpline
from scipy.spatial.transform import Rotation, Slerp

from simart_pipeline import clock, frames
from simart_pipeline.config import recording_format
from simart_pipeline.mobility import bags
from simart_pipeline.mobility.errors import ReplayError

POSITION = ("x_m", "y_m", "z_m")
QUATERNION = ("qx", "qy", "qz", "qw")
VELOCITY = ("vx_mps", "vy_mps", "vz_mps")


def read_recording(trajectory, scene_dir: str | Path) -> dict[str, np.ndarray]:
    """The recording a ``config.ReplayTrajectory`` names (relative to ``scene_dir``), in world.

    :returns: the layout of :func:`read_csv`; times are not yet offset (``resample`` does that).
    """
    path = Path(scene_dir) / trajectory.path
    if recording_format(trajectory.path) == "csv":
        rec = read_csv(path)
    else:
        rec = bags.read_bag_trajectory(path, trajectory.topic, stamp=trajectory.stamp or "header",
                                       time_origin=trajectory.time_origin,
                                       child_frame_id=trajectory.child_frame_id,
                                       parent_frame_id=trajectory.parent_frame_id)
    return to_world(rec, trajectory.recording_frame.translation_m, trajectory.recording_frame.rpy_deg)


def to_world(rec: dict[str, np.ndarray], translation_m=(0.0, 0.0, 0.0), rpy_deg=(0.0, 0.0, 0.0)
             ) -> dict[str, np.ndarray]:
    """A recording moved from its own frame into world, that frame's pose in world being
    ``translation_m`` and ``rpy_deg``; body-frame quantities (angular rate) stay as they are."""
    if not any(translation_m) and not any(rpy_deg):
        return rec  # identity: keep the recorded values bit for bit
    r = frames.rotation_from_rpy_deg(rpy_deg)
    out = dict(rec)
    out["position_m"] = r.apply(rec["position_m"]) + np.asarray(translation_m, np.float64)
    if "velocity_mps" in rec:
        out["velocity_mps"] = r.apply(rec["velocity_mps"])
    if "orientation_xyzw" in rec:
        out["orientation_xyzw"] = (r * Rotation.from_quat(rec["orientation_xyzw"])).as_quat()
    return out


def read_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Read a trajectory CSV: ``time_ns`` [n] int64, ``position_m`` [n, 3], optional
    ``orientation_xyzw`` [n, 4] and ``velocity_mps`` [n, 3]."""
    path = Path(path)
    try:
        with path.open() as f:
            header = [h.strip() for h in f.readline().strip().split(",")]
        table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=object)
    except (OSError, ValueError) as exc:
        raise ReplayError(f"{path}: cannot read the trajectory CSV: {exc}") from None
    if table.shape[1] != len(header):
        raise ReplayError(f"{path}: {table.shape[1]} columns per row but {len(header)} in the header")
    col = {h: i for i, h in enumerate(header)}
    missing = [c for c in POSITION if c not in col]
    if missing or ("time_ns" not in col and "time_s" not in col):
        raise ReplayError(f"{path}: the header needs time_ns (or time_s) and {', '.join(POSITION)}; "
                          f"missing {', '.join(missing) or 'a time column'}")
    try:
        if "time_ns" in col:
            t_ns = np.array([int(v) for v in table[:, col["time_ns"]]], np.int64)
        else:
            t_ns = np.array([clock.seconds_to_ns(v) for v in table[:, col["time_s"]]], np.int64)

        def block(names):
            return table[:, [col[c] for c in names]].astype(np.float64)

        out = {"time_ns": t_ns, "position_m": block(POSITION)}
        if all(c in col for c in QUATERNION):
            out["orientation_xyzw"] = block(QUATERNION)
        if all(c in col for c in VELOCITY):
            out["velocity_mps"] = block(VELOCITY)
    except ValueError as exc:
        raise ReplayError(f"{path}: not a number: {exc}") from None
    if len(t_ns) < 2:
        raise ReplayError(f"{path}: at least two recorded poses are needed, found {len(t_ns)}")
    if np.any(np.diff(t_ns) <= 0):
        i = int(np.argmax(np.diff(t_ns) <= 0)) + 1
        raise ReplayError(f"{path}: times must increase strictly; row {i + 1} does not")
    for k, v in out.items():
        if not np.all(np.isfinite(v)):
            raise ReplayError(f"{path}: {k} holds a non-finite value")
    if "orientation_xyzw" in out:
        norm = np.linalg.norm(out["orientation_xyzw"], axis=1)
        if np.any(np.abs(norm - 1) > 1e-3):
            raise ReplayError(f"{path}: quaternions must have unit norm (found {norm.min():.4f}..{norm.max():.4f})")
    return out


def write_csv(traj: xr.Dataset, platform: str, path: str | Path) -> None:
    """Write one platform of a ``trajectory`` dataset as a replayable CSV (full float precision)."""
    p = traj.sel(platform=platform)
    num = np.concatenate([p["position_m"].values, p["orientation_xyzw"].values,
                          p["velocity_mps"].values], axis=1)
    lines = [",".join(("time_ns",) + POSITION + QUATERNION + VELOCITY)]
    for t, row in zip(p["time"].values.astype(np.int64), num):
        lines.append(",".join([str(int(t))] + [repr(float(v)) for v in row]))
    Path(path).write_text("\n".join(lines) + "\n")


def resample(rec: dict[str, np.ndarray], times_ns: np.ndarray, time_offset_s: float = 0.0) -> dict[str, np.ndarray]:
    """Poses at ``times_ns`` in the layout of ``trajectory.evaluate_waypoints``."""
    t_rec_ns = rec["time_ns"] + clock.seconds_to_ns(time_offset_s)
    t_rec = clock.ns_to_seconds(t_rec_ns)
    q_ns = np.asarray(times_ns, np.int64)
    q = np.clip(clock.ns_to_seconds(q_ns), t_rec[0], t_rec[-1])
    moving = (q_ns >= t_rec_ns[0]) & (q_ns <= t_rec_ns[-1])
    pos_rec = rec["position_m"]
    vel_rec = rec.get("velocity_mps")
    spline = CubicSpline(t_rec, pos_rec, axis=0) if vel_rec is None else None
    if vel_rec is None:
        vel_rec = spline(t_rec, 1)
    pos = CubicHermiteSpline(t_rec, pos_rec, vel_rec, axis=0)(q)
    vel = np.stack([np.interp(q, t_rec, vel_rec[:, i]) for i in range(3)], axis=-1)
    acc_rec = np.gradient(vel_rec, t_rec, axis=0)
    acc = np.stack([np.interp(q, t_rec, acc_rec[:, i]) for i in range(3)], axis=-1)
    if "orientation_xyzw" in rec:
        rot_rec = Rotation.from_quat(rec["orientation_xyzw"])
    else:
        rot_rec = Rotation.from_euler("z", np.arctan2(vel_rec[:, 1], vel_rec[:, 0])[:, None])
    rot = Slerp(t_rec, rot_rec)(q)
    quat = rot.as_quat()
    if "angular_velocity_radps" in rec:  # recorded (Odometry twist): linear between records
        ang = np.stack([np.interp(q, t_rec, rec["angular_velocity_radps"][:, i]) for i in range(3)], axis=-1)
    else:
        # Body angular rate from consecutive records: rotvec of q_i^-1 q_{i+1} over the interval.
        dt = np.diff(t_rec)
        w_seg = (rot_rec[:-1].inv() * rot_rec[1:]).as_rotvec() / dt[:, None]
        seg = np.clip(np.searchsorted(t_rec, q, side="right") - 1, 0, len(dt) - 1)
        ang = w_seg[seg]
    # Exactly at a recorded instant: the recorded values, bit for bit.
    hit = np.searchsorted(t_rec_ns, q_ns)
    exact = (hit < len(t_rec_ns)) & (t_rec_ns[np.minimum(hit, len(t_rec_ns) - 1)] == q_ns)
    idx = hit[exact]
    pos[exact] = pos_rec[idx]
    vel[exact] = vel_rec[idx]
    if "orientation_xyzw" in rec:
        quat[exact] = rec["orientation_xyzw"][idx]
    if "angular_velocity_radps" in rec:
        ang[exact] = rec["angular_velocity_radps"][idx]
    vel[~moving] = 0.0
    acc[~moving] = 0.0
    ang[~moving] = 0.0
    return {"position_m": pos, "velocity_mps": vel, "acceleration_mps2": acc,
            "orientation_xyzw": quat, "angular_velocity_radps": ang}
