"""The one scene config schema: ``scenes/<name>/scene.yaml``.

Every key is declared in this package, one module per concept, with its unit in its name, its
default and its bounds:

- :mod:`.source`: the world origin and the geometry source (procedural, OSM, user mesh);
- :mod:`.devices`: antenna arrays, sensors (one shared base), base stations and their radars,
  platforms, limits;
- :mod:`.actors`: bodies of platforms and static actors;
- :mod:`.trajectories` and :mod:`.recordings`: waypoints or a replayed recording;
- :mod:`.sensor_imports`: sensor streams imported from bags;
- :mod:`.radio`: materials, ray tracing, OFDM numerology;
- :mod:`.link`: receiver noise, codebook, resource allocation, link adaptation;
- :mod:`.ckm`: the channel-knowledge-map grid;
- :mod:`.scene`: the shared clock, :class:`SceneConfig` and :func:`load_scene_config`.

A wrong key or value is reported with the file's name and the key path
(``platforms.0.sensors.1.rate_hz``) before any work starts; :func:`load_scene_config` collects every
problem at once.
"""

from simart_pipeline.config.actors import ActorKind, Body, StaticActor
from simart_pipeline.config.base import ConfigError, Vec2, Vec3
from simart_pipeline.config.ckm import MAX_TILES_PER_AXIS, Ckm
from simart_pipeline.config.devices import (DEFAULT_LIMITS, Array, BaseStation, Camera, DynamicLimits, Gps, Imu,
                                            Lidar, Mount, Platform, Radar, Sensor, SensorBase)
from simart_pipeline.config.link import Codebook, Link, Receiver
from simart_pipeline.config.radio import DEFAULT_TAG_MATERIALS, Materials, Ofdm, RayTracing
from simart_pipeline.config.recordings import BAG_TIME_ORIGINS, RECORDING_FORMATS, recording_format
from simart_pipeline.config.scene import Clock, SceneConfig, load_scene_config, resolve_source_path
from simart_pipeline.config.sensor_imports import ImportedStream, SensorImport
from simart_pipeline.config.source import (MeshImportRules, MeshPartRule, MeshSource, OsmSource,
                                           ProceduralSource, SionnaXmlSource, Source, WorldOrigin,
                                           check_mesh_labels)
from simart_pipeline.config.trajectories import (RecordingFrame, ReplayTrajectory, TrajectorySource,
                                                 WaypointTrajectory)

__all__ = [
    "ActorKind", "Body", "Radar", "StaticActor",
    "Array", "BAG_TIME_ORIGINS", "BaseStation", "Camera", "Ckm", "Clock", "Codebook", "ConfigError",
    "DEFAULT_LIMITS", "DEFAULT_TAG_MATERIALS", "DynamicLimits", "Gps", "ImportedStream", "Imu", "Lidar",
    "Link", "MAX_TILES_PER_AXIS", "Materials", "MeshImportRules", "MeshPartRule", "MeshSource", "Mount",
    "Ofdm", "OsmSource", "Platform", "ProceduralSource", "RECORDING_FORMATS", "RayTracing", "Receiver",
    "RecordingFrame", "ReplayTrajectory", "SceneConfig", "Sensor", "SensorBase", "SensorImport",
    "SionnaXmlSource", "Source",
    "TrajectorySource", "Vec2", "Vec3", "WaypointTrajectory", "WorldOrigin", "check_mesh_labels",
    "load_scene_config", "recording_format", "resolve_source_path",
]
