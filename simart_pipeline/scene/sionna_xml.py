"""A Mitsuba/Sionna RT scene XML (Sionna's bundled scenes, Blender exports) as a scene source.

The file is checked with a plain XML parser first (well-formed, every mesh file it names relative
and inside the scene directory and present, every BSDF a shape uses a radio material of a known
kind), then loaded by Mitsuba exactly as ``sionna.rt.load_scene`` loads it (Sionna's own
``process_xml`` turns ``itu_*`` / ``mat-itu_*`` named BSDFs into ITU radio materials; ``<default>``
parameters, transforms, ``ply`` / ``obj`` / ``serialized`` shapes are Mitsuba's business). Every
shape becomes a part of :mod:`simart_pipeline.scene.mesh_import` (name: the shape's id; material:
its BSDF's id; tag: its ITU type or ``radio-material``), labelled by the source's
``semantic_classes``, so that

- the **visual mesh** is every shape at full detail (instance id: the shape's 1-based position in
  the file);
- the **radio mesh** is the same shapes (no decimation by default), grouped by (semantic class,
  radio material), each material written into ``radio/scene.xml`` as the file's own ``<bsdf>``
  element (ITU type, thickness, permittivity, conductivity, scattering coefficient, XPD, scattering
  pattern: all that Sionna reads), renamed ``mat_xml-<its id>``;
- the **source geometry** has one building footprint per connected solid of the obstacle classes.

``docs/sionna-scenes.md`` says how to use it and what is carried over.
"""

from __future__ import annotations

import copy
import re
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from simart_pipeline.config import MeshImportRules, MeshPartRule, SionnaXmlSource
from simart_pipeline.scene import simplify
from simart_pipeline.scene.geometry import SourceGeometry
from simart_pipeline.scene.mesh_import import (_Y_UP_TO_Z_UP, ImportedMesh, MeshPart, build_from_imported,
                                               joined_parts, source_geometry_from_imported)
from simart_pipeline.scene.meshes import SceneMeshes

RADIO_BSDF_TYPES = ("itu-radio-material", "radio-material")
MATERIAL_PREFIX = "xml-"  # the project's name of a scene XML's material: xml-<BSDF id>


class SionnaXmlError(ValueError):
    """A scene XML that cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class XmlMaterial:
    """One radio material of a scene XML, as the radio scene will hold it."""

    name: str              # the project's name: xml-<BSDF id>
    bsdf_id: str           # its id in the file
    kind: str              # itu-radio-material or radio-material
    itu_type: str | None   # ITU-R P.2040 type, for itu-radio-material
    element: str           # the <bsdf> element written into radio/scene.xml (id mat_<name>)


def _fail(xml: Path, problem: str) -> SionnaXmlError:
    return SionnaXmlError(f"{xml}: {problem}")


def _substitute_defaults(root: ET.Element) -> None:
    """Replace ``$name`` in attribute values by the file's ``<default name value>`` (Mitsuba's rule)."""
    defaults = {d.get("name"): d.get("value", "") for d in root.iter("default") if d.get("name")}
    if not defaults:
        return
    rx = re.compile(r"\$(" + "|".join(re.escape(k) for k in sorted(defaults, key=len, reverse=True)) + r")")
    for el in root.iter():
        if el.tag == "default":
            continue
        for k, v in el.attrib.items():
            if "$" in v:
                el.attrib[k] = rx.sub(lambda m: defaults[m.group(1)], v)


def _unwrap_twosided(root: ET.Element) -> None:
    """A ``twosided`` BSDF around a radio material is that radio material (under the outer id):
    Sionna RT's radio materials act on both sides of a surface anyway."""
    for parent in [root, *root.iter("shape")]:
        for i, el in enumerate(list(parent)):
            if el.tag != "bsdf" or el.get("type") != "twosided":
                continue
            inner = el.find("bsdf")
            if inner is not None and inner.get("type") in RADIO_BSDF_TYPES:
                inner = copy.deepcopy(inner)
                if el.get("id"):
                    inner.set("id", el.get("id"))
                inner.tail = el.tail
                parent.remove(el)
                parent.insert(i, inner)


