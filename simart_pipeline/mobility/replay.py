"""Offline replay: a recorded trajectory (CSV or ROS bag) resampled onto the shared clock.

:func:`read_recording` reads what a platform's ``trajectory: {kind: replay}`` names, by file name:
a CSV (:func:`read_csv`), or a ROS1 bag, rosbag2 storage file or directory
(:func:`simart_pipeline.mobility.bags.read_bag_trajectory`), moves it from the recording's frame
into the scene's world frame (``recording_frame``; identity by default, which leaves every value
untouched), and applies the stamp rules of :func:`clean`. :func:`replay_platform` is the one entry:
read, clean, resample, check against the platform's dynamic limits (:func:`check_limits`).

CSV layout (header required, one row per recorded pose):

- ``time_ns`` (int64) or ``time_s``; ``x_m, y_m, z_m``: base_link origin in the world frame (ENU);
- optional ``qx, qy, qz, qw``: rotation of base_link into world (scalar last); without it the
  heading follows the horizontal velocity and the platform stays level;
- optional ``vx_mps, vy_mps, vz_mps``: velocity in world.

A bag's recording may also carry ``angular_velocity_radps`` (Odometry: base_link's, in base_link);
without it the angular rate comes from consecutive orientations.

Stamp rules (:func:`clean`, the same for CSVs and bags; ``docs/mobility.md``, "Replay"):

- out of order: sorted by stamp (header stamps say when a pose was taken, not when it arrived);
- repeated stamp, same values: kept once; repeated stamp, another pose: refused;
- jitter: poses closer in time than ``JITTER_FRACTION`` of the recording's median interval (arrival
  bursts of record times) are one pose: their mean time, position, velocity and orientation, so a
  burst can never imply a speed its poses do not have;
- gaps longer than the replay's ``max_gap_s``: refused, naming the gap;
- two sources on one topic (poses that jump to another track and back, at least twice): refused.

Resampling never invents motion: between two recorded poses the position moves on the straight
segment between them (linear interpolation, so it stays inside their convex hull) and an instant
that equals a recorded one takes the recorded values bit for bit (an exported trajectory replayed at
the pose rate gives the very same poses and CIRs). Velocity is the recorded one (Odometry twist, CSV
velocity columns) where the recording has it; otherwise the central difference of the neighbouring
poses, (p[i+1] - p[i-1]) / (t[i+1] - t[i-1]), one-sided at the ends, i.e. the time-weighted mean of
the two adjacent segments' displacement per time, and linear in between: its magnitude never exceeds
the largest displacement per time of the segments around the instant. Acceleration is the gradient of
those velocities, linear in between; orientations slerp; recorded angular rates are linear in
between. Before the first and after the last record the platform holds still at the end pose.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation, Slerp

from simart_pipeline import clock, frames
from simart_pipeline.config import recording_format
from simart_pipeline.mobility import bags
from simart_pipeline.mobility.errors import ReplayError

POSITION = ("x_m", "y_m", "z_m")
QUATERNION = ("qx", "qy", "qz", "qw")
VELOCITY = ("vx_mps", "vy_mps", "vz_mps")

# Poses closer in time than this share of the recording's median interval are one pose (jitter).
JITTER_FRACTION = 0.1
# Two sources on one topic: a jump to another track and back, each leg longer than
# INTERLEAVE_MIN_JUMP_M (position noise is far smaller) and faster than INTERLEAVE_SPEED_FACTOR times
# the platform's top speed, the return landing within half the jump of where it left; at least
# INTERLEAVE_MIN_RETURNS of them (one is a glitch, which the limits check catches).
INTERLEAVE_MIN_JUMP_M = 0.5
INTERLEAVE_SPEED_FACTOR = 3.0
INTERLEAVE_MIN_RETURNS = 2
# Limits check: replayed speed and acceleration may exceed the limits by this share (recorded noise);
# acceleration is the velocity change over LIMITS_WINDOW_S, since the finite difference of noisy
# recorded poses over one interval amplifies noise far beyond any real acceleration.
LIMITS_TOLERANCE = 0.05
LIMITS_WINDOW_S = 0.5

log = logging.getLogger(__name__)


def read_recording(trajectory, scene_dir: str | Path, max_speed_mps: float | None = None
                   ) -> dict[str, np.ndarray]:
    """The recording a ``config.ReplayTrajectory`` names (relative to ``scene_dir``), in world,
    cleaned by the stamp rules of :func:`clean` (``max_speed_mps``: the platform's, for telling two
    sources on one topic apart).

    :returns: the layout of :func:`read_csv`; times are not yet offset (``resample`` does that).
    """
    path = Path(scene_dir) / trajectory.path
    if recording_format(trajectory.path) == "csv":
        rec, where, hint = read_csv(path), f"{path}", ""
    else:
        stamp = trajectory.stamp or "header"
        rec = bags.read_bag_trajectory(path, trajectory.topic, stamp=stamp,
                                       time_origin=trajectory.time_origin,
                                       child_frame_id=trajectory.child_frame_id,
                                       parent_frame_id=trajectory.parent_frame_id)
        where = f"{path}: topic {trajectory.topic}"
        hint = "; try stamp: record (the bag's record times)" if stamp == "header" else ""
    rec = to_world(rec, trajectory.recording_frame.translation_m, trajectory.recording_frame.rpy_deg)
    return clean(rec, where, max_gap_s=trajectory.max_gap_s,
                 max_speed_mps=max_speed_mps, repeated_hint=hint)


def replay_platform(platform, t_ns: np.ndarray, scene_dir: str | Path) -> dict[str, np.ndarray]:
    """A replayed platform's poses at ``t_ns``: its recording read and cleaned, checked against its
    limits (:func:`checked_recording`), resampled onto the clock (:func:`resample`)."""
    rec = checked_recording(platform, scene_dir)
    return resample(rec, t_ns, platform.trajectory.time_offset_s)


def checked_recording(platform, scene_dir: str | Path) -> dict[str, np.ndarray]:
    """A replayed platform's recording, read and cleaned (:func:`read_recording`), its motion checked
    against the platform's limits by its ``trajectory.dynamic_limits`` policy (:func:`check_limits`)."""
    tr = platform.trajectory
    rec = read_recording(tr, scene_dir, max_speed_mps=platform.limits.max_speed_mps)
    where = f"{Path(scene_dir) / tr.path}" + (f": topic {tr.topic}" if tr.topic else "")
    check_limits(rec, tr.time_offset_s, platform.limits, f"{where}: platform {platform.name}",
                 tr.dynamic_limits)
    return rec


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


