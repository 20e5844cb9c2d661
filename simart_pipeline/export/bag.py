"""A session as one ROS bag: rosbag2 (MCAP or SQLite 3) or ROS 1, written with ``rosbags``.

:func:`write_session_bag` streams message by message: every stream is a generator that reads one
instant of its store at a time, and the generators are merged by stamp (``heapq.merge``), so the
memory held is one message per stream, whatever the session's length.

Time: header stamps and bag times are the shared clock, nanoseconds of simulated time since the
session's start (stamp 0 is the first instant); ``/clock`` carries it at the pose rate (run players
with ``use_sim_time``). Frames: the frame tree of ``simart_pipeline.frames``; ``/tf`` holds every
platform's ``world -> <platform>/base_link`` at the pose rate, ``/tf_static`` the base stations,
the sensor mounts (and camera optical frames), the bodies of the platforms relative to their
base_link and the static actors. Topics and message types: ``docs/ros-export.md``.

Wireless streams use the ``simart_msgs`` messages shipped in ``export/simart_msgs`` (a ROS 2
interface package; ``export/simart_msgs_ros1`` builds the same files with catkin); the bag stores
their definitions, so readers decode them without the package.
"""

from __future__ import annotations

import heapq
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline import frames
from simart_pipeline.config import SceneConfig
from simart_pipeline.vocabulary import SEMANTIC_CLASS_NAMES

FORMATS = ("mcap", "rosbag2-sqlite3", "rosbag1")
MSG_DIR = Path(__file__).resolve().parent / "simart_msgs" / "msg"
TOP_K_BEAMS = 5

# vision_msgs, which neither of rosbags' stores holds: ROS 2 (vision_msgs 4.x) and ROS 1 (noetic).
VISION_MSGS_ROS2 = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": "vision_msgs/ObjectHypothesis hypothesis\n"
                                                "geometry_msgs/PoseWithCovariance pose\n",
    "vision_msgs/msg/Detection2D": "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
                                   "vision_msgs/BoundingBox2D bbox\nstring id\n",
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n",
}
VISION_MSGS_ROS1 = {
    "vision_msgs/msg/BoundingBox2D": "geometry_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": "int64 id\nfloat64 score\ngeometry_msgs/PoseWithCovariance pose\n",
    "vision_msgs/msg/Detection2D": "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
                                   "vision_msgs/BoundingBox2D bbox\nsensor_msgs/Image source_img\n",
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n",
}


