"""The scene root: the shared clock, :class:`SceneConfig` and the loader of ``scene.yaml``."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from simart_pipeline.config.actors import StaticActor
from simart_pipeline.config.base import ConfigError, _Model, _rate_has_exact_clock
from simart_pipeline.config.ckm import Ckm
from simart_pipeline.config.devices import BaseStation, Platform
from simart_pipeline.config.link import Codebook, Link, Receiver
from simart_pipeline.config.radio import Materials, Ofdm, RayTracing
from simart_pipeline.config.sensor_imports import SensorImport
from simart_pipeline.config.source import Source, WorldOrigin
from simart_pipeline.config.study import BeamStudy
from simart_pipeline.vocabulary import WEATHERS, WeatherName


class Clock(_Model):
    """The shared simulated clock: every stream samples it at its own rate from t = 0."""

    duration_s: float = Field(gt=0, le=3600)
    radio_rate_hz: float = 10.0
    pose_rate_hz: float = 100.0
    _rate = field_validator("radio_rate_hz", "pose_rate_hz")(
        classmethod(lambda cls, v: _rate_has_exact_clock(v)))


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
    weathers: tuple[WeatherName, ...] = WEATHERS
    seed: int = Field(0, description="seed of every random draw (sensor noise, layouts)")
    static_actors: tuple[StaticActor, ...] = Field(
        (), description="parked vehicles, standing people: bodies without a trajectory")
    sensor_imports: tuple[SensorImport, ...] = Field(
        (), description="recorded sensor streams imported from bags in place of the embedded renderer")
    beam_study: BeamStudy | None = Field(None, description="the beam-prediction case study (docs/beam-study.md)")

    @model_validator(mode="after")
    def _study_devices(self):
        st = self.beam_study
        if st is None:
            return self
        bs = next((b for b in self.base_stations if b.name == st.base_station), None)
        if bs is None:
            raise ValueError(f"beam_study.base_station: no base station named {st.base_station!r}")
        if not any(c.name == st.camera for c in bs.sensors):
            raise ValueError(f"beam_study.camera: base station {bs.name} has no camera named {st.camera!r}")
        p = next((q for q in self.platforms if q.name == st.platform), None)
        if p is None:
            raise ValueError(f"beam_study.platform: no platform named {st.platform!r}")
        if p.trajectory.kind != "waypoints" or len(p.trajectory.waypoints_m) < 3:
            raise ValueError(f"beam_study.platform: {p.name} needs a waypoint trajectory of at least two "
                             "legs (each leg is one flight)")
        if not any(s.kind == "gps" and s.name == st.gps for s in p.sensors):
            raise ValueError(f"beam_study.gps: platform {p.name} has no GPS named {st.gps!r}")
        return self

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
        names = [d.name for d in (*self.base_stations, *self.platforms, *self.static_actors)]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"device and actor names must be unique; repeated: {', '.join(dup)}")
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
        radars = {(b.radar.array, b.radar.diffuse_reflection) for b in self.base_stations if b.radar is not None}
        if len(radars) > 1:
            raise ValueError("base_stations: every radar must use the same array and diffuse_reflection "
                             "(one Sionna RT scene traces them all)")
        if len(set(self.weathers)) != len(self.weathers):
            raise ValueError("weathers: listed twice")
        return self

    def digest(self) -> str:
        """SHA-256 of the canonical JSON form: the config hash in every store's provenance."""
        blob = json.dumps(self.model_dump(mode="json"), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()


def _loc(loc: tuple) -> str:
    # Drop pydantic's union tags (e.g. 'procedural', 'camera') from the key path.
    # A tag is followed by the key inside the union's member; a last element is a key itself
    # (``body.mesh``).
    parts = [str(p) for i, p in enumerate(loc)
             if not (isinstance(p, str) and p in _UNION_TAGS and i < len(loc) - 1)]
    return ".".join(parts) or "(top level)"


_UNION_TAGS = {"procedural", "osm", "mesh", "sionna_xml", "camera", "lidar", "imu", "gps", "waypoints", "replay"}


_YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def load_scene_config(scene_dir: str | Path) -> SceneConfig:
    """Read and validate ``scene_dir/scene.yaml``; raise :class:`ConfigError` listing every problem."""
    scene_dir = Path(scene_dir)
    path = scene_dir / "scene.yaml"
    if not path.is_file():
        raise ConfigError([f"{path}: (top level): no scene.yaml in {scene_dir}"])
    try:
        # libyaml's loader when PyYAML has it: the pure-Python one took 60 ms a load, and every
        # asset reads its scene's config (about 100 loads a demo run).
        raw = yaml.load(path.read_text(encoding="utf-8"), Loader=_YAML_LOADER)
    except UnicodeDecodeError as exc:
        raise ConfigError([f"{path}: (top level): not UTF-8 text (byte {exc.start}: {exc.reason})"]) from None
    except OSError as exc:
        raise ConfigError([f"{path}: (top level): cannot read it: {exc.strerror or exc}"]) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "(top level)"
        what = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError([f"{path}: {where}: not valid YAML: {what}"]) from None
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
    # Every file the config names: (key, path, what to say when it is missing or None when another
    # stage checks, may be a rosbag2 directory). One rule for all: it stays inside the scene folder.
    named = [(f"platforms.{i}.trajectory.path", p.trajectory.path, "file not found", True)
             for i, p in enumerate(cfg.platforms) if p.trajectory.kind == "replay"]
    named += [(f"sensor_imports.{i}.path", imp.path, "bag not found", True)
              for i, imp in enumerate(cfg.sensor_imports)]
    if cfg.source.kind in ("osm", "mesh", "sionna_xml"):
        named.append(("source.path", cfg.source.path, "file not found", False))
    named += [(f"platforms.{i}.body.mesh", p.body.mesh, "file not found", False)
              for i, p in enumerate(cfg.platforms) if p.body.is_file]
    named += [(f"static_actors.{i}.body.mesh", a.body.mesh, "file not found", False)
              for i, a in enumerate(cfg.static_actors) if a.body.is_file]
    if cfg.codebook.path is not None:
        named.append(("codebook.path", cfg.codebook.path, None, False))  # read by `simart validate`
    root = scene_dir.resolve()
    for key, rel, missing, bag_dir in named:
        f = (scene_dir / rel).resolve()
        if not f.is_relative_to(root):
            problems.append(f"{path}: {key}: {rel!r} points outside the scene directory")
        elif missing and not (f.is_file() or (bag_dir and (f / "metadata.yaml").is_file())):
            problems.append(f"{path}: {key}: {missing}: {f}"
                            + (" (a rosbag2 directory needs its metadata.yaml)" if bag_dir and f.is_dir() else ""))
    if problems:
        raise ConfigError(problems)
    return cfg


def resolve_source_path(scene_dir: Path, cfg: SceneConfig) -> Path:
    return (Path(scene_dir) / cfg.source.path).resolve()