def _seconds(t_ns) -> str:
    return f"{float(clock.ns_to_seconds(int(t_ns))):.6f} s"


def clean(rec: dict[str, np.ndarray], where: str, *, max_gap_s: float | None = None,
          max_speed_mps: float | None = None, repeated_hint: str = "") -> dict[str, np.ndarray]:
    """A recording under the stamp rules of the module docstring: sorted, repeated stamps with equal
    values kept once (another pose: refused), jitter merged, gaps and two interleaved sources refused.

    :param where: the file (and topic) named by every error.
    :param max_gap_s: a longer interval between poses is refused (None: any).
    :param max_speed_mps: the platform's top speed, for telling two sources apart (None: not checked).
    :raises ReplayError: for each refusal, naming ``where``, the instant and the values.
    """
    t = np.asarray(rec["time_ns"], np.int64)
    if len(t) < 2:
        raise ReplayError(f"{where}: at least two recorded poses are needed, found {len(t)}")
    order = np.argsort(t, kind="stable")
    rec = {k: np.asarray(v)[order] for k, v in rec.items()}
    t = rec["time_ns"]
    same = np.concatenate([[False], np.diff(t) == 0])
    if same.any():
        num = np.concatenate([v.reshape(len(t), -1) for k, v in rec.items() if k != "time_ns"], axis=1)
        differ = same & np.any(num != np.roll(num, 1, axis=0), axis=1)
        if differ.any():
            i = int(np.argmax(differ))
            raise ReplayError(
                f"{where}: {int(differ.sum())} recorded poses repeat the stamp of the one before with other "
                f"values (the first at {_seconds(t[i])}: position {np.round(rec['position_m'][i - 1], 3).tolist()} "
                f"and {np.round(rec['position_m'][i], 3).tolist()} m){repeated_hint}")
        rec = {k: v[~same] for k, v in rec.items()}
    if len(rec["time_ns"]) < 2:
        raise ReplayError(f"{where}: at least two recorded poses with distinct stamps are needed, "
                          f"found {len(rec['time_ns'])}")
    if max_speed_mps is not None:
        _refuse_interleaved(rec, where, max_speed_mps)
    rec = _merge_jitter(rec)
    dt_s = np.diff(rec["time_ns"]) / 1e9
    if max_gap_s is not None and (dt_s > max_gap_s).any():
        i = int(np.argmax(dt_s))
        raise ReplayError(f"{where}: {int((dt_s > max_gap_s).sum())} gap(s) between recorded poses exceed "
                          f"trajectory.max_gap_s = {max_gap_s:g} s, the longest {dt_s[i]:.3f} s from "
                          f"{_seconds(rec['time_ns'][i])}: replay a gap-free part (time_offset_s, clock.duration_s) "
                          "or raise max_gap_s to move in a straight line across")
    return rec


