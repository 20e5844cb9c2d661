"""OpenStreetMap extracts (.osm XML, .osm.pbf) to source geometry, with pyosmium.

First version: building areas (multipolygon relations included) extruded from ``min_height`` to
``height``, else ``building:levels`` (+ ``roof:levels``) x the storey height, else the configured
default; highways as centre lines with a width from ``width``, ``lanes`` x 3.5 m, or the class;
a ground rectangle around everything. Projection to the local ENU frame is exact (pymap3d,
WGS84). ``building:part`` shapes (Simple 3D Buildings) are the scene-construction issue's work:
here outlines are extruded and parts are ignored.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pymap3d
import shapely
from shapely.geometry import LineString, Polygon

from simart_pipeline.config import SceneConfig, resolve_source_path
from simart_pipeline.scene.geometry import Feature, SourceGeometry

log = logging.getLogger(__name__)

# Typical carriageway widths (m) by highway class when neither width nor lanes is tagged.
HIGHWAY_WIDTH_M = {"motorway": 11.0, "trunk": 10.0, "primary": 10.0, "secondary": 8.0, "tertiary": 7.0,
                   "residential": 6.0, "unclassified": 6.0, "service": 4.0, "living_street": 5.0,
                   "pedestrian": 5.0, "footway": 2.0, "cycleway": 2.0, "path": 1.5, "steps": 2.0}
LANE_WIDTH_M = 3.5
_LENGTH = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*(m|meters?|metres?|ft|feet|'|)\s*$", re.IGNORECASE)


def parse_length_m(text: str | None) -> float | None:
    """OSM length values: ``12``, ``12 m``, ``40'``, ``40 ft``; None when absent or unparsable."""
    if text is None:
        return None
    m = _LENGTH.match(text.replace(",", "."))
    if not m:
        return None
    value = float(m.group(1))
    return value * 0.3048 if m.group(2).lower() in ("ft", "feet", "'") else value


def _levels(text: str | None) -> float | None:
    try:
        return float(text) if text is not None else None
    except ValueError:
        return None


def building_heights(tags, default_height_m: float, storey_height_m: float) -> tuple[float, float]:
    """(min_height_m, height_m) of a building from its tags."""
    height = parse_length_m(tags.get("height"))
    if height is None:
        levels = _levels(tags.get("building:levels"))
        if levels is not None:
            height = (levels + (_levels(tags.get("roof:levels")) or 0.0)) * storey_height_m
    if height is None or height <= 0:
        height = default_height_m
    low = parse_length_m(tags.get("min_height"))
    if low is None:
        min_level = _levels(tags.get("building:min_level"))
        low = min_level * storey_height_m if min_level is not None else 0.0
    return (low if low < height else 0.0), height


def read_osm(cfg: SceneConfig, scene_dir) -> SourceGeometry:
    import osmium

    path = resolve_source_path(Path(scene_dir), cfg)
    src = cfg.source
    lat0, lon0, alt0 = cfg.origin.latitude_deg, cfg.origin.longitude_deg, cfg.origin.altitude_m

    def enu(lons, lats):
        e, n, _ = pymap3d.geodetic2enu(np.asarray(lats), np.asarray(lons), alt0, lat0, lon0, alt0)
        return np.column_stack([e, n])

    bbox = None
    if src.bbox_deg is not None:
        lo, la, hi_lo, hi_la = src.bbox_deg
        corners = enu([lo, hi_lo], [la, hi_la])
        bbox = shapely.box(*corners[0], *corners[1])
    out = SourceGeometry()
    try:
        fp = osmium.FileProcessor(str(path)).with_locations().with_areas() \
            .with_filter(osmium.filter.KeyFilter("building", "highway"))
        for obj in fp:
            tags = obj.tags
            if obj.is_area() and "building" in tags:
                for outer in obj.outer_rings():
                    shell = enu([n.lon for n in outer], [n.lat for n in outer])
                    holes = [enu([n.lon for n in r], [n.lat for n in r]) for r in obj.inner_rings(outer)]
                    poly = Polygon(shell, holes)
                    if not poly.is_valid:
                        fixed = shapely.make_valid(poly)
                        parts = [g for g in getattr(fixed, "geoms", [fixed]) if isinstance(g, Polygon)]
                        if not parts:
                            log.warning("%s: building %s (OSM id) has an invalid outline; dropped",
                                        path, obj.orig_id())
                            continue
                        log.warning("%s: building %s (OSM id) had an invalid outline; repaired", path, obj.orig_id())
                        poly = max(parts, key=lambda g: g.area)
                    low, high = building_heights(tags, src.default_building_height_m, src.storey_height_m)
                    out.features.append(Feature("building", poly, int(obj.orig_id()), height_m=high,
                                                min_height_m=low, radio_material=cfg.materials.building))
            elif obj.is_way() and "highway" in tags and tags.get("area") != "yes":
                # Extracts cut ways at their border: nodes outside it have no location.
                nodes = [n for n in obj.nodes if n.location.valid()]
                pts = enu([n.lon for n in nodes], [n.lat for n in nodes])
                if len(pts) < 2:
                    continue
                width = parse_length_m(tags.get("width"))
                if width is None and _levels(tags.get("lanes")):
                    width = _levels(tags.get("lanes")) * LANE_WIDTH_M
                width = width or HIGHWAY_WIDTH_M.get(tags.get("highway"), 5.0)
                out.features.append(Feature("road", LineString(pts), int(obj.id), width_m=width,
                                            radio_material=cfg.materials.road))
    except RuntimeError as exc:
        raise ValueError(f"{path}: not a readable OSM file: {exc}") from None
    if bbox is not None:
        out.features = [f for f in out.features if f.geometry.intersects(bbox)]
    if not out.features:
        raise ValueError(f"{path}: no building or highway inside the selected area")
    extent = bbox if bbox is not None else shapely.box(
        *shapely.union_all([f.geometry for f in out.features]).buffer(10.0).bounds)
    out.features.append(Feature("ground", extent, 0, radio_material=cfg.materials.ground))
    return out
