"""The stream contract: one constructor per sensor kind, shared by the renderers and the bag import.

A ``sensor_frames`` group is built here and only here: :func:`camera_stream`, :func:`lidar_stream`,
:func:`imu_stream` and :func:`gps_stream` take the arrays a source has and return the kind's dataset
(dims, coords, dtypes, units, ``long_name``, ``nan_means``, chunks), and :func:`stream_attrs` gives
the group attrs every kind shares (identity, frames, mount, time sampling, provenance, weather). The
embedded renderers (:mod:`.camera`, :mod:`.lidar`, :mod:`.inertial`) and the bag import
(:mod:`.bag_import`) call them and declare none of that themselves.

A rendered stream and an imported stream of one kind therefore hold the same variables, the same
dims per variable and the same attrs keys (group attrs and per-variable attrs); the one exception is
LiDAR ``field_<name>``: PointCloud2 fields other than ``x y z intensity`` kept as recorded. What a
source cannot know is filled with a documented absent value (``docs/sensor-plugin.md``):

- a variable a source does not measure: NaN (float, with ``nan_means`` saying so), ``False``
  (masks), 0 (labels: unlabeled / no instance);
- a numeric attr that does not apply: NaN; a text attr: ``"none"``; a count: 0.

Whether a stream is recorded is told by the per-message stamps: a constructor given
``header_stamp_ns`` and ``record_time_ns`` builds an imported stream, one given none a rendered
stream, whose stamps are its sample instants (equal to ``time``).
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline import frames
from simart_pipeline.config import WorldOrigin
from simart_pipeline.sensing.weather import WEATHER_MODELS
from simart_pipeline.vocabulary import AXES, QUATERNION_COMPONENTS, QUATERNION_ORDER, semantic_flag_attrs

NONE = "none"  # a text attr that does not apply to the stream's source
RENDERED = "rendered by simart-pipeline (docs/sensing.md)"
IMPORTED = "imported from a bag (docs/sensor-plugin.md)"
RENDERED_TIME_SAMPLING = "fixed rate: clock.sample_times_ns(duration_s, rate_hz)"
IMPORTED_TIME_SAMPLING = "recorded message stamps, not sampled at a fixed rate"
WEATHER_APPLIED = "applied: the weather_* parameters (sensing/weather.py)"
WEATHER_NOT_APPLIED = "none: a recorded stream is imported as recorded, the same in every weather"
MOUNT_COMMENT = ("pose of sensor_frame_id in parent_frame_id: translation (m) and roll about x, "
                 "pitch about y, yaw about z (deg, extrinsic xyz)")

# Provenance attrs of every group, with their values for a rendered stream.
RENDERED_PROVENANCE = {
    "source": RENDERED, "source_file": NONE, "source_format": NONE, "source_topic": NONE,
    "source_message_type": NONE, "source_frame_id": NONE,
    "source_stamp": "the sample instants of the shared clock",
    "time_origin": "session start", "time_origin_ns": 0, "time_offset_s": 0.0,
    "num_messages_in_bag": 0, "num_messages_outside_session": 0, "num_repeated_stamps_dropped": 0,
}


def _absent(value):
    if isinstance(value, str):
        return NONE
    if isinstance(value, (list, tuple)):
        return [_absent(v) for v in value]
    return float("nan")


def weather_attrs(weather: str, *, applied: bool) -> dict:
    """``weather``, ``weather_<parameter>`` (the session weather's model, :mod:`.weather`) and
    ``weather_model``: whether it was applied to the stream. An unknown or empty weather (an import
    outside a session) gives every parameter its absent value."""
    wx = WEATHER_MODELS.get(weather)
    if wx is None:
        wx_attrs = {k: _absent(v) for k, v in next(iter(WEATHER_MODELS.values())).attrs().items()}
        wx_attrs["weather"] = weather
    else:
        wx_attrs = wx.attrs()
    return {**wx_attrs, "weather_model": WEATHER_APPLIED if applied else WEATHER_NOT_APPLIED}


def stream_attrs(device: str, device_kind: str, sensor: str, sensor_kind: str, times_ns: np.ndarray, *,
                 mount_translation_m, mount_rpy_deg, mount_rotation: Rotation, weather: dict,
                 rate_hz: float = float("nan"), provenance: dict | None = None,
                 extrinsics_source: str = "config: the sensor's mount",
                 pose_source: str = "the device's pose at the sample instants composed with the mount") -> dict:
    """The group attrs every stream carries.

    :param device_kind: ``platform`` or ``base_station``.
    :param times_ns: the stream's ``time`` values (for ``mean_rate_hz``).
    :param weather: :func:`weather_attrs`.
    :param rate_hz: the configured rate of a rendered stream; NaN (default) for a recorded one.
    :param provenance: the keys of ``RENDERED_PROVENANCE`` for an imported stream (all required);
        None for a rendered stream, which takes ``RENDERED_PROVENANCE``.
    """
    if provenance is None:
        prov = dict(RENDERED_PROVENANCE)
    else:
        missing = set(RENDERED_PROVENANCE) - set(provenance)
        extra = set(provenance) - set(RENDERED_PROVENANCE)
        if missing or extra:
            raise ValueError(f"provenance keys: missing {sorted(missing)}, unknown {sorted(extra)}")
        prov = dict(provenance)
    optical = sensor_kind == "camera"
    t = np.asarray(times_ns)
    attrs = {
        "device": device, "device_kind": device_kind, "sensor": sensor, "sensor_kind": sensor_kind,
        "rate_hz": rate_hz,
        "frame_id": frames.sensor_frame(device, sensor, optical=optical),
        "parent_frame_id": frames.base_link(device),
        "sensor_frame_id": frames.sensor_frame(device, sensor),
        "mount_translation_m": list(mount_translation_m), "mount_rpy_deg": list(mount_rpy_deg),
        "mount_quaternion_xyzw": mount_rotation.as_quat().tolist(),
        "mount_comment": MOUNT_COMMENT,
        "quaternion_order": QUATERNION_ORDER,
    }
    if optical:
        attrs["optical_to_sensor_quaternion_xyzw"] = frames.OPTICAL_TO_BODY.as_quat().tolist()
        attrs["optical_comment"] = ("frame_id is the optical frame (z forward, x right, y down), "
                                    "rotated from sensor_frame_id by optical_to_sensor_quaternion_xyzw")
    attrs.update(weather)
    attrs.update(prov)
    attrs.update(
        time_sampling=RENDERED_TIME_SAMPLING if provenance is None else IMPORTED_TIME_SAMPLING,
        mean_rate_hz=float((len(t) - 1) / (t[-1] - t[0]) * 1e9) if len(t) > 1 and t[-1] > t[0] else 0.0,
        extrinsics_source=extrinsics_source, pose_source=pose_source)
    return attrs


def _model_attrs(kind: str, keys: dict, model: dict) -> dict:
    unknown = set(model) - set(keys)
    if unknown:
        raise ValueError(f"{kind} stream: attrs {sorted(unknown)} are not in the contract")
    return {k: model.get(k, v) for k, v in keys.items()}


def _finish(ds: xr.Dataset, times_ns: np.ndarray, header_stamp_ns, record_time_ns, model: dict) -> xr.Dataset:
    """The time coordinate, the axis / quaternion labels, the per-message stamps and the kind's attrs."""
    t = np.asarray(times_ns).astype(np.int64)
    recorded = header_stamp_ns is not None
    coords = {"time": ("time", t, dict(units="ns", long_name="simulated time since session start" +
                                       (" (recorded message stamps)" if recorded else "")))}
    coords.update({k: v for k, v in (("axis", AXES), ("quaternion", QUATERNION_COMPONENTS)) if k in ds.dims})
    ds = ds.assign_coords(coords)
    if recorded:
        ds["header_stamp_ns"] = ("time", np.asarray(header_stamp_ns, np.int64),
                                 dict(units="ns", long_name="the message's header stamp, as recorded"))
        ds["record_time_ns"] = ("time", np.asarray(record_time_ns, np.int64),
                                dict(units="ns", long_name="the bag's record time of the message"))
    else:
        same = "the sample instant, equal to time (a rendered stream has no {})"
        ds["header_stamp_ns"] = ("time", t.copy(), dict(units="ns", long_name=same.format("message header")))
        ds["record_time_ns"] = ("time", t.copy(), dict(units="ns", long_name=same.format("record time")))
    ds.attrs.update(model)
    return ds


def _const(value, shape, dtype) -> np.ndarray:
    """A constant array of ``shape`` that takes no memory (read-only broadcast)."""
    return np.broadcast_to(np.asarray(value, dtype), shape)


def diagonal_covariance(std, n: int) -> np.ndarray:
    """[n, 3, 3] covariance diag(std^2) per sample, from per-axis standard deviations [3]."""
    return np.tile(np.diag(np.asarray(std, np.float64) ** 2), (n, 1, 1))


# --- camera ----------------------------------------------------------------------------------------------

CAMERA_ATTRS = {"width_px": 0, "height_px": 0, "horizontal_fov_deg": float("nan"), "max_depth_m": float("nan"),
                "projection": NONE, "pose_model": NONE}


def camera_stream(times_ns, rgb: np.ndarray, position_m: np.ndarray, orientation_xyzw: np.ndarray, *,
                  camera_matrix: np.ndarray | None, distortion_model: str | None = None,
                  distortion_coefficients: np.ndarray | None = None, depth_m: np.ndarray | None = None,
                  semantic_class: np.ndarray | None = None, instance_id: np.ndarray | None = None,
                  max_depth_m: float = float("nan"), shading_model: str = NONE, source_encoding: str = NONE,
                  header_stamp_ns=None, record_time_ns=None, model: dict | None = None,
                  actor_truth: dict | None = None) -> xr.Dataset:
    """A camera stream: ``rgb`` [time, y, x, channel] uint8 and the optical frame's pose per frame.

    ``actor_truth`` (rendered, :func:`actor_truth_variables`): the ground truth of every actor per
    frame on an ``actor`` dim; without it (imported streams, scenes without actors) the dim is empty.

    Rendered (no stamps): ``depth_m`` (NaN: sky), ``semantic_class``, ``instance_id`` and
    ``camera_matrix`` are given; ``distortion_coefficients`` default to five zeros (``plumb_bob``
    with all-zero D: no distortion, as in ROS). Imported: ``depth_m`` NaN ("not recorded"),
    ``depth_valid`` False, ``semantic_class`` 0 (unlabeled), ``instance_id`` 0; ``camera_matrix`` and
    ``distortion_coefficients`` (five values) NaN without a CameraInfo.
    ``model``: the keys of ``CAMERA_ATTRS`` the source knows (the rest take their absent values).
    """
    recorded = header_stamp_ns is not None
    n, h, w, _ = rgb.shape
    img = (n, h, w)
    no_depth = depth_m is None
    if no_depth:
        depth_m = _const(np.nan, img, np.float32)
    depth_valid = _const(False, img, bool) if no_depth else ~np.isnan(depth_m)
    if semantic_class is None:
        semantic_class = _const(0, img, np.uint8)
    if instance_id is None:
        instance_id = _const(0, img, np.int64)
    if camera_matrix is None:
        camera_matrix = np.full((3, 3), np.nan)
    if distortion_coefficients is None:
        distortion_coefficients = np.full(5, np.nan) if recorded else np.zeros(5)
        distortion_model = distortion_model or ("unknown" if recorded else "plumb_bob")
    unlabeled = ("0 (unlabeled) everywhere: a recorded image carries no labels" if recorded else
                 "0 (unlabeled) where no surface is seen: sky or beyond max_depth_m")
    ds = xr.Dataset(
        {
            "rgb": (("time", "y", "x", "channel"), rgb,
                    dict(units="1", long_name="colour image, 8-bit as recorded (sRGB assumed)" if recorded
                         else "colour image, sRGB-encoded 8-bit",
                         shading_model=shading_model, source_encoding=source_encoding)),
            "depth_m": (("time", "y", "x"), depth_m,
                        dict(units="m", long_name="z-depth of the visible surface along the optical axis",
                             nan_means="not recorded: an imported camera stream has no depth" if no_depth
                             else "no surface within max_depth_m along the pixel's ray (sky)",
                             max_depth_m=max_depth_m)),
            "depth_valid": (("time", "y", "x"), depth_valid,
                            dict(units="1", long_name="false everywhere: no depth recorded" if no_depth else
                                 "the pixel sees a surface within max_depth_m "
                                 "(depth_m, semantic_class and instance_id are defined)")),
            "semantic_class": (("time", "y", "x"), semantic_class,
                               dict(units="1", long_name="semantic class of the visible surface",
                                    **semantic_flag_attrs(), comment=unlabeled)),
            "instance_id": (("time", "y", "x"), instance_id,
                            dict(units="1", long_name="source feature id (OSM or generated id) of the "
                                                      "visible surface",
                                 comment="0 everywhere: a recorded image carries no instances" if recorded
                                 else "0 where no surface is seen; source ids are positive")),
            "camera_matrix": (("row", "col"), camera_matrix,
                              dict(units="px", long_name="pinhole intrinsics K from CameraInfo (OpenCV convention: "
                                   "pixel centres at integer coordinates)" if recorded else
                                   "pinhole intrinsics K (OpenCV convention: pixel centres at integer coordinates)",
                                   nan_means="unknown: imported without a camera_info_topic")),
            "position_m": (("time", "axis"), np.asarray(position_m, np.float64),
                           dict(units="m", long_name="optical frame origin in world (ENU)")),
            "orientation_xyzw": (("time", "quaternion"), orientation_xyzw,
                                 dict(units="1", long_name="unit quaternion rotating the optical frame "
                                                           "into world, scalar last")),
            "distortion_coefficients": ("distortion_coefficient", distortion_coefficients, dict(
                units="1", long_name=f"lens distortion coefficients, {distortion_model or 'no'} model "
                                     + ("(CameraInfo D)" if recorded else "(all zero: no distortion)"),
                distortion_model=distortion_model,
                nan_means="unknown: imported without a camera_info_topic")),
        },
        coords={"channel": ["r", "g", "b"]},
    )
    for name in ("rgb", "depth_m", "depth_valid", "semantic_class", "instance_id"):
        ds[name].encoding["chunks"] = (1,) + ds[name].shape[1:]
    ds = ds.assign(actor_truth_variables(n, **(actor_truth or {})))
    attrs = _model_attrs("camera", CAMERA_ATTRS, dict(model or {}, width_px=w, height_px=h, max_depth_m=max_depth_m))
    return _finish(ds, times_ns, header_stamp_ns, record_time_ns, attrs)


BOX_CORNERS = ("u_min", "v_min", "u_max", "v_max")


def actor_truth_variables(n: int, names=(), instance_id=(), semantic_class=(), pixel_count=None,
                          visible_box_px=None, projected_box_px=None, distance_m=None) -> dict:
    """Per frame and actor: visible pixel count, the box of the visible pixels, the projection of
    the body's vertices, and the distance to the body's bounding-box centre."""
    a = len(names)
    nan_box = np.full((n, a, 4), np.nan, np.float32)
    box = dict(units="px", box_corners="u_min, v_min, u_max, v_max: pixel indices (centres at "
               "integers), inclusive")
    return {
        "actor_pixel_count": (("time", "actor"), np.zeros((n, a), np.int32) if pixel_count is None
                              else pixel_count, dict(units="1", long_name="pixels whose instance_id is "
                                                     "the actor's (0: not visible in the frame)")),
        "actor_visible_box_px": (("time", "actor", "box_corner"), nan_box if visible_box_px is None
                                 else visible_box_px, dict(long_name="bounding box of the actor's visible "
                                                           "pixels", nan_means="not visible", **box)),
        "actor_projected_box_px": (("time", "actor", "box_corner"), nan_box.copy() if projected_box_px is None
                                   else projected_box_px, dict(
                                       long_name="bounding box of the projection of the actor's mesh "
                                       "vertices, occlusion and image borders ignored",
                                       nan_means="a vertex lies behind the camera", **box)),
        "actor_distance_m": (("time", "actor"), np.full((n, a), np.nan) if distance_m is None else distance_m,
                             dict(units="m", long_name="distance from the optical centre to the centre of "
                                  "the actor body's bounding box")),
        "actor_instance_id": ("actor", np.asarray(instance_id, np.int64).reshape(a),
                              dict(units="1", long_name="the actor's instance_id in the images")),
        "actor_semantic_class": ("actor", np.asarray(semantic_class, np.uint8).reshape(a),
                                 dict(units="1", long_name="the actor's semantic class", **semantic_flag_attrs())),
        "actor": ("actor", np.asarray(names, dtype=str).reshape(a), dict(long_name="actor name")),
        "box_corner": ("box_corner", list(BOX_CORNERS)),
    }


def horizontal_fov_deg(camera_matrix: np.ndarray, width_px: int) -> float:
    """The horizontal field of view of a pinhole K (deg)."""
    return float(np.degrees(2 * np.arctan(width_px / (2 * camera_matrix[0, 0]))))


# --- LiDAR -----------------------------------------------------------------------------------------------

LIDAR_ATTRS = {"channels": 0, "horizontal_samples": 0, "vertical_fov_deg": [float("nan")] * 2,
               "max_range_m": float("nan"), "range_noise_std_m": float("nan"),
               "effective_range_noise_std_m": float("nan"), "dropout_probability": float("nan"),
               "pose_model": NONE, "beam_model": NONE, "point_fields": [], "layout": NONE}
NO_INTENSITY = "the embedded LiDAR model has no intensity"


def lidar_stream(times_ns, range_m: np.ndarray, points_m: np.ndarray, valid: np.ndarray, position_m: np.ndarray,
                 orientation_xyzw: np.ndarray, *, point_count: np.ndarray, elevation_rad: np.ndarray | None = None,
                 azimuth_rad: np.ndarray | None = None, semantic_class: np.ndarray | None = None,
                 intensity: np.ndarray | None = None, fields: dict[str, np.ndarray] | None = None,
                 header_stamp_ns=None, record_time_ns=None, model: dict | None = None) -> xr.Dataset:
    """A LiDAR stream on (time, ring, azimuth): ``range_m``, ``valid``, ``points_m`` (…, axis) in the
    sensor frame, ``semantic_class``, ``intensity``, ``point_count`` per sweep.

    Rendered: the beam grid with its ``elevation_rad`` / ``azimuth_rad``; ``intensity`` NaN (the
    embedded model has none). Imported: a message's row is a ring and its column an azimuth (an
    unorganised cloud is one ring), padded to the largest cloud with NaN / ``valid`` False;
    ``elevation_rad`` / ``azimuth_rad`` NaN (unknown), ``semantic_class`` 0 (unlabeled),
    ``intensity`` as recorded (NaN where the cloud has none), ``fields``: the other PointCloud2
    fields, stored as ``field_<name>`` (the only variables outside the contract).
    """
    recorded = header_stamp_ns is not None
    n, rings, n_az = range_m.shape
    grid = (n, rings, n_az)
    if elevation_rad is None:
        elevation_rad = np.full(rings, np.nan)
    if azimuth_rad is None:
        azimuth_rad = np.full(n_az, np.nan)
    if semantic_class is None:
        semantic_class = _const(0, grid, np.uint8)
    no_point = ("no point: beyond the message's rows or columns, or a non-finite point in the message "
                "(see valid)" if recorded else "no return (see range_m)")
    ds = xr.Dataset(
        {
            "range_m": (("time", "ring", "azimuth"), range_m,
                        dict(units="m", long_name="distance of the point from the sensor origin" if recorded
                             else "range of the beam's return (with range noise)",
                             nan_means=no_point if recorded else
                             "no return: nothing within max_range_m, or dropped by the weather")),
            "valid": (("time", "ring", "azimuth"), valid,
                      dict(units="1", long_name="a finite point of the message (points_m, range_m defined)"
                           if recorded else "the beam returned (range_m, points_m and semantic_class defined)")),
            "points_m": (("time", "ring", "azimuth", "axis"), points_m,
                         dict(units="m", long_name="return point in the sensor frame (x fwd, y left, z up)"
                              + (", as recorded" if recorded else ""), nan_means=no_point)),
            "semantic_class": (("time", "ring", "azimuth"), semantic_class,
                               dict(units="1", long_name="semantic class of the surface hit",
                                    **semantic_flag_attrs(),
                                    comment="0 (unlabeled) everywhere: a recorded cloud carries no labels"
                                    if recorded else "0 (unlabeled) where there is no return")),
            "position_m": (("time", "axis"), np.asarray(position_m, np.float64),
                           dict(units="m", long_name="sensor frame origin in world (ENU) at the "
                                + ("cloud's stamp" if recorded else "sweep"))),
            "orientation_xyzw": (("time", "quaternion"), orientation_xyzw,
                                 dict(units="1", long_name="unit quaternion rotating the sensor frame into world at the "
                                      + ("cloud's stamp" if recorded else "sweep") + ", scalar last")),
            "point_count": ("time", np.asarray(point_count, np.int64),
                            dict(units="1", long_name="points in the message (height x width), finite or not"
                                 if recorded else "beams in the sweep (channels x horizontal_samples), "
                                 "returned or not")),
            "intensity": (("time", "ring", "azimuth"),
                          _const(np.nan, grid, np.float32) if intensity is None else intensity,
                          dict(units="1", long_name="return intensity (PointCloud2 field 'intensity' as "
                               "recorded, sensor-specific scale)",
                               nan_means=("no point, or the cloud has no intensity field" if recorded
                                          else NO_INTENSITY),
                               comment="defined where valid; an integer field is 0 where there is no point")),
        },
        coords={
            "elevation_rad": ("ring", elevation_rad, dict(units="rad", long_name="beam elevation above the "
                                                          "sensor's x-y plane", nan_means="unknown for a "
                                                          "recorded cloud")),
            "azimuth_rad": ("azimuth", azimuth_rad, dict(units="rad", long_name="beam azimuth from +x towards +y",
                                                         nan_means="unknown for a recorded cloud")),
        },
    )
    for name, arr in (fields or {}).items():
        attrs = dict(units="1", long_name=f"PointCloud2 field {name!r} as recorded (sensor-specific scale)",
                     comment="defined where the message has a point; an integer field is 0 elsewhere")
        if np.issubdtype(arr.dtype, np.floating):
            attrs["nan_means"] = "no point (beyond the message's rows or columns)"
        ds[f"field_{name}"] = (("time", "ring", "azimuth"), arr, attrs)
    for name in ds.data_vars:
        if ds[name].dims[1:3] == ("ring", "azimuth"):
            ds[name].encoding["chunks"] = (1,) + ds[name].shape[1:]
    attrs = _model_attrs("lidar", LIDAR_ATTRS, model or {})
    return _finish(ds, times_ns, header_stamp_ns, record_time_ns, attrs)


# --- IMU -------------------------------------------------------------------------------------------------

IMU_ATTRS = {"gravity_mps2": float("nan"), "accel_noise_std_mps2": float("nan"),
             "gyro_noise_std_radps": float("nan"), "accel_bias_mps2": [float("nan")] * 3,
             "gyro_bias_radps": [float("nan")] * 3, "noise_model": NONE, "lever_arm": NONE,
             "gravity_convention": "sensor_msgs/Imu: specific force, +g up at rest"}


def imu_stream(times_ns, linear_acceleration_mps2: np.ndarray, angular_velocity_radps: np.ndarray,
               orientation_xyzw: np.ndarray, *, linear_acceleration_covariance: np.ndarray,
               angular_velocity_covariance: np.ndarray, reported_orientation_xyzw: np.ndarray | None = None,
               reported_orientation_covariance: np.ndarray | None = None, header_stamp_ns=None,
               record_time_ns=None, model: dict | None = None) -> xr.Dataset:
    """An IMU stream: specific force and angular rate in the IMU frame, the IMU frame's orientation.

    Covariances [time, row, col]: rendered, diag(noise std^2) (:func:`diagonal_covariance`);
    imported, as recorded (all 0: unknown). ``reported_orientation_xyzw``: what the IMU reported,
    NaN without an estimate, with ``reported_orientation_covariance`` first element -1 (the
    ``sensor_msgs/Imu`` rule), which is also what a rendered stream has (the default).
    """
    recorded = header_stamp_ns is not None
    n = len(linear_acceleration_mps2)
    if reported_orientation_xyzw is None:
        reported_orientation_xyzw = np.full((n, 4), np.nan)
    if reported_orientation_covariance is None:
        reported_orientation_covariance = np.zeros((n, 3, 3))
        reported_orientation_covariance[:, 0, 0] = -1.0
    how = ", as recorded" if recorded else " with bias and noise"
    ds = xr.Dataset({
        "linear_acceleration_mps2": (("time", "axis"), linear_acceleration_mps2, dict(
            units="m s-2", long_name="specific force in the IMU frame (gravity reaction included, +g up at rest)"
            + how)),
        "angular_velocity_radps": (("time", "axis"), angular_velocity_radps, dict(
            units="rad s-1", long_name="angular velocity of the IMU frame, expressed in the IMU frame, "
            + ("as recorded" if recorded else "with bias and noise"))),
        "orientation_xyzw": (("time", "quaternion"), orientation_xyzw, dict(
            units="1", long_name="unit quaternion rotating the IMU frame into world, from the scene's "
            "trajectory and the mount, scalar last" if recorded else
            "true unit quaternion rotating the IMU frame into world, scalar last")),
        "reported_orientation_xyzw": (("time", "quaternion"), reported_orientation_xyzw, dict(
            units="1", long_name="orientation the IMU reported: its frame into the IMU's own reference "
                                 "frame, scalar last, as recorded",
            nan_means="the message carries no orientation (orientation_covariance[0] = -1)" if recorded
            else "the embedded IMU reports no orientation estimate")),
        "linear_acceleration_covariance": (("time", "row", "col"), linear_acceleration_covariance, dict(
            units="m2 s-4", long_name="covariance of linear_acceleration_mps2, " +
            ("as recorded (all 0: unknown)" if recorded else "diag(accel_noise_std_mps2^2)"))),
        "angular_velocity_covariance": (("time", "row", "col"), angular_velocity_covariance, dict(
            units="rad2 s-2", long_name="covariance of angular_velocity_radps, " +
            ("as recorded (all 0: unknown)" if recorded else "diag(gyro_noise_std_radps^2)"))),
        "reported_orientation_covariance": (("time", "row", "col"), reported_orientation_covariance, dict(
            units="rad2", long_name="covariance of reported_orientation_xyzw about x, y, z" +
            (", as recorded" if recorded else "") + " (-1 in the first element: no orientation)")),
    })
    attrs = _model_attrs("imu", IMU_ATTRS, model or {})
    return _finish(ds, times_ns, header_stamp_ns, record_time_ns, attrs)


# --- GPS -------------------------------------------------------------------------------------------------

GPS_ATTRS = {"horizontal_noise_std_m": float("nan"), "vertical_noise_std_m": float("nan"),
             "origin_latitude_deg": float("nan"), "origin_longitude_deg": float("nan"),
             "origin_altitude_m": float("nan"), "noise_model": NONE}
NO_FIX = "no fix (NavSatStatus -1, or a non-finite value in the message)"


def gps_stream(times_ns, latitude_deg: np.ndarray, longitude_deg: np.ndarray, altitude_m: np.ndarray,
               fix_enu_m: np.ndarray, position_enu_m: np.ndarray, origin: WorldOrigin, *, fix_valid: np.ndarray,
               fix_status: np.ndarray, fix_service: np.ndarray, position_covariance_m2: np.ndarray,
               position_covariance_type: np.ndarray, header_stamp_ns=None, record_time_ns=None,
               model: dict | None = None) -> xr.Dataset:
    """A GPS stream: the WGS84 fix, the fix in the scene's ENU frame, its NavSatStatus and
    covariance, and the antenna's position from the trajectory and the mount.

    Rendered: the noisy fix, ``fix_valid`` True, ``fix_status`` 0 (fix), ``fix_service`` 1 (GPS),
    ``position_covariance_m2`` diag(h^2, h^2, v^2), ``position_covariance_type`` 2 (diagonal_known).
    """
    recorded = header_stamp_ns is not None
    rec = ", as recorded" if recorded else ""
    ds = xr.Dataset({
        "latitude_deg": ("time", latitude_deg, dict(units="degrees_north", long_name="WGS84 latitude of the fix"
                                                    + rec, standard_name="latitude", nan_means=NO_FIX)),
        "longitude_deg": ("time", longitude_deg, dict(units="degrees_east", long_name="WGS84 longitude of the "
                                                      "fix" + rec, standard_name="longitude", nan_means=NO_FIX)),
        "altitude_m": ("time", altitude_m, dict(units="m", long_name="WGS84 ellipsoidal height of the fix" + rec,
                                                nan_means=NO_FIX)),
        "position_enu_m": (("time", "axis"), position_enu_m, dict(
            units="m", long_name="antenna position in world (ENU) from the scene's trajectory and the mount"
            if recorded else "true antenna position in world (ENU), no noise")),
        "fix_enu_m": (("time", "axis"), fix_enu_m, dict(units="m", long_name="the fix in world (ENU about the "
                                                        "scene origin)", nan_means=NO_FIX)),
        "fix_valid": ("time", fix_valid, dict(units="1", long_name="the message holds a fix")),
        "fix_status": ("time", np.asarray(fix_status, np.int8), dict(
            units="1", long_name="sensor_msgs/NavSatStatus status", flag_values=[-1, 0, 1, 2],
            flag_meanings="no_fix fix sbas_fix gbas_fix")),
        "fix_service": ("time", np.asarray(fix_service, np.uint16), dict(
            units="1", long_name="sensor_msgs/NavSatStatus service", flag_masks=[1, 2, 4, 8],
            flag_meanings="gps glonass compass galileo")),
        "position_covariance_m2": (("time", "row", "col"), position_covariance_m2, dict(
            units="m2", long_name="covariance of the fix in ENU, " +
            ("as recorded" if recorded else "diag(h^2, h^2, v^2) of the noise model"))),
        "position_covariance_type": ("time", np.asarray(position_covariance_type, np.uint8), dict(
            units="1", long_name="sensor_msgs/NavSatFix position_covariance_type", flag_values=[0, 1, 2, 3],
            flag_meanings="unknown approximated diagonal_known known")),
    })
    attrs = _model_attrs("gps", GPS_ATTRS, dict(model or {}, origin_latitude_deg=origin.latitude_deg,
                                                origin_longitude_deg=origin.longitude_deg,
                                                origin_altitude_m=origin.altitude_m))
    return _finish(ds, times_ns, header_stamp_ns, record_time_ns, attrs)
