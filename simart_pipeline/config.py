"""The one scene config schema: ``scenes/<name>/scene.yaml``.

Every key is declared here, with its unit in its name, its default and its bounds. A wrong key or
value is reported with the file's name and the key path (``platforms.0.sensors.1.rate_hz``) before
any work starts; :func:`load_scene_config` collects every problem at once.
"""

from __future__ import annotations

import hashlib
import json
import math
from fractions import Fraction
from pathlib import Path
from typing import Annotated, Literal, Union

import yaml
from pydantic import (BaseModel, ConfigDict, Discriminator, Field, Tag, ValidationError, field_validator,
                      model_validator)

from simart_pipeline.radio.materials import RADIO_MATERIALS

WEATHERS = ("sunny", "rainy", "night")
MAX_TILES_PER_AXIS = 4  # the static tile partitions are r0c0 .. r3c3 (partitions/__init__.py)


def _inside_scene_dir(v: str, what: str) -> str:
    """A path in the config must be relative and stay inside the scene directory."""
    p = Path(v)
    if p.is_absolute() or ".." in p.parts:
        raise ValueError(f"{v!r}: {what} must lie inside the scene directory (a relative path "
                         "without '..')")
    return v


class ConfigError(ValueError):
    """A scene config problem; ``problems`` holds one ``file: key.path: message`` line each."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        super().__init__("\n".join(problems))


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Vec3 = tuple[float, float, float]
Vec2 = tuple[float, float]


class WorldOrigin(_Model):
    """Geodetic origin of the local ENU world frame (WGS84)."""

    latitude_deg: float = Field(ge=-90, le=90)
    longitude_deg: float = Field(ge=-180, le=180)
    altitude_m: float = 0.0


class ProceduralSource(_Model):
    """The project's own city-block layout: a grid of blocks with one building each."""

    kind: Literal["procedural"]
    blocks: tuple[int, int] = (3, 3)
    block_size_m: Vec2 = (40.0, 30.0)
    street_width_m: float = Field(20.0, gt=0)
    building_height_m: Vec2 = (10.0, 30.0)
    building_inset_m: float = Field(3.0, ge=0)
    seed: int = 7

    @field_validator("blocks")
    @classmethod
    def _blocks_positive(cls, v):
        if min(v) < 1:
            raise ValueError("both block counts must be >= 1")
        return v


class OsmSource(_Model):
    """An OpenStreetMap extract (.osm XML or .osm.pbf), path relative to the scene directory."""

    kind: Literal["osm"]
    path: str
    bbox_deg: tuple[float, float, float, float] | None = Field(
        None, description="min_lon, min_lat, max_lon, max_lat; whole extract when absent")
    default_building_height_m: float = Field(10.0, gt=0)
    storey_height_m: float = Field(3.0, gt=0)
    facade_detail: bool = Field(True, description="window frames on the visual mesh's facades")

    _inside = field_validator("path")(classmethod(lambda cls, v: _inside_scene_dir(v, "the extract")))

    @field_validator("bbox_deg")
    @classmethod
    def _bbox_ordered(cls, v):
        if v is not None and not (-180 <= v[0] < v[2] <= 180 and -90 <= v[1] < v[3] <= 90):
            raise ValueError("expected min_lon < max_lon and min_lat < max_lat, in degrees")
        return v


class MeshPartRule(_Model):
    """How the parts that ``match`` are labelled and simplified (``docs/user-meshes.md``).

    ``match`` is a case-insensitive glob (``window_frame*``) or, prefixed ``re:``, a regular
    expression (full match), tried against a part's node name, node path (``Room/Desk``), mesh
    name, visual material name and tags. For each field, the first matching rule that sets it wins.
    """

    match: str = Field(min_length=1)
    semantic_class: str | None = None
    radio_material: str | None = None
    drop: bool | None = Field(None, description="remove from the radio mesh (the visual mesh keeps it)")
    keep: bool | None = Field(None, description="never removed by the size threshold")

    @field_validator("match")
    @classmethod
    def _pattern(cls, v):
        if v.startswith("re:"):
            import re

            try:
                re.compile(v[3:])
            except re.error as exc:
                raise ValueError(f"not a valid regular expression: {exc}") from None
        return v

    @model_validator(mode="after")
    def _known_names(self):
        check_mesh_labels(self.semantic_class, self.radio_material)
        return self


