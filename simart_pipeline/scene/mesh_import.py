"""User-defined meshes (OBJ, PLY, STL, glTF/GLB) to paired visual and radio meshes.

A file is read with its scene graph (trimesh): every node that holds triangles becomes a *part*
with its node name, node path (``Room/Desk``), mesh name, visual material name and tags (glTF
``extras``: ``tags`` / ``tag``, and explicit ``semantic_class`` / ``radio_material`` keys). Parts
are labelled by the rules of :class:`~simart_pipeline.config.MeshImportRules`, then

- the **visual mesh** is every part at full detail, each face carrying its part's semantic class
  and its part id (the instance id, 1-based, parts ordered by path and mesh name);
- the **radio mesh** drops the parts removed by a rule, merges vertices, drops connected parts
  smaller than ``min_part_extent_m``, decimates (``simplify.decimate``), and groups the rest by
  (semantic class, radio material), as the OSM path does.

:func:`build_from_mesh` returns both with a report (triangle counts, reduction, Hausdorff deviation,
what was removed and why); :func:`source_geometry_from_mesh` derives building footprints and a
ground polygon for the ``osm_extract`` asset (``docs/user-meshes.md`` says how).
"""

from __future__ import annotations

import fnmatch
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
import trimesh

from simart_pipeline.config import MeshImportRules, check_mesh_labels
from simart_pipeline.scene import simplify, solids
from simart_pipeline.scene.geometry import Feature, SourceGeometry
from simart_pipeline.scene.meshes import SceneMeshes
from simart_pipeline.vocabulary import SemanticClass

SUPPORTED_SUFFIXES = (".obj", ".ply", ".stl", ".gltf", ".glb")
_Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])  # (x, y, z) -> (x, -z, y)
_LABEL_KEYS = ("semantic_class", "radio_material")
GROUND_PLANE_TOLERANCE_M = 0.05  # a ground within this of z = 0 everywhere is the plane z = 0


class MeshImportError(ValueError):
    """A user mesh that cannot be imported; the message names the file and the problem."""


@dataclass
class MeshPart:
    """One node of the file's scene graph that holds triangles, in the ENU world frame (m)."""

    name: str
    path: str
    mesh_name: str
    material_name: str
    tags: tuple[str, ...]
    extras: dict
    mesh: trimesh.Trimesh
    part_id: int = 0
    semantic_class: str = ""
    radio_material: str = ""
    drop_rule: str | None = None
    keep: bool = False

    def candidates(self) -> list[str]:
        return [s for s in (self.name, self.path, self.mesh_name, self.material_name, *self.tags) if s]


@dataclass
class ImportedMesh:
    """Labelled parts and their triangles with vertices merged across the whole file."""

    source: Path
    rules: MeshImportRules
    parts: list[MeshPart]
    vertices: np.ndarray        # [v, 3] float64, m, merged
    faces: np.ndarray           # [f, 3] int64 into ``vertices``; the visual faces, in order
    face_part: np.ndarray       # [f] int64 index into ``parts``
    dropped_degenerate: int = 0
    skipped: list[str] = field(default_factory=list)

    def face_attr(self, attr: str) -> np.ndarray:
        return np.asarray([getattr(p, attr) for p in self.parts])[self.face_part]


def _fail(source: Path, problem: str) -> MeshImportError:
    return MeshImportError(f"{source}: {problem}")


def _load_scene(source: Path) -> trimesh.Scene:
    suffix = source.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise _fail(source, f"unsupported mesh format {source.suffix!r}; supported: "
                            f"{', '.join(SUPPORTED_SUFFIXES)}")
    if not source.is_file():
        raise _fail(source, "file not found")
    kwargs = {"process": False}
    if suffix == ".obj":  # one part per object / group, not one per material
        kwargs.update(split_objects=True, split_groups=True, group_material=False)
    try:
        return trimesh.load_scene(source, **kwargs)
    except Exception as exc:  # trimesh raises many kinds for broken files
        raise _fail(source, f"cannot read the {suffix} file: {type(exc).__name__}: {exc}") from None