def typestore(fmt: str):
    """rosbags' Humble (rosbag2) or Noetic (ROS 1) store plus simart_msgs and vision_msgs."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ros1 = fmt == "rosbag1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    add = {}
    for f in sorted(MSG_DIR.glob("*.msg")):
        add.update(get_types_from_msg(f.read_text(), f"simart_msgs/msg/{f.stem}"))
    for name, text in (VISION_MSGS_ROS1 if ros1 else VISION_MSGS_ROS2).items():
        add.update(get_types_from_msg(text, name))
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        add.update(get_types_from_msg("geometry_msgs/TransformStamped[] transforms\n", "tf2_msgs/msg/TFMessage"))
    ts.register(add)
    return ts


@dataclass
class Msg:
    t_ns: int
    topic: str
    msgtype: str
    fields: dict
    latched: bool = False


class _Sink:
    """One open bag: connections made on first use, each message serialised and written."""

    def __init__(self, path: Path, fmt: str, ts):
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.fmt, self.ts, self.ros1 = fmt, ts, fmt == "rosbag1"
        if self.ros1:
            self.writer = Writer1(path)
        else:
            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer(path, version=9, storage_plugin=plugin)
        self.writer.open()
        self.connections: dict[str, object] = {}
        self.counts: dict[str, int] = {}

    def _connection(self, m: Msg):
        conn = self.connections.get(m.topic)
        if conn is None:
            if self.ros1:
                conn = self.writer.add_connection(m.topic, m.msgtype, typestore=self.ts, latching=int(m.latched))
            else:
                conn = self.writer.add_connection(m.topic, m.msgtype, typestore=self.ts,
                                                  offered_qos_profiles=[_latched_qos()] if m.latched else ())
            self.connections[m.topic] = conn
        return conn

    def write(self, m: Msg) -> None:
        msg = self.build(m.msgtype, m.fields)
        data = self.ts.serialize_ros1(msg, m.msgtype) if self.ros1 else self.ts.serialize_cdr(msg, m.msgtype)
        self.writer.write(self._connection(m), int(m.t_ns), data)
        self.counts[m.topic] = self.counts.get(m.topic, 0) + 1

    def build(self, msgtype: str, fields: dict):
        """The message object of ``msgtype`` from a dict (nested dicts: nested messages, by the
        field's declared type); ROS 1 spellings (Header.seq, CameraInfo's D/K/R/P) filled in."""
        cls = self.ts.types[msgtype]
        out = {}
        for name, ftype in self.ts.fielddefs[msgtype][1]:
            key = name if name in fields else {"D": "d", "K": "k", "R": "r", "P": "p"}.get(name, name)
            if key not in fields:
                if name == "seq":
                    out[name] = 0
                    continue
                raise KeyError(f"{msgtype}: no value for field {name!r}")
            value = fields[key]
            out[name] = self._value(ftype, value)
        return cls(**out)

    def _value(self, ftype, value):
        from rosbags.interfaces import Nodetype

        kind, sub = ftype
        if kind == Nodetype.NAME:
            return self.build(sub, value) if isinstance(value, dict) else value
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            (elem_kind, elem), _ = sub
            if elem_kind == Nodetype.NAME:
                return [self.build(elem, v) if isinstance(v, dict) else v for v in value]
            base = elem[0]
            if base == "string":
                return list(value)
            return np.ascontiguousarray(np.asarray(value).reshape(-1), dtype=_NUMPY[base])
        return value

    def close(self) -> None:
        self.writer.close()


_NUMPY = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
          "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32, "int64": np.int64,
          "uint64": np.uint64, "float32": np.float32, "float64": np.float64}


def _latched_qos():
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, zero, zero,
               QosLiveliness.AUTOMATIC, zero, False)


# --- message fields --------------------------------------------------------------------------------

def _time(t_ns: int) -> dict:
    t = int(t_ns)
    return {"sec": t // 1_000_000_000, "nanosec": t % 1_000_000_000}


def header(t_ns: int, frame_id: str) -> dict:
    return {"stamp": _time(t_ns), "frame_id": frame_id, "seq": 0}


def _vec(v) -> dict:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _quat(q) -> dict:
    return {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}


def _transform(t_ns, parent, child, xyz, xyzw) -> dict:
    return {"header": header(t_ns, parent), "child_frame_id": child,
            "transform": {"translation": _vec(xyz), "rotation": _quat(xyzw)}}


def _covariance(c) -> np.ndarray:
    return np.nan_to_num(np.asarray(c, np.float64).reshape(-1), nan=-1.0)


# --- streams ---------------------------------------------------------------------------------------

BLOCK_BYTES = 8 << 20  # a stream reads its store this much at a time (one instant at least)


def _instants(ds: xr.Dataset) -> Iterator[tuple[int, _Instant]]:
    """``(index, the variables at that instant)`` (an :class:`_Instant`) in time order, read from
    the store a block of instants at a time: one read per block, not per message, and never more
    than about :data:`BLOCK_BYTES` (or one instant) of a stream in memory."""
    n = ds.sizes["time"]
    step = max(1, BLOCK_BYTES // max(1, ds.nbytes // max(n, 1)))
    for start in range(0, n, step):
        block = ds.isel(time=slice(start, start + step)).load()
        # per variable, once a block: its values, the time axis (None: no time dim), the other dims
        arrays = [(name, v.values, v.dims.index("time") if "time" in v.dims else None,
                   tuple(d for d in v.dims if d != "time")) for name, v in block.variables.items()]
        for k in range(block.sizes["time"]):
            # the trailing Ellipsis keeps a 0-d array (not a bare str or scalar) where one value is left
            yield start + k, _Instant({name: (a if axis is None else a[(slice(None),) * axis + (k, ...)], rest)
                                       for name, a, axis, rest in arrays})


class _Values:
    __slots__ = ("values",)

    def __init__(self, values: np.ndarray):
        self.values = values

    @property
    def shape(self) -> tuple[int, ...]:
        return self.values.shape


class _Instant:
    """One instant of a stream: its variables as numpy views, read like an xarray Dataset
    (``f[name].values``, ``f.sizes``, ``f.isel(dim=i)``, ``name in f``). xarray's ``isel`` cost
    about 1 ms a message, a third of a demo bag's export."""

    __slots__ = ("_vars", "sizes")

    def __init__(self, variables: dict[str, tuple[np.ndarray, tuple[str, ...]]]):
        self._vars = variables
        self.sizes = {d: n for a, dims in variables.values() for d, n in zip(dims, a.shape)}

    def __contains__(self, name: str) -> bool:
        return name in self._vars

    def __getitem__(self, name: str) -> _Values:
        return _Values(self._vars[name][0])

    def isel(self, **index: int) -> _Instant:
        return _Instant({name: (a[(*(index.get(d, slice(None)) for d in dims), ...)],
                                tuple(d for d in dims if d not in index))
                         for name, (a, dims) in self._vars.items()})


