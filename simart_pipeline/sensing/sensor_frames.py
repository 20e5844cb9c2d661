"""The sensing stage: every sensor of every device of a scene, for one weather, as one tree.

:func:`build_sensor_frames` is what the ``sensor_frames`` asset stores: every stream of the scene's
``sensor_imports`` (``config.SensorImport``) is read from its bag into the group
``/<device>/<sensor>`` (:mod:`.bag_import`), replacing the embedded sensor of that name or adding
one, and every other configured sensor is rendered (:func:`render_sensor_frames`).

:func:`render_sensor_frames` returns an ``xarray.DataTree`` with one group per sensor at
``/<device>/<sensor>`` (device = platform or base-station name). Each group has its own ``time``
coordinate (int64 ns, ``clock.sample_times_ns(duration, rate_hz)``), the sensor's variables (see
:mod:`.camera`, :mod:`.lidar`, :mod:`.inertial`) and attrs naming its frames, its mount, its kind and
rate, and the weather with the weather model's parameters (:mod:`.weather`). Rendered and imported
groups of one kind follow one contract (:mod:`.contract`, ``docs/sensor-plugin.md``). Poses and
random streams: :mod:`.streams`.

The Mitsuba scene is built only when a camera or a LiDAR is rendered, once per call.
"""

from __future__ import annotations

from pathlib import Path

import xarray as xr

from simart_pipeline import clock, frames
from simart_pipeline.config import Camera, Gps, Imu, Lidar, SceneConfig
from simart_pipeline.scene import actors
from simart_pipeline.scene.meshes import SceneMeshes
from simart_pipeline.sensing import camera, contract, inertial, lidar, raycast
from simart_pipeline.sensing.bag_import import import_streams
from simart_pipeline.sensing.streams import device_kind, device_poses, mount_rotation, sensor_poses, stream_rng
from simart_pipeline.sensing.weather import weather_model

SENSING_MODEL_VERSION = 3  # 3: actors in cameras and LiDARs, actor ground truth per camera frame


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
    tree = render_sensor_frames(meshes, traj, rendered_cfg, weather, scene_dir)
    if not imported:
        return tree
    groups = {node.path: node.to_dataset() for node in tree.subtree if node.has_data}
    for imp in cfg.sensor_imports:
        groups.update(import_streams(imp, cfg, traj, scene_dir, weather))
    out = xr.DataTree.from_dict(groups)
    out.attrs.update(tree.attrs, imported_streams=sorted(f"/{d}/{s}" for d, s in imported))
    return out


def render_sensor_frames(meshes: SceneMeshes, traj: xr.Dataset, cfg: SceneConfig,
                         weather: str, scene_dir: str | Path | None = None) -> xr.DataTree:
    """Render every sensor of ``cfg`` in ``weather``: a tree with a group per ``/<device>/<sensor>``.
    Cameras and LiDARs see every actor (``scene.actors``) except their own platform's body."""
    wx = weather_model(weather)
    wx_attrs = contract.weather_attrs(weather, applied=True)
    caster: raycast.RayCaster | None = None
    bodies: list[actors.Actor] | None = None

    def get_caster() -> raycast.RayCaster:
        nonlocal caster, bodies
        if caster is None:
            caster = raycast.RayCaster(meshes)
            bodies = actors.scene_actors(cfg, scene_dir)
            if bodies:
                caster.actors = raycast.ActorLayer(bodies)
        return caster

    def view(device, sensor, t_ns) -> raycast.ActorView | None:
        if not bodies:
            return None
        own = tuple(a for a, act in enumerate(bodies)
                    if act.platform == device.name and not sensor.mount.sees_own_body)
        return raycast.ActorView(bodies, actors.actor_poses(bodies, traj, t_ns), own)

    groups: dict[str, xr.Dataset] = {}
    for device in (*cfg.platforms, *cfg.base_stations):
        for sensor in device.sensors:
            t_ns = clock.sample_times_ns(cfg.clock.duration_s, sensor.rate_hz)
            rng = stream_rng(cfg.seed, device.name, sensor.name, weather)
            pos_b, rot_b, poses = device_poses(device, traj, t_ns)
            if isinstance(sensor, Camera):
                pos_s, rot_s = sensor_poses(pos_b, rot_b, sensor)
                ds = camera.render_camera(get_caster(), sensor, t_ns, pos_s, rot_s * frames.OPTICAL_TO_BODY,
                                          wx, rng, view(device, sensor, t_ns))
            elif isinstance(sensor, Lidar):
                pos_s, rot_s = sensor_poses(pos_b, rot_b, sensor)
                ds = lidar.render_lidar(get_caster(), sensor, t_ns, pos_s, rot_s, wx, rng,
                                        view(device, sensor, t_ns))
            elif isinstance(sensor, Imu):
                ds = inertial.render_imu(sensor, t_ns, poses, rng)
            elif isinstance(sensor, Gps):
                ds = inertial.render_gps(sensor, t_ns, poses, cfg.origin, rng)
            else:  # pragma: no cover - the config schema admits no other kind
                raise TypeError(f"unknown sensor kind {type(sensor).__name__}")
            pose = ("the trajectory" if device_kind(device) == "platform" else "the base station's fixed pose")
            ds.attrs.update(contract.stream_attrs(
                device.name, device_kind(device), sensor.name, sensor.kind, t_ns,
                mount_translation_m=sensor.mount.translation_m, mount_rpy_deg=sensor.mount.rpy_deg,
                mount_rotation=mount_rotation(sensor), weather=wx_attrs, rate_hz=sensor.rate_hz,
                pose_source=f"{pose} at the sample instants composed with the mount"))
            groups[f"/{device.name}/{sensor.name}"] = ds
    tree = xr.DataTree.from_dict(groups) if groups else xr.DataTree()
    tree.attrs.update(weather=weather, weather_description=wx.description, world_frame_id=frames.WORLD,
                      sensing_model_version=SENSING_MODEL_VERSION, scene=cfg.name, seed=cfg.seed)
    return tree