def check_mesh_labels(semantic_class: str | None = None, radio_material: str | None = None) -> None:
    """Raise ValueError for a semantic class or radio material the project does not know."""
    # Imported here: scene.meshes imports this module, a cycle at import time.
    from simart_pipeline.radio.materials import RADIO_MATERIALS
    from simart_pipeline.scene.meshes import SemanticClass

    names = [c.name.lower() for c in SemanticClass]
    if semantic_class is not None and semantic_class not in names:
        raise ValueError(f"unknown semantic class {semantic_class!r}; known: {', '.join(names)}")
    if radio_material is not None and radio_material not in RADIO_MATERIALS:
        raise ValueError(f"unknown radio material {radio_material!r}; known: {', '.join(RADIO_MATERIALS)}")


class MeshImportRules(_Model):
    """Import, labelling and simplification of a user mesh into paired visual and radio meshes."""

    up_axis: Literal["auto", "y", "z"] = Field(
        "auto", description="the file's up axis; auto: y for glTF/GLB (the glTF spec), z otherwise")
    scale_m_per_unit: float = Field(1.0, gt=0, description="metres per file unit (glTF is metres)")
    parts: tuple[MeshPartRule, ...] = ()
    default_semantic_class: str = "building"
    default_radio_material: str = "concrete"
    min_part_extent_m: float = Field(
        1.0, ge=0, description="connected parts whose bounding box is smaller than this along every "
        "axis are removed from the radio mesh")
    merge_tolerance_m: float = Field(1e-4, gt=0, le=0.1, description="vertices closer than this merge")
    decimation: Literal["lossless", "quadric", "none"] = "lossless"
    decimation_target_fraction: float = Field(
        0.5, gt=0, le=1, description="quadric only: triangles kept per smooth patch, after lossless")
    sharp_edge_angle_deg: float = Field(
        30.0, gt=0, lt=180, description="quadric only: edges bending more than this are kept exactly")
    drop_degenerate_faces: bool = Field(
        False, description="drop zero-area faces instead of refusing the mesh")
    obstacle_classes: tuple[str, ...] = Field(
        ("building",), description="semantic classes whose parts become building footprints of the "
        "source geometry (device placement and trajectory clearance checks, indoor masks)")
    wall_sheet_thickness_m: float = Field(
        0.1, gt=0, description="thickness given to open (sheet) walls in building footprints")
    hausdorff_samples: int = Field(20_000, ge=100, le=10_000_000)
    seed: int = 0

    @model_validator(mode="after")
    def _known_defaults(self):
        check_mesh_labels(self.default_semantic_class, self.default_radio_material)
        for c in self.obstacle_classes:
            check_mesh_labels(semantic_class=c)
        return self


class MeshSource(_Model):
    """A user-built mesh (OBJ, PLY, STL, glTF/GLB), path relative to the scene directory."""

    kind: Literal["mesh"]
    path: str
    rules: MeshImportRules = Field(default_factory=lambda: MeshImportRules())

    _inside = field_validator("path")(classmethod(lambda cls, v: _inside_scene_dir(v, "the mesh")))


Source = Annotated[Union[ProceduralSource, OsmSource, MeshSource], Field(discriminator="kind")]


class Materials(_Model):
    """Radio material per semantic class, and OSM tag rules that override it.

    Materials are :data:`simart_pipeline.radio.materials.RADIO_MATERIALS` names (ITU-R P.2040-3
    Table 3, valid 1-100 GHz, plus water and wet facades). ``tags`` maps an OSM key to a mapping
    of its values to materials; it is merged over :data:`DEFAULT_TAG_MATERIALS` (a key given here
    replaces single values, not the whole key). A feature takes the material of the first rule
    whose key and value it carries (keys in the order of the merged mapping), else its class's.
    """

    building: str = "concrete"
    road: str = "concrete"
    ground: str = "medium_dry_ground"
    vegetation: str = "medium_dry_ground"
    water: str = "fresh_water"
    thickness_m: float = Field(0.2, gt=0)
    tags: dict[str, dict[str, str]] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _known(self):
        for key in ("building", "road", "ground", "vegetation", "water"):
            if getattr(self, key) not in RADIO_MATERIALS:
                raise ValueError(f"{key}: unknown radio material {getattr(self, key)!r}; "
                                 f"known: {', '.join(RADIO_MATERIALS)}")
        for key, values in self.tags.items():
            for value, mat in values.items():
                if mat not in RADIO_MATERIALS:
                    raise ValueError(f"tags.{key}.{value}: unknown radio material {mat!r}; "
                                     f"known: {', '.join(RADIO_MATERIALS)}")
        return self

    def tag_rules(self) -> dict[str, dict[str, str]]:
        """:data:`DEFAULT_TAG_MATERIALS` with this config's ``tags`` merged over it."""
        merged = {k: dict(v) for k, v in DEFAULT_TAG_MATERIALS.items()}
        for key, values in self.tags.items():
            merged.setdefault(key, {}).update(values)
        return merged