def _static_transforms(cfg: SceneConfig, actors) -> Msg:
    from simart_pipeline.sensing.streams import base_station_rotation

    tfs = []
    for b in cfg.base_stations:
        tfs.append(_transform(0, frames.WORLD, frames.base_link(b.name), b.position_m,
                              base_station_rotation(b).as_quat()))
    for dev in (*cfg.platforms, *cfg.base_stations):
        for s in dev.sensors:
            rot = frames.rotation_from_rpy_deg(s.mount.rpy_deg)
            tfs.append(_transform(0, frames.base_link(dev.name), frames.sensor_frame(dev.name, s.name),
                                  s.mount.translation_m, rot.as_quat()))
            if s.kind == "camera":
                tfs.append(_transform(0, frames.sensor_frame(dev.name, s.name),
                                      frames.sensor_frame(dev.name, s.name, optical=True), (0, 0, 0),
                                      frames.OPTICAL_TO_BODY.as_quat()))
    for act in actors:
        if act.platform is not None:  # the body hangs below the antenna point (the pose)
            tfs.append(_transform(0, frames.base_link(act.name), f"{act.name}/body", -act.antenna_point_m,
                                  (0, 0, 0, 1)))
        else:
            q = Rotation.from_euler("z", act.static_yaw_deg, degrees=True).as_quat()
            tfs.append(_transform(0, frames.WORLD, f"{act.name}/body", act.static_position_m, q))
    return Msg(0, "/tf_static", "tf2_msgs/msg/TFMessage", {"transforms": tfs}, latched=True)


def _pose_streams(traj: xr.Dataset, pose_rate_times: np.ndarray) -> Iterator[Msg]:
    names = [str(p) for p in traj["platform"].values]
    keep = ["position_m", "velocity_mps", "orientation_xyzw", "angular_velocity_radps"]
    for i, f in _instants(traj[keep]):
        t = int(pose_rate_times[i])
        yield Msg(t, "/clock", "rosgraph_msgs/msg/Clock", {"clock": _time(t)})
        p, v, q, w = (f[k].values for k in keep)
        yield Msg(t, "/tf", "tf2_msgs/msg/TFMessage", {"transforms": [
            _transform(t, frames.WORLD, frames.base_link(n), p[k], q[k]) for k, n in enumerate(names)]})
        for k, n in enumerate(names):
            v_body = Rotation.from_quat(q[k]).inv().apply(v[k])  # REP 147: twist in child frame
            yield Msg(t, f"/{n}/odom", "nav_msgs/msg/Odometry", {
                "header": header(t, frames.WORLD), "child_frame_id": frames.base_link(n),
                "pose": {"pose": {"position": _vec(p[k]), "orientation": _quat(q[k])}, "covariance": np.zeros(36)},
                "twist": {"twist": {"linear": _vec(v_body), "angular": _vec(w[k])}, "covariance": np.zeros(36)}})


def _image(t, frame, h, w, encoding, step, data) -> dict:
    return {"header": header(t, frame), "height": h, "width": w, "encoding": encoding, "is_bigendian": 0,
            "step": step, "data": np.ascontiguousarray(data).view(np.uint8).reshape(-1)}


