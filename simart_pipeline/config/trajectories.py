"""Trajectories: waypoints under dynamic limits, or a recording replayed onto the shared clock."""

from __future__ import annotations

import math
from typing import Annotated, Literal, Union

from pydantic import Discriminator, Field, Tag, field_validator, model_validator

from simart_pipeline.config.base import Vec3, _inside_scene_dir, _Model
from simart_pipeline.config.recordings import _bag_time_origin, recording_format


class WaypointTrajectory(_Model):
    """Waypoints in the ENU world frame (m), joined under the platform's dynamic limits
    (``docs/mobility.md``): from rest to rest, cruising at ``speed_mps``, cutting each corner by at
    most ``waypoint_tolerance_m`` and slowing down in turns; ground vehicles follow the roads."""

    kind: Literal["waypoints"] = "waypoints"
    waypoints_m: tuple[Vec3, ...]
    speed_mps: float = Field(gt=0, le=100, description="cruise speed, at most limits.max_speed_mps")
    start_offset_s: float = Field(0.0, ge=0, description="the platform waits at its first waypoint until then")
    waypoint_tolerance_m: float = Field(
        1.0, ge=0, description="largest distance the path may keep from an interior waypoint when it "
        "cuts the corner there; 0: stop at every waypoint")
    follow_roads: bool | None = Field(
        None, description="route between consecutive waypoints along the scene's road centre lines; "
        "default: true for ground vehicles when the scene has roads, false otherwise (not for UAVs)")
    max_road_snap_distance_m: float = Field(
        10.0, gt=0, description="road following: a waypoint farther than this from every road is an error")
    min_road_width_m: float | None = Field(
        None, ge=0, description="road following: narrower roads are not used; default 3 m for ground "
        "vehicles (no footways, cycleways or paths), 0 for pedestrians")

    @field_validator("waypoints_m")
    @classmethod
    def _two(cls, v):
        if len(v) < 2:
            raise ValueError("at least two waypoints are needed")
        for k in range(len(v) - 1):
            if math.dist(v[k], v[k + 1]) <= 1e-9:  # m; the path needs a direction between them
                raise ValueError(f"waypoints {k} and {k + 1} coincide")
        return v


class RecordingFrame(_Model):
    """Pose of a recording's own frame (``odom``, ``map``, ...) in the scene's world frame."""

    translation_m: Vec3 = (0.0, 0.0, 0.0)
    rpy_deg: Vec3 = Field((0.0, 0.0, 0.0), description="roll about x, pitch about y, yaw about z (deg)")


class ReplayTrajectory(_Model):
    """A recorded trajectory replayed onto the shared clock (offline replay).

    ``path`` (relative to the scene directory; its suffix says the format) is a CSV with a header:
    ``time_ns`` (or ``time_s``), ``x_m``, ``y_m``, ``z_m`` in the world frame, optionally
    ``qx, qy, qz, qw`` (base_link into world) and ``vx_mps, vy_mps, vz_mps``; or a ROS1 bag
    (``.bag``), a rosbag2 storage file (``.db3``, ``.mcap``) or a rosbag2 directory, read by
    ``topic``: ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``nav_msgs/Odometry``
    or ``tf2_msgs/TFMessage`` (the pose of ``child_frame_id`` in ``parent_frame_id``, chained).
    Bag times are ``stamp`` (message header or bag record time) minus ``time_origin`` (the first
    message read, the bag's first record time, or an absolute stamp in ns). See
    ``simart_pipeline.mobility.replay`` and ``.bags``, ``docs/sensor-plugin.md``.
    """

    kind: Literal["replay"]
    path: str
    time_offset_s: float = Field(0.0, description="added to the recorded times")
    topic: str | None = Field(None, description="bags only (required there): the topic to read")
    child_frame_id: str | None = Field(None, description="/tf only: the platform's frame (base_link)")
    parent_frame_id: str | None = Field(None, description="/tf only: the frame the poses are in")
    stamp: Literal["header", "record"] | None = Field(
        None, description="bags only: header stamps (default) or bag record times")
    time_origin: str | int | None = Field(
        None, description="bags only: first_message (default), bag_start, or an absolute stamp (ns)")
    recording_frame: RecordingFrame = Field(
        default_factory=lambda: RecordingFrame(),
        description="pose of the frame the recorded poses are given in, in the scene's world frame")
    max_gap_s: float = Field(
        1.0, gt=0, le=3600,
        description="a longer interval between recorded poses is refused (raise it to interpolate across)")
    dynamic_limits: Literal["refuse", "warn", "accept"] = Field(
        "refuse", description="replayed speed or acceleration above the platform's limits: refuse the "
        "replay (default), warn and replay, or accept silently (docs/mobility.md, 'Replay')")
    _inside = field_validator("path")(classmethod(lambda cls, v: _inside_scene_dir(v, "the recording")))
    _origin = field_validator("time_origin")(classmethod(lambda cls, v: _bag_time_origin(v)))

    @model_validator(mode="after")
    def _format(self):
        fmt = recording_format(self.path)
        bag_only = [k for k in ("topic", "child_frame_id", "parent_frame_id", "stamp", "time_origin")
                    if getattr(self, k) is not None]
        if fmt == "csv" and bag_only:
            raise ValueError(f"{', '.join(bag_only)}: only for bags; a CSV carries its own times and poses")
        if fmt != "csv" and not self.topic:
            raise ValueError("topic: a bag needs the topic of the poses (PoseStamped, Odometry or /tf)")
        if (self.child_frame_id is None) != (self.parent_frame_id is None):
            raise ValueError("child_frame_id and parent_frame_id go together (a /tf lookup)")
        return self


def _trajectory_kind(v) -> str:
    return (v.get("kind", "waypoints") if isinstance(v, dict) else getattr(v, "kind", "waypoints"))


TrajectorySource = Annotated[
    Union[Annotated[WaypointTrajectory, Tag("waypoints")], Annotated[ReplayTrajectory, Tag("replay")]],
    Discriminator(_trajectory_kind)]