# OSM tag values to radio materials. P.2040-3 has no asphalt or stone: asphalt and paved surfaces
# use concrete (the usual proxy), natural stone uses marble (its only stone); loose surfaces use
# the ground classes. Water bodies use the Debye water models of radio.materials.
DEFAULT_TAG_MATERIALS: dict[str, dict[str, str]] = {
    "building:material": {
        "brick": "brick", "concrete": "concrete", "reinforced_concrete": "concrete",
        "cement_block": "concrete", "plaster": "concrete", "glass": "glass", "mirror": "glass",
        "metal": "metal", "steel": "metal", "aluminium": "metal", "copper": "metal", "gold": "metal",
        "wood": "wood", "timber_framing": "wood", "stone": "marble", "sandstone": "marble",
        "limestone": "marble", "granite": "marble", "marble": "marble"},
    "surface": {
        "asphalt": "concrete", "concrete": "concrete", "concrete:plates": "concrete",
        "concrete:lanes": "concrete", "paved": "concrete", "paving_stones": "concrete",
        "sett": "marble", "cobblestone": "marble", "unhewn_cobblestone": "marble", "stone": "marble",
        "metal": "metal", "wood": "wood", "gravel": "very_dry_ground", "fine_gravel": "very_dry_ground",
        "sand": "very_dry_ground", "unpaved": "medium_dry_ground", "compacted": "medium_dry_ground",
        "dirt": "medium_dry_ground", "earth": "medium_dry_ground", "ground": "medium_dry_ground",
        "grass": "medium_dry_ground", "mud": "wet_ground"},
    "natural": {"water": "fresh_water", "bay": "sea_water", "strait": "sea_water", "wetland": "wet_ground"},
    "water": {"lagoon": "sea_water", "sea": "sea_water"},
    "landuse": {"reservoir": "fresh_water", "basin": "fresh_water"},
}


class Array(_Model):
    """A uniform planar array in the y-z plane of its device, boresight +x (Sionna PlanarArray)."""

    rows: int = Field(1, ge=1)
    cols: int = Field(1, ge=1)
    spacing_wavelengths: float = Field(0.5, gt=0)
    pattern: Literal["iso", "dipole", "hw_dipole", "tr38901"] = "iso"
    polarization: Literal["V", "H"] = "V"

    @property
    def num_antennas(self) -> int:
        return self.rows * self.cols


class Mount(_Model):
    """Pose of a sensor in its parent's base_link: translation and roll/pitch/yaw (deg)."""

    translation_m: Vec3 = (0.0, 0.0, 0.0)
    rpy_deg: Vec3 = (0.0, 0.0, 0.0)


def _rate_has_exact_clock(rate_hz: float) -> float:
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise ValueError("rate must be a positive finite number of Hz")
    if Fraction(str(rate_hz)) > 10**9:
        raise ValueError("rate above 1 GHz cannot be sampled on a nanosecond clock")
    return rate_hz


class Camera(_Model):
    kind: Literal["camera"]
    name: str
    rate_hz: float = 2.0
    width_px: int = Field(320, ge=8, le=8192)
    height_px: int = Field(240, ge=8, le=8192)
    horizontal_fov_deg: float = Field(90.0, gt=1, lt=179)
    max_depth_m: float = Field(500.0, gt=0)
    mount: Mount = Mount()
    _rate = field_validator("rate_hz")(classmethod(lambda cls, v: _rate_has_exact_clock(v)))


class Lidar(_Model):
    kind: Literal["lidar"]
    name: str
    rate_hz: float = 5.0
    channels: int = Field(16, ge=1, le=256)
    vertical_fov_deg: Vec2 = (-15.0, 15.0)
    horizontal_samples: int = Field(512, ge=8, le=8192)
    max_range_m: float = Field(120.0, gt=0)
    range_noise_std_m: float = Field(0.02, ge=0)
    mount: Mount = Mount()
    _rate = field_validator("rate_hz")(classmethod(lambda cls, v: _rate_has_exact_clock(v)))


class Imu(_Model):
    kind: Literal["imu"]
    name: str
    rate_hz: float = 100.0
    accel_noise_std_mps2: float = Field(0.02, ge=0)
    gyro_noise_std_radps: float = Field(0.002, ge=0)
    accel_bias_mps2: Vec3 = (0.0, 0.0, 0.0)
    gyro_bias_radps: Vec3 = (0.0, 0.0, 0.0)
    mount: Mount = Mount()
    _rate = field_validator("rate_hz")(classmethod(lambda cls, v: _rate_has_exact_clock(v)))


