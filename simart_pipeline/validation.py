"""Checks of a scene beyond its schema: inputs readable, devices placed where they can be."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from simart_pipeline.config import ConfigError, SceneConfig, load_scene_config
from simart_pipeline.mobility.trajectory import plan_platform
from simart_pipeline.scene import geometry, source


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
    for i, p in enumerate(cfg.platforms):
        for k, w in enumerate(getattr(p.trajectory, "waypoints_m", ())):
            if inside(w):
                problems.append(f"{where}: platforms.{i}.trajectory.waypoints_m.{k}: {list(w)} is inside a building")
        if p.trajectory.kind == "waypoints":
            try:  # the route along roads and the motion under the limits, as the trajectory asset plans them
                plan_platform(p, geom)
            except ValueError as exc:
                problems.append(f"{where}: platforms.{i}.trajectory: {exc}")
    ground = geom.of_class("ground")
    if ground:
        import shapely

        extent = shapely.union_all([g.geometry for g in ground])
        ckm = cfg.ckm
        box = shapely.box(ckm.center_m[0] - ckm.size_m[0] / 2, ckm.center_m[1] - ckm.size_m[1] / 2,
                          ckm.center_m[0] + ckm.size_m[0] / 2, ckm.center_m[1] + ckm.size_m[1] / 2)
        if not box.intersects(extent):
            problems.append(f"{where}: ckm: the grid does not overlap the scene's ground")
    return cfg, problems