def _parse(xml: Path) -> ET.Element:
    if not xml.is_file():
        raise _fail(xml, "file not found")
    try:
        root = ET.fromstring(xml.read_bytes())
    except ET.ParseError as exc:
        raise _fail(xml, f"malformed XML: {exc}") from None
    if root.tag != "scene":
        raise _fail(xml, f"not a Mitsuba scene: the root element is <{root.tag}>, expected <scene>")
    _substitute_defaults(root)
    _unwrap_twosided(root)
    return root


def _shape_name(shape: ET.Element, i: int) -> str:
    return shape.get("id") or shape.get("name") or f"#{i + 1} ({shape.get('type')})"


def _mesh_files(xml: Path, root: ET.Element, scene_dir: Path) -> list[tuple[str, str, Path]]:
    """(shape, file as written, resolved path) of every file the XML names; refuse unsafe ones."""
    for tag in ("include", "path"):
        if root.find(f".//{tag}") is not None:
            raise _fail(xml, f"<{tag}> elements are not supported; name mesh files relative to the XML")
    top = scene_dir.resolve()
    out = []
    for i, shape in enumerate(root.iter("shape")):
        for s in shape.findall("string[@name='filename']"):
            rel = s.get("value", "")
            p = Path(rel)
            f = (xml.parent / p).resolve()
            if p.is_absolute() or not f.is_relative_to(top):
                raise _fail(xml, f"shape {_shape_name(shape, i)!r}: mesh file {rel!r} lies outside the scene "
                                 f"directory {scene_dir} (give a relative path inside it)")
            if not f.is_file():
                raise _fail(xml, f"shape {_shape_name(shape, i)!r}: mesh file not found: {f}")
            out.append((_shape_name(shape, i), rel, f))
    return out


def referenced_files(scene_dir: Path, xml_rel: str) -> list[str]:
    """The mesh files a scene XML names, relative to ``scene_dir`` (for staleness hashes); [] when
    the XML cannot be read (the reader reports why)."""
    xml = Path(scene_dir) / xml_rel
    try:
        files = _mesh_files(xml, _parse(xml), Path(scene_dir))
    except (SionnaXmlError, OSError):
        return []
    top = Path(scene_dir).resolve()
    return sorted({str(f.relative_to(top)) for _, _, f in files})


def _radio_bsdfs(root: ET.Element) -> dict[str, ET.Element]:
    """The outermost BSDFs (children of the scene or of a shape) by id."""
    out = {}
    for el in list(root.findall("bsdf")) + list(root.findall(".//shape/bsdf")):
        if el.get("id"):
            out[el.get("id")] = el
    return out


def _check_itu_types(xml: Path, root: ET.Element) -> None:
    from sionna.rt.radio_materials.itu import ITU_MATERIALS_PROPERTIES

    for bid, el in _radio_bsdfs(root).items():
        if el.get("type") != "itu-radio-material":
            continue
        t = el.find("string[@name='type']")
        itu = t.get("value") if t is not None else None
        if itu not in ITU_MATERIALS_PROPERTIES:
            raise _fail(xml, f"material {bid!r}: unknown ITU material type {itu!r}; known: "
                             f"{', '.join(sorted(ITU_MATERIALS_PROPERTIES))}")


def _material_names(ids: list[str]) -> dict[str, str]:
    """BSDF id -> the project's material name (safe in file names and XML ids, unique)."""
    out, used = {}, set()
    for bid in ids:
        base = MATERIAL_PREFIX + (re.sub(r"[^A-Za-z0-9_.-]", "-", bid) or "material")
        name, k = base, 2
        while name in used:
            name, k = f"{base}-{k}", k + 1
        used.add(name)
        out[bid] = name
    return out