class Gps(_Model):
    kind: Literal["gps"]
    name: str
    rate_hz: float = 1.0
    horizontal_noise_std_m: float = Field(1.5, ge=0)
    vertical_noise_std_m: float = Field(3.0, ge=0)
    mount: Mount = Mount()
    _rate = field_validator("rate_hz")(classmethod(lambda cls, v: _rate_has_exact_clock(v)))


Sensor = Annotated[Union[Camera, Lidar, Imu, Gps], Field(discriminator="kind")]


class BaseStation(_Model):
    name: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$")
    position_m: Vec3
    # Sionna orientation (alpha, beta, gamma) = yaw about z, pitch about y, roll about x; deg.
    orientation_deg: Vec3 = (0.0, 0.0, 0.0)
    array: Array = Array(rows=8, cols=8, pattern="tr38901")
    power_dbm: float = 30.0
    sensors: tuple[Camera, ...] = ()


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


# Recording formats by file name: a CSV, a ROS1 bag, a rosbag2 storage file, or (no suffix) a rosbag2
# directory with its metadata.yaml (docs/sensor-plugin.md).
RECORDING_FORMATS = {".csv": "csv", ".bag": "ros1", ".db3": "rosbag2", ".mcap": "rosbag2", "": "rosbag2"}
BAG_TIME_ORIGINS = ("first_message", "bag_start")


def recording_format(path: str) -> str:
    """``csv``, ``ros1`` or ``rosbag2`` from a recording's file name; ValueError for anything else."""
    suffix = Path(path).suffix.lower()
    if suffix not in RECORDING_FORMATS:
        raise ValueError(f"{path!r}: unknown recording format {suffix!r}; expected .csv, .bag (ROS1), "
                         ".db3 or .mcap (rosbag2 storage file) or a rosbag2 directory (no suffix)")
    return RECORDING_FORMATS[suffix]


def _bag_time_origin(v):
    if v is None or (isinstance(v, int) and not isinstance(v, bool)) or v in BAG_TIME_ORIGINS:
        return v
    raise ValueError(f"expected {' or '.join(BAG_TIME_ORIGINS)} or an integer stamp in ns, got {v!r}")


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


class DynamicLimits(_Model):
    """Bounds a waypoint trajectory never exceeds (``docs/mobility.md``); defaults per platform kind
    in :data:`DEFAULT_LIMITS`, which a platform's ``limits`` overrides key by key.

    Accelerations exclude gravity. Tangential (along the path) and lateral (across it) are each
    capped by ``max_acceleration_mps2`` as well. The yaw limits shape turns in place (at stops);
    while moving, the heading follows the velocity. Heights are above the ground plane z = 0.
    """

    max_speed_mps: float = Field(gt=0, le=100)
    max_acceleration_mps2: float = Field(gt=0, le=100)
    max_tangential_acceleration_mps2: float = Field(gt=0, le=100)
    max_lateral_acceleration_mps2: float = Field(gt=0, le=100)
    max_jerk_mps3: float = Field(gt=0, le=1000)
    max_yaw_rate_radps: float = Field(gt=0, le=50)
    max_yaw_acceleration_radps2: float = Field(gt=0, le=500)
    min_height_above_ground_m: float | None = Field(None, description="UAV altitude band: lower bound")
    max_height_above_ground_m: float | None = Field(None, description="UAV altitude band: upper bound")