def _tags(meta: dict | None) -> list[str]:
    if not isinstance(meta, dict):
        return []
    out = []
    for key in ("tags", "tag"):
        v = meta.get(key)
        if isinstance(v, str):
            out += [t.strip() for t in v.split(",") if t.strip()]
        elif isinstance(v, (list, tuple)):
            out += [str(t) for t in v]
    return out


def read_parts(source: Path, rules: MeshImportRules) -> tuple[list[MeshPart], list[str]]:
    """Every triangle-holding node of ``source`` as a :class:`MeshPart` in world ENU metres.

    :return: (parts sorted by path and mesh name, names of skipped non-triangle geometry)
    """
    source = Path(source)
    scene = _load_scene(source)
    graph = scene.graph
    parents = graph.transforms.parents
    up = rules.up_axis if rules.up_axis != "auto" else ("y" if source.suffix.lower() in (".gltf", ".glb") else "z")
    to_world = np.diag([rules.scale_m_per_unit] * 3 + [1.0]) @ (_Y_UP_TO_Z_UP if up == "y" else np.eye(4))
    parts, skipped = [], []
    for node in graph.nodes_geometry:
        matrix, geom_name = graph[node]
        geom = scene.geometry[geom_name]
        if not isinstance(geom, trimesh.Trimesh):
            skipped.append(f"{node} ({type(geom).__name__})")
            continue
        # glTF primitives become child nodes with random names: name them after their node.
        chain, n = [], node
        if geom.metadata.get("from_gltf_primitive") and n in parents:
            n = parents[n]
        extras: dict = {}
        tags: list[str] = []
        while n is not None and n != graph.base_frame:
            chain.append(n)
            meta = graph.transforms.edge_data.get((parents.get(n), n), {}).get("metadata")
            tags += _tags(meta)
            for key in _LABEL_KEYS:  # the nearest node that says it wins
                if isinstance(meta, dict) and key in meta and key not in extras:
                    extras[key] = meta[key]
            n = parents.get(n)
        tags += _tags(geom.metadata)
        for key in _LABEL_KEYS:
            if key in geom.metadata and key not in extras:
                extras[key] = geom.metadata[key]
        material = getattr(getattr(geom.visual, "material", None), "name", None) or ""
        transform = to_world @ matrix
        vertices = trimesh.transform_points(np.asarray(geom.vertices, np.float64), transform)
        faces = np.asarray(geom.faces, np.int64)
        if np.linalg.det(transform[:3, :3]) < 0:  # a mirroring node: keep the faces facing out
            faces = faces[:, ::-1]
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        parts.append(MeshPart(name=chain[0] if chain else str(node), path="/".join(reversed(chain)),
                              mesh_name=str(geom_name), material_name=str(material),
                              tags=tuple(dict.fromkeys(tags)), extras=extras, mesh=mesh))
    parts.sort(key=lambda p: (p.path, p.mesh_name))
    for i, p in enumerate(parts):
        p.part_id = i + 1
    return parts, skipped


def _matches(pattern: str, candidates: list[str]) -> bool:
    if pattern.startswith("re:"):
        rx = re.compile(pattern[3:], re.IGNORECASE)
        return any(rx.fullmatch(c) for c in candidates)
    pat = pattern.lower()
    return any(fnmatch.fnmatchcase(c.lower(), pat) for c in candidates)


