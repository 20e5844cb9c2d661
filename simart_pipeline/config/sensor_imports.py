"""Sensor streams recorded by another simulator or a real robot, imported from bags in place of the
embedded renderer (``docs/sensor-plugin.md``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from simart_pipeline.config.base import _inside_scene_dir, _Model
from simart_pipeline.config.devices import Mount
from simart_pipeline.config.recordings import _bag_time_origin, recording_format


class ImportedStream(_Model):
    """One recorded sensor stream of a bag, imported as the ``sensor_frames`` group
    ``/<device>/<sensor>`` in place of the embedded renderer (``docs/sensor-plugin.md``).

    It replaces the configured sensor of the same name on ``device`` (which must then be of the same
    kind) or adds one. Kinds and message types: ``camera`` (``sensor_msgs/Image`` in an 8-bit colour
    or mono encoding, or ``CompressedImage`` JPEG/PNG), ``lidar`` (``PointCloud2``), ``imu``
    (``Imu``), ``gps`` (``NavSatFix``). Extrinsics: ``config`` takes ``mount`` (default: the mount of
    the embedded sensor of the same name, else identity); ``tf`` looks up the pose of the messages'
    frame in ``base_frame_id`` on the bag's ``/tf_static`` and ``/tf`` at the first message.
    """

    device: str
    sensor: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$")
    kind: Literal["camera", "lidar", "imu", "gps"]
    topic: str = Field(min_length=1)
    camera_info_topic: str | None = Field(None, description="camera only: sensor_msgs/CameraInfo "
                                          "topic giving the intrinsics")
    image_frame: Literal["optical", "body"] = Field(
        "optical", description="camera only: the axes of the images' frame_id: optical (z forward, "
        "x right, y down; the ROS convention) or body (x forward, y left, z up)")
    extrinsics: Literal["config", "tf"] = "config"
    mount: Mount | None = Field(None, description="extrinsics: config only")
    base_frame_id: str = Field("base_link", description="extrinsics: tf only; the bag's name of the "
                               "device's base_link")
    frame_id: str | None = Field(None, description="replaces the messages' header frame_id (for "
                                 "recordings whose frame_id is empty or wrong)")

    @model_validator(mode="after")
    def _consistent(self):
        if self.kind != "camera" and (self.camera_info_topic is not None or self.image_frame != "optical"):
            raise ValueError("camera_info_topic and image_frame are for cameras only")
        if self.extrinsics == "tf" and self.mount is not None:
            raise ValueError("mount: give it with extrinsics: config, not tf")
        return self


class SensorImport(_Model):
    """Sensor streams recorded by another simulator (or a real robot) in one bag.

    ``path`` (relative to the scene directory): a ROS1 bag, a rosbag2 storage file (``.db3``,
    ``.mcap``) or a rosbag2 directory. Times: ``stamp`` (message header, or bag record time) minus
    ``time_origin`` (the earliest stamp of the imported streams, the bag's first record time, or an
    absolute stamp in ns), plus ``time_offset_s``; messages outside the session's clock are dropped.
    """

    path: str
    stamp: Literal["header", "record"] = "header"
    time_origin: str | int = "first_message"
    time_offset_s: float = 0.0
    streams: tuple[ImportedStream, ...] = Field(min_length=1)
    _inside = field_validator("path")(classmethod(lambda cls, v: _inside_scene_dir(v, "the bag")))
    _origin = field_validator("time_origin")(classmethod(lambda cls, v: _bag_time_origin(v)))

    @field_validator("path")
    @classmethod
    def _a_bag(cls, v):
        if recording_format(v) == "csv":
            raise ValueError(f"{v!r}: sensor streams are imported from bags, not CSV files")
        return v