# Defaults per platform kind; where the numbers come from: docs/mobility.md, "Limits".
DEFAULT_LIMITS: dict[str, dict[str, float | None]] = {
    # PX4 multicopter auto mode: MPC_ACC_HOR 3 m s-2, MPC_ACC_HOR_MAX 5 m s-2, MPC_JERK_AUTO 4 m s-3,
    # MPC_YAWRAUTO_MAX 45 deg/s; top speed of small multirotors ~20 m s-1; EU 2019/947 open
    # category: at most 120 m above the ground.
    "uav": {"max_speed_mps": 20.0, "max_acceleration_mps2": 5.0, "max_tangential_acceleration_mps2": 3.0,
            "max_lateral_acceleration_mps2": 5.0, "max_jerk_mps3": 4.0, "max_yaw_rate_radps": 0.785,
            "max_yaw_acceleration_radps2": 1.57, "min_height_above_ground_m": 2.0,
            "max_height_above_ground_m": 120.0},
    # Urban car: 50 km/h; ISO 15622 (ACC) 2 m s-2 and 2.5 m s-3; ISO 11270 (lane keeping) 3 m s-2 lateral.
    "ground_vehicle": {"max_speed_mps": 13.9, "max_acceleration_mps2": 3.0,
                       "max_tangential_acceleration_mps2": 2.0, "max_lateral_acceleration_mps2": 3.0,
                       "max_jerk_mps3": 2.5, "max_yaw_rate_radps": 0.5, "max_yaw_acceleration_radps2": 0.5},
    # Walking: free speed ~1.34 m s-1 (Weidmann 1993), brisk walk up to 2.5 m s-1; gait starts and
    # turns of about 1 m s-2.
    "pedestrian": {"max_speed_mps": 2.5, "max_acceleration_mps2": 1.5, "max_tangential_acceleration_mps2": 1.0,
                   "max_lateral_acceleration_mps2": 1.0, "max_jerk_mps3": 2.0, "max_yaw_rate_radps": 1.5,
                   "max_yaw_acceleration_radps2": 3.0},
}
GRAVITY_MPS2 = 9.80665  # a multirotor cannot accelerate downward faster without turning over


class Platform(_Model):
    name: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$")
    kind: Literal["uav", "ground_vehicle", "pedestrian"]
    array: Array = Array()
    trajectory: TrajectorySource
    limits: DynamicLimits | None = Field(None, description="overrides of the kind's DEFAULT_LIMITS; "
                                         "always filled in after validation")
    sensors: tuple[Sensor, ...] = ()

    @model_validator(mode="before")
    @classmethod
    def _kind_defaults(cls, data):
        # The kind's defaults under whatever the config gives, key by key.
        if isinstance(data, dict) and data.get("kind") in DEFAULT_LIMITS:
            given = data.get("limits")
            if given is None or isinstance(given, dict):
                data = {**data, "limits": {**DEFAULT_LIMITS[data["kind"]], **(given or {})}}
        return data

    @model_validator(mode="after")
    def _within_limits(self):
        lim, tr = self.limits, self.trajectory
        if lim is None:  # only for a kind without defaults, which the schema refuses already
            return self
        band = (lim.min_height_above_ground_m, lim.max_height_above_ground_m)
        if self.kind != "uav":
            if band != (None, None):
                raise ValueError(f"platform {self.name}: limits: an altitude band applies to UAVs only")
        else:
            if lim.max_acceleration_mps2 >= GRAVITY_MPS2:
                raise ValueError(f"platform {self.name}: limits.max_acceleration_mps2 must stay below "
                                 f"g = {GRAVITY_MPS2} m/s2 for a multirotor")
            if None not in band and band[0] >= band[1]:
                raise ValueError(f"platform {self.name}: limits: min_height_above_ground_m must be below "
                                 "max_height_above_ground_m")
        if tr.kind != "waypoints":
            return self
        if tr.speed_mps > lim.max_speed_mps:
            raise ValueError(f"platform {self.name}: trajectory.speed_mps {tr.speed_mps} exceeds "
                             f"limits.max_speed_mps {lim.max_speed_mps} of a {self.kind}")
        if self.kind == "uav" and tr.follow_roads:
            raise ValueError(f"platform {self.name}: trajectory.follow_roads is for ground vehicles and pedestrians")
        lo = -math.inf if band[0] is None else band[0]
        hi = math.inf if band[1] is None else band[1]
        for k, w in enumerate(tr.waypoints_m):
            if not lo <= w[2] <= hi:
                raise ValueError(f"platform {self.name}: trajectory.waypoints_m.{k} {list(w)} is {w[2]} m "
                                 f"above the ground, outside its altitude band [{band[0]}, {band[1]}] m "
                                 "(limits.min/max_height_above_ground_m)")
        return self


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


class Clock(_Model):
    """The shared simulated clock: every stream samples it at its own rate from t = 0."""

    duration_s: float = Field(gt=0, le=3600)
    radio_rate_hz: float = 10.0
    pose_rate_hz: float = 100.0
    _rate = field_validator("radio_rate_hz", "pose_rate_hz")(
        classmethod(lambda cls, v: _rate_has_exact_clock(v)))


