"""Checks of a scene beyond its schema, before any work: every input the config names is opened
(source file, replay recordings and their topics, sensor-import bags, topics and message types,
codebook file) and devices are placed where they can be. Each problem is one
``file: key.path: message`` line; messages speak of what a platform has (waypoints for a planned
path, recorded instants for a replay)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from simart_pipeline import clock
from simart_pipeline.config import ConfigError, SceneConfig, load_scene_config
from simart_pipeline.link.beams import load_codebook
from simart_pipeline.mobility import replay
from simart_pipeline.mobility.bags import Bag
from simart_pipeline.mobility.trajectory import plan_platform
from simart_pipeline.scene import geometry, source
from simart_pipeline.scene.actors import scene_actors
from simart_pipeline.sensing import ros_messages
from simart_pipeline.sensing.bag_import import MESSAGE_TYPES


def scene_problems(scene_dir: str | Path) -> tuple[SceneConfig | None, list[str]]:
    """Every problem of the scene at ``scene_dir``, each as ``file: key.path: message``."""
    scene_dir = Path(scene_dir)
    where = scene_dir / "scene.yaml"
    try:
        cfg = load_scene_config(scene_dir)
    except ConfigError as exc:
        return None, exc.problems
    problems: list[str] = []
    try:
        geom = source.build_source_geometry(cfg, scene_dir)
    except NotImplementedError as exc:
        return cfg, [f"{where}: source.kind: {exc}"]
    except (OSError, ValueError, RuntimeError) as exc:
        return cfg, [f"{where}: source: cannot read the scene's source: {exc}"]
    if not geom.features:
        problems.append(f"{where}: source: the source holds no building, road or ground")

    def inside(p) -> bool:
        return bool(geometry.inside_buildings(geom, np.array([p[0]]), np.array([p[1]]), np.array([p[2]]))[0])

    for i, b in enumerate(cfg.base_stations):
        if inside(b.position_m):
            problems.append(f"{where}: base_stations.{i}.position_m: {b.name} at {list(b.position_m)} "
                            "is inside a building")
    plans = {}  # platform index -> its planned motion
    for i, p in enumerate(cfg.platforms):
        for k, w in enumerate(getattr(p.trajectory, "waypoints_m", ())):
            if inside(w):
                problems.append(f"{where}: platforms.{i}.trajectory.waypoints_m.{k}: {list(w)} is inside a building")
        if p.trajectory.kind == "waypoints":
            try:  # the route along roads and the motion under the limits, as the trajectory asset plans them
                plans[i] = plan_platform(p, geom)
            except ValueError as exc:
                problems.append(f"{where}: platforms.{i}.trajectory: {exc}")
        else:
            problems += _replay_problems(p, i, scene_dir, geom, where)
    problems += _import_problems(cfg, scene_dir, where)
    try:  # every body file reads
        scene_actors(cfg, scene_dir)
    except ValueError as exc:  # MeshImportError: the message names the file and the problem
        problems.append(f"{where}: {exc}")
    for i, a in enumerate(cfg.static_actors):
        if a.body.mesh != "none" and inside(a.position_m):
            problems.append(f"{where}: static_actors.{i}.position_m: {a.name} at {list(a.position_m)} "
                            "is inside a building")
    if cfg.codebook.path is not None:
        try:
            load_codebook(scene_dir / cfg.codebook.path, cfg.base_stations[0].array.num_antennas)
        except ValueError as exc:
            problems.append(f"{where}: codebook.path: {exc}")
    problems += _extent_problems(cfg, geom, where)
    problems += _ground_problems(cfg, geom, where, plans)
    return cfg, problems


def _ground_problems(cfg: SceneConfig, geom, where: Path, plans: dict) -> list[str]:
    """Base stations, waypoints, planned paths (``plans``: platform index -> its motion plan) and
    CKM planes below the ground surface of a source whose ground is not the plane z = 0 (a mesh or
    Sionna scene with terrain): their heights are ENU z above the origin, not above the ground, so
    on a hill they lie inside it."""
    if geom.ground_surface_m is None:
        return []
    from simart_pipeline.ckm.grid import cell_centres, outside_region

    ckm = cfg.ckm
    y, x = cell_centres(ckm)
    xx, yy = np.meshgrid(x, y)
    traced = ~outside_region(ckm, x, y)
    devices = _placements(cfg)
    paths = {i: _path_samples(plan) for i, plan in plans.items()}
    path_xyz = np.concatenate([np.zeros((0, 3)), *paths.values()])
    qx = np.concatenate([[d[2][0] for d in devices], xx[traced], path_xyz[:, 0]])
    qy = np.concatenate([[d[2][1] for d in devices], yy[traced], path_xyz[:, 1]])
    ground = geometry.ground_elevation_m(geom, qx, qy)  # one interpolation for every point
    relief = geom.ground_surface_m[:, 2]
    above = f"heights are ENU z above the scene's origin, not above ground (the ground rises {relief.min():.1f} .. " \
            f"{relief.max():.1f} m)"
    problems = []
    for (key, what, pos), z in zip(devices, ground[:len(devices)]):
        if pos[2] < z:
            problems.append(f"{where}: {key}: {what} lies {z - pos[2]:.1f} m below the ground surface there "
                            f"({z:.1f} m): {above}")
    n_cells = int(traced.sum())
    cells, start = ground[len(devices):len(devices) + n_cells], len(devices) + n_cells
    for i, xyz in paths.items():
        depth = ground[start:start + len(xyz)] - xyz[:, 2]
        start += len(xyz)
        if (depth > 0).any():  # waypoints above the ground, the path between them not (a ridge)
            j = int(np.argmax(depth))
            problems.append(f"{where}: platforms.{i}.trajectory: the planned path runs up to {depth[j]:.1f} m below "
                            f"the ground surface (at {np.round(xyz[j], 1).tolist()}, the ground "
                            f"{xyz[j, 2] + depth[j]:.1f} m): add waypoints over the rise; {above}")
    for k, h in enumerate(ckm.heights):
        below = cells > h
        if below.any():
            key = "ckm.height_m" if ckm.heights_m is None else f"ckm.heights_m.{k}"
            problems.append(f"{where}: {key}: the plane at {h:g} m lies below the ground surface in "
                            f"{100 * below.mean():.3g} % of the grid's cells (the ground there: {cells.min():.1f} .. "
                            f"{cells.max():.1f} m): {above}; CKM planes are horizontal, so place the grid where "
                            "the ground stays below them (ckm.center_m, size_m, region_m) or raise the height")
    return problems


def _extent_problems(cfg: SceneConfig, geom, where: Path) -> list[str]:
    """Base stations, waypoints and the CKM grid outside the scene's ground (x, y): nothing there to
    stand on or reflect from, so their channels and cells would be computed in empty space."""
    ground = geom.of_class("ground")
    if not ground:  # a source without ground (a mesh or Sionna scene that has none)
        return []
    import shapely

    extent = shapely.union_all([g.geometry for g in ground])
    held = extent.buffer(EXTENT_TOLERANCE_M)
    x0, y0, x1, y1 = (round(v, 1) for v in extent.bounds)
    hint = _WIDER_SOURCE.get(cfg.source.kind)
    beyond = f"beyond the scene's ground (x {x0} .. {x1} m, y {y0} .. {y1} m{'; ' + hint if hint else ''})"
    problems = [f"{where}: {key}: {what} lies {beyond}" for key, what, pos in _placements(cfg)
                if not held.covers(shapely.Point(pos[:2]))]
    ckm = cfg.ckm
    box = shapely.box(ckm.center_m[0] - ckm.size_m[0] / 2, ckm.center_m[1] - ckm.size_m[1] / 2,
                      ckm.center_m[0] + ckm.size_m[0] / 2, ckm.center_m[1] + ckm.size_m[1] / 2)
    outside = box.difference(held).area / box.area
    if outside > 0:
        problems.append(f"{where}: ckm: {100 * outside:.3g} % of the grid (x {box.bounds[0]:g} .. {box.bounds[2]:g} m, "
                        f"y {box.bounds[1]:g} .. {box.bounds[3]:g} m) lies {beyond}: move ckm.center_m or "
                        "shrink ckm.size_m")
    return problems


def _placements(cfg: SceneConfig) -> list[tuple[str, str, tuple]]:
    """(config key, what it is, position m) of every base station and waypoint of the scene."""
    out = [(f"base_stations.{i}.position_m", f"{b.name} at {list(b.position_m)}", b.position_m)
           for i, b in enumerate(cfg.base_stations)]
    return out + [(f"platforms.{i}.trajectory.waypoints_m.{k}", str(list(w)), w)
                  for i, p in enumerate(cfg.platforms) for k, w in enumerate(getattr(p.trajectory, "waypoints_m", ()))]


def _path_samples(plan, step_m: float = 1.0, most: int = 20_000) -> np.ndarray:
    """``[n, 3]`` points along a planned path, about ``step_m`` apart or closer (at most about ``most``)."""
    p = plan.segment_samples()["position_m"]
    length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0
    segments = max(len(plan.seg_t0), 1)
    # every segment as finely as if it were the whole path: segments differ in length
    per_segment = int(np.clip(np.ceil(length / step_m) + 1, 2, max(most // segments, 2)))
    return plan.segment_samples(per_segment)["position_m"]


EXTENT_TOLERANCE_M = 0.01  # an OSM box's edges are parallels: curved in the local frame, by millimetres
_WIDER_SOURCE = {"osm": "the extract's area, or source.bbox_deg where set",
                 "procedural": "source.blocks, block_size_m and street_width_m set its size"}


def _replay_problems(platform, i: int, scene_dir: Path, geom, where: Path) -> list[str]:
    """The recording read as the trajectory stage reads it (file, topic, message type, stamp rules,
    dynamic limits), and its recorded poses checked against the buildings."""
    try:
        rec = replay.checked_recording(platform, scene_dir)
    except (OSError, ValueError) as exc:  # ReplayError and BagError name the file and the topic
        return [f"{where}: platforms.{i}.trajectory: {exc}"]
    pos = rec["position_m"]
    inside = geometry.inside_buildings(geom, pos[:, 0], pos[:, 1], pos[:, 2])
    if not inside.any():
        return []
    k = int(np.argmax(inside))
    t_s = float(clock.ns_to_seconds(rec["time_ns"][k] - rec["time_ns"][0]))
    return [f"{where}: platforms.{i}.trajectory: {int(inside.sum())} of {len(pos)} recorded poses of "
            f"{platform.name} lie inside a building, the first {t_s:.3f} s into the recording at "
            f"{np.round(pos[k], 2).tolist()} m: check trajectory.recording_frame (where the recording's "
            "frame sits in the scene) and the recording"]


def _import_problems(cfg: SceneConfig, scene_dir: Path, where: Path) -> list[str]:
    """Every sensor-import bag opened, every topic and CameraInfo topic there with a type the import reads."""
    problems = []
    for i, imp in enumerate(cfg.sensor_imports):
        try:
            with Bag(scene_dir / imp.path) as bag:
                for j, st in enumerate(imp.streams):
                    for key, topic, types in (("topic", st.topic, MESSAGE_TYPES[st.kind]),
                                              ("camera_info_topic", st.camera_info_topic, (ros_messages.CAMERA_INFO,))):
                        if topic is None:
                            continue
                        try:
                            bag.msgtype(topic, types)
                        except ValueError as exc:
                            problems.append(f"{where}: sensor_imports.{i}.streams.{j}.{key}: {exc}")
        except (OSError, ValueError) as exc:
            problems.append(f"{where}: sensor_imports.{i}.path: {exc}")
    return problems