def label_parts(parts: list[MeshPart], rules: MeshImportRules, source: Path) -> None:
    """Set each part's semantic class, radio material, drop rule and keep flag.

    For each field: the first rule that matches and sets it; else the part's own glTF extras; else
    the rules' default.
    """
    for p in parts:
        cand = p.candidates()
        chosen: dict = {}
        for rule in rules.parts:
            if not _matches(rule.match, cand):
                continue
            for key in ("semantic_class", "radio_material", "drop", "keep"):
                if getattr(rule, key) is not None and key not in chosen:
                    chosen[key] = (getattr(rule, key), rule.match)
        for key in _LABEL_KEYS:
            if key not in chosen and key in p.extras:
                try:
                    check_mesh_labels(**{key: str(p.extras[key])})
                except ValueError as exc:
                    raise _fail(source, f"node {p.path!r}: extras.{key}: {exc}") from None
                chosen[key] = (str(p.extras[key]), "extras")
        p.semantic_class = chosen.get("semantic_class", (rules.default_semantic_class,))[0]
        p.radio_material = chosen.get("radio_material", (rules.default_radio_material,))[0]
        p.drop_rule = chosen["drop"][1] if chosen.get("drop", (False,))[0] else None
        p.keep = bool(chosen.get("keep", (False,))[0])


