"""Stage one: the scene's source geometry, from whichever source its config names."""

from __future__ import annotations

from simart_pipeline.config import SceneConfig, resolve_source_path
from simart_pipeline.scene.geometry import SourceGeometry
from simart_pipeline.scene.mesh_import import source_geometry_from_mesh
from simart_pipeline.scene.osm import read_osm
from simart_pipeline.scene.procedural import procedural_layout


def build_source_geometry(cfg: SceneConfig, scene_dir) -> SourceGeometry:
    """Dispatch on the scene's source kind."""
    if cfg.source.kind == "procedural":
        return procedural_layout(cfg.source, cfg)
    if cfg.source.kind == "osm":
        return read_osm(cfg, scene_dir)
    if cfg.source.kind == "mesh":
        origin = (cfg.origin.latitude_deg, cfg.origin.longitude_deg, cfg.origin.altitude_m)
        return source_geometry_from_mesh(resolve_source_path(scene_dir, cfg), cfg.source.rules, origin)
    if cfg.source.kind == "sionna_xml":
        from simart_pipeline.scene.sionna_xml import source_geometry_from_sionna_xml

        origin = (cfg.origin.latitude_deg, cfg.origin.longitude_deg, cfg.origin.altitude_m)
        return source_geometry_from_sionna_xml(resolve_source_path(scene_dir, cfg), cfg.source, scene_dir, origin)
    raise NotImplementedError(f"scene {cfg.name}: unknown source kind {cfg.source.kind!r}")