def _refuse_interleaved(rec: dict[str, np.ndarray], where: str, max_speed_mps: float) -> None:
    t_s = rec["time_ns"] / 1e9
    p = rec["position_m"]
    step = np.diff(p, axis=0)
    dist = np.linalg.norm(step, axis=1)
    jump = (dist > INTERLEAVE_MIN_JUMP_M) & (dist / np.diff(t_s) > INTERLEAVE_SPEED_FACTOR * max_speed_mps)
    # a jump out (p[i-1] -> p[i]) and one back (p[i] -> p[i+1]) landing near where it left
    back = np.linalg.norm(p[2:] - p[:-2], axis=1) < 0.5 * np.minimum(dist[:-1], dist[1:])
    returns = np.flatnonzero(jump[:-1] & jump[1:] & back) + 1
    if len(returns) >= INTERLEAVE_MIN_RETURNS:
        i = int(returns[0])
        raise ReplayError(
            f"{where}: the poses jump to another track and back {len(returns)} times (the first at "
            f"{_seconds(rec['time_ns'][i])}: {np.round(p[i - 1], 2).tolist()} -> {np.round(p[i], 2).tolist()} -> "
            f"{np.round(p[i + 1], 2).tolist()} m, faster than {INTERLEAVE_SPEED_FACTOR:g} x the platform's "
            f"{max_speed_mps:g} m/s): the recording seems to interleave two sources; record one per topic "
            "or pick the platform's own topic or frame")


