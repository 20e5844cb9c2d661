"""One scene build: a source file to paired meshes on disk (``simart scene build``, ``paired_meshes``).

``DIR/radio/scene.xml`` with ``DIR/radio/meshes/*.ply``, ``DIR/visual/visual.ply`` with
``DIR/visual/face_labels.zarr``, and ``DIR/scene.json``: the world origin, the source, the counts
(buildings, triangles per mesh, materials), the map attribution and every warning of the reader.
The directory is written aside and renamed into place (``stores.write_directory``): a failed build
leaves nothing, or the previous version, behind.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from simart_pipeline import stores
from simart_pipeline.config import Materials, SceneConfig, resolve_source_path
from simart_pipeline.scene import meshes
from simart_pipeline.scene.geometry import FEATURE_CLASSES, SourceGeometry

OSM_SUFFIXES = (".osm", ".osm.pbf", ".pbf", ".osm.gz", ".osm.bz2", ".osm.xml")
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".gltf", ".glb")
FRAME = "ENU world frame (x east, y north, z up; m) around the origin; the ground is z = 0"


class SceneBuildError(ValueError):
    """A scene that cannot be built; the message names the file or directory."""


def source_kind(source: Path) -> str:
    """``osm`` or ``mesh`` from the file name's suffix."""
    name = Path(source).name.lower()
    if name.endswith(OSM_SUFFIXES):
        return "osm"
    if name.endswith(MESH_SUFFIXES):
        return "mesh"
    raise SceneBuildError(f"{source}: unknown source type; expected an OSM extract "
                          f"({', '.join(OSM_SUFFIXES)}) or a mesh ({', '.join(MESH_SUFFIXES)})")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _origin_dict(origin) -> dict | None:
    if origin is None:
        return None
    return {"latitude_deg": float(origin[0]), "longitude_deg": float(origin[1]), "altitude_m": float(origin[2])}


def geometry_info(geom: SourceGeometry) -> dict:
    """What scene.json says about the source geometry: origin, attribution, feature counts, warnings."""
    info = {"origin": _origin_dict(geom.origin), "frame": FRAME,
            "source_features": {c: len(geom.of_class(c)) for c in FEATURE_CLASSES},
            "warnings": list(geom.warnings)}
    if geom.attribution:
        info["attribution"] = geom.attribution
    return info


def paired_meshes_for_scene(cfg: SceneConfig, scene_dir: Path | None, geom: SourceGeometry,
                            extra_info: dict | None = None) -> meshes.PairedMeshesOutput:
    """The ``paired_meshes`` of a configured scene: built from ``geom``, or from the user's mesh."""
    info = dict(extra_info or {})
    info.update(geometry_info(geom))
    if geom.origin is None:
        info["origin"] = _origin_dict((cfg.origin.latitude_deg, cfg.origin.longitude_deg, cfg.origin.altitude_m))
    if cfg.source.kind == "mesh":  # the user's mesh itself, labelled and simplified
        from simart_pipeline.scene.mesh_import import build_from_mesh

        m, report = build_from_mesh(resolve_source_path(Path(scene_dir), cfg), cfg.source.rules)
        info["mesh_import"] = report
    elif cfg.source.kind == "sionna_xml":  # the scene XML's shapes with their own radio materials
        from simart_pipeline.scene.sionna_xml import build_from_sionna_xml

        m, report = build_from_sionna_xml(resolve_source_path(Path(scene_dir), cfg), cfg.source, Path(scene_dir))
        info["sionna_xml"] = report
    else:
        osm = cfg.source.kind == "osm"
        m = meshes.build_meshes(geom, storey_height_m=cfg.source.storey_height_m if osm else 3.0,
                                facade_detail=cfg.source.facade_detail if osm else True)
    return meshes.PairedMeshesOutput(m, info, cfg.materials.thickness_m, cfg.ofdm.carrier_frequency_hz)


def check_out_dir(out: Path, force: bool, source: Path | None = None) -> None:
    """Refuse an existing non-empty ``out`` unless ``force`` (the build then replaces it whole), and
    always an ``out`` whose replacement would destroy more than a build: the working directory or one
    of its parents, a file system root, or a directory holding the source file."""
    out = Path(out)
    o = out.resolve()
    cwd = Path.cwd().resolve()
    if out.name in ("", ".", "..") or o == cwd or o in cwd.parents or o == Path(o.anchor):
        raise SceneBuildError(f"{out}: unsafe output directory (the working directory, one of its parents "
                              "or a root); give a directory of its own")
    if source is not None and o in Path(source).resolve().parents:
        raise SceneBuildError(f"{out}: holds the source file {source}; give an output directory outside it")
    if out.exists() and not out.is_dir():
        raise SceneBuildError(f"{out}: exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise SceneBuildError(f"{out}: directory exists and is not empty; pass --force to replace it")


def build_scene(source: str | Path, out: str | Path, *, origin: tuple[float, float, float] | None = None,
                bbox_deg: tuple[float, float, float, float] | None = None, force: bool = False,
                frequency_hz: float = 3.5e9, materials: Materials | None = None,
                storey_height_m: float = 3.0, default_building_height_m: float = 10.0,
                facade_detail: bool = True) -> dict:
    """Build paired meshes from an OSM extract or a mesh file into directory ``out``.

    :param origin: (latitude deg, longitude deg, altitude m) of the world frame; None: the
        extract's centre for OSM, none recorded for a mesh (its own coordinates are the frame)
    :param bbox_deg: (min_lon, min_lat, max_lon, max_lat), OSM only
    :param frequency_hz: carrier frequency at which non-ITU radio materials (water) are written
    :return: the content of ``out/scene.json``
    :raises SceneBuildError, OsmReadError, MeshImportError: with the file's name and the problem;
        nothing is written then
    """
    source, out = Path(source), Path(out)
    kind = source_kind(source)
    if not source.is_file():
        raise SceneBuildError(f"{source}: no such file")
    check_out_dir(out, force, source)
    materials = materials or Materials()
    info = {"source": {"kind": kind, "file": source.name, "sha256": _sha256(source)}}
    if kind == "osm":
        from simart_pipeline.scene.osm import read_extract

        geom = read_extract(source, origin, bbox_deg, materials=materials, storey_height_m=storey_height_m,
                            default_building_height_m=default_building_height_m)
        info.update(geometry_info(geom))
        info["bbox_deg"] = list(bbox_deg) if bbox_deg is not None else None
        m = meshes.build_meshes(geom, storey_height_m=storey_height_m, facade_detail=facade_detail)
    else:
        if bbox_deg is not None:
            raise SceneBuildError(f"{source}: --bbox applies to OSM extracts, not to meshes")
        from simart_pipeline.scene.mesh_import import build_from_mesh

        m, report = build_from_mesh(source)
        info.update(origin=_origin_dict(origin), frame=FRAME, mesh_import=report)
    info["generator"] = "simart scene build"
    out_info = dict(info)
    stores.write_directory(out, lambda d: meshes.save(m, d, out_info, materials.thickness_m, frequency_hz))
    return json.loads((out / "scene.json").read_text())
