"""ROS sensor message payloads as numpy arrays: images, point clouds, camera intrinsics.

Message objects are those ``rosbags`` deserialises (ROS1 or ROS2 definitions: field names such as
CameraInfo's ``K``/``k`` differ in case between the two and both are taken). JPEG and PNG are
decoded by OpenCV (already a dependency); a ``PointCloud2`` is read with a numpy structured dtype
built from its ``fields`` (name, offset, datatype, count), its ``point_step``, ``row_step`` and
endianness, so any layout a driver publishes is read without copying point by point.
"""

from __future__ import annotations

import numpy as np

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
IMU = "sensor_msgs/msg/Imu"
NAV_SAT_FIX = "sensor_msgs/msg/NavSatFix"

# sensor_msgs/PointField datatypes (INT8 = 1 ... FLOAT64 = 8)
POINT_FIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}

# sensor_msgs/image_encodings.h: 8-bit colour and mono encodings -> (channels, order)
IMAGE_ENCODINGS = {"rgb8": (3, "rgb"), "bgr8": (3, "bgr"), "rgba8": (4, "rgb"), "bgra8": (4, "bgr"),
                   "mono8": (1, "mono"), "8UC1": (1, "mono"), "8UC3": (3, "bgr"), "8UC4": (4, "bgr")}


class MessageError(ValueError):
    """A message whose payload cannot be decoded; the caller adds the file and topic."""


def _field(msg, *names):
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise MessageError(f"{type(msg).__name__} has none of the fields {', '.join(names)}")


def _to_rgb(img: np.ndarray, order: str) -> np.ndarray:
    if img.ndim == 2 or order == "mono":
        g = img.reshape(img.shape[0], img.shape[1])
        return np.repeat(g[:, :, None], 3, axis=2)
    rgb = img[:, :, :3]
    return np.ascontiguousarray(rgb[:, :, ::-1] if order == "bgr" else rgb)


def image_rgb(msg, msgtype: str) -> tuple[np.ndarray, str]:
    """``[height, width, 3]`` uint8 RGB of an ``Image`` (8-bit colour or mono encodings) or a
    JPEG/PNG ``CompressedImage``, and the source encoding (mono is replicated into r, g, b)."""
    import cv2

    data = np.asarray(msg.data, np.uint8)
    if msgtype == COMPRESSED_IMAGE:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise MessageError(f"compressed image (format {msg.format!r}) is not a JPEG or PNG OpenCV "
                               "can decode")
        if img.dtype != np.uint8:
            raise MessageError(f"compressed image (format {msg.format!r}) has {img.dtype} pixels; a "
                               "camera stream needs 8-bit colour (16-bit PNG is a depth image)")
        channels = 1 if img.ndim == 2 else img.shape[2]
        return _to_rgb(img, "mono" if channels == 1 else "bgr"), f"{msg.format} (decoded, {channels} channels)"
    enc = msg.encoding
    if enc not in IMAGE_ENCODINGS:
        raise MessageError(f"image encoding {enc!r} is not supported for rgb; supported: "
                           f"{', '.join(IMAGE_ENCODINGS)}")
    channels, order = IMAGE_ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if step < w * channels or len(data) < h * step:
        raise MessageError(f"image {w}x{h} {enc}: step {step} and {len(data)} bytes do not hold it")
    img = data[:h * step].reshape(h, step)[:, :w * channels].reshape(h, w, channels)
    return _to_rgb(img, order), enc


def camera_intrinsics(msg) -> dict:
    """``camera_matrix`` K [3, 3] px, ``distortion_model``, ``distortion_coefficients``, size."""
    k = np.asarray(_field(msg, "k", "K"), np.float64).reshape(3, 3)
    d = np.asarray(_field(msg, "d", "D"), np.float64)
    return {"camera_matrix": k, "distortion_model": str(msg.distortion_model),
            "distortion_coefficients": d, "width_px": int(msg.width), "height_px": int(msg.height)}


def point_cloud_dtype(msg) -> np.dtype:
    """The structured dtype of one point of a ``PointCloud2`` (its ``point_step`` bytes)."""
    endian = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in POINT_FIELD_DTYPES:
            raise MessageError(f"point field {f.name!r} has unknown datatype {f.datatype}")
        if not f.name or f.name in names:
            continue  # unnamed padding or a repeated name: nothing to read
        code = endian + POINT_FIELD_DTYPES[f.datatype]
        names.append(f.name)
        formats.append((code, (int(f.count),)) if f.count > 1 else code)
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": int(msg.point_step)})


def point_cloud_array(msg) -> np.ndarray:
    """``[height * width]`` structured array of a ``PointCloud2`` (row-major), fields by name."""
    dtype = point_cloud_dtype(msg)
    missing = [c for c in "xyz" if c not in dtype.names]
    if missing:
        raise MessageError(f"point cloud has no field {', '.join(missing)}; fields: {', '.join(dtype.names)}")
    h, w, step = int(msg.height), int(msg.width), int(msg.row_step)
    data = np.asarray(msg.data, np.uint8)
    if step < w * dtype.itemsize or len(data) < h * step:
        raise MessageError(f"point cloud {w}x{h}: row_step {step} and {len(data)} bytes do not hold "
                           f"{dtype.itemsize}-byte points")
    rows = np.ascontiguousarray(data[:h * step].reshape(h, step)[:, :w * dtype.itemsize])
    return rows.view(dtype).reshape(-1)
