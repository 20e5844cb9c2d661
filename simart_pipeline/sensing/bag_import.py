"""The sensor plug-in contract: streams recorded by another simulator, imported from a bag.

:func:`build_sensor_frames` is what the ``sensor_frames`` asset stores: every stream of the scene's
``sensor_imports`` (``config.SensorImport``) is read from its bag into the group
``/<device>/<sensor>``, replacing the embedded sensor of that name or adding one, and every other
configured sensor is rendered as before (``streams.render_sensor_frames``). The contract each group
honours is ``docs/sensor-plugin.md``; in short:

- ``time``: int64 ns on the shared clock, ``stamp - time_origin + time_offset_s`` (the header stamps
  or the bag's record times, as configured); the stamps are recorded, not sampled at a rate; messages
  outside the session ``[0, duration]`` are dropped and counted; ``header_stamp_ns`` and
  ``record_time_ns`` keep both original stamps of every message kept.
- the embedded variable names, dims, dtypes and units: ``rgb`` (time, y, x, channel) uint8;
  LiDAR ``points_m``, ``range_m``, ``valid`` per (time, point) since a recorded cloud is a list of
  points, not a ring x azimuth grid; IMU ``linear_acceleration_mps2`` (specific force) and
  ``angular_velocity_radps``; GPS ``latitude_deg``, ``longitude_deg``, ``altitude_m``.
- poses: ``position_m`` / ``orientation_xyzw`` (and GPS ``position_enu_m``) are the scene's
  trajectory at the message times composed with the mount, exactly as for rendered streams; the mount
  comes from the config or from the bag's /tf_static and /tf (``extrinsics: tf``).
- provenance attrs: ``source_file``, ``source_format``, ``source_topic``, ``source_message_type``,
  ``source_frame_id`` (the messages' own frame ids), ``source_stamp``, ``time_origin_ns``,
  ``extrinsics_source``; weather is not applied to a recorded stream.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline import clock, frames
from simart_pipeline.config import BaseStation, ImportedStream, SceneConfig, SensorImport
from simart_pipeline.mobility.bags import Bag, BagError, frame_name, read_tf, stamp_ns, time_origin_ns
from simart_pipeline.vocabulary import AXES
from simart_pipeline.vocabulary import QUATERNION_COMPONENTS as QUAT
from simart_pipeline.sensing import ros_messages as rm
from simart_pipeline.sensing.streams import device_poses, render_sensor_frames

MESSAGE_TYPES = {"camera": (rm.IMAGE, rm.COMPRESSED_IMAGE), "lidar": (rm.POINT_CLOUD2,), "imu": (rm.IMU,),
                 "gps": (rm.NAV_SAT_FIX,)}
TIME_SAMPLING = "recorded message stamps, not sampled at a fixed rate"
NO_WEATHER = "none: a recorded stream is imported as recorded, the same in every weather"


class StreamImportError(BagError):
    """A stream that cannot be imported; the message names the file and the topic."""


def build_sensor_frames(meshes, traj: xr.Dataset, cfg: SceneConfig, weather: str,
                        scene_dir: str | Path | None) -> xr.DataTree:
    """Imported streams from ``cfg.sensor_imports`` plus every other sensor rendered: one tree with a
    group per ``/<device>/<sensor>`` (``meshes`` is used only when a camera or LiDAR is rendered)."""
    imported = {(s.device, s.sensor) for imp in cfg.sensor_imports for s in imp.streams}
    if imported and scene_dir is None:
        raise ValueError(f"scene {cfg.name}: imported sensor streams need the scene directory")

    def keep(dev):
        return tuple(s for s in dev.sensors if (dev.name, s.name) not in imported)

    rendered_cfg = cfg.model_copy(update={
        "platforms": tuple(p.model_copy(update={"sensors": keep(p)}) for p in cfg.platforms),
        "base_stations": tuple(b.model_copy(update={"sensors": keep(b)}) for b in cfg.base_stations)})
    tree = render_sensor_frames(meshes, traj, rendered_cfg, weather)
    if not imported:
        return tree
    groups = {node.path: node.to_dataset() for node in tree.subtree if node.has_data}
    for imp in cfg.sensor_imports:
        groups.update(import_streams(imp, cfg, traj, scene_dir, weather))
    out = xr.DataTree.from_dict(groups)
    out.attrs.update(tree.attrs, imported_streams=sorted(f"/{d}/{s}" for d, s in imported))
    return out


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
        return rm.point_cloud_array(msg)
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
    if st.kind == "camera":
        ds = _camera(payloads, info, pos_s, rot_s * frames.OPTICAL_TO_BODY, where)
    elif st.kind == "lidar":
        ds = _lidar(payloads, pos_s, rot_s)
    elif st.kind == "imu":
        ds = _imu(payloads, rot_s)
    else:
        ds = _gps(payloads, pos_s, cfg)
    coords = {"time": ("time", t_ns.astype(np.int64), dict(
        units="ns", long_name="simulated time since session start (recorded message stamps)"))}
    coords.update({k: v for k, v in (("axis", AXES), ("quaternion", QUAT)) if k in ds.dims})
    ds = ds.assign_coords(coords)
    ds["header_stamp_ns"] = ("time", np.array([r[0] for r in rows], np.int64),
                             dict(units="ns", long_name="the message's header stamp, as recorded"))
    ds["record_time_ns"] = ("time", np.array([r[1] for r in rows], np.int64),
                            dict(units="ns", long_name="the bag's record time of the message"))
    optical = st.kind == "camera"
    mount_rpy = m_rot.as_euler("xyz", degrees=True)
    ds.attrs.update({
        "device": device.name,
        "device_kind": "base_station" if isinstance(device, BaseStation) else "platform",
        "sensor": st.sensor, "sensor_kind": st.kind,
        "frame_id": frames.sensor_frame(device.name, st.sensor, optical=optical),
        "parent_frame_id": frames.base_link(device.name),
        "sensor_frame_id": frames.sensor_frame(device.name, st.sensor),
        "mount_translation_m": m_pos.tolist(), "mount_rpy_deg": mount_rpy.tolist(),
        "mount_quaternion_xyzw": m_rot.as_quat().tolist(),
        "mount_comment": "pose of sensor_frame_id in parent_frame_id: translation (m) and roll about x, "
                         "pitch about y, yaw about z (deg, extrinsic xyz)",
        "quaternion_order": frames.QUATERNION_ORDER,
        "source": "imported from a bag (docs/sensor-plugin.md)",
        "source_file": imp.path, "source_format": fmt, "source_topic": st.topic,
        "source_message_type": msgtype, "source_frame_id": ", ".join(source_frames),
        "source_stamp": "message header stamps" if imp.stamp == "header" else "bag record times",
        "time_origin": str(imp.time_origin), "time_origin_ns": int(origin),
        "time_offset_s": imp.time_offset_s, "time_sampling": TIME_SAMPLING,
        "num_messages_in_bag": len(stamps), "num_messages_outside_session": int((~inside).sum()),
        "num_repeated_stamps_dropped": int((~first).sum()),
        "mean_rate_hz": float((len(t_ns) - 1) / (t_ns[-1] - t_ns[0]) * 1e9) if len(t_ns) > 1 else 0.0,
        "extrinsics_source": extrinsics,
        "pose_source": "the scene's trajectory at the message times composed with the mount",
        "weather": weather, "weather_model": NO_WEATHER,
    })
    if optical:
        ds.attrs["optical_to_sensor_quaternion_xyzw"] = frames.OPTICAL_TO_BODY.as_quat().tolist()
        ds.attrs["optical_comment"] = ("frame_id is the optical frame (z forward, x right, y down), "
                                       "rotated from sensor_frame_id by optical_to_sensor_quaternion_xyzw")
    return ds


def _camera(payloads, info, position_m, rotation, where) -> xr.Dataset:
    shapes = {p[0].shape for p in payloads}
    if len(shapes) > 1:
        raise StreamImportError(f"{where}: the images change size ({', '.join(map(str, sorted(shapes)))})")
    rgb = np.stack([p[0] for p in payloads])
    n, h, w, _ = rgb.shape
    ds = xr.Dataset({
        "rgb": (("time", "y", "x", "channel"), rgb,
                dict(units="1", long_name="colour image, 8-bit as recorded (sRGB assumed)",
                     source_encoding=", ".join(sorted({p[1] for p in payloads})))),
        "position_m": (("time", "axis"), position_m,
                       dict(units="m", long_name="optical frame origin in world (ENU)")),
        "orientation_xyzw": (("time", "quaternion"), rotation.as_quat().reshape(n, 4),
                             dict(units="1", long_name="unit quaternion rotating the optical frame into "
                                                       "world, scalar last")),
    }, coords={"channel": ["r", "g", "b"]})
    ds["rgb"].encoding["chunks"] = (1, h, w, 3)
    ds.attrs.update(width_px=w, height_px=h, pose_model="pose at the image stamp")
    if info is None:
        ds.attrs["projection"] = "unknown: no camera_info_topic configured"
        return ds
    if (info["width_px"], info["height_px"]) not in ((w, h), (0, 0)):
        raise StreamImportError(f"{where}: CameraInfo is {info['width_px']}x{info['height_px']} but the images "
                           f"are {w}x{h}")
    k = info["camera_matrix"]
    ds["camera_matrix"] = (("row", "col"), k, dict(
        units="px", long_name="pinhole intrinsics K from CameraInfo (OpenCV convention: pixel centres "
                              "at integer coordinates)"))
    ds["distortion_coefficients"] = ("distortion_coefficient", info["distortion_coefficients"], dict(
        units="1", long_name=f"lens distortion coefficients, {info['distortion_model']} model (CameraInfo D)"))
    ds.attrs.update(horizontal_fov_deg=float(np.degrees(2 * np.arctan(w / (2 * k[0, 0])))),
                    projection=f"pinhole with {info['distortion_model'] or 'no'} lens distortion "
                               "(distortion_coefficients); images as recorded, not rectified")
    return ds


def _padded(arrays: list[np.ndarray], fill, dtype) -> np.ndarray:
    out = np.full((len(arrays), max(len(a) for a in arrays)) + arrays[0].shape[1:], fill, dtype)
    for i, a in enumerate(arrays):
        out[i, :len(a)] = a
    return out


def _lidar(payloads, position_m, rotation) -> xr.Dataset:
    xyz_dtype = np.result_type(*[payloads[0].dtype[c].base for c in "xyz"], np.float32)
    xyz = [np.stack([p[c].astype(xyz_dtype) for c in "xyz"], axis=-1) for p in payloads]
    points = _padded(xyz, np.nan, xyz_dtype)
    count = np.array([len(p) for p in payloads], np.int64)
    present = np.arange(points.shape[1])[None, :] < count[:, None]
    valid = present & np.isfinite(points).all(axis=-1)
    points = np.where(valid[..., None], points, np.nan).astype(xyz_dtype)
    n = len(payloads)
    ds = xr.Dataset({
        "points_m": (("time", "point", "axis"), points,
                     dict(units="m", long_name="return point in the sensor frame (x fwd, y left, z up), "
                                               "as recorded", nan_means="no point: beyond point_count, or "
                                               "a non-finite point in the message (see valid)")),
        "range_m": (("time", "point"), np.linalg.norm(points, axis=-1).astype(xyz_dtype),
                    dict(units="m", long_name="distance of the point from the sensor origin",
                         nan_means="no point (see valid)")),
        "valid": (("time", "point"), valid,
                  dict(units="1", long_name="a finite point of the message (points_m, range_m defined)")),
        "point_count": ("time", count, dict(units="1", long_name="points in the message (height x width), "
                                                                 "finite or not")),
        "position_m": (("time", "axis"), position_m,
                       dict(units="m", long_name="sensor frame origin in world (ENU) at the cloud's stamp")),
        "orientation_xyzw": (("time", "quaternion"), rotation.as_quat().reshape(n, 4),
                             dict(units="1", long_name="unit quaternion rotating the sensor frame into "
                                                       "world at the cloud's stamp, scalar last")),
    })
    common = [f for f in payloads[0].dtype.names if all(f in p.dtype.names for p in payloads)]
    for name in common:
        base = payloads[0].dtype[name]
        if name in "xyz" or base.shape:  # a multi-count field is not part of the contract: skipped
            continue
        floating = np.issubdtype(base, np.floating)
        arr = _padded([p[name] for p in payloads], np.nan if floating else 0, base.newbyteorder("="))
        attrs = dict(units="1", long_name=f"PointCloud2 field {name!r} as recorded (sensor-specific scale)",
                     comment="defined where point < point_count")
        if floating:
            attrs["nan_means"] = "no point (beyond point_count)"
        ds["intensity" if name == "intensity" else f"field_{name}"] = (("time", "point"), arr, attrs)
    for name in ds.data_vars:
        if ds[name].dims[:2] == ("time", "point"):
            ds[name].encoding["chunks"] = (1,) + ds[name].shape[1:]
    ds.attrs.update(point_fields=common, layout="unorganised: point = row * width + "
                    "column of the message's cloud, padded with NaN to the largest cloud",
                    pose_model="whole cloud from the pose at its stamp (no motion compensation)")
    return ds


def _imu(payloads, rotation) -> xr.Dataset:
    n = len(payloads)
    acc, gyr = (np.array([p[i] for p in payloads], np.float64) for i in (0, 1))
    rep = np.array([p[2] for p in payloads], np.float64)
    cov = [np.stack([p[i] for p in payloads]).reshape(n, 3, 3) for i in (3, 4, 5)]
    has_orientation = cov[2][:, 0, 0] != -1  # sensor_msgs/Imu: covariance[0] = -1 means no estimate
    rep[~has_orientation] = np.nan
    ds = xr.Dataset({
        "linear_acceleration_mps2": (("time", "axis"), acc, dict(
            units="m s-2", long_name="specific force in the IMU frame (gravity reaction included, +g up "
                                     "at rest), as recorded")),
        "angular_velocity_radps": (("time", "axis"), gyr, dict(
            units="rad s-1", long_name="angular velocity of the IMU frame, expressed in the IMU frame, "
                                       "as recorded")),
        "orientation_xyzw": (("time", "quaternion"), rotation.as_quat().reshape(n, 4), dict(
            units="1", long_name="unit quaternion rotating the IMU frame into world, from the scene's "
                                 "trajectory and the mount, scalar last")),
        "reported_orientation_xyzw": (("time", "quaternion"), rep, dict(
            units="1", long_name="orientation the IMU reported: its frame into the IMU's own reference "
                                 "frame, scalar last, as recorded",
            nan_means="the message carries no orientation (orientation_covariance[0] = -1)")),
        "linear_acceleration_covariance": (("time", "row", "col"), cov[0], dict(
            units="m2 s-4", long_name="covariance of linear_acceleration_mps2, as recorded (all 0: unknown)")),
        "angular_velocity_covariance": (("time", "row", "col"), cov[1], dict(
            units="rad2 s-2", long_name="covariance of angular_velocity_radps, as recorded (all 0: unknown)")),
        "reported_orientation_covariance": (("time", "row", "col"), cov[2], dict(
            units="rad2", long_name="covariance of reported_orientation_xyzw about x, y, z, as recorded "
                                    "(-1 in the first element: no orientation)")),
    })
    ds.attrs.update(noise_model="as recorded", gravity_convention="sensor_msgs/Imu: specific force, "
                    "+g up at rest")
    return ds


def _gps(payloads, position_m, cfg: SceneConfig) -> xr.Dataset:
    o = cfg.origin
    lla = np.array([p[:3] for p in payloads], np.float64)
    status = np.array([p[3] for p in payloads], np.int8)
    fix = (status >= 0) & np.isfinite(lla).all(axis=1)  # NavSatStatus.STATUS_NO_FIX = -1
    lla[~fix] = np.nan
    enu = frames.geodetic_to_enu(lla, o.latitude_deg, o.longitude_deg, o.altitude_m)
    nan = "no fix (NavSatStatus -1, or a non-finite value in the message)"
    ds = xr.Dataset({
        "latitude_deg": ("time", lla[:, 0], dict(units="degrees_north", long_name="WGS84 latitude of the fix, "
                                                 "as recorded", standard_name="latitude", nan_means=nan)),
        "longitude_deg": ("time", lla[:, 1], dict(units="degrees_east", long_name="WGS84 longitude of the fix, "
                                                  "as recorded", standard_name="longitude", nan_means=nan)),
        "altitude_m": ("time", lla[:, 2], dict(units="m", long_name="WGS84 ellipsoidal height of the fix, "
                                               "as recorded", nan_means=nan)),
        "fix_enu_m": (("time", "axis"), enu, dict(units="m", long_name="the fix in world (ENU about the "
                                                  "scene origin)", nan_means=nan)),
        "fix_valid": ("time", fix, dict(units="1", long_name="the message holds a fix")),
        "fix_status": ("time", status, dict(units="1", long_name="sensor_msgs/NavSatStatus status",
                                            flag_values=[-1, 0, 1, 2],
                                            flag_meanings="no_fix fix sbas_fix gbas_fix")),
        "fix_service": ("time", np.array([p[4] for p in payloads], np.uint16), dict(
            units="1", long_name="sensor_msgs/NavSatStatus service", flag_masks=[1, 2, 4, 8],
            flag_meanings="gps glonass compass galileo")),
        "position_covariance_m2": (("time", "row", "col"), np.stack([p[5] for p in payloads]).reshape(-1, 3, 3),
                                   dict(units="m2", long_name="covariance of the fix in ENU, as recorded")),
        "position_covariance_type": ("time", np.array([p[6] for p in payloads], np.uint8), dict(
            units="1", long_name="sensor_msgs/NavSatFix position_covariance_type", flag_values=[0, 1, 2, 3],
            flag_meanings="unknown approximated diagonal_known known")),
        "position_enu_m": (("time", "axis"), position_m, dict(
            units="m", long_name="antenna position in world (ENU) from the scene's trajectory and the mount")),
    })
    ds.attrs.update(origin_latitude_deg=o.latitude_deg, origin_longitude_deg=o.longitude_deg,
                    origin_altitude_m=o.altitude_m, noise_model="as recorded")
    return ds
