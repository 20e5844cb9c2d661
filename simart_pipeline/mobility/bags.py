"""Recorded trajectories from ROS bags, and the bag access shared with the sensor import.

Formats (by file name, ``config.recording_format``): ROS1 bags (``.bag``), rosbag2 storage files
(``.db3`` sqlite3, ``.mcap``) and rosbag2 directories (with ``metadata.yaml``), all read through
``rosbags``' ``AnyReader``, which takes message definitions from the bag itself.

A trajectory is read from one topic, by message type:

- ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``: the pose (position and orientation
  of the platform's base_link in the header's frame); velocities are left to ``replay.resample``
  (the derivative of a spline through the positions).
- ``nav_msgs/Odometry``: the pose, and the twist, which REP 105 puts in ``child_frame_id``
  (base_link): its linear part is rotated into the pose's frame by the pose's orientation; its
  angular part is base_link's angular velocity in base_link, as the trajectory stores it.
- ``tf2_msgs/TFMessage`` (``/tf``, with ``/tf_static`` when the bag has it): the pose of
  ``child_frame_id`` in ``parent_frame_id``, composed along the frame tree (through their common
  ancestor) at every stamp of the chain's moving links where all of them have data; each link is
  interpolated as tf2 does (linear translation, slerp rotation) and taken as recorded at its own
  stamps.

Times: ``stamp`` is ``header`` (the messages' header stamps; for /tf each transform's own) or
``record`` (the bag's record time); ``time_origin`` is ``first_message`` (the earliest stamp read),
``bag_start`` (the bag's first record time) or an absolute stamp (int ns). The dict returned is the
one ``replay.read_csv`` returns (``time_ns`` since the origin, ``position_m``, ``orientation_xyzw``
unless every message lacks one, ``velocity_mps`` and ``angular_velocity_radps`` for Odometry).

Quirks of real bags handled: frame ids with a leading ``/`` (ROS1 tf_prefix) are stripped;
messages whose header stamps run out of order are sorted; repeated stamps with equal values are
dropped (different values are an error that suggests record times); all-zero quaternions mean "no
orientation" (then the heading follows the velocity); a damaged or truncated bag is an error
naming the file.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from simart_pipeline import clock
from simart_pipeline.config import BAG_TIME_ORIGINS, recording_format
from simart_pipeline.mobility.errors import ReplayError

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC = "/tf_static"
TRAJECTORY_TYPES = (POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, ODOMETRY, TF_MESSAGE)


class BagError(ReplayError):
    """A bag that cannot be read as asked; the message names the file."""


def frame_name(frame_id: str) -> str:
    """A tf frame id without ROS1's leading ``/`` (``/gps`` and ``gps`` are the same frame)."""
    return frame_id.lstrip("/")


def stamp_ns(stamp) -> int:
    """A ``builtin_interfaces/Time`` (ROS1 ``time``) as int ns."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class Bag:
    """An open bag (a context manager): its topics and its messages; every error names the file."""

    def __init__(self, path: str | Path):
        from rosbags.highlevel import AnyReader

        self.path = Path(path)
        try:
            fmt = recording_format(self.path.name)
        except ValueError as exc:
            raise BagError(str(exc)) from None
        if fmt == "csv":
            raise BagError(f"{self.path}: a CSV, not a bag")
        if not self.path.exists():
            raise BagError(f"{self.path}: no such bag")
        if self.path.is_dir() and not (self.path / "metadata.yaml").is_file():
            raise BagError(f"{self.path}: a rosbag2 directory needs its metadata.yaml")
        self.format = "ROS1" if fmt == "ros1" else "rosbag2"
        try:
            self.reader = AnyReader([self.path])
        except Exception as exc:  # rosbags raises its own errors, OSError or sqlite errors here
            raise BagError(f"{self.path}: cannot open the {self.format} bag: {exc}") from None

    def __enter__(self) -> Bag:
        try:
            self.reader.open()
        except Exception as exc:  # a truncated ROS1 bag has no index; a bad rosbag2 no metadata
            raise BagError(f"{self.path}: cannot read the {self.format} bag (truncated or corrupt?): "
                           f"{exc}") from None
        return self

    def __exit__(self, *exc) -> None:
        self.reader.close()

    @property
    def topics(self) -> dict[str, str]:
        """Topic -> message type (``pkg/msg/Type``), sorted by topic."""
        return {c.topic: c.msgtype for c in sorted(self.reader.connections, key=lambda c: c.topic)}

    @property
    def start_ns(self) -> int:
        """Record time of the bag's first message (ns)."""
        return int(self.reader.start_time)

    def msgtype(self, topic: str, allowed: Sequence[str] | None = None) -> str:
        """The topic's message type; errors name the file and list its topics."""
        topics = self.topics
        if topic not in topics:
            listing = ", ".join(f"{t} ({m})" for t, m in topics.items()) or "none"
            raise BagError(f"{self.path}: no topic {topic!r}; the bag has: {listing}")
        if allowed is not None and topics[topic] not in allowed:
            raise BagError(f"{self.path}: topic {topic} holds {topics[topic]}; expected "
                           f"{' or '.join(allowed)}")
        return topics[topic]

    def messages(self, topics: Sequence[str]) -> Iterator[tuple[str, str, int, object]]:
        """``(topic, msgtype, record time ns, message)`` of ``topics`` in record-time order."""
        conns = [c for c in self.reader.connections if c.topic in set(topics)]
        try:
            for conn, t, raw in self.reader.messages(connections=conns):
                yield conn.topic, conn.msgtype, int(t), self.reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # damaged chunks surface as struct, lz4, bz2, sqlite or serde errors
            raise BagError(f"{self.path}: cannot read the messages of {', '.join(topics)} (truncated or "
                           f"corrupt?): {type(exc).__name__}: {exc}") from None


