"""Paired meshes: a visual mesh for the sensor renderer and a radio mesh for Sionna RT, one frame.

- **Visual mesh**: one triangle mesh (``visual/visual.ply``) whose faces carry a semantic class and
  an instance id (the OSM id; a building part carries its outline's) in ``visual/face_labels.zarr``.
  Buildings have their roofs and window frames (:mod:`simart_pipeline.scene.extrude`).
- **Radio mesh**: the same buildings without facade detail, and the same ground surfaces, one PLY
  per (semantic class, radio material) under ``radio/meshes/`` and a Mitsuba XML scene
  ``radio/scene.xml`` whose BSDFs come from :func:`simart_pipeline.radio.materials.bsdf_xml`,
  loadable by plain ``sionna.rt.load_scene``. Each building is a closed solid of its own (its
  vertices are not shared with a neighbour's), so every connected part is watertight.

Ground surfaces tile the plane z = 0 without overlap, in this order of precedence: building
footprints, roads (centre lines buffered by half their width, and road areas), parking, water,
vegetation, and the ground (the scene's extent minus everything else).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np
import shapely
import trimesh
import xarray as xr
from shapely.geometry import LineString, Polygon

from simart_pipeline import stores
from simart_pipeline.scene import extrude
from simart_pipeline.scene.geometry import SourceGeometry, polygons_of
from simart_pipeline.vocabulary import SemanticClass, semantic_flag_attrs


# Source feature class -> (semantic class, radio mesh class name)
CLASS_OF_FEATURE = {"building": SemanticClass.BUILDING, "building_part": SemanticClass.BUILDING,
                    "road": SemanticClass.ROAD, "parking": SemanticClass.ROAD,
                    "water": SemanticClass.WATER, "vegetation": SemanticClass.VEGETATION,
                    "ground": SemanticClass.GROUND}
# Flat layers in order of precedence: an earlier one takes the ground from a later one.
FLAT_LAYERS = ("road", "parking", "water", "vegetation")
ON_GROUND_M = 0.05  # a volume whose bottom is this close to z = 0 stands on the ground


@dataclass
class SceneMeshes:
    visual: trimesh.Trimesh
    face_class: np.ndarray      # [num_faces] uint8, SemanticClass
    face_instance: np.ndarray   # [num_faces] int64, source feature id
    radio: dict[tuple[str, str], trimesh.Trimesh]  # (class name, radio material) -> mesh
    root: Path | None = None  # the directory it was loaded from, if any
    info: dict = field(default_factory=dict)  # scene.json, when loaded
    # Radio materials the project does not define (a scene XML's own): name -> its <bsdf> element,
    # whose id is ``mat_<name>``; written into radio/scene.xml as they are.
    material_xml: dict[str, str] = field(default_factory=dict)

    @property
    def radio_materials(self) -> list[str]:
        return sorted({m for _, m in self.radio})

    def counts(self) -> dict:
        return {"visual_triangles": int(len(self.visual.faces)),
                "radio_triangles": int(sum(len(m.faces) for m in self.radio.values())),
                "radio_triangles_per_mesh": {f"{c}_{m}": int(len(mesh.faces))
                                             for (c, m), mesh in sorted(self.radio.items())},
                "radio_meshes": len(self.radio), "radio_materials": self.radio_materials,
                "buildings": int(len(np.unique(self.face_instance[self.face_class == SemanticClass.BUILDING])))}


class _Chunks:
    """Triangle soup gathered piecewise, joined once at the end (numpy, no per-piece Trimesh)."""

    def __init__(self):
        self.v, self.f, self.cls, self.inst = [], [], [], []
        self.n = 0

    def add(self, vertices, faces, cls, inst):
        if len(faces) == 0:
            return
        self.v.append(np.asarray(vertices, np.float64))
        self.f.append(np.asarray(faces, np.int64) + self.n)
        self.cls.append(np.broadcast_to(np.asarray(cls, np.uint8), (len(faces),)))
        self.inst.append(np.broadcast_to(np.asarray(inst, np.int64), (len(faces),)))
        self.n += len(vertices)

    def mesh(self) -> trimesh.Trimesh:
        if not self.f:
            return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
        return trimesh.Trimesh(np.concatenate(self.v), np.concatenate(self.f), process=False)

    def labels(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.f:
            return np.zeros(0, np.uint8), np.zeros(0, np.int64)
        return np.concatenate(self.cls), np.concatenate(self.inst)


def _flat(poly: Polygon) -> tuple[np.ndarray, np.ndarray]:
    v2, tri = extrude.triangulate(poly)
    return np.column_stack([v2, np.zeros(len(v2))]), tri


def _radio_class(feature_class: str) -> str:
    return {"building_part": "building", "parking": "road"}.get(feature_class, feature_class)


def flat_surfaces(geom: SourceGeometry, footprints: list[Polygon]) -> list[tuple[object, Polygon]]:
    """(feature, polygon) of every ground surface, tiling the plane without overlap.

    Each surface keeps what no building on the ground and no earlier surface (see
    :data:`FLAT_LAYERS`) took; spatial indexes keep this near-linear in the number of features.
    """
    grounds = geom.of_class("ground")
    extent = shapely.union_all([g.geometry for g in grounds]) if grounds else None
    items = []
    for cls in FLAT_LAYERS:
        for f in geom.of_class(cls):
            if isinstance(f.geometry, LineString):
                area = f.geometry.buffer(f.width_m / 2, cap_style="round", quad_segs=4)
            else:
                area = f.geometry
            if extent is not None:
                area = area.intersection(extent)
            if not area.is_empty:
                items.append((f, area))
    areas = [a for _, a in items]
    out = []
    tree = shapely.STRtree(areas) if areas else None
    foot_tree = shapely.STRtree(footprints) if footprints else None
    for i, (f, area) in enumerate(items):
        earlier = [areas[j] for j in tree.query(area, predicate="intersects") if j < i]
        if foot_tree is not None:
            earlier += [footprints[j] for j in foot_tree.query(area, predicate="intersects")]
        own = area.difference(shapely.union_all(earlier)) if earlier else area
        out += [(f, p) for p in polygons_of(own)]
    taken = shapely.union_all(footprints + areas) if (footprints or areas) else Polygon()
    for g in grounds:
        out += [(g, p) for p in polygons_of(g.geometry.difference(taken))]
    return out


def build_meshes(geom: SourceGeometry, *, storey_height_m: float = 3.0,
                 facade_detail: bool = True) -> SceneMeshes:
    """Extrude buildings under their roofs, lay the ground surfaces, label every visual face.

    :param storey_height_m: storey height for window rows where ``building:levels`` is untagged
    :param facade_detail: window frames on the visual mesh
    """
    visual = _Chunks()
    radio: dict[tuple[str, str], _Chunks] = {}
    walls, storeys, wall_inst = [], [], []
    footprints, bands, on_ground = [], [], []
    for f in geom.volumes():
        bottom = 0.0 if np.isnan(f.min_height_m) else float(f.min_height_m)
        for poly in polygons_of(f.geometry):
            solid = extrude.building_solid(poly, bottom, float(f.height_m), f.roof_shape or "flat",
                                           f.roof_height_m, f.roof_across)
            visual.add(solid.vertices, solid.faces, SemanticClass.BUILDING, f.instance_id)
            radio.setdefault(("building", f.radio_material), _Chunks()).add(
                solid.vertices, solid.faces, SemanticClass.BUILDING, f.instance_id)
            walls.append(solid.walls)
            eave = solid.walls[:, 5].min() if len(solid.walls) else bottom
            levels = f.levels if f.levels == f.levels and f.levels >= 1 else None
            storey = (eave - bottom) / levels if levels else storey_height_m
            storeys.append(np.full(len(solid.walls), max(storey, 1.0)))
            wall_inst.append(np.full(len(solid.walls), f.instance_id, np.int64))
            footprints.append(poly)
            bands.append((bottom, float(f.height_m)))
            on_ground.append(bottom <= ON_GROUND_M)
    if facade_detail and walls:
        v, fc, inst = extrude.window_frames(np.concatenate(walls), np.concatenate(storeys),
                                            np.concatenate(wall_inst), footprints, np.asarray(bands))
        if len(fc):
            visual.add(v, fc, SemanticClass.BUILDING, inst)
    grounded = [p for p, g in zip(footprints, on_ground) if g]
    for f, poly in flat_surfaces(geom, grounded):
        v, tri = _flat(poly)
        cls = CLASS_OF_FEATURE[f.feature_class]
        visual.add(v, tri, cls, f.source_id)
        radio.setdefault((_radio_class(f.feature_class), f.radio_material), _Chunks()).add(v, tri, cls, f.source_id)
    if not visual.f:
        raise ValueError("the source geometry has no building, road or ground to mesh")
    face_class, face_instance = visual.labels()
    return SceneMeshes(visual.mesh(), face_class, face_instance,
                       {key: c.mesh() for key, c in sorted(radio.items()) if c.f})


def radio_scene_xml(radio: dict[tuple[str, str], trimesh.Trimesh], thickness_m: float,
                    frequency_hz: float | None = None, origin: tuple | None = None,
                    material_xml: dict[str, str] | None = None) -> str:
    """Mitsuba 3 scene XML: one radio-material BSDF per material (:func:`radio.materials.bsdf_xml`),
    one PLY shape per (class, material); the world origin as a comment.

    :param frequency_hz: the carrier frequency, needed by materials that are not ITU ones (water,
        wet facades), whose permittivity and conductivity are written for it
    :param material_xml: {material: its ``<bsdf id="mat_<material>">`` element}, written as it is,
        for materials the project does not define (a scene XML's own, ``scene/sionna_xml.py``)
    """
    from simart_pipeline.radio import materials

    material_xml = material_xml or {}
    mats = sorted({m for _, m in radio})
    custom = [m for m in mats if m not in materials.ITU_MATERIALS and m not in material_xml]
    if custom and frequency_hz is None:
        raise ValueError(f"radio materials {', '.join(custom)} need the carrier frequency")
    lines = ['<scene version="2.1.0">']
    if origin is not None:
        lat, lon, alt = origin
        lines.append(f"  <!-- world frame: ENU (x east, y north, z up; m) around WGS84 latitude {lat!r} deg, "
                     f"longitude {lon!r} deg, altitude {alt!r} m -->")
    if frequency_hz is not None:
        lines.append(f"  <!-- radio materials at {frequency_hz!r} Hz -->")
    for mat in mats:
        if mat in material_xml:
            lines.append("  " + material_xml[mat])
        else:
            lines.append("  " + materials.bsdf_xml(mat, frequency_hz or 0.0, thickness_m))
    for cls, mat in sorted(radio):
        name = f"{cls}_{mat}"
        ref = f"mat_{mat}" if mat in material_xml else materials.bsdf_id(mat)
        lines += [f'  <shape type="ply" id="{escape(name)}">',
                  f'    <string name="filename" value="meshes/{escape(name)}.ply"/>',
                  '    <boolean name="face_normals" value="true"/>',
                  f'    <ref id="{escape(ref)}" name="bsdf"/>',
                  '  </shape>']
    lines.append("</scene>")
    return "\n".join(lines) + "\n"


def save(meshes: SceneMeshes, out: Path, scene_info: dict, thickness_m: float,
         frequency_hz: float | None = None) -> None:
    """Write the paired meshes into directory ``out`` (see the module docstring for the layout).

    :param frequency_hz: carrier frequency for the radio materials; default
        ``scene_info["carrier_frequency_hz"]`` when present
    :param scene_info: written to ``scene.json`` with the mesh counts; its ``origin``
        (``latitude_deg``, ``longitude_deg``, ``altitude_m``) is also recorded in the XML
    """
    out = Path(out)
    if frequency_hz is None:
        frequency_hz = scene_info.get("carrier_frequency_hz")
    origin = scene_info.get("origin")
    origin_t = (origin["latitude_deg"], origin["longitude_deg"], origin["altitude_m"]) if origin else None
    xml = radio_scene_xml(meshes.radio, thickness_m, frequency_hz, origin_t, meshes.material_xml)
    (out / "radio" / "meshes").mkdir(parents=True)
    (out / "visual").mkdir()
    for (cls, mat), mesh in meshes.radio.items():
        mesh.export(out / "radio" / "meshes" / f"{cls}_{mat}.ply", encoding="binary")
    (out / "radio" / "scene.xml").write_text(xml)
    meshes.visual.export(out / "visual" / "visual.ply", encoding="binary")
    labels = xr.Dataset({
        "semantic_class": ("face", meshes.face_class,
                           {"long_name": "semantic class of each visual face", **semantic_flag_attrs()}),
        "instance_id": ("face", meshes.face_instance,
                        {"long_name": "source feature id (OSM id) of each visual face"}),
    })
    stores.write_store(labels, out / "visual" / "face_labels.zarr")
    info = dict(scene_info, counts=meshes.counts(), radio_thickness_m=thickness_m)
    if frequency_hz is not None:
        info["carrier_frequency_hz"] = frequency_hz
    (out / "scene.json").write_text(json.dumps(info, indent=2, sort_keys=True, ensure_ascii=False) + "\n")


def load(path: Path) -> SceneMeshes:
    """Read a directory written by :func:`save`."""
    path = Path(path)
    visual = trimesh.load(path / "visual" / "visual.ply", process=False, force="mesh")
    labels = stores.open_store(path / "visual" / "face_labels.zarr").load()
    radio = {}
    for ply in sorted((path / "radio" / "meshes").glob("*.ply")):
        cls, mat = ply.stem.split("_", 1)
        radio[(cls, mat)] = trimesh.load(ply, process=False, force="mesh")
    info = json.loads((path / "scene.json").read_text()) if (path / "scene.json").is_file() else {}
    return SceneMeshes(visual, labels["semantic_class"].values, labels["instance_id"].values, radio,
                       root=path, info=info)


@dataclass
class PairedMeshesOutput:
    """What the ``paired_meshes`` asset hands to the store writer: meshes plus scene facts."""

    meshes: SceneMeshes
    scene_info: dict
    thickness_m: float
    frequency_hz: float | None = None

    def save(self, out: Path) -> None:
        save(self.meshes, out, self.scene_info, self.thickness_m, self.frequency_hz)


def radio_scene_file(path: Path) -> Path:
    return Path(path) / "radio" / "scene.xml"
