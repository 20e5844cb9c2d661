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
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

WEATHERS = ("sunny", "rainy", "night")
# ITU-R P.2040 materials that Sionna RT's ITURadioMaterial knows.
ITU_MATERIALS = (
    "vacuum", "concrete", "brick", "plasterboard", "wood", "glass", "ceiling_board", "chipboard",
    "plywood", "marble", "floorboard", "metal", "very_dry_ground", "medium_dry_ground", "wet_ground",
)
MAX_TILES_PER_AXIS = 4  # the static tile partitions are r0c0 .. r3c3 (partitions/__init__.py)


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


class MeshSource(_Model):
    """A user-built mesh (OBJ, PLY, STL, glTF/GLB), path relative to the scene directory."""

    kind: Literal["mesh"]
    path: str


Source = Annotated[Union[ProceduralSource, OsmSource, MeshSource], Field(discriminator="kind")]


class Materials(_Model):
    """ITU radio material per semantic class (valid 1-100 GHz, ITU-R P.2040-3 Table 3)."""

    building: str = "concrete"
    road: str = "concrete"
    ground: str = "medium_dry_ground"
    thickness_m: float = Field(0.2, gt=0)

    @model_validator(mode="after")
    def _known(self):
        for key in ("building", "road", "ground"):
            if getattr(self, key) not in ITU_MATERIALS:
                raise ValueError(f"{key}: unknown ITU material {getattr(self, key)!r}; "
                                 f"known: {', '.join(ITU_MATERIALS)}")
        return self


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
    """Waypoints in the ENU world frame (m) flown at constant speed, turning at each waypoint."""

    kind: Literal["waypoints"] = "waypoints"
    waypoints_m: tuple[Vec3, ...]
    speed_mps: float = Field(gt=0, le=100)
    start_offset_s: float = Field(0.0, ge=0)

    @field_validator("waypoints_m")
    @classmethod
    def _two(cls, v):
        if len(v) < 2:
            raise ValueError("at least two waypoints are needed")
        return v


class Platform(_Model):
    name: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$")
    kind: Literal["uav", "ground_vehicle", "pedestrian"]
    array: Array = Array()
    trajectory: WaypointTrajectory
    sensors: tuple[Sensor, ...] = ()


class Clock(_Model):
    """The shared simulated clock: every stream samples it at its own rate from t = 0."""

    duration_s: float = Field(gt=0, le=3600)
    radio_rate_hz: float = 10.0
    pose_rate_hz: float = 100.0
    _rate = field_validator("radio_rate_hz", "pose_rate_hz")(
        classmethod(lambda cls, v: _rate_has_exact_clock(v)))


class RayTracing(_Model):
    """Sionna RT PathSolver settings."""

    max_depth: int = Field(3, ge=0, le=10)
    samples_per_src: int = Field(100_000, ge=1_000, le=100_000_000)
    max_num_paths_per_src: int = Field(1_000_000, ge=1)
    los: bool = True
    specular_reflection: bool = True
    diffuse_reflection: bool = False
    refraction: bool = False
    seed: int = 42
    max_receivers_per_call: int = Field(2000, ge=1)


class Ofdm(_Model):
    """OFDM numerology (3GPP TS 38.211 4.2): subcarrier spacing 15 * 2**mu kHz."""

    carrier_frequency_hz: float = Field(3.5e9, gt=1e8, lt=1e12)
    numerology_mu: int = Field(1, ge=0, le=6)
    num_resource_blocks: int = Field(51, ge=1, le=275)
    num_ofdm_symbols: int = Field(14, ge=1)
    cyclic_prefix: Literal["normal", "extended"] = "normal"

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
    """DFT codebook of the base-station UPA: oversampling per axis (1 = orthogonal beams)."""

    oversampling: int = Field(1, ge=1, le=8)


class Ckm(_Model):
    """Channel-knowledge-map grid: a fixed-height plane split into tiles (the tile partitions)."""

    center_m: Vec2 = (0.0, 0.0)
    size_m: Vec2 = (100.0, 100.0)
    cell_size_m: float = Field(5.0, gt=0)
    height_m: float = 1.5
    tiles: tuple[int, int] = Field((2, 2), description="tiles along x, along y")

    @field_validator("tiles")
    @classmethod
    def _tiles(cls, v):
        if not (1 <= v[0] <= MAX_TILES_PER_AXIS and 1 <= v[1] <= MAX_TILES_PER_AXIS):
            raise ValueError(f"tiles per axis must be within 1..{MAX_TILES_PER_AXIS}")
        return v

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
    ckm: Ckm = Ckm()
    weathers: tuple[Literal["sunny", "rainy", "night"], ...] = WEATHERS
    seed: int = Field(0, description="seed of every random draw (sensor noise, layouts)")

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


_UNION_TAGS = {"procedural", "osm", "mesh", "camera", "lidar", "imu", "gps"}


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
    if cfg.source.kind in ("osm", "mesh"):
        src = resolve_source_path(scene_dir, cfg)
        if not src.is_file():
            problems.append(f"{path}: source.path: file not found: {src}")
    if problems:
        raise ConfigError(problems)
    return cfg


def resolve_source_path(scene_dir: Path, cfg: SceneConfig) -> Path:
    return (Path(scene_dir) / cfg.source.path).resolve()