def _camera_stream(path: str, ds: xr.Dataset) -> Iterator[Msg]:
    base = f"/{path}"
    frame = ds.attrs["frame_id"]
    h, w = ds.sizes["y"], ds.sizes["x"]
    k = ds["camera_matrix"].values
    d = np.nan_to_num(ds["distortion_coefficients"].values)
    p = np.zeros((3, 4))
    p[:, :3] = k
    # instance ids (OSM ids, 2^48 + actor index) do not fit 16 bits: a dense index per camera,
    # its table on .../instance_ids (0: no surface)
    ids = np.unique(np.concatenate([np.unique(f["instance_id"].values) for _, f in _instants(ds[["instance_id"]])]
                                   or [[0]]))
    ids = ids[ids != 0]
    if len(ids) > 65535:
        raise ValueError(f"{path}: {len(ids)} instances do not fit a mono16 image")
    yield Msg(0, f"{base}/instance_ids", "std_msgs/msg/String",
              {"data": json.dumps({"0": 0, **{str(i + 1): int(v) for i, v in enumerate(ids)}})}, latched=True)
    names = [str(a) for a in ds["actor"].values] if "actor" in ds.coords or "actor" in ds.dims else []
    for i, f in _instants(ds):
        t = int(ds["time"].values[i])
        yield Msg(t, f"{base}/image_raw", "sensor_msgs/msg/Image", _image(t, frame, h, w, "rgb8", 3 * w, f["rgb"].values))
        yield Msg(t, f"{base}/depth", "sensor_msgs/msg/Image",
                  _image(t, frame, h, w, "32FC1", 4 * w, f["depth_m"].values.astype("<f4")))
        yield Msg(t, f"{base}/semantic", "sensor_msgs/msg/Image",
                  _image(t, frame, h, w, "mono8", w, f["semantic_class"].values.astype(np.uint8)))
        inst = f["instance_id"].values
        dense = np.searchsorted(ids, inst) + 1
        dense = np.where(inst == 0, 0, dense).astype("<u2")
        yield Msg(t, f"{base}/instance", "sensor_msgs/msg/Image", _image(t, frame, h, w, "mono16", 2 * w, dense))
        yield Msg(t, f"{base}/camera_info", "sensor_msgs/msg/CameraInfo", {
            "header": header(t, frame), "height": h, "width": w, "distortion_model": "plumb_bob",
            "d": d.astype(np.float64), "k": k.reshape(-1), "r": np.eye(3).reshape(-1), "p": p.reshape(-1),
            "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}})
        if names:
            dets = []
            for j, name in enumerate(names):
                if int(f["actor_pixel_count"].values[j]) == 0:
                    continue
                u0, v0, u1, v1 = (float(x) for x in f["actor_visible_box_px"].values[j])
                cls = SEMANTIC_CLASS_NAMES[int(ds["actor_semantic_class"].values[j])]
                dets.append({"name": name, "cls": cls, "cx": (u0 + u1) / 2, "cy": (v0 + v1) / 2,
                             "sx": u1 - u0 + 1, "sy": v1 - v0 + 1, "index": j})
            yield Msg(t, f"{base}/actors", "vision_msgs/msg/Detection2DArray",
                      {"header": header(t, frame), "detections": dets})


def _lidar_stream(path: str, ds: xr.Dataset) -> Iterator[Msg]:
    frame = ds.attrs["frame_id"]
    rings, n_az = ds.sizes["ring"], ds.sizes["azimuth"]
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("range", 12, 7), ("semantic_class", 16, 2)]
    point = np.dtype({"names": ["x", "y", "z", "range", "semantic_class"],
                      "formats": ["<f4", "<f4", "<f4", "<f4", "u1"], "offsets": [0, 4, 8, 12, 16], "itemsize": 20})
    for i, f in _instants(ds):
        t = int(ds["time"].values[i])
        pts = np.zeros((rings, n_az), point)
        xyz = f["points_m"].values
        pts["x"], pts["y"], pts["z"] = xyz[..., 0], xyz[..., 1], xyz[..., 2]
        pts["range"], pts["semantic_class"] = f["range_m"].values, f["semantic_class"].values
        yield Msg(t, f"/{path}/points", "sensor_msgs/msg/PointCloud2", {
            "header": header(t, frame), "height": rings, "width": n_az,
            "fields": [{"name": nm, "offset": off, "datatype": dt, "count": 1} for nm, off, dt in fields],
            "is_bigendian": False, "point_step": point.itemsize, "row_step": point.itemsize * n_az,
            "data": pts.reshape(-1).view(np.uint8), "is_dense": False})


def _imu_stream(path: str, ds: xr.Dataset) -> Iterator[Msg]:
    frame = ds.attrs["frame_id"]
    for i, f in _instants(ds):
        t = int(ds["time"].values[i])
        yield Msg(t, f"/{path}", "sensor_msgs/msg/Imu", {
            "header": header(t, frame), "orientation": _quat(f["reported_orientation_xyzw"].values),
            "orientation_covariance": _covariance(f["reported_orientation_covariance"].values),
            "angular_velocity": _vec(f["angular_velocity_radps"].values),
            "angular_velocity_covariance": _covariance(f["angular_velocity_covariance"].values),
            "linear_acceleration": _vec(f["linear_acceleration_mps2"].values),
            "linear_acceleration_covariance": _covariance(f["linear_acceleration_covariance"].values)})


def _gps_stream(path: str, ds: xr.Dataset) -> Iterator[Msg]:
    frame = ds.attrs["frame_id"]
    for i, f in _instants(ds):
        t = int(ds["time"].values[i])
        yield Msg(t, f"/{path}", "sensor_msgs/msg/NavSatFix", {
            "header": header(t, frame),
            "status": {"status": int(f["fix_status"].values), "service": int(f["fix_service"].values)},
            "latitude": float(f["latitude_deg"].values), "longitude": float(f["longitude_deg"].values),
            "altitude": float(f["altitude_m"].values),
            "position_covariance": np.asarray(f["position_covariance_m2"].values, np.float64).reshape(-1),
            "position_covariance_type": int(f["position_covariance_type"].values)})


def _paths_fields(f: _Instant, actors: list[str]) -> dict:
    a = f["a"].values
    return {"num_rx_ant": a.shape[0], "num_tx_ant": a.shape[1], "num_paths": a.shape[-1],
            "max_depth": f.sizes["depth"], "a_real": np.ascontiguousarray(a.real).reshape(-1).astype(np.float32),
            "a_imag": np.ascontiguousarray(a.imag).reshape(-1).astype(np.float32),
            "tau_s": f["tau_s"].values.astype(np.float64),
            **{k: f[f"{k}"].values.astype(np.float32) for k in ("theta_t_rad", "phi_t_rad", "theta_r_rad",
                                                                   "phi_r_rad", "doppler_hz")},
            "interaction": f["interaction"].values.reshape(-1).astype(np.uint8),
            "interaction_actor": (f["interaction_actor"].values if "interaction_actor" in f
                                  else np.full(f["interaction"].shape, -1)).reshape(-1).astype(np.int16),
            "actors": actors, "los": f["los"].values.tolist(), "valid": f["valid"].values.tolist()}


def _cir_streams(cirs: xr.Dataset) -> Iterator[Msg]:
    actors = [str(a) for a in cirs["actor"].values] if "actor" in cirs.coords else []
    tx, rx = cirs["tx"].values, cirs["rx"].values
    for i, f in _instants(cirs):
        t = int(cirs["time"].values[i])
        for link in range(cirs.sizes["link"]):
            fl = f.isel(link=link)
            yield Msg(t, f"/simart/cir/{tx[link]}/{rx[link]}", "simart_msgs/msg/ChannelImpulseResponse", {
                "header": header(t, frames.WORLD), "tx": str(tx[link]), "rx": str(rx[link]),
                **_paths_fields(fl, actors), "link_status": int(fl["link_status"].values)})


def _kpi_streams(kpis: xr.Dataset) -> Iterator[Msg]:
    plats = [str(p) for p in kpis["platform"].values]
    tx, rx = kpis["tx"].values, kpis["rx"].values
    for i, f in _instants(kpis):
        t = int(kpis["time"].values[i])
        for k, p in enumerate(plats):
            fp = f.isel(platform=k)
            yield Msg(t, f"/simart/kpis/{p}", "simart_msgs/msg/LinkKpis", {
                "header": header(t, frames.base_link(p)), "platform": p, "served": bool(fp["rx_served"].values),
                "serving_tx": str(fp["serving_tx"].values), "serving_beam": int(fp["serving_beam"].values),
                **{k2: float(fp[k2].values) for k2 in ("sinr_db", "effective_sinr_db", "snr_db", "bler", "tbler",
                                                       "mcs_rate_bps", "shannon_rate_bps")},
                "mcs_index": int(fp["mcs_index"].values), "tbs_bits": int(fp["tbs_bits"].values)})
        for link in range(kpis.sizes["link"]):
            fl = f.isel(link=link)
            gains = fl["beam_gain_db"].values
            order = np.argsort(-np.nan_to_num(gains, nan=-np.inf), kind="stable")[:TOP_K_BEAMS]
            yield Msg(t, f"/simart/beams/{tx[link]}/{rx[link]}", "simart_msgs/msg/BeamReport", {
                "header": header(t, frames.base_link(str(tx[link]))), "tx": str(tx[link]), "rx": str(rx[link]),
                "best_beam": int(fl["best_beam"].values), "best_beam_gain_db": float(fl["best_beam_gain_db"].values),
                "best_beam_sinr_db": float(fl["best_beam_sinr_db"].values),
                "top_k_beams": order.astype(np.int64), "top_k_gains_db": gains[order].astype(np.float64)})


def ckm_layer_names(ckm: xr.Dataset) -> list[str]:
    """The map's layers exported: every variable over (height, y, x), with or without bs first
    (``beam_gain_db``, with a beam dim, is left out: ``best_beam`` and its gain summarise it)."""
    return sorted(n for n, v in ckm.data_vars.items() if v.dims in (("height", "y", "x"), ("bs", "height", "y", "x")))


def _ckm_messages(ckm: xr.Dataset, materials: str) -> Iterator[Msg]:
    x, y = ckm["x"].values, ckm["y"].values
    res = float(x[1] - x[0]) if len(x) > 1 else float("nan")
    from simart_pipeline.ckm.maps import masked_cells

    masked = np.broadcast_to(masked_cells(ckm), (len(ckm["height"]), len(y), len(x)))  # every mask of its mode
    for name in ckm_layer_names(ckm):
        var = ckm[name]
        stations = [str(b) for b in ckm["bs"].values] if "bs" in var.dims else [""]
        for s, bs in enumerate(stations):
            for h, height in enumerate(ckm["height"].values):
                arr = (var.isel(bs=s) if bs else var).isel(height=h).values
                data = arr.astype(np.float64)
                # the masks and the outdoor share describe every cell; the layers only the unmasked
                valid = np.isfinite(data) & (True if name.startswith("cell_") else ~masked[h])
                topic = f"/simart/ckm/{materials}/{name}" + (f"/{bs}" if bs else "")
                yield Msg(0, topic, "simart_msgs/msg/CkmLayer", {
                    "header": header(0, frames.WORLD), "layer": name, "units": str(var.attrs.get("units", "")),
                    "base_station": bs, "materials": materials, "height_m": float(height),
                    "origin_x_m": float(x[0]), "origin_y_m": float(y[0]), "resolution_m": res,
                    "rows": len(y), "cols": len(x), "data": data.reshape(-1), "valid": valid.reshape(-1).tolist()},
                    latched=True)


def _radar_streams(radar: xr.DataTree) -> Iterator[Msg]:
    for node in radar.children.values():
        ds = node.to_dataset()
        bs = node.name
        actors = [str(a) for a in ds["actor"].values]
        rd_attrs = ds["range_doppler_power_db"].attrs
        for i, f in _instants(ds):
            t = int(ds["time"].values[i])
            yield Msg(t, f"/simart/radar/{bs}/echoes", "simart_msgs/msg/RadarEchoes", {
                "header": header(t, frames.WORLD), "base_station": bs, **_paths_fields(f, actors)})
            yield Msg(t, f"/simart/radar/{bs}/range_doppler", "simart_msgs/msg/RangeDopplerMap", {
                "header": header(t, frames.base_link(bs)), "base_station": bs, "window": str(rd_attrs["window"]),
                "num_range_bins": ds.sizes["range_bin"], "num_velocity_bins": ds.sizes["velocity_bin"],
                "range_m": ds["range_m"].values, "radial_velocity_mps": ds["radial_velocity_mps"].values,
                "power_db": f["range_doppler_power_db"].values.reshape(-1).astype(np.float32),
                "range_resolution_m": float(rd_attrs["range_resolution_m"]),
                "velocity_resolution_mps": float(rd_attrs["velocity_resolution_mps"]), "actors": actors,
                **{f"actor_{k}": f[f"actor_{k}"].values.astype(np.float64)
                   for k in ("range_m", "radial_velocity_mps", "azimuth_rad", "elevation_rad")}})


def _origin_message(cfg: SceneConfig) -> Msg:
    o = cfg.origin
    return Msg(0, "/simart/world_origin", "sensor_msgs/msg/NavSatFix", {
        "header": header(0, frames.WORLD), "status": {"status": 0, "service": 0},
        "latitude": o.latitude_deg, "longitude": o.longitude_deg, "altitude": o.altitude_m,
        "position_covariance": np.zeros(9), "position_covariance_type": 0}, latched=True)


def session_messages(session: xr.DataTree, cfg: SceneConfig, *, actors=(), ckm: xr.Dataset | None = None,
                     ckm_materials: str = "", radar: xr.DataTree | None = None) -> Iterator[Msg]:
    """Every message of a session bag, in stamp order (latched ones first)."""
    yield _origin_message(cfg)
    yield _static_transforms(cfg, actors)
    if ckm is not None:
        yield from _ckm_messages(ckm, ckm_materials)
    traj = session["trajectory"].to_dataset()
    streams = [_pose_streams(traj, traj["time"].values)]
    if "sensors" in session.children:
        for node in session["sensors"].subtree:
            if not node.has_data:
                continue
            ds = node.to_dataset()
            path = node.path.split("/sensors/", 1)[1]
            if "rgb" in ds:
                streams.append(_camera_stream(path, ds))
            elif "points_m" in ds:
                streams.append(_lidar_stream(path, ds))
            elif "linear_acceleration_mps2" in ds:
                streams.append(_imu_stream(path, ds))
            elif "latitude_deg" in ds:
                streams.append(_gps_stream(path, ds))
            else:  # pragma: no cover - the stream contract has no other kind
                raise ValueError(f"sensor group {node.path}: not a camera, LiDAR, IMU or GPS stream")
    streams.append(_cir_streams(session["cirs"].to_dataset()))
    streams.append(_kpi_streams(session["kpis"].to_dataset()))
    if radar is not None and radar.children:
        streams.append(_radar_streams(radar))
    merged = heapq.merge(*(_keyed(gen, s) for s, gen in enumerate(streams)), key=lambda km: km[0])
    yield from (m for _, m in merged)


def _keyed(gen: Iterator[Msg], s: int):
    for k, m in enumerate(gen):
        yield (m.t_ns, s, k), m


def write_session_bag(out: str | Path, fmt: str, session: xr.DataTree, cfg: SceneConfig, **kw) -> dict:
    """Write the session as one bag at ``out`` (a rosbag2 directory, or a ROS 1 ``.bag`` file);
    returns ``{topic: message count}``. ``kw``: :func:`session_messages`'s ``actors``, ``ckm``,
    ``ckm_materials``, ``radar``."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown bag format {fmt!r}; known: {', '.join(FORMATS)}")
    ts = typestore(fmt)
    sink = _Sink(Path(out), fmt, ts)
    try:
        for m in session_messages(session, cfg, **kw):
            if m.msgtype == "vision_msgs/msg/Detection2DArray":
                m = Msg(m.t_ns, m.topic, m.msgtype, _detections(m.fields, fmt == "rosbag1"), m.latched)
            sink.write(m)
    finally:
        sink.close()
    return dict(sorted(sink.counts.items()))


def _detections(fields: dict, ros1: bool) -> dict:
    pose = {"pose": {"position": _vec((0, 0, 0)), "orientation": _quat((0, 0, 0, 1))}, "covariance": np.zeros(36)}
    dets = []
    for d in fields["detections"]:
        if ros1:
            dets.append({"header": fields["header"], "results": [{"id": d["index"], "score": 1.0, "pose": pose}],
                         "bbox": {"center": {"x": d["cx"], "y": d["cy"], "theta": 0.0}, "size_x": d["sx"],
                                  "size_y": d["sy"]},
                         "source_img": {"header": fields["header"], "height": 0, "width": 0, "encoding": "",
                                        "is_bigendian": 0, "step": 0, "data": np.zeros(0, np.uint8)}})
        else:
            dets.append({"header": fields["header"], "results": [
                {"hypothesis": {"class_id": d["cls"], "score": 1.0}, "pose": pose}],
                "bbox": {"center": {"position": {"x": d["cx"], "y": d["cy"]}, "theta": 0.0},
                         "size_x": d["sx"], "size_y": d["sy"]}, "id": d["name"]})
    return {"header": fields["header"], "detections": dets}


def export_session(out: str | Path, fmt: str, session: xr.DataTree, cfg: SceneConfig, **kw) -> dict:
    """:func:`write_session_bag` into place atomically: a rosbag2 directory (``mcap``,
    ``rosbag2-sqlite3``) or a ROS 1 file (``rosbag1``) appears at ``out`` whole or not at all."""
    from simart_pipeline import stores

    counts: dict = {}
    stores.write_named(Path(out), lambda p: counts.update(write_session_bag(p, fmt, session, cfg, **kw)))
    return counts