class RayTracing(_Model):
    """Sionna RT PathSolver settings (always run in its deterministic mode, with ``seed``)."""

    max_depth: int = Field(3, ge=0, le=10)
    samples_per_src: int = Field(100_000, ge=1_000, le=100_000_000)
    max_num_paths_per_src: int = Field(1_000_000, ge=1)
    los: bool = True
    specular_reflection: bool = True
    diffuse_reflection: bool = False
    refraction: bool = False
    diffraction: bool = False
    edge_diffraction: bool = False
    seed: int = 42
    max_receivers_per_call: int = Field(2000, ge=1)
    max_solver_memory_gib: float = Field(
        4.0, gt=0, description="receivers per PathSolver call are capped so that the deterministic "
        "solver's working set (about 48 B x depth x samples x receivers, measured) stays below this")
    store_interaction_points: bool = Field(
        False, description="store every path's interaction points (time x link x depth x path x 3)")


class Ofdm(_Model):
    """OFDM numerology (3GPP TS 38.211 4.2): subcarrier spacing 15 * 2**mu kHz."""

    carrier_frequency_hz: float = Field(3.5e9, gt=1e8, lt=1e12)
    numerology_mu: int = Field(1, ge=0, le=6)
    num_resource_blocks: int = Field(51, ge=1, le=275)
    num_ofdm_symbols: int = Field(14, ge=1)
    cyclic_prefix: Literal["normal", "extended"] = "normal"

    @model_validator(mode="after")
    def _cyclic_prefix(self):
        # TS 38.211 Table 4.2-1: the extended cyclic prefix exists only for mu = 2; a slot holds
        # 14 OFDM symbols with the normal prefix and 12 with the extended one (Table 4.3.2-1/-2).
        per_slot = 12 if self.cyclic_prefix == "extended" else 14
        if self.cyclic_prefix == "extended" and self.numerology_mu != 2:
            raise ValueError("cyclic_prefix: 'extended' exists only for numerology_mu 2 (60 kHz)")
        if self.num_ofdm_symbols > per_slot:
            raise ValueError(f"num_ofdm_symbols: at most {per_slot} per slot with the "
                             f"{self.cyclic_prefix} cyclic prefix")
        return self

    @property
    def subcarrier_spacing_hz(self) -> float:
        return 15e3 * 2 ** self.numerology_mu

    @property
    def num_subcarriers(self) -> int:
        return 12 * self.num_resource_blocks  # TS 38.211: 12 subcarriers per resource block

    @property
    def bandwidth_hz(self) -> float:
        return self.num_subcarriers * self.subcarrier_spacing_hz


class Receiver(_Model):
    noise_figure_db: float = Field(7.0, ge=0)
    temperature_k: float = Field(290.0, gt=0)


class Codebook(_Model):
    """DFT codebook of the base-station UPA: oversampling per axis (1 = orthogonal beams).

    ``visible_only`` drops the grid beams whose direction cosines lie outside the unit circle
    (no real direction; 12 of the 64 beams of an 8 x 8 half-wavelength array). ``path`` names a
    ``.npy`` file of complex precoders ``[num_beams, num_tx_antennas]`` (Sionna antenna order,
    relative to the scene directory) that replaces the DFT grid.
    """

    oversampling: int = Field(1, ge=1, le=8)
    visible_only: bool = False
    path: str | None = None


class Link(_Model):
    """Link and system level (docs/link-level.md): resource allocation, TBS overheads, MCS table,
    link adaptation. Downlink: base stations transmit the PDSCH to the platforms."""

    first_resource_block: int = Field(0, ge=0, description="first allocated resource block")
    num_allocated_resource_blocks: int | None = Field(
        None, ge=1, description="allocated resource blocks; None: from first_resource_block to "
                                "the carrier's last")
    dmrs_re_per_prb: int = Field(12, ge=0, le=72, description="DMRS resource elements per PRB "
                                 "and slot, N_DMRS^PRB of TS 38.214 5.1.3.2")
    overhead_re_per_prb: Literal[0, 6, 12, 18] = Field(
        0, description="xOverhead, N_oh^PRB of TS 38.214 5.1.3.2")
    mcs_table: Literal[1, 2] = Field(
        1, description="TS 38.214 Table 5.1.3.1-1 (64QAM) or -2 (256QAM); the EESM beta table "
                       "covers these two")
    bler_target: float = Field(0.1, gt=0, lt=1, description="transport BLER target of link "
                                                              "adaptation")
    link_adaptation: Literal["inner_loop", "outer_loop"] = "inner_loop"
    olla_delta_up_db: float = Field(1.0, gt=0, description="outer loop: offset step on a NACK")
    olla_offset_limits_db: Vec2 = (-20.0, 20.0)

    @model_validator(mode="after")
    def _limits(self):
        if self.olla_offset_limits_db[0] > self.olla_offset_limits_db[1]:
            raise ValueError("olla_offset_limits_db: the lower limit exceeds the upper one")
        return self


