"""Streams recorded by another simulator or a robot, imported from a bag into the stream contract.

:func:`import_streams` reads every stream of one ``sensor_imports`` entry (``config.SensorImport``)
and builds each group with the kind's constructor of :mod:`.contract`, the one the renderers use:
the same variables, dims and attrs keys as a rendered stream, with what a bag cannot hold (depth,
labels, noise model) filled with the contract's absent values. The sensing stage that calls it is
:func:`.sensor_frames.build_sensor_frames`; the contract is ``docs/sensor-plugin.md``. In short:

- ``time``: int64 ns on the shared clock, ``stamp - time_origin + time_offset_s`` (the header stamps
  or the bag's record times, as configured); the stamps are recorded, not sampled at a rate; messages
  outside the session ``[0, duration]`` are dropped and counted; ``header_stamp_ns`` and
  ``record_time_ns`` keep both original stamps of every message kept.
- LiDAR: a PointCloud2 row is a ring and its column an azimuth (an unorganised cloud is one ring),
  padded with NaN to the largest cloud; fields other than ``x y z intensity`` are kept as
  ``field_<name>``.
- poses: ``position_m`` / ``orientation_xyzw`` (and GPS ``position_enu_m``) are the scene's
  trajectory at the message times composed with the mount, exactly as for rendered streams; the mount
  comes from the config or from the bag's /tf_static and /tf (``extrinsics: tf``).
- provenance attrs (``source_*``, ``time_origin*``, ``num_messages_*``, ``extrinsics_source``):
  :func:`.contract.stream_attrs`; weather is not applied to a recorded stream.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline import clock, frames
from simart_pipeline.config import BaseStation, ImportedStream, SceneConfig, SensorImport
from simart_pipeline.mobility.bags import Bag, BagError, frame_name, read_tf, stamp_ns, time_origin_ns
from simart_pipeline.sensing import contract
from simart_pipeline.sensing import ros_messages as rm
from simart_pipeline.sensing.streams import device_kind, device_poses

MESSAGE_TYPES = {"camera": (rm.IMAGE, rm.COMPRESSED_IMAGE), "lidar": (rm.POINT_CLOUD2,), "imu": (rm.IMU,),
                 "gps": (rm.NAV_SAT_FIX,)}


class StreamImportError(BagError):
    """A stream that cannot be imported; the message names the file and the topic."""


def import_streams(imp: SensorImport, cfg: SceneConfig, traj: xr.Dataset | None, scene_dir: str | Path,
                   weather: str = "") -> dict[str, xr.Dataset]:
    """Every stream of one bag as ``{"/<device>/<sensor>": dataset}`` (see the module docstring)."""
    path = Path(scene_dir) / imp.path
    with Bag(path) as bag:
        for st in imp.streams:
            bag.msgtype(st.topic, MESSAGE_TYPES[st.kind])
            if st.camera_info_topic:
                bag.msgtype(st.camera_info_topic, (rm.CAMERA_INFO,))
        topics = sorted({st.topic for st in imp.streams} | {st.camera_info_topic for st in imp.streams
                                                              if st.camera_info_topic})
        rows: dict[str, list] = {t: [] for t in topics}
        for topic, msgtype, t_rec, msg in bag.messages(topics):
            if msgtype == rm.CAMERA_INFO:
                if not rows[topic]:  # intrinsics are taken from the first CameraInfo
                    rows[topic].append(rm.camera_intrinsics(msg))
                continue
            # decoded later, only if kept: a JPEG stays compressed until then
            rows[topic].append((stamp_ns(msg.header.stamp), t_rec, frame_name(msg.header.frame_id), msg, msgtype))
        for st in imp.streams:
            if not rows[st.topic]:
                raise StreamImportError(f"{path}: topic {st.topic} has no messages")
        used = {t: np.array([r[0] if imp.stamp == "header" else r[1] for r in rows[t]], np.int64)
                for t in {st.topic for st in imp.streams}}
        origin = time_origin_ns(imp.time_origin, np.concatenate(list(used.values())), bag)
        tf = None
        if any(st.extrinsics == "tf" for st in imp.streams):
            tf_topics = [t for t in ("/tf", "/tf_static") if t in bag.topics]
            if not tf_topics:
                raise StreamImportError(f"{path}: extrinsics: tf, but the bag has no /tf or /tf_static")
            tf = read_tf(bag, tf_topics[0], imp.stamp)
        fmt, types = bag.format, bag.topics
    out = {}
    for st in imp.streams:
        info = rows[st.camera_info_topic][0] if st.camera_info_topic and rows[st.camera_info_topic] else None
        out[f"/{st.device}/{st.sensor}"] = _stream_dataset(
            st, imp, cfg, traj, rows[st.topic], used[st.topic], origin, tf, info, path,
            fmt, types[st.topic], weather)
    return out


def _decode(msgtype: str, msg):
    if msgtype in (rm.IMAGE, rm.COMPRESSED_IMAGE):
        return rm.image_rgb(msg, msgtype)
    if msgtype == rm.POINT_CLOUD2:
        return rm.point_cloud_array(msg), int(msg.height), int(msg.width)
    if msgtype == rm.IMU:
        return (list(_v(msg.linear_acceleration)), list(_v(msg.angular_velocity)),
                [msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w],
                np.asarray(msg.linear_acceleration_covariance, np.float64),
                np.asarray(msg.angular_velocity_covariance, np.float64),
                np.asarray(msg.orientation_covariance, np.float64))
    return (msg.latitude, msg.longitude, msg.altitude, int(msg.status.status), int(msg.status.service),
            np.asarray(msg.position_covariance, np.float64), int(msg.position_covariance_type))


def _v(v):
    return v.x, v.y, v.z


def _mount(st: ImportedStream, cfg: SceneConfig, device, tf, source_frame: str, t_abs: int,
           path: Path) -> tuple[np.ndarray, Rotation, str]:
    """Sensor-frame pose in base_link (translation, rotation) and where it came from."""
    if st.extrinsics == "tf":
        frame = frame_name(st.frame_id or source_frame)
        if not frame:
            raise StreamImportError(f"{path}: topic {st.topic}: the messages have no frame_id to look up "
                               "on /tf; set frame_id")
        pos, quat = tf.lookup(st.base_frame_id, frame, np.array([t_abs]))
        rot = Rotation.from_quat(quat[0])
        if st.kind == "camera" and st.image_frame == "optical":
            rot = rot * frames.OPTICAL_TO_BODY.inv()  # the image frame is optical; the mount is the body
        return pos[0], rot, f"tf: pose of {frame!r} in {frame_name(st.base_frame_id)!r} at the first message"
    mount, what = st.mount, "config: the stream's mount"
    if mount is None:
        same = [s for s in device.sensors if s.name == st.sensor]
        mount, what = (same[0].mount, "config: the embedded sensor's mount") if same else (None, "identity")
    if mount is None:
        return np.zeros(3), Rotation.identity(), "identity: no mount configured"
    return (np.asarray(mount.translation_m, np.float64), frames.rotation_from_rpy_deg(mount.rpy_deg), what)


def _stream_dataset(st: ImportedStream, imp: SensorImport, cfg: SceneConfig, traj, rows: list,
                    stamps: np.ndarray, origin: int, tf, info, path: Path, fmt: str, msgtype: str,
                    weather: str) -> xr.Dataset:
    where = f"{path}: topic {st.topic}"
    t = stamps - origin + clock.seconds_to_ns(imp.time_offset_s)
    inside = (t >= 0) & (t <= clock.seconds_to_ns(cfg.clock.duration_s))
    if not inside.any():
        raise StreamImportError(f"{where}: none of its {len(t)} messages falls in the session (0 .. "
                           f"{cfg.clock.duration_s} s); their times span {t.min() / 1e9:.3f} .. "
                           f"{t.max() / 1e9:.3f} s after the origin: check stamp, time_origin, time_offset_s")
    idx = np.flatnonzero(inside)
    idx = idx[np.argsort(t[idx], kind="stable")]
    first = np.concatenate([[True], np.diff(t[idx]) > 0])  # a repeated stamp: the first message wins
    idx = idx[first]
    payloads = []
    for i in idx:
        try:
            payloads.append(_decode(rows[i][4], rows[i][3]))
        except (rm.MessageError, ValueError) as exc:
            raise StreamImportError(f"{where}, message {i}: {exc}") from None
    rows = [rows[i] for i in idx]
    t_ns = t[idx]
    device = next(d for d in (*cfg.platforms, *cfg.base_stations) if d.name == st.device)
    if traj is None and not isinstance(device, BaseStation):
        raise ValueError(f"{where}: platform {device.name}'s stream needs the trajectory for its poses")
    source_frames = sorted({r[2] for r in rows})
    m_pos, m_rot, extrinsics = _mount(st, cfg, device, tf, rows[0][2], int(stamps[idx[0]]), path)
    pos_b, rot_b, _ = device_poses(device, traj, t_ns)
    pos_s, rot_s = (pos_b + rot_b.apply(m_pos)).reshape(-1, 3), rot_b * m_rot
    stamps_kept = dict(header_stamp_ns=[r[0] for r in rows], record_time_ns=[r[1] for r in rows])
    if st.kind == "camera":
        ds = _camera(t_ns, stamps_kept, payloads, info, pos_s, rot_s * frames.OPTICAL_TO_BODY, where)
    elif st.kind == "lidar":
        ds = _lidar(t_ns, stamps_kept, payloads, pos_s, rot_s)
    elif st.kind == "imu":
        ds = _imu(t_ns, stamps_kept, payloads, rot_s)
    else:
        ds = _gps(t_ns, stamps_kept, payloads, pos_s, cfg)
    ds.attrs.update(contract.stream_attrs(
        device.name, device_kind(device), st.sensor, st.kind, t_ns, mount_translation_m=m_pos.tolist(),
        mount_rpy_deg=m_rot.as_euler("xyz", degrees=True).tolist(), mount_rotation=m_rot,
        weather=contract.weather_attrs(weather, applied=False),
        extrinsics_source=extrinsics,
        pose_source="the scene's trajectory at the message times composed with the mount",
        provenance={
            "source": contract.IMPORTED, "source_file": imp.path, "source_format": fmt,
            "source_topic": st.topic, "source_message_type": msgtype,
            "source_frame_id": ", ".join(source_frames),
            "source_stamp": "message header stamps" if imp.stamp == "header" else "bag record times",
            "time_origin": str(imp.time_origin), "time_origin_ns": int(origin),
            "time_offset_s": imp.time_offset_s, "num_messages_in_bag": len(stamps),
            "num_messages_outside_session": int((~inside).sum()),
            "num_repeated_stamps_dropped": int((~first).sum())}))
    return ds


def _camera(t_ns, stamps, payloads, info, position_m, rotation, where) -> xr.Dataset:
    shapes = {p[0].shape for p in payloads}
    if len(shapes) > 1:
        raise StreamImportError(f"{where}: the images change size ({', '.join(map(str, sorted(shapes)))})")
    rgb = np.stack([p[0] for p in payloads])
    n, h, w, _ = rgb.shape
    model = {"pose_model": "pose at the image stamp", "projection": "unknown: no camera_info_topic configured"}
    k, lens = None, {}
    if info is not None:
        if (info["width_px"], info["height_px"]) not in ((w, h), (0, 0)):
            raise StreamImportError(f"{where}: CameraInfo is {info['width_px']}x{info['height_px']} but the "
                                    f"images are {w}x{h}")
        k = info["camera_matrix"]
        lens = dict(distortion_model=info["distortion_model"], distortion_coefficients=info["distortion_coefficients"])
        model.update(horizontal_fov_deg=contract.horizontal_fov_deg(k, w),
                     projection=f"pinhole with {info['distortion_model'] or 'no'} lens distortion "
                                "(distortion_coefficients); images as recorded, not rectified")
    return contract.camera_stream(t_ns, rgb, position_m, rotation.as_quat().reshape(n, 4), camera_matrix=k,
                                  source_encoding=", ".join(sorted({p[1] for p in payloads})),
                                  shading_model="none: as recorded", model=model, **lens, **stamps)


def _grid(clouds: list[np.ndarray], shape: tuple[int, int, int], fill, dtype) -> np.ndarray:
    """Clouds [rows, columns, ...] into one array [time, ring, azimuth, ...] padded with ``fill``."""
    out = np.full(shape + clouds[0].shape[2:], fill, dtype)
    for i, c in enumerate(clouds):
        out[i, :c.shape[0], :c.shape[1]] = c
    return out


def _lidar(t_ns, stamps, payloads, position_m, rotation) -> xr.Dataset:
    clouds = [p.reshape(h, w) for p, h, w in payloads]
    first = clouds[0].dtype
    shape = (len(clouds), max(c.shape[0] for c in clouds), max(c.shape[1] for c in clouds))
    xyz_dtype = np.result_type(*[first[c].base for c in "xyz"], np.float32)
    xyz = [np.stack([c[f].astype(xyz_dtype) for f in "xyz"], axis=-1) for c in clouds]
    points = _grid(xyz, shape, np.nan, xyz_dtype)
    present = _grid([np.ones(c.shape, bool) for c in clouds], shape, False, bool)
    valid = present & np.isfinite(points).all(axis=-1)
    points = np.where(valid[..., None], points, np.nan).astype(xyz_dtype)
    common = [f for f in first.names if all(f in c.dtype.names for c in clouds)]
    fields = {}
    for name in common:
        base = first[name]
        if name in "xyz" or base.shape:  # a multi-count field is not part of the contract: skipped
            continue
        fill = np.nan if np.issubdtype(base, np.floating) else 0
        fields[name] = _grid([c[name] for c in clouds], shape, fill, base.newbyteorder("="))
    # a cloud that carries its ranges (as simart's own export does) keeps them as recorded; others
    # get the norm of x, y, z (which differs from a recorded range by float rounding)
    recorded = fields.pop("range", None)
    range_m = np.linalg.norm(points, axis=-1).astype(xyz_dtype) if recorded is None or not \
        np.issubdtype(recorded.dtype, np.floating) else np.where(valid, recorded, np.nan).astype(xyz_dtype)
    return contract.lidar_stream(
        t_ns, range_m, points, valid, position_m,
        rotation.as_quat().reshape(len(clouds), 4), point_count=[c.size for c in clouds],
        intensity=fields.pop("intensity", None), fields=fields, **stamps,
        model={"channels": shape[1], "horizontal_samples": shape[2], "point_fields": common,
               "layout": "a message's row is a ring and its column an azimuth (an unorganised cloud, height 1, "
                         "is one ring), padded with NaN to the largest cloud",
               "pose_model": "whole cloud from the pose at its stamp (no motion compensation)",
               "beam_model": "as recorded"})


def _imu(t_ns, stamps, payloads, rotation) -> xr.Dataset:
    n = len(payloads)
    acc, gyr = (np.array([p[i] for p in payloads], np.float64) for i in (0, 1))
    rep = np.array([p[2] for p in payloads], np.float64)
    cov = [np.stack([p[i] for p in payloads]).reshape(n, 3, 3) for i in (3, 4, 5)]
    has_orientation = cov[2][:, 0, 0] != -1  # sensor_msgs/Imu: covariance[0] = -1 means no estimate
    rep[~has_orientation] = np.nan
    return contract.imu_stream(
        t_ns, acc, gyr, rotation.as_quat().reshape(n, 4), linear_acceleration_covariance=cov[0],
        angular_velocity_covariance=cov[1], reported_orientation_xyzw=rep, reported_orientation_covariance=cov[2],
        model={"noise_model": "as recorded", "lever_arm": "as recorded: the IMU measures at its own origin"},
        **stamps)


def _gps(t_ns, stamps, payloads, position_m, cfg: SceneConfig) -> xr.Dataset:
    o = cfg.origin
    lla = np.array([p[:3] for p in payloads], np.float64)
    status = np.array([p[3] for p in payloads], np.int8)
    fix = (status >= 0) & np.isfinite(lla).all(axis=1)  # NavSatStatus.STATUS_NO_FIX = -1
    lla[~fix] = np.nan
    enu = frames.geodetic_to_enu(lla, o.latitude_deg, o.longitude_deg, o.altitude_m)
    return contract.gps_stream(
        t_ns, lla[:, 0], lla[:, 1], lla[:, 2], enu, position_m, o, fix_valid=fix, fix_status=status,
        fix_service=[p[4] for p in payloads],
        position_covariance_m2=np.stack([p[5] for p in payloads]).reshape(-1, 3, 3),
        position_covariance_type=[p[6] for p in payloads], model={"noise_model": "as recorded"}, **stamps)