def _load_mitsuba(xml: Path, processed: str):
    """Mitsuba's scene of Sionna's processed XML, with the XML's folder first on the file resolver."""
    import mitsuba as mi

    old = mi.file_resolver()
    fres = mi.FileResolver(old)
    fres.prepend(str(xml.parent.resolve()))
    mi.set_file_resolver(fres)
    try:
        return mi.load_string(processed, optimize=False)
    except Exception as exc:  # Mitsuba raises RuntimeError with its parser's message
        msg = str(exc).strip().splitlines()
        raise _fail(xml, f"Mitsuba cannot load the scene: {msg[-1] if msg else type(exc).__name__}") from None
    finally:
        mi.set_file_resolver(old)


def _mesh_rules(src: SionnaXmlSource) -> MeshImportRules:
    """The mesh-import rules that stand for ``src``: labels by its classes, nothing removed."""
    return MeshImportRules(
        parts=tuple(MeshPartRule(match=p, semantic_class=c) for p, c in src.semantic_classes.items()),
        default_semantic_class=src.default_semantic_class, min_part_extent_m=0.0,
        merge_tolerance_m=src.merge_tolerance_m, decimation=src.decimation,
        obstacle_classes=src.obstacle_classes, wall_sheet_thickness_m=src.wall_sheet_thickness_m,
        hausdorff_samples=src.hausdorff_samples)


def read_sionna_xml(xml: Path, src: SionnaXmlSource, scene_dir: Path) -> tuple[ImportedMesh, dict[str, XmlMaterial]]:
    """Every shape of a scene XML as a labelled part in world ENU metres, and its radio materials.

    :param xml: the scene file; mesh files are resolved relative to its folder
    :param scene_dir: the scene directory, which every mesh file must lie in
    :return: (parts with merged vertices and faces in file order, {material name: XmlMaterial})
    :raises SionnaXmlError: malformed XML, unsafe or missing mesh file, a BSDF that is not a radio
        material, an unknown ITU type, a shape that is not a triangle mesh, no triangle at all
    """
    from simart_pipeline import engine

    xml, scene_dir = Path(xml), Path(scene_dir)
    root = _parse(xml)
    _mesh_files(xml, root, scene_dir)
    engine.init()
    import mitsuba as mi
    from sionna.rt.radio_materials.radio_material_base import RadioMaterialBase
    from sionna.rt.scene_utils import process_xml

    _check_itu_types(xml, root)
    original = _radio_bsdfs(root)
    try:
        processed = process_xml(ET.tostring(root, encoding="unicode"), merge_shapes=False)
    except ValueError as exc:  # a BSDF without an id, an ITU name without the itu_ prefix
        raise _fail(xml, str(exc).replace("\n", " ")) from None
    proc_root = ET.fromstring(processed)
    _check_itu_types(xml, proc_root)  # types that come from itu_<type> names
    bsdfs = _radio_bsdfs(proc_root)
    scene = _load_mitsuba(xml, processed)
    rules = _mesh_rules(src)
    to_world = np.diag([src.scale_m_per_unit] * 3 + [1.0]) @ (_Y_UP_TO_Z_UP if src.up_axis == "y" else np.eye(4))
    shapes = list(scene.shapes())
    used = []
    for sh in shapes:
        if not isinstance(sh, mi.Mesh):
            raise _fail(xml, f"shape {sh.id()!r} is a {type(sh).__name__}, not a triangle mesh (Sionna RT "
                             "needs meshes: ply, obj or serialized)")
        b = sh.bsdf()
        if not isinstance(b, RadioMaterialBase):
            el = original.get(b.id())
            kind = el.get("type") if el is not None else type(b).__name__
            raise _fail(xml, f"shape {sh.id()!r}: material {b.id()!r} is a {kind!r} BSDF, not a radio "
                             "material; use <bsdf type=\"itu-radio-material\">, <bsdf type=\"radio-material\"> "
                             "or an id starting itu_ / mat-itu_")
        if b.id() not in used:
            used.append(b.id())
    names = _material_names(used)
    mats = {}
    for bid, name in names.items():
        if bid not in bsdfs:
            raise _fail(xml, f"material {bid!r}: no <bsdf> element of the scene or of a shape has this id")
        el = copy.deepcopy(bsdfs[bid])
        el.set("id", f"mat_{name}")
        for e in el.iter():  # one line: no indentation text
            e.text = e.tail = None
        itu = el.find("string[@name='type']") if el.get("type") == "itu-radio-material" else None
        mats[name] = XmlMaterial(name, bid, el.get("type"), itu.get("value") if itu is not None else None,
                                 ET.tostring(el, encoding="unicode"))
    parts = []
    for i, sh in enumerate(shapes):
        b = sh.bsdf()
        mat = mats[names[b.id()]]
        v = np.array(sh.vertex_positions_buffer(), np.float64).reshape(-1, 3)
        f = np.array(sh.faces_buffer(), np.int64).reshape(-1, 3)
        mesh = trimesh.Trimesh(trimesh.transform_points(v, to_world), f, process=False)
        parts.append(MeshPart(name=sh.id(), path=sh.id(), mesh_name="", material_name=b.id(),
                              tags=(mat.itu_type or mat.kind,), extras={}, mesh=mesh, part_id=i + 1))
    parts = [p for p in parts if len(p.mesh.faces)]
    if not parts:
        raise _fail(xml, "the scene holds no triangle")
    vertices, faces, face_part = joined_parts(parts, rules, xml, _fail)
    for p in parts:
        p.radio_material = names[p.material_name]
    # Degenerate and non-manifold faces are kept, as Sionna keeps them: the report counts them.
    return ImportedMesh(xml, rules, parts, vertices, faces, face_part), mats