def joined_parts(parts: list[MeshPart], rules: MeshImportRules, source: Path,
                 fail=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Label ``parts`` (:func:`label_parts`) and join them into one table: (vertices, with those
    closer than ``rules.merge_tolerance_m`` merged; faces into them; each face's part index).
    Refuses non-finite coordinates and faces into missing vertices with ``fail(source, problem)``
    (default: :class:`MeshImportError`)."""
    fail = fail or _fail
    label_parts(parts, rules, source)
    raw_v = np.concatenate([p.mesh.vertices for p in parts])
    if not np.all(np.isfinite(raw_v)):
        raise fail(source, "vertex coordinates include NaN or inf")
    offsets = np.cumsum([0] + [len(p.mesh.vertices) for p in parts])[:-1]
    raw_f = np.concatenate([p.mesh.faces + o for p, o in zip(parts, offsets)])
    if raw_f.min() < 0 or raw_f.max() >= len(raw_v):
        raise fail(source, "a face refers to a vertex that does not exist")
    face_part = np.concatenate([np.full(len(p.mesh.faces), i, np.int64) for i, p in enumerate(parts)])
    vertices, inverse = simplify.merge_vertices(raw_v, rules.merge_tolerance_m)
    return vertices, inverse[raw_f], face_part


def import_mesh(source: Path, rules: MeshImportRules | None = None) -> ImportedMesh:
    """Read, label and check ``source``; refuse empty meshes, degenerate and non-manifold faces."""
    source = Path(source)
    rules = rules or MeshImportRules()
    parts, skipped = read_parts(source, rules)
    parts = [p for p in parts if len(p.mesh.faces)]
    if not parts:
        raise _fail(source, "the file holds no triangle" + (f" (only {', '.join(skipped)})" if skipped else ""))
    vertices, faces, face_part = joined_parts(parts, rules, source)
    degenerate = simplify.degenerate_faces(vertices, faces)
    dropped = int(degenerate.sum())
    if dropped and not rules.drop_degenerate_faces:
        bad = sorted({parts[i].path for i in face_part[degenerate]})
        raise _fail(source, f"{dropped} degenerate (zero-area) face(s) in part(s) {', '.join(bad[:5])}"
                            f"{' ...' if len(bad) > 5 else ''}; fix the mesh or set "
                            "source.rules.drop_degenerate_faces: true")
    faces, face_part = faces[~degenerate], face_part[~degenerate]
    edges, count = simplify.edge_use_counts(faces, face_part)
    if np.any(count > 2):
        bad = sorted({parts[i].path for i in edges[count > 2, 0]})
        raise _fail(source, f"{int((count > 2).sum())} non-manifold edge(s) (shared by more than two "
                            f"faces) in part(s) {', '.join(bad[:5])}{' ...' if len(bad) > 5 else ''}")
    if len(faces) == 0:
        raise _fail(source, "the file holds no triangle with a non-zero area")
    return ImportedMesh(source, rules, parts, vertices, faces, face_part, dropped, skipped)


def _radio_faces(imp: ImportedMesh) -> tuple[np.ndarray, dict]:
    """Mask of the faces the radio mesh keeps, and what was removed by which reason."""
    dropped_part = np.array([p.drop_rule is not None for p in imp.parts])
    by_pattern = dropped_part[imp.face_part]
    active = np.flatnonzero(~by_pattern)
    n, label = simplify.face_components(imp.faces[active], len(imp.vertices))
    extent = simplify.component_extents_m(imp.vertices, imp.faces[active], label, n)
    exempt = np.zeros(n, bool)
    np.logical_or.at(exempt, label, np.array([p.keep for p in imp.parts])[imp.face_part[active]])
    small = (extent < imp.rules.min_part_extent_m) & ~exempt
    keep = np.zeros(len(imp.faces), bool)
    keep[active[~small[label]]] = True
    rules_hit: dict[str, int] = {}
    for p in imp.parts:
        if p.drop_rule is not None:
            rules_hit[p.drop_rule] = rules_hit.get(p.drop_rule, 0) + 1
    removed = {
        "pattern": {"parts": int(dropped_part.sum()), "triangles": int(by_pattern.sum()),
                    "parts_per_rule": rules_hit},
        "small_part": {"components": int(small.sum()), "triangles": int(small[label].sum()),
                       "min_part_extent_m": imp.rules.min_part_extent_m},
        "degenerate": {"triangles": imp.dropped_degenerate},
    }
    return keep, removed


def build_from_mesh(source: Path, rules: MeshImportRules | None = None) -> tuple[SceneMeshes, dict]:
    """Paired visual and radio meshes of a user mesh file, and a report of the simplification.

    :param source: an ``.obj``, ``.ply``, ``.stl``, ``.gltf`` or ``.glb`` file
    :param rules: labelling and simplification rules; the defaults of ``MeshImportRules`` if None
    :return: (meshes, report); the report holds ``visual_triangles``, ``radio_triangles``,
        ``triangle_reduction`` (visual / radio), ``radio_meshes`` (triangles per (class, material)
        mesh), ``removed`` (by reason: ``pattern``, ``small_part``, ``degenerate``),
        ``hausdorff_p95_m`` and ``hausdorff_max_m`` (larger of both directions, m) and the
        per-direction values, ``parts`` and ``parts_per_class``
    :raises MeshImportError: unreadable file, unsupported suffix, empty mesh, degenerate or
        non-manifold faces, nothing left for the radio mesh
    """
    t0 = time.perf_counter()
    return build_from_imported(import_mesh(source, rules), t0)


def build_from_imported(imp: ImportedMesh, t0: float | None = None) -> tuple[SceneMeshes, dict]:
    """:func:`build_from_mesh` of parts already read and labelled (a mesh file's, or a scene XML's
    shapes: :mod:`simart_pipeline.scene.sionna_xml`); ``t0``: when the import started."""
    t0 = time.perf_counter() if t0 is None else t0
    rules = imp.rules
    cls_of = {c.name.lower(): c for c in SemanticClass}
    visual = trimesh.Trimesh(imp.vertices, imp.faces, process=False)
    visual.remove_unreferenced_vertices()
    face_class = np.array([int(cls_of[p.semantic_class]) for p in imp.parts], np.uint8)[imp.face_part]
    face_instance = np.array([p.part_id for p in imp.parts], np.int64)[imp.face_part]
    keep, removed = _radio_faces(imp)
    if not keep.any():
        raise _fail(imp.source, "every part was removed from the radio mesh (by a drop rule or by "
                                f"min_part_extent_m = {rules.min_part_extent_m} m)")
    t1 = time.perf_counter()
    keys = sorted({(p.semantic_class, p.radio_material) for p in imp.parts})
    face_group = np.array([keys.index((p.semantic_class, p.radio_material)) for p in imp.parts])[imp.face_part]
    radio, before = {}, 0
    for g, key in enumerate(keys):
        sel = keep & (face_group == g)
        if not sel.any():
            continue
        before += int(sel.sum())
        mesh = trimesh.Trimesh(imp.vertices, imp.faces[sel], process=False)
        mesh.remove_unreferenced_vertices()
        radio[key] = simplify.decimate(mesh, rules.decimation, rules.decimation_target_fraction,
                                       rules.sharp_edge_angle_deg)
    t2 = time.perf_counter()
    if rules.decimation == "none" and keep.all():  # the radio mesh is the visual mesh: no deviation
        dev = {"samples": 0, **{f"{d}_{q}_m": 0.0 for d in ("visual_to_radio", "radio_to_visual", "hausdorff")
                                for q in ("p95", "max")}}
    else:
        dev = simplify.hausdorff_m(visual, trimesh.util.concatenate(list(radio.values())),
                                   samples=rules.hausdorff_samples, seed=rules.seed)
    t3 = time.perf_counter()
    meshes = SceneMeshes(visual, face_class, face_instance, radio)
    n_vis, n_radio = len(visual.faces), sum(len(m.faces) for m in radio.values())
    per_class: dict[str, int] = {}
    for p in imp.parts:
        per_class[p.semantic_class] = per_class.get(p.semantic_class, 0) + 1
    report = {
        "source": str(imp.source), "parts": len(imp.parts), "parts_per_class": per_class,
        "skipped_geometry": imp.skipped,
        "visual_triangles": n_vis, "radio_triangles": n_radio,
        "triangle_reduction": n_vis / n_radio, "removed": removed,
        "decimation": {"mode": rules.decimation, "triangles_before": before, "triangles_after": n_radio},
        "radio_meshes": {f"{c}_{m}": len(mesh.faces) for (c, m), mesh in radio.items()},
        **{k: v for k, v in dev.items() if k != "samples"}, "hausdorff_samples": dev["samples"],
        "timings_s": {"import": round(t1 - t0, 3), "simplify": round(t2 - t1, 3),
                      "deviation": round(t3 - t2, 3)},
    }
    return meshes, report


def _shadow(tri: np.ndarray) -> shapely.Geometry:
    """Union of the xy projections of triangles [f, 3, 3] that are not vertical."""
    xy = tri[:, :, :2]
    u, v = xy[:, 1] - xy[:, 0], xy[:, 2] - xy[:, 0]
    area = 0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
    return shapely.union_all(shapely.polygons(xy[area > 1e-9]))


def _component_footprints(tri: np.ndarray, closed: bool, sheet_thickness_m: float) -> list[shapely.Polygon]:
    """Footprint polygons of one connected component given as triangles [f, 3, 3] (m)."""
    signed_volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    if closed and signed_volume > 0:
        shape = _shadow(tri)  # a solid: its shadow (vertical faces cast none, the others cover it)
    else:
        # A sheet (open or inward-facing surface): only its steep faces bar the way, as thin walls.
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        steep = np.abs(n[:, 2]) < 0.5 * np.linalg.norm(n, axis=1)
        if not steep.any():
            return []
        xy = tri[steep][:, :, :2]
        lines = shapely.linestrings(np.concatenate([xy[:, [0, 1]], xy[:, [1, 2]]]))
        shape = shapely.union_all(lines).buffer(sheet_thickness_m / 2, cap_style="square")
    return _polygons(shape)


def _polygons(shape) -> list[shapely.Polygon]:
    shape = shape.buffer(0)
    return [p.simplify(1e-6) for p in getattr(shape, "geoms", [shape])
            if isinstance(p, shapely.Polygon) and p.area > 0]


def source_geometry_from_mesh(source: Path, rules: MeshImportRules | None = None,
                              origin: tuple[float, float, float] | None = None) -> SourceGeometry:
    """Building footprints, surfaces and a ground polygon of a user mesh, for ``osm_extract``.

    Footprints come from the triangles of the ``obstacle_classes`` that the radio mesh keeps, one
    ``building`` feature per connected component of each part: a closed outward-facing component
    (a solid) contributes its shadow, an open one (a sheet) its steep faces thickened to
    ``wall_sheet_thickness_m``; the height band is the component's z range. Road, water and
    vegetation parts become area features (their shadow). The ground is the mesh's bounding
    rectangle, with the radio material of the largest ground, road or water area. Feature ids are
    part ids (the visual mesh's instance ids).

    :param origin: WGS84 latitude, longitude (deg) and altitude (m) of the ENU origin, recorded
    """
    return source_geometry_from_imported(import_mesh(source, rules), origin)


def source_geometry_from_imported(imp: ImportedMesh, origin: tuple[float, float, float] | None = None,
                                  join_parts: bool = False) -> SourceGeometry:
    """:func:`source_geometry_from_mesh` of parts already read and labelled.

    :param join_parts: find connected components across parts (a building split into a wall and a
        roof shape is one), take a component that is closed, or open only at its bottom (its open
        edges on horizontal rings its faces rise from: walls and a roof without a floor, a tower
        open on a roof; :func:`simart_pipeline.scene.solids.enclosing_parts`), for a solid whichever
        way its faces point, and a flat or otherwise open one for a sheet
    """
    keep, _ = _radio_faces(imp)
    cls = imp.face_attr("semantic_class")
    mats = imp.face_attr("radio_material")
    out = SourceGeometry(origin=origin)
    sel = np.flatnonzero(keep & np.isin(cls, list(imp.rules.obstacle_classes)))
    if len(sel):
        # Components within each part (or across parts): key every vertex by its part (or by 0).
        f, part = imp.faces[sel], imp.face_part[sel]
        keys = np.column_stack([np.repeat(np.zeros_like(part) if join_parts else part, 3), f.ravel()])
        _, local = np.unique(keys, axis=0, return_inverse=True)
        local = local.reshape(-1, 3)
        n, label = simplify.face_components(local, int(local.max()) + 1)
        edges, count = simplify.edge_use_counts(local, label)
        open_comp = np.zeros(n, bool)
        open_comp[edges[count != 2, 0]] = True
        if join_parts:  # a solid as the CKM's indoor mask sees one (scene/solids.py)
            pos = np.zeros((int(local.max()) + 1, 3))
            pos[local.ravel()] = imp.vertices[f.ravel()]
            encloses, _ = solids.enclosing_parts(pos, local, label, n, imp.rules.merge_tolerance_m, with_caps=False)
            open_comp = ~encloses
        for k in range(n):
            fk = np.flatnonzero(label == k)
            tri = imp.vertices[f[fk]]
            if join_parts and not open_comp[k] and \
                    np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() < 0:
                tri = tri[:, ::-1]  # a solid facing inwards (Sionna RT does not mind): a solid all the same
            p = imp.parts[int(part[fk[0]])]
            for poly in _component_footprints(tri, not open_comp[k], imp.rules.wall_sheet_thickness_m):
                out.features.append(Feature("building", poly, p.part_id, height_m=float(tri[:, :, 2].max()),
                                            min_height_m=float(tri[:, :, 2].min()),
                                            radio_material=p.radio_material))
    for i, p in enumerate(imp.parts):
        if p.semantic_class in ("road", "water", "vegetation"):
            for poly in _polygons(_shadow(imp.vertices[imp.faces[imp.face_part == i]])):
                out.features.append(Feature(p.semantic_class, poly, p.part_id, radio_material=p.radio_material))
    corners = imp.vertices[np.unique(imp.faces)]
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    flat = np.isin(cls, ["ground", "road", "water"])
    material = imp.rules.default_radio_material
    if flat.any():
        area = trimesh.triangles.area(imp.vertices[imp.faces[flat]])
        names, inv = np.unique(mats[flat], return_inverse=True)
        material = str(names[np.argmax(np.bincount(inv, weights=area))])
    out.features.append(Feature("ground", shapely.box(lo[0], lo[1], hi[0], hi[1]),
                                len(imp.parts) + 1, radio_material=material))
    if flat.any():  # a relief, or a plane off z = 0: heights above the origin are not above ground
        surface = imp.vertices[np.unique(imp.faces[flat])]
        if np.abs(surface[:, 2]).max() > GROUND_PLANE_TOLERANCE_M:
            out.ground_surface_m = surface
    return out