class Ckm(_Model):
    """Channel-knowledge-map grid: horizontal planes at one or more heights, split into tiles (the
    tile partitions). Cells inside buildings or outside ``region_m`` are masked and never traced."""

    center_m: Vec2 = (0.0, 0.0)
    size_m: Vec2 = (100.0, 100.0)
    cell_size_m: float = Field(5.0, gt=0)
    height_m: float | None = Field(None, description="one receiver height (m); or use heights_m")
    heights_m: tuple[float, ...] | None = Field(None, description="several heights: a 3D voxel map")
    region_m: tuple[Vec2, ...] | None = Field(
        None, description="polygon (ENU x, y vertices) of the region of interest; default the whole grid")
    tiles: tuple[int, int] = Field((2, 2), description="tiles along x, along y")
    mode: Literal["reference", "fast"] = Field(
        "reference", description="reference: PathSolver at cell centres; fast: one shoot-and-bounce pass")
    deterministic_solver: bool = Field(
        False, description="reference mode: PathSolver(deterministic=True) instead of its default "
        "candidate generator, which finds the same paths here at a fraction of the time and memory "
        "per receiver (docs/ckm.md)")
    num_rays: int = Field(10_000_000, ge=1_000, description="fast mode: rays per transmitter")
    min_hits_for_spread: int = Field(10, ge=1, description="fast mode: fewer ray hits mask the spreads")
    weathers: tuple[Literal["sunny", "rainy", "night"], ...] | None = Field(
        None, description="weathers whose radio materials get a map (default: the scene's); weathers "
        "with equal materials share one map")

    @field_validator("tiles")
    @classmethod
    def _tiles(cls, v):
        if not (1 <= v[0] <= MAX_TILES_PER_AXIS and 1 <= v[1] <= MAX_TILES_PER_AXIS):
            raise ValueError(f"tiles per axis must be within 1..{MAX_TILES_PER_AXIS}")
        return v

    @model_validator(mode="after")
    def _heights(self):
        if self.height_m is not None and self.heights_m is not None:
            raise ValueError("give height_m or heights_m, not both")
        if self.heights_m is not None and (not self.heights_m or len(set(self.heights_m)) != len(self.heights_m)):
            raise ValueError("heights_m: at least one height, none repeated")
        if self.region_m is not None and len(self.region_m) < 3:
            raise ValueError("region_m: a polygon needs at least three vertices")
        return self

    @property
    def heights(self) -> tuple[float, ...]:
        """Receiver heights (m): ``heights_m``, else ``(height_m,)``, else 1.5 m."""
        if self.heights_m is not None:
            return tuple(self.heights_m)
        return (1.5 if self.height_m is None else self.height_m,)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows along y, cols along x)."""
        return (max(1, round(self.size_m[1] / self.cell_size_m)),
                max(1, round(self.size_m[0] / self.cell_size_m)))


class SceneConfig(_Model):
    name: str = Field(pattern=r"^[a-z0-9][a-z0-9_-]*$")
    description: str = ""
    source: Source
    origin: WorldOrigin
    materials: Materials = Materials()
    base_stations: tuple[BaseStation, ...] = Field(min_length=1)
    platforms: tuple[Platform, ...] = Field(min_length=1)
    clock: Clock
    ray_tracing: RayTracing = RayTracing()
    ofdm: Ofdm = Ofdm()
    receiver: Receiver = Receiver()
    codebook: Codebook = Codebook()
    link: Link = Link()
    ckm: Ckm = Ckm()
    weathers: tuple[Literal["sunny", "rainy", "night"], ...] = WEATHERS
    seed: int = Field(0, description="seed of every random draw (sensor noise, layouts)")
    sensor_imports: tuple[SensorImport, ...] = Field(
        (), description="recorded sensor streams imported from bags in place of the embedded renderer")

    @model_validator(mode="after")
    def _imports_match_devices(self):
        devices = {d.name: d for d in (*self.base_stations, *self.platforms)}
        seen = set()
        for i, imp in enumerate(self.sensor_imports):
            for j, st in enumerate(imp.streams):
                where = f"sensor_imports.{i}.streams.{j}"
                if st.device not in devices:
                    raise ValueError(f"{where}.device: no platform or base station named {st.device!r}; "
                                     f"known: {', '.join(devices)}")
                if (st.device, st.sensor) in seen:
                    raise ValueError(f"{where}: {st.device}/{st.sensor} is imported twice")
                seen.add((st.device, st.sensor))
                same = [s for s in devices[st.device].sensors if s.name == st.sensor]
                if same and same[0].kind != st.kind:
                    raise ValueError(f"{where}.kind: {st.kind!r} cannot replace {st.device}/{st.sensor}, "
                                     f"a {same[0].kind}")
        return self

    @model_validator(mode="after")
    def _unique_names(self):
        names = [d.name for d in (*self.base_stations, *self.platforms)]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"device names must be unique; repeated: {', '.join(dup)}")
        for dev in (*self.base_stations, *self.platforms):
            sn = [s.name for s in dev.sensors]
            dup = sorted({n for n in sn if sn.count(n) > 1})
            if dup:
                raise ValueError(f"{dev.name}: sensor names must be unique; repeated: {', '.join(dup)}")
        # Sionna RT holds one transmit and one receive array per scene.
        for group, devs in (("base_stations", self.base_stations), ("platforms", self.platforms)):
            if len({d.array for d in devs}) > 1:
                raise ValueError(f"{group}: every device must use the same array (Sionna RT holds "
                                 "one array per scene for transmitters and one for receivers)")
        if len(set(self.weathers)) != len(self.weathers):
            raise ValueError("weathers: listed twice")
        return self

    def digest(self) -> str:
        """SHA-256 of the canonical JSON form: the config hash in every store's provenance."""
        blob = json.dumps(self.model_dump(mode="json"), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()


def _loc(loc: tuple) -> str:
    # Drop pydantic's union tags (e.g. 'procedural', 'camera') from the key path.
    parts = [str(p) for p in loc if not (isinstance(p, str) and p in _UNION_TAGS)]
    return ".".join(parts) or "(top level)"


_UNION_TAGS = {"procedural", "osm", "mesh", "camera", "lidar", "imu", "gps", "waypoints", "replay"}


def load_scene_config(scene_dir: str | Path) -> SceneConfig:
    """Read and validate ``scene_dir/scene.yaml``; raise :class:`ConfigError` listing every problem."""
    scene_dir = Path(scene_dir)
    path = scene_dir / "scene.yaml"
    if not path.is_file():
        raise ConfigError([f"{path}: no scene.yaml in {scene_dir}"])
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError([f"{path}: not valid YAML: {exc}"]) from None
    if not isinstance(raw, dict):
        raise ConfigError([f"{path}: (top level): expected a mapping of keys, got {type(raw).__name__}"])
    try:
        cfg = SceneConfig.model_validate(raw)
    except ValidationError as exc:
        errors = exc.errors()
        # A list whose only item failed also reports itself "too short": noise, not a problem.
        errors = [e for e in errors if not (e["type"] == "too_short" and any(
            len(o["loc"]) > len(e["loc"]) and o["loc"][:len(e["loc"])] == e["loc"] for o in errors))]
        raise ConfigError([f"{path}: {_loc(e['loc'])}: {e['msg']}" for e in errors]) from None
    problems = []
    if cfg.name != scene_dir.resolve().name:
        problems.append(f"{path}: name: {cfg.name!r} differs from the scene directory's name "
                        f"{scene_dir.resolve().name!r}")
    for i, p in enumerate(cfg.platforms):
        if p.trajectory.kind == "replay":
            rec = (scene_dir / p.trajectory.path).resolve()
            if not rec.is_relative_to(scene_dir.resolve()):
                problems.append(f"{path}: platforms.{i}.trajectory.path: {p.trajectory.path!r} points "
                                "outside the scene directory")
            elif not (rec.is_file() or (rec / "metadata.yaml").is_file()):
                problems.append(f"{path}: platforms.{i}.trajectory.path: file not found: {rec}"
                                + (" (a rosbag2 directory needs its metadata.yaml)" if rec.is_dir() else ""))
    for i, imp in enumerate(cfg.sensor_imports):
        bag = (scene_dir / imp.path).resolve()
        if not bag.is_relative_to(scene_dir.resolve()):
            problems.append(f"{path}: sensor_imports.{i}.path: {imp.path!r} points outside the scene directory")
        elif not (bag.is_file() or (bag / "metadata.yaml").is_file()):
            problems.append(f"{path}: sensor_imports.{i}.path: bag not found: {bag}")
    if cfg.source.kind in ("osm", "mesh"):
        src = resolve_source_path(scene_dir, cfg)
        if not src.is_file():
            problems.append(f"{path}: source.path: file not found: {src}")
    if problems:
        raise ConfigError(problems)
    return cfg


def resolve_source_path(scene_dir: Path, cfg: SceneConfig) -> Path:
    return (Path(scene_dir) / cfg.source.path).resolve()