def _merge_jitter(rec: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Poses closer in time than JITTER_FRACTION of the median interval merged into their mean."""
    t = rec["time_ns"]
    dt = np.diff(t)
    threshold = JITTER_FRACTION * float(np.median(dt))
    if not (dt < threshold).any():
        return rec
    # greedy clusters: a cluster spans less than the threshold from its first pose
    group = np.empty(len(t), np.int64)
    g, first = 0, t[0]
    for i, ti in enumerate(t):
        if ti - first >= threshold:
            g, first = g + 1, ti
        group[i] = g
    starts = np.flatnonzero(np.concatenate([[True], np.diff(group) > 0]))
    counts = np.diff(np.append(starts, len(t)))
    out = {}
    for k, v in rec.items():
        if k == "time_ns":
            out[k] = np.round(np.add.reduceat(v.astype(np.float64), starts) / counts).astype(np.int64)
            single = counts == 1
            out[k][single] = v[starts[single]]  # untouched poses keep their exact stamps
        elif k == "orientation_xyzw":
            ref = v[starts][group]  # sign-align each quaternion to its cluster's first
            aligned = np.where(np.sum(v * ref, axis=1, keepdims=True) < 0, -v, v)
            mean = np.add.reduceat(aligned, starts) / counts[:, None]
            out[k] = mean / np.linalg.norm(mean, axis=1, keepdims=True)
            out[k][counts == 1] = v[starts[counts == 1]]
        else:
            out[k] = np.add.reduceat(v, starts, axis=0) / counts.reshape(-1, *([1] * (v.ndim - 1)))
            out[k][counts == 1] = v[starts[counts == 1]]
    return out


def check_limits(rec: dict[str, np.ndarray], time_offset_s: float, limits, where: str,
                 policy: str = "refuse") -> list[str]:
    """The replayed motion against ``limits`` (a ``config.DynamicLimits``): speed at every recorded
    instant, and acceleration as the velocity change over LIMITS_WINDOW_S (or the recording's span if
    shorter), both with LIMITS_TOLERANCE; only over the recording's span (the holds before and after
    are the replay's own rule, not recorded motion).

    :param policy: ``refuse`` raises ReplayError, ``warn`` logs a warning, ``accept`` says nothing.
    :returns: the violations found (one line each), whatever the policy.
    """
    t = rec["time_ns"]
    span_s = (t[-1] - t[0]) / 1e9
    window_s = min(LIMITS_WINDOW_S, span_s)
    window_ns = clock.seconds_to_ns(window_s)
    q0 = np.arange(t[0], t[-1] - window_ns + 1, clock.seconds_to_ns(window_s / 4), dtype=np.int64)
    if len(q0) == 0:
        q0 = t[:1]
    # one resampling: the recorded instants, then each window's start and end
    v = resample(rec, np.concatenate([t, q0, q0 + window_ns]), 0.0)["velocity_mps"]
    speed = np.linalg.norm(v[:len(t)], axis=1)
    starts, ends = v[len(t):len(t) + len(q0)], v[len(t) + len(q0):]
    accel = np.linalg.norm(ends - starts, axis=1) / window_s
    problems = []
    for name, values, at, limit, key, unit in (
            ("speed", speed, t, limits.max_speed_mps, "max_speed_mps", "m/s"),
            (f"acceleration (over {window_s:g} s)", accel, q0, limits.max_acceleration_mps2,
             "max_acceleration_mps2", "m/s2")):
        over = values > limit * (1 + LIMITS_TOLERANCE)
        if over.any():
            i = int(np.argmax(values))
            problems.append(
                f"{where}: replayed {name} reaches {values[i]:.3g} {unit} at "
                f"{_seconds(at[i] + clock.seconds_to_ns(time_offset_s))} on the clock, above limits.{key} "
                f"{limit:g} {unit} (+{LIMITS_TOLERANCE:.0%}); check the recording's stamps and frame, "
                "raise the platform's limits, or set trajectory.dynamic_limits: warn or accept")
    if problems and policy == "refuse":
        raise ReplayError(problems[0])
    if problems and policy == "warn":
        for p in problems:
            log.warning(p)
    return problems


def velocity_estimate(t_s: np.ndarray, position_m: np.ndarray) -> np.ndarray:
    """Velocity at recorded instants without a recorded one: the central difference of the
    neighbouring poses (one-sided at the ends), never faster than the adjacent segments."""
    v = np.empty_like(position_m)
    v[1:-1] = (position_m[2:] - position_m[:-2]) / (t_s[2:] - t_s[:-2])[:, None]
    v[0] = (position_m[1] - position_m[0]) / (t_s[1] - t_s[0])
    v[-1] = (position_m[-1] - position_m[-2]) / (t_s[-1] - t_s[-2])
    return v


def resample(rec: dict[str, np.ndarray], times_ns: np.ndarray, time_offset_s: float = 0.0) -> dict[str, np.ndarray]:
    """Poses at ``times_ns`` in the layout of ``trajectory.evaluate_waypoints``."""
    t_rec_ns = rec["time_ns"] + clock.seconds_to_ns(time_offset_s)
    t_rec = clock.ns_to_seconds(t_rec_ns)
    q_ns = np.asarray(times_ns, np.int64)
    q = np.clip(clock.ns_to_seconds(q_ns), t_rec[0], t_rec[-1])
    moving = (q_ns >= t_rec_ns[0]) & (q_ns <= t_rec_ns[-1])
    pos_rec = rec["position_m"]
    vel_rec = rec.get("velocity_mps")
    if vel_rec is None:
        vel_rec = velocity_estimate(t_rec, pos_rec)
    pos = np.stack([np.interp(q, t_rec, pos_rec[:, i]) for i in range(3)], axis=-1)
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