def time_origin_ns(origin: str | int | None, stamps: np.ndarray, bag: Bag) -> int:
    """The absolute stamp (ns) that becomes t = 0 (see the module docstring)."""
    if origin is None or origin == "first_message":
        return int(np.min(stamps))
    if origin == "bag_start":
        return bag.start_ns
    if isinstance(origin, str):
        raise BagError(f"{bag.path}: time origin {origin!r} is not one of {', '.join(BAG_TIME_ORIGINS)} "
                       "or an integer stamp")
    return int(origin)


def _xyz(v) -> list[float]:
    return [v.x, v.y, v.z]


def _xyzw(q) -> list[float]:
    return [q.x, q.y, q.z, q.w]


class TfTree:
    """The frame tree of a bag's /tf and /tf_static: one parent per frame, each link a time series
    (or one static value), looked up as tf2 does (linear translation, slerp rotation)."""

    def __init__(self, path: Path):
        self.path = path
        self._raw: dict[str, tuple[str, bool, list]] = {}  # child -> (parent, static, [(t, xyz, xyzw)])
        self.links: dict[str, tuple[str, np.ndarray, np.ndarray, np.ndarray]] = {}

    def add(self, parent: str, child: str, t_ns: int, xyz, xyzw, static: bool) -> None:
        parent, child = frame_name(parent), frame_name(child)
        old = self._raw.setdefault(child, (parent, static, []))
        if old[0] != parent:
            raise BagError(f"{self.path}: frame {child!r} has two parents, {old[0]!r} and {parent!r} "
                           "(tf allows one)")
        if static:  # /tf_static is latched: the last value holds at every time
            self._raw[child] = (parent, True, [(0, xyz, xyzw)])
        elif not old[1]:
            old[2].append((t_ns, xyz, xyzw))

    def finish(self) -> TfTree:
        for child, (parent, static, rows) in self._raw.items():
            rows = sorted(rows, key=lambda r: r[0])
            t = np.array([r[0] for r in rows], np.int64)
            keep = np.concatenate([[True], np.diff(t) > 0])  # a repeated stamp: the first wins, as in tf2
            xyz = np.array([r[1] for r in rows], np.float64)[keep]
            quat = np.array([r[2] for r in rows], np.float64)[keep]
            self.links[child] = (parent, None if static else t[keep], xyz, quat)
        return self

    def _up(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self.links:
            chain.append(self.links[chain[-1]][0])
            if len(chain) > len(self.links) + 1:
                raise BagError(f"{self.path}: the tf tree has a loop through {frame!r}")
        return chain

    def chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """Frames from ``source`` and from ``target`` up to (not including) their common ancestor."""
        target, source = frame_name(target), frame_name(source)
        for f in (target, source):
            if f not in self.links and not any(p == f for p, *_ in self.links.values()):
                raise BagError(f"{self.path}: no frame {f!r} on /tf or /tf_static; frames: "
                               f"{', '.join(sorted(self.frames()))}")
        up_s, up_t = self._up(source), self._up(target)
        common = next((f for f in up_s if f in up_t), None)
        if common is None:
            raise BagError(f"{self.path}: frames {source!r} and {target!r} are in unconnected tf trees "
                           f"(roots {up_s[-1]!r} and {up_t[-1]!r})")
        return up_s[:up_s.index(common)], up_t[:up_t.index(common)]

    def frames(self) -> set[str]:
        return set(self.links) | {p for p, *_ in self.links.values()}

    def moving_times(self, target: str, source: str) -> np.ndarray:
        """Stamps of the chain's moving links, within the span where every one of them has data."""
        a, b = self.chain(target, source)
        stamps = [self.links[f][1] for f in (*a, *b) if self.links[f][1] is not None]
        if not stamps:
            raise BagError(f"{self.path}: the pose of {source!r} in {target!r} never changes "
                           "(only static transforms): no trajectory to replay")
        t = np.unique(np.concatenate(stamps))
        lo, hi = max(s[0] for s in stamps), min(s[-1] for s in stamps)
        return t[(t >= lo) & (t <= hi)]

    def _link_at(self, child: str, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Quaternion [n, 4] and translation [n, 3] of one link at ``t_ns`` (held beyond its span)."""
        _, t, xyz, quat = self.links[child]
        n = len(t_ns)
        if t is None or len(t) == 1:
            return np.tile(quat[-1], (n, 1)), np.tile(xyz[-1], (n, 1))
        q = np.clip(t_ns, t[0], t[-1])
        ts = clock.ns_to_seconds(q - t[0])  # relative seconds keep ns resolution in float64
        knots = clock.ns_to_seconds(t - t[0])
        pos = np.stack([np.interp(ts, knots, xyz[:, i]) for i in range(3)], axis=-1)
        rot = Slerp(knots, Rotation.from_quat(quat))(ts).as_quat()
        hit = np.searchsorted(t, q)
        exact = (hit < len(t)) & (t[np.minimum(hit, len(t) - 1)] == q)
        pos[exact], rot[exact] = xyz[hit[exact]], quat[hit[exact]]  # as recorded at its own stamps
        return rot, pos

    def _to_ancestor(self, frames_up: list[str], t_ns: np.ndarray) -> tuple[Rotation, np.ndarray]:
        rot, pos = Rotation.identity(len(t_ns)), np.zeros((len(t_ns), 3))
        for f in frames_up:  # T_parent_source = T_parent_f * T_f_source, walking up
            q, p = self._link_at(f, t_ns)
            r = Rotation.from_quat(q)
            rot, pos = r * rot, p + r.apply(pos)
        return rot, pos

    def lookup(self, target: str, source: str, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pose of ``source`` in ``target`` at ``t_ns`` [n]: position [n, 3] m, quaternion [n, 4]."""
        t_ns = np.asarray(t_ns, np.int64)
        a, b = self.chain(target, source)
        if len(a) == 1 and not b:  # one link: as recorded, bit for bit at its stamps
            q, p = self._link_at(a[0], t_ns)
            return p, q
        r_s, p_s = self._to_ancestor(a, t_ns)
        r_t, p_t = self._to_ancestor(b, t_ns)
        return r_t.inv().apply(p_s - p_t), (r_t.inv() * r_s).as_quat()


def read_tf(bag: Bag, topic: str = "/tf", stamp: str = "header") -> TfTree:
    """Every transform of ``topic`` (moving) and of ``/tf_static`` if the bag has it (static)."""
    tree = TfTree(bag.path)
    topics = [topic] + ([TF_STATIC_TOPIC] if TF_STATIC_TOPIC in bag.topics and topic != TF_STATIC_TOPIC else [])
    for tp in topics:
        bag.msgtype(tp, (TF_MESSAGE,))
    for tp, _, t_rec, msg in bag.messages(topics):
        for tf in msg.transforms:
            t = stamp_ns(tf.header.stamp) if stamp == "header" else t_rec
            tree.add(tf.header.frame_id, tf.child_frame_id, t, _xyz(tf.transform.translation),
                     _xyzw(tf.transform.rotation), static=tp == TF_STATIC_TOPIC)
    return tree.finish()


def read_bag_trajectory(path: str | Path, topic: str, *, stamp: str = "header",
                        time_origin: str | int | None = "first_message", child_frame_id: str | None = None,
                        parent_frame_id: str | None = None) -> dict[str, np.ndarray]:
    """A recorded trajectory from a bag, in the layout of ``replay.read_csv``.

    :param topic: a PoseStamped, PoseWithCovarianceStamped, Odometry or TFMessage topic.
    :param child_frame_id, parent_frame_id: for TFMessage topics only: the platform's frame and the
        frame its poses are given in.
    :returns: ``time_ns`` [n] int64 since the origin, ``position_m`` [n, 3], ``orientation_xyzw``
        [n, 4] (absent when no message carries one), and for Odometry ``velocity_mps`` [n, 3] (in the
        pose's frame) and ``angular_velocity_radps`` [n, 3] (in base_link).
    """
    path = Path(path)
    stamp = stamp or "header"
    with Bag(path) as bag:
        msgtype = bag.msgtype(topic, TRAJECTORY_TYPES)
        if (msgtype == TF_MESSAGE) != (child_frame_id is not None and parent_frame_id is not None):
            raise BagError(f"{path}: topic {topic} ({msgtype}): child_frame_id and parent_frame_id "
                           + ("are needed for a /tf topic" if msgtype == TF_MESSAGE else
                              "are for /tf topics only"))
        if msgtype == TF_MESSAGE:
            tree = read_tf(bag, topic, stamp)
            t = tree.moving_times(parent_frame_id, child_frame_id)
            pos, quat = tree.lookup(parent_frame_id, child_frame_id, t)
            rec = {"time_ns": t, "position_m": pos, "orientation_xyzw": quat}
        else:
            rows = []
            for _, _, t_rec, msg in bag.messages([topic]):
                t = stamp_ns(msg.header.stamp) if stamp == "header" else t_rec
                pose = msg.pose.pose if msgtype != POSE_STAMPED else msg.pose
                row = [t, *_xyz(pose.position), *_xyzw(pose.orientation)]
                if msgtype == ODOMETRY:
                    row += [*_xyz(msg.twist.twist.linear), *_xyz(msg.twist.twist.angular)]
                rows.append(row)
            if not rows:
                raise BagError(f"{path}: topic {topic} has no messages")
            t = np.array([r[0] for r in rows], np.int64)
            num = np.array([r[1:] for r in rows], np.float64)
            rec = {"time_ns": t, "position_m": num[:, 0:3], "orientation_xyzw": num[:, 3:7]}
            if msgtype == ODOMETRY:
                rec["twist_linear"], rec["angular_velocity_radps"] = num[:, 7:10], num[:, 10:13]
        rec["time_ns"] = rec["time_ns"] - time_origin_ns(time_origin, rec["time_ns"], bag)
    return _checked(rec, path, topic)


def _checked(rec: dict[str, np.ndarray], path: Path, topic: str) -> dict[str, np.ndarray]:
    """Orientation-less messages handled, twist rotated to world, values checked; the stamp rules
    (order, repeats, jitter, gaps, two sources) are ``replay.clean``'s, for bags and CSVs alike."""
    where = f"{path}: topic {topic}"
    n = len(rec["time_ns"])
    if n < 2:
        raise BagError(f"{where}: at least two poses are needed, found {n}")
    for k, v in rec.items():
        if not np.all(np.isfinite(v)):
            raise BagError(f"{where}: {k} holds a non-finite value")
    norm = np.linalg.norm(rec["orientation_xyzw"], axis=1)
    if np.all(norm == 0):  # an orientation-less recording: resample heads along the velocity
        del rec["orientation_xyzw"]
        if "twist_linear" in rec:
            raise BagError(f"{where}: the odometry has no orientation, so its twist (in child_frame_id, "
                           "REP 105) cannot be rotated into the pose's frame")
    elif np.any(np.abs(norm - 1) > 1e-3):
        i = int(np.argmax(np.abs(norm - 1)))
        raise BagError(f"{where}: quaternions must have unit norm (message {i}: {norm[i]:.4f})")
    if "twist_linear" in rec:  # REP 105: the twist is in child_frame_id, i.e. base_link
        rec["velocity_mps"] = Rotation.from_quat(rec["orientation_xyzw"]).apply(rec.pop("twist_linear"))
    return rec
