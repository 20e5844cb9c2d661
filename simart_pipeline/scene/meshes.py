"""Paired meshes: a visual mesh for the sensor renderer and a radio mesh for Sionna RT, one frame.

- **Visual mesh**: one triangle mesh (``visual/visual.ply``) whose faces carry a semantic class and
  an instance id (the source feature's id) in ``visual/face_labels.zarr``.
- **Radio mesh**: one PLY per (semantic class, ITU radio material) under ``radio/meshes/`` and a
  Mitsuba XML scene ``radio/scene.xml`` with ``itu-radio-material`` BSDFs, loadable by plain
  ``sionna.rt.load_scene``.

Both come from the same source geometry: buildings are footprints extruded from ``min_height_m``
to ``height_m``; roads are their centre lines buffered by half their width; the ground is its
polygon minus roads and building footprints, so no two surfaces overlap.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import shapely
import trimesh
import xarray as xr
from shapely.geometry import MultiPolygon, Polygon

from simart_pipeline import stores
from simart_pipeline.scene.geometry import SourceGeometry


class SemanticClass(IntEnum):
    """Per-face semantic class of the visual mesh (and of camera segmentation images)."""

    UNLABELED = 0
    GROUND = 1
    ROAD = 2
    BUILDING = 3
    VEGETATION = 4
    WATER = 5
    VEHICLE = 6


def semantic_flag_attrs() -> dict:
    """CF ``flag_values`` / ``flag_meanings`` of :class:`SemanticClass`, for every label variable."""
    return {"flag_values": np.array([int(c) for c in SemanticClass], np.uint8),
            "flag_meanings": " ".join(c.name.lower() for c in SemanticClass)}


_CLASS_OF_FEATURE = {"building": SemanticClass.BUILDING, "road": SemanticClass.ROAD,
                     "ground": SemanticClass.GROUND}


@dataclass
class SceneMeshes:
    visual: trimesh.Trimesh
    face_class: np.ndarray      # [num_faces] uint8, SemanticClass
    face_instance: np.ndarray   # [num_faces] int64, source feature id
    radio: dict[tuple[str, str], trimesh.Trimesh]  # (class name, ITU material) -> mesh
    root: Path | None = None  # the directory it was loaded from, if any

    @property
    def radio_materials(self) -> list[str]:
        return sorted({m for _, m in self.radio})

    def counts(self) -> dict:
        return {"visual_triangles": int(len(self.visual.faces)),
                "radio_triangles": int(sum(len(m.faces) for m in self.radio.values())),
                "radio_meshes": len(self.radio), "radio_materials": self.radio_materials,
                "buildings": int(len(np.unique(self.face_instance[self.face_class == SemanticClass.BUILDING])))}


def _polygons(geom) -> list[Polygon]:
    if isinstance(geom, Polygon):
        return [geom] if not geom.is_empty else []
    if isinstance(geom, MultiPolygon):
        return [g for g in geom.geoms if not g.is_empty]
    return [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon) and not g.is_empty]


def _flat(poly: Polygon, z: float = 0.0) -> trimesh.Trimesh:
    """Triangulate a polygon (holes included) at height ``z`` with faces pointing up (+z)."""
    v2, f = trimesh.creation.triangulate_polygon(poly)
    v = np.column_stack([v2, np.full(len(v2), z)])
    mesh = trimesh.Trimesh(v, f, process=False)
    if len(mesh.faces) and mesh.face_normals[:, 2].mean() < 0:
        mesh.faces = mesh.faces[:, ::-1]
    return mesh


def _extrude(poly: Polygon, bottom: float, top: float) -> trimesh.Trimesh:
    mesh = trimesh.creation.extrude_polygon(poly, top - bottom)
    mesh.apply_translation([0.0, 0.0, bottom])
    return mesh


def build_meshes(geom: SourceGeometry) -> SceneMeshes:
    """Extrude buildings, lay roads and ground; label every visual face."""
    parts: list[tuple[trimesh.Trimesh, int, int, str, str]] = []
    footprints = []
    for f in geom.of_class("building"):
        bottom = 0.0 if np.isnan(f.min_height_m) else f.min_height_m
        for poly in _polygons(f.geometry.buffer(0)):
            parts.append((_extrude(poly, bottom, f.height_m), SemanticClass.BUILDING, f.source_id,
                          "building", f.radio_material))
            footprints.append(poly)
    grounds = geom.of_class("ground")
    extent = shapely.union_all([g.geometry for g in grounds]) if grounds else None
    roads_area = []
    for f in geom.of_class("road"):
        area = f.geometry.buffer(f.width_m / 2, cap_style="flat")
        if extent is not None:
            area = area.intersection(extent)
        roads_area.append((f, area))
    # Each road keeps only what no building and no earlier road took, so crossings are laid once;
    # spatial indexes keep this near-linear in the number of roads.
    road_polys = [a for _, a in roads_area]
    road_tree = shapely.STRtree(road_polys)
    foot_tree = shapely.STRtree(footprints)
    for i, (f, area) in enumerate(roads_area):
        earlier = [road_polys[j] for j in road_tree.query(area, predicate="intersects") if j < i]
        blocking = earlier + [footprints[j] for j in foot_tree.query(area, predicate="intersects")]
        own = area.difference(shapely.union_all(blocking)) if blocking else area
        for poly in _polygons(own):
            parts.append((_flat(poly), SemanticClass.ROAD, f.source_id, "road", f.radio_material))
    taken = shapely.union_all(footprints + road_polys) if (footprints or road_polys) else Polygon()
    for f in grounds:
        for poly in _polygons(f.geometry.difference(taken)):
            parts.append((_flat(poly), SemanticClass.GROUND, f.source_id, "ground", f.radio_material))
    if not parts:
        raise ValueError("the source geometry has no building, road or ground to mesh")
    visual = trimesh.util.concatenate([p[0] for p in parts])
    face_class = np.concatenate([np.full(len(p[0].faces), p[1], np.uint8) for p in parts])
    face_instance = np.concatenate([np.full(len(p[0].faces), p[2], np.int64) for p in parts])
    groups: dict[tuple[str, str], list[trimesh.Trimesh]] = {}
    for mesh, _, _, cls, mat in parts:
        groups.setdefault((cls, mat), []).append(mesh)
    radio = {}
    for key, meshes in sorted(groups.items()):
        merged = trimesh.util.concatenate(meshes)
        merged.merge_vertices()
        radio[key] = merged
    return SceneMeshes(visual, face_class, face_instance, radio)


def radio_scene_xml(radio: dict[tuple[str, str], trimesh.Trimesh], thickness_m: float) -> str:
    """Mitsuba 3 scene XML with one ``itu-radio-material`` per material (Sionna RT format)."""
    lines = ['<scene version="2.1.0">']
    for mat in sorted({m for _, m in radio}):
        lines += [f'  <bsdf type="itu-radio-material" id={quoteattr("itu_" + mat)}>',
                  f'    <string name="type" value={quoteattr(mat)}/>',
                  f'    <float name="thickness" value="{thickness_m:g}"/>',
                  '  </bsdf>']
    for cls, mat in sorted(radio):
        name = f"{cls}_{mat}"
        lines += [f'  <shape type="ply" id={quoteattr(name)}>',
                  f'    <string name="filename" value={quoteattr("meshes/" + name + ".ply")}/>',
                  '    <boolean name="face_normals" value="true"/>',
                  f'    <ref id={quoteattr("itu_" + mat)} name="bsdf"/>',
                  '  </shape>']
    lines.append("</scene>")
    return "\n".join(lines) + "\n"


def save(meshes: SceneMeshes, out: Path, scene_info: dict, thickness_m: float) -> None:
    """Write the paired meshes into directory ``out`` (see the module docstring for the layout)."""
    out = Path(out)
    (out / "radio" / "meshes").mkdir(parents=True)
    (out / "visual").mkdir()
    for (cls, mat), mesh in meshes.radio.items():
        mesh.export(out / "radio" / "meshes" / f"{cls}_{mat}.ply", encoding="binary")
    (out / "radio" / "scene.xml").write_text(radio_scene_xml(meshes.radio, thickness_m))
    meshes.visual.export(out / "visual" / "visual.ply", encoding="binary")
    labels = xr.Dataset({
        "semantic_class": ("face", meshes.face_class,
                           {"long_name": "semantic class of each visual face", **semantic_flag_attrs()}),
        "instance_id": ("face", meshes.face_instance,
                        {"long_name": "source feature id (OSM id) of each visual face"}),
    })
    stores.write_store(labels, out / "visual" / "face_labels.zarr")
    info = dict(scene_info, counts=meshes.counts())
    (out / "scene.json").write_text(json.dumps(info, indent=2, sort_keys=True) + "\n")


def load(path: Path) -> SceneMeshes:
    """Read a directory written by :func:`save`."""
    path = Path(path)
    visual = trimesh.load(path / "visual" / "visual.ply", process=False, force="mesh")
    labels = stores.open_store(path / "visual" / "face_labels.zarr").load()
    radio = {}
    for ply in sorted((path / "radio" / "meshes").glob("*.ply")):
        cls, mat = ply.stem.split("_", 1)
        radio[(cls, mat)] = trimesh.load(ply, process=False, force="mesh")
    return SceneMeshes(visual, labels["semantic_class"].values, labels["instance_id"].values, radio,
                       root=path)


@dataclass
class PairedMeshesOutput:
    """What the ``paired_meshes`` asset hands to the store writer: meshes plus scene facts."""

    meshes: SceneMeshes
    scene_info: dict
    thickness_m: float

    def save(self, out: Path) -> None:
        save(self.meshes, out, self.scene_info, self.thickness_m)


def radio_scene_file(path: Path) -> Path:
    return Path(path) / "radio" / "scene.xml"