def build_from_sionna_xml(xml: Path, src: SionnaXmlSource, scene_dir: Path) -> tuple[SceneMeshes, dict]:
    """Paired visual and radio meshes of a scene XML, with its own radio materials, and a report.

    :return: (meshes, report): the report of :func:`mesh_import.build_from_imported` with
        ``shapes``, ``degenerate_faces``, ``non_manifold_edges`` and ``materials`` (per material
        name: BSDF id, kind, ITU type, shapes)
    """
    t0 = time.perf_counter()
    imp, mats = read_sionna_xml(xml, src, scene_dir)
    m, report = build_from_imported(imp, t0)
    m.material_xml = {name: mat.element for name, mat in mats.items()}
    _, count = simplify.edge_use_counts(imp.faces)
    per_mat: dict[str, int] = {}
    for p in imp.parts:
        per_mat[p.radio_material] = per_mat.get(p.radio_material, 0) + 1
    report.update(
        shapes=len(imp.parts),
        degenerate_faces=int(simplify.degenerate_faces(imp.vertices, imp.faces).sum()),
        non_manifold_edges=int((count > 2).sum()),
        materials={name: {"bsdf_id": mat.bsdf_id, "kind": mat.kind, "itu_type": mat.itu_type,
                          "shapes": per_mat.get(name, 0)} for name, mat in mats.items()})
    return m, report


def source_geometry_from_sionna_xml(xml: Path, src: SionnaXmlSource, scene_dir: Path,
                                    origin: tuple[float, float, float] | None = None) -> SourceGeometry:
    """Building footprints, area features and a ground polygon of a scene XML, for ``osm_extract``
    (:func:`mesh_import.source_geometry_from_imported`, components joined across shapes: a building
    exported as a wall shape and a roof shape is one solid).

    :param origin: WGS84 latitude, longitude (deg) and altitude (m) of the ENU origin (the XML
        carries none: the scene config's ``origin``)
    """
    imp, _ = read_sionna_xml(xml, src, scene_dir)
    return source_geometry_from_imported(imp, origin, join_parts=True)
