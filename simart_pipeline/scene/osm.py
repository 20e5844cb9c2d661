"""OpenStreetMap extracts (.osm XML, .osm.pbf) to source geometry, with pyosmium.

- **Reading**: one pyosmium pass with node locations and area assembly (multipolygon relations
  included). libosmium's XML parser refuses entity declarations, so external entities and entity
  expansion ("billion laughs") are errors, never expanded; malformed XML is an error naming the file.
- **Projection**: every node of every kept feature is projected in one vectorised call
  (``pymap3d.geodetic2enu``, WGS84, exact) around the world origin, by default the extract's centre
  (the bounding box's, else the file header's, else that of every node the file holds). Nodes are
  taken on the ellipsoid at the origin's altitude and only east/north are kept: the ground is the
  plane z = 0 (the Earth's curvature would put it 8 cm lower 1 km away).
- **Clipping**: with a bounding box, buildings whose footprint's representative point lies inside
  are kept whole (a cut building would get a wall that does not exist); roads and land cover are
  cut at the box; the ground is the box.
- **Extent** without a bounding box: the file header's box, else the box of every node the file
  holds (an Overpass extract has no header box, and its nodes fill the area it was cut from; the
  buildings' box would drop the roads and ground of an area where few buildings are mapped), grown
  to the buildings' where one overhangs it.
- **Buildings** (Simple 3D Buildings): heights from ``height``/``min_height`` (with units), else
  ``building:levels`` (+ ``roof:levels``) and ``building:min_level`` times the storey height, else
  the default; ``roof:shape`` (flat, gabled, hipped, pyramidal, skillion; others approximated),
  ``roof:height``/``roof:levels``, ``roof:orientation``. A ``building:part`` belongs to the outline
  named in a ``type=building`` relation, else to the smallest outline containing it; an outline
  with parts is not extruded (its parts are).
- **Roads**: ``highway`` ways as centre lines with a width from ``width``, else ``lanes`` x 3.5 m,
  else the class; highway areas as road surfaces. Tunnels and underground ways are left out.
- **Land cover**: parking, water, vegetation areas (see :func:`landcover_class`).
- **Invalid polygons** are repaired with ``shapely.make_valid`` or dropped, each with a warning
  naming the file and the OSM id (logged, and kept in :attr:`SourceGeometry.warnings`).

OSM ids: ways keep their id, relations are negated (as osm2pgsql does), so the two never collide.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pymap3d
import shapely
from shapely.geometry import LineString, MultiPolygon, Polygon

from simart_pipeline.config import Materials, SceneConfig, resolve_source_path
from simart_pipeline.provenance import OSM_ATTRIBUTION
from simart_pipeline.scene.geometry import Feature, SourceGeometry, polygons_of
from simart_pipeline.scene.osm_tags import (NOT_A_ROAD, building_heights, is_underground, landcover_class,
                                            material_of, number, parse_length_m, road_width_m, roof_of)

log = logging.getLogger(__name__)

ATTRIBUTION = OSM_ATTRIBUTION  # "Map data © OpenStreetMap contributors, ODbL 1.0 (...)"
MIN_AREA_M2 = 0.5  # repaired footprints smaller than this are dropped


@dataclass
class _Raw:
    """A feature as read: rings (or the line) in lon/lat, tags, class."""

    cls: str
    oid: int                 # ways positive, relations negative
    what: str                # "way 123" / "relation 45", for messages
    tags: dict
    rings: list[list[np.ndarray]] = field(default_factory=list)  # per polygon: [shell, *holes], [n, 2] lon/lat
    line: np.ndarray | None = None


def _ring(nodes) -> np.ndarray:
    return np.array([(n.lon, n.lat) for n in nodes], np.float64)


@dataclass
class _Pass:
    raws: list[_Raw] = field(default_factory=list)
    building_objects: dict[int, str] = field(default_factory=dict)  # oid -> description, every tagged one
    building_areas: set[int] = field(default_factory=set)  # buildings and parts that assembled
    closed_ways: dict[int, tuple[str, dict, np.ndarray]] = field(default_factory=dict)  # complete, closed
    relation_parts: dict[int, int] = field(default_factory=dict)  # part oid -> outline oid (type=building)


def _read(path: Path) -> _Pass:
    import osmium

    out = _Pass()
    keys = ("building", "building:part", "highway", "area:highway", "landuse", "natural", "leisure",
            "amenity", "water", "waterway", "type")
    fp = osmium.FileProcessor(str(path)).with_locations().with_areas() \
        .with_filter(osmium.filter.KeyFilter(*keys))
    for obj in fp:
        tags = obj.tags
        if obj.is_area():
            rel = not obj.from_way()
            oid = -obj.orig_id() if rel else obj.orig_id()
            what = f"{'relation' if rel else 'way'} {obj.orig_id()}"
            if tags.get("building", "no") != "no":
                cls = "building"
            elif tags.get("building:part", "no") != "no":
                cls = "building_part"
            else:
                cls = landcover_class(tags)
            if cls is None or is_underground(tags) and cls.startswith("building"):
                continue
            raw = _Raw(cls, oid, what, dict(tags))
            for outer in obj.outer_rings():
                raw.rings.append([_ring(outer)] + [_ring(inner) for inner in obj.inner_rings(outer)])
            if raw.rings:
                out.raws.append(raw)
                if cls.startswith("building"):
                    out.building_areas.add(oid)
        elif obj.is_way():
            cls = "building" if tags.get("building", "no") != "no" else (
                "building_part" if tags.get("building:part", "no") != "no" else None)
            if cls and not is_underground(tags):
                if cls == "building":
                    out.building_objects[obj.id] = f"way {obj.id}"
                # libosmium assembles no area from a self-intersecting ring: keep it for repair.
                if obj.is_closed() and len(obj.nodes) >= 4 and all(n.location.valid() for n in obj.nodes):
                    out.closed_ways[obj.id] = (cls, dict(tags), _ring(obj.nodes))
            hw = tags.get("highway")
            if hw and hw not in NOT_A_ROAD and tags.get("area") != "yes" and not is_underground(tags):
                # Extracts cut ways at their border: nodes outside it have no location. Each run
                # of located nodes is a line of its own.
                run: list = []
                runs = [run]
                for n in obj.nodes:
                    if n.location.valid():
                        run.append((n.lon, n.lat))
                    elif run:
                        run = []
                        runs.append(run)
                for r in runs:
                    if len(r) >= 2:
                        out.raws.append(_Raw("road", obj.id, f"way {obj.id}", dict(tags),
                                             line=np.asarray(r, np.float64)))
        elif obj.is_relation():
            if tags.get("building", "no") != "no" and tags.get("type") == "multipolygon" \
                    and not is_underground(tags):
                out.building_objects[-obj.id] = f"relation {obj.id}"
            if tags.get("type") == "building":
                members = [(m.type, m.ref, m.role) for m in obj.members]
                outline = [(-ref if t == "r" else ref) for t, ref, role in members if role == "outline"]
                if outline:
                    for t, ref, role in members:
                        if role == "part":
                            out.relation_parts[-ref if t == "r" else ref] = outline[0]
    for wid, (cls, tags, ring) in out.closed_ways.items():
        if wid not in out.building_areas:
            out.raws.append(_Raw(cls, wid, f"way {wid}", tags, rings=[[ring]]))
            out.building_areas.add(wid)
    return out


def _header_box(path: Path):
    """(min_lon, min_lat, max_lon, max_lat) from the file header, or None."""
    import osmium

    reader = osmium.io.Reader(str(path), osmium.osm.osm_entity_bits.NOTHING)
    try:
        box = reader.header().box()
    finally:
        reader.close()
    if not box.valid():
        return None
    return (box.bottom_left.lon, box.bottom_left.lat, box.top_right.lon, box.top_right.lat)


def _node_box(path: Path):
    """(min_lon, min_lat, max_lon, max_lat) of every located node of the file, or None."""
    import osmium

    lon_min = lat_min = np.inf
    lon_max = lat_max = -np.inf
    for n in osmium.FileProcessor(str(path), osmium.osm.NODE):
        loc = n.location
        if loc.valid():
            lon, lat = loc.lon, loc.lat
            lon_min, lon_max = min(lon_min, lon), max(lon_max, lon)
            lat_min, lat_max = min(lat_min, lat), max(lat_max, lat)
    return None if lon_min > lon_max else (lon_min, lat_min, lon_max, lat_max)


def _has_any_object(path: Path) -> bool:
    import osmium

    for _ in osmium.FileProcessor(str(path)):
        return True
    return False


class OsmReadError(ValueError):
    """An extract that cannot be turned into a scene; the message names the file."""


def read_osm(cfg: SceneConfig, scene_dir) -> SourceGeometry:
    """The source geometry of a scene whose source is an OSM extract (``cfg.source``)."""
    src = cfg.source
    return read_extract(resolve_source_path(Path(scene_dir), cfg),
                        origin=(cfg.origin.latitude_deg, cfg.origin.longitude_deg, cfg.origin.altitude_m),
                        bbox_deg=src.bbox_deg, materials=cfg.materials,
                        default_building_height_m=src.default_building_height_m,
                        storey_height_m=src.storey_height_m)


def read_extract(path: str | Path, origin: tuple[float, float, float] | None = None,
                 bbox_deg: tuple[float, float, float, float] | None = None, *,
                 materials: Materials | None = None, default_building_height_m: float = 10.0,
                 storey_height_m: float = 3.0) -> SourceGeometry:
    """Read an OSM extract into source geometry in the local ENU frame.

    :param path: ``.osm`` (XML, optionally ``.gz``/``.bz2``) or ``.osm.pbf``
    :param origin: (latitude deg, longitude deg, altitude m) of the world frame; None: the
        extract's centre (the bounding box's, else the header's, else its nodes') at altitude 0
    :param bbox_deg: (min_lon, min_lat, max_lon, max_lat) to clip to; None: the whole extract
    :raises OsmReadError: unreadable, malformed or hostile file, empty extract, no buildings
    """
    path = Path(path)
    materials = materials or Materials()
    rules = materials.tag_rules()
    if not path.is_file():
        raise OsmReadError(f"{path}: no such file")
    try:
        raw = _read(path)
        # The extract's own box: its header's, else its nodes' (not needed where a box is given)
        extract_box = None if bbox_deg is not None else (_header_box(path) or _node_box(path))
    except RuntimeError as exc:  # libosmium: XML syntax, entities, unknown format, bad PBF
        raise OsmReadError(f"{path}: not a readable OSM file: {exc}") from None
    warnings: list[str] = []

    def warn(msg: str) -> None:
        msg = f"{path.name}: {msg}"
        log.warning(msg)
        warnings.append(msg)

    for oid, what in sorted(raw.building_objects.items()):
        if oid not in raw.building_areas:
            warn(f"building {what}: its outline is not a closed ring with every node in the extract "
                 "(or its multipolygon does not assemble); dropped")
    buildings = [r for r in raw.raws if r.cls == "building"]
    if not buildings:
        if not _has_any_object(path):
            raise OsmReadError(f"{path}: the extract is empty (no node, way or relation)")
        raise OsmReadError(f"{path}: the extract holds no building (no closed way or multipolygon "
                           "tagged building=*)")
    # The origin and the extent, in lon/lat.
    bld_ll = np.concatenate([r.rings[0][0] for r in buildings])
    bld_box = (*bld_ll.min(0), *bld_ll.max(0))
    centre_box = bbox_deg or extract_box or bld_box
    if origin is None:
        origin = ((centre_box[1] + centre_box[3]) / 2, (centre_box[0] + centre_box[2]) / 2, 0.0)
    lat0, lon0, alt0 = origin

    # One vectorised projection of every node of every feature.
    arrays = []
    for r in raw.raws:
        arrays += [ring for poly in r.rings for ring in poly] if r.line is None else [r.line]
    box_ring = None
    if bbox_deg is not None:
        box_ring = _densified_box(bbox_deg)
        arrays.append(box_ring)
    elif extract_box is not None:
        arrays.append(_densified_box(extract_box))
    sizes = np.array([len(a) for a in arrays])
    ll = np.concatenate(arrays)
    e, n, _ = pymap3d.geodetic2enu(ll[:, 1], ll[:, 0], np.full(len(ll), alt0), lat0, lon0, alt0)
    xy = np.column_stack([e, n])
    pieces = np.split(xy, np.cumsum(sizes)[:-1])
    it = iter(pieces)
    polys: list = []
    for r in raw.raws:
        if r.line is None:
            polys.append([[next(it) for _ in poly] for poly in r.rings])
        else:
            polys.append(next(it))
    frame_box = Polygon(next(it)) if (bbox_deg is not None or extract_box is not None) else None

    out = SourceGeometry(origin=(float(lat0), float(lon0), float(alt0)), attribution=ATTRIBUTION,
                         warnings=warnings)
    src = {"default_building_height_m": default_building_height_m, "storey_height_m": storey_height_m}
    feats = []
    for r, g in zip(raw.raws, polys):
        if r.line is not None:
            f = _road(r, g, materials, rules)
        else:
            f = _area(r, g, warn, materials, rules, **src)
        if f is not None:
            feats.append((r, f))

    # Building parts to their outlines (Simple 3D Buildings).
    outlines = [f for r, f in feats if f.feature_class == "building"]
    by_id = {f.source_id: f for f in outlines}
    tree = shapely.STRtree([f.geometry for f in outlines])
    areas = np.array([f.geometry.area for f in outlines])
    for r, f in feats:
        if f.feature_class != "building_part":
            continue
        parent = raw.relation_parts.get(f.source_id)
        if parent not in by_id:
            hits = tree.query(f.geometry.representative_point(), predicate="within")
            parent = outlines[hits[np.argmin(areas[hits])]].source_id if len(hits) else None
        if parent is not None:
            f.parent_id = parent
            by_id[parent].has_parts = True
    # An outline also tagged building:part is a part of itself (S3DB): extruded once, as a part.
    extra = []
    for r, f in feats:
        if f.feature_class == "building" and f.has_parts and r.tags.get("building:part", "no") != "no":
            extra.append((r, Feature("building_part", f.geometry, f.source_id, f.height_m, f.min_height_m,
                                     radio_material=f.radio_material, roof_shape=f.roof_shape,
                                     roof_height_m=f.roof_height_m, roof_across=f.roof_across,
                                     levels=f.levels, parent_id=f.source_id)))
    feats += extra

    # Clip to the bounding box, or find the extent of the scene.
    if bbox_deg is not None:
        extent = frame_box
        kept = {f.source_id for _, f in feats if f.feature_class == "building"
                and extent.contains(f.geometry.representative_point())}
        if not kept:
            raise OsmReadError(f"{path}: no building inside the bounding box {list(bbox_deg)}")
    else:
        b = shapely.bounds([f.geometry for f in outlines])
        fps = shapely.box(*b[:, :2].min(0), *b[:, 2:].max(0))
        extent = fps.union(frame_box).envelope if frame_box is not None else fps.buffer(20.0, join_style="mitre")
        kept = set(by_id)
    for _, f in feats:
        if f.feature_class == "building":
            if f.source_id in kept:
                out.features.append(f)
        elif f.feature_class == "building_part":
            if f.parent_id in kept or (not f.parent_id and extent.contains(f.geometry.representative_point())):
                out.features.append(f)
        else:
            g = f.geometry if extent.contains(f.geometry) else f.geometry.intersection(extent)
            if f.feature_class == "road" and f.width_m == f.width_m:  # a centre line
                for line in _lines_of(g):
                    out.features.append(Feature("road", line, f.source_id, width_m=f.width_m,
                                                radio_material=f.radio_material))
            else:
                polys_ = polygons_of(g)
                if polys_:
                    f.geometry = polys_[0] if len(polys_) == 1 else MultiPolygon(polys_)
                    out.features.append(f)
    out.features.append(Feature("ground", extent, 0, radio_material=materials.ground))
    order = {c: i for i, c in enumerate(("building", "building_part", "road", "parking", "water",
                                         "vegetation", "ground"))}
    out.features.sort(key=lambda f: order[f.feature_class])
    return out


def _densified_box(box, n: int = 16) -> np.ndarray:
    """A lon/lat box as a closed ring with ``n`` points per side (its edges stay straight in lon/lat)."""
    x0, y0, x1, y1 = box
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    xs = np.concatenate([x0 + (x1 - x0) * t, np.full(n, x1), x1 - (x1 - x0) * t, np.full(n, x0)])
    ys = np.concatenate([np.full(n, y0), y0 + (y1 - y0) * t, np.full(n, y1), y1 - (y1 - y0) * t])
    return np.column_stack([xs, ys])


def _lines_of(g) -> list[LineString]:
    if isinstance(g, LineString):
        return [g] if not g.is_empty and g.length > 0 else []
    return [x for x in getattr(g, "geoms", []) if isinstance(x, LineString) and x.length > 0]


def _road(r: _Raw, xy: np.ndarray, materials: Materials, rules: dict) -> Feature:
    return Feature("road", LineString(xy), r.oid, width_m=road_width_m(r.tags),
                   radio_material=material_of(r.tags, "road", materials, rules))


def _area(r: _Raw, rings: list[list[np.ndarray]], warn, materials: Materials, rules: dict, *,
          default_building_height_m: float, storey_height_m: float) -> Feature | None:
    what = f"{r.cls.replace('_', ' ')} {r.what}"
    shapes = [Polygon(poly[0], poly[1:]) for poly in rings if len(poly[0]) >= 4]
    if not shapes:
        warn(f"{what}: no ring with three distinct nodes; dropped")
        return None
    geom = shapes[0] if len(shapes) == 1 else MultiPolygon(shapes)
    is_building = r.cls.startswith("building")
    if not geom.is_valid:
        reason = shapely.is_valid_reason(geom)
        fixed = polygons_of(shapely.make_valid(geom))
        area = sum(p.area for p in fixed)
        if area < MIN_AREA_M2:
            warn(f"{what}: invalid outline ({reason}) that no repair keeps an area of; dropped")
            return None
        warn(f"{what}: invalid outline ({reason}); repaired with shapely.make_valid "
             f"({geom.area:.1f} -> {area:.1f} m2)")
        geom = fixed[0] if len(fixed) == 1 else MultiPolygon(fixed)
    if geom.is_empty or geom.area <= 0:
        warn(f"{what}: outline without area; dropped")
        return None
    if not is_building:
        return Feature(r.cls, geom, r.oid, radio_material=material_of(r.tags, r.cls, materials, rules))
    tags = r.tags
    for key in ("height", "min_height", "roof:height"):
        if key in tags and parse_length_m(tags[key]) is None:
            warn(f"{what}: {key}={tags[key]!r} is not a length; ignored")
    low, high = building_heights(tags, default_building_height_m, storey_height_m)
    shape, roof_h, across = roof_of(tags, high, low, storey_height_m)
    return Feature(r.cls, geom, r.oid, height_m=high, min_height_m=low,
                   radio_material=material_of(tags, r.cls, materials, rules), roof_shape=shape,
                   roof_height_m=roof_h, roof_across=across,
                   levels=number(tags.get("building:levels")) or np.nan)
