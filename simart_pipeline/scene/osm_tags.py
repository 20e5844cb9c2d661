"""What OSM tags mean for a scene: lengths, building heights, roofs, land cover, road widths, materials.

Plain functions of a tag mapping (``dict`` or pyosmium ``TagList``), used by
:mod:`simart_pipeline.scene.osm`; the conventions are the OSM wiki's Simple 3D Buildings and
``highway``/``landuse`` pages.
"""

from __future__ import annotations

import re

import numpy as np

from simart_pipeline.config import Materials

# Typical carriageway widths (m) by highway class when neither width nor lanes is tagged.
HIGHWAY_WIDTH_M = {"motorway": 11.0, "trunk": 10.0, "primary": 10.0, "secondary": 8.0, "tertiary": 7.0,
                   "motorway_link": 5.0, "trunk_link": 5.0, "primary_link": 5.0, "secondary_link": 5.0,
                   "tertiary_link": 5.0, "residential": 6.0, "unclassified": 6.0, "service": 4.0,
                   "living_street": 5.0, "pedestrian": 5.0, "track": 3.0, "busway": 4.0,
                   "footway": 2.0, "cycleway": 2.0, "bridleway": 2.0, "path": 1.5, "steps": 2.0,
                   "corridor": 2.0}
DEFAULT_ROAD_WIDTH_M = 5.0
LANE_WIDTH_M = 3.5
# Ways that are not (yet) a surface one can drive or walk on.
NOT_A_ROAD = {"proposed", "construction", "abandoned", "razed", "platform", "elevator", "bus_stop",
              "no", "escape", "raceway"}
# roof:shape values this reader meshes approximately, as the nearest supported shape.
ROOF_SHAPE_APPROX = {"flat": "flat", "gabled": "gabled", "hipped": "hipped", "pyramidal": "pyramidal",
                     "skillion": "skillion", "lean_to": "skillion", "half-hipped": "hipped",
                     "side_hipped": "hipped", "mansard": "hipped", "gambrel": "gabled", "saltbox": "gabled",
                     "round": "gabled", "dome": "pyramidal", "onion": "pyramidal", "cone": "pyramidal"}
MAX_HEIGHT_M = 1000.0  # taller than any building: a tagging error
VEGETATION = {
    "landuse": {"grass", "meadow", "forest", "village_green", "recreation_ground", "flowerbed",
                "allotments", "orchard", "vineyard", "farmland", "cemetery", "greenfield", "plant_nursery"},
    "leisure": {"park", "garden", "pitch", "golf_course", "dog_park"},
    "natural": {"wood", "scrub", "grassland", "heath", "wetland", "fell"},
}
WATER = {"natural": {"water", "bay", "strait"}, "landuse": {"reservoir", "basin"},
         "waterway": {"riverbank", "dock"}}
_LENGTH = re.compile(r"^\s*~?\s*([0-9]*\.?[0-9]+)\s*(m|meters?|metres?|ft|feet|'|)\s*$", re.IGNORECASE)
_FEET_INCHES = re.compile(r"^\s*([0-9]+)\s*'\s*([0-9]*\.?[0-9]+)\s*\"\s*$")


def parse_length_m(text: str | None) -> float | None:
    """OSM length values: ``12``, ``12 m``, ``40'``, ``40 ft``, ``12'6"``; None when absent or unparsable."""
    if text is None:
        return None
    text = text.replace(",", ".")
    m = _FEET_INCHES.match(text)
    if m:
        return float(m.group(1)) * 0.3048 + float(m.group(2)) * 0.0254
    m = _LENGTH.match(text)
    if not m:
        return None
    value = float(m.group(1))
    return value * 0.3048 if m.group(2).lower() in ("ft", "feet", "'") else value


def number(text: str | None) -> float | None:
    try:
        value = float(text.replace(",", ".")) if text is not None else None
    except ValueError:
        return None
    return value if value is not None and np.isfinite(value) and value >= 0 else None


def building_heights(tags, default_height_m: float, storey_height_m: float) -> tuple[float, float]:
    """(min_height_m, height_m) of a building or part from its tags (Simple 3D Buildings).

    ``height`` (roof included) else (``building:levels`` + ``roof:levels``) x storey height (plus
    ``roof:height`` when tagged instead of roof levels), else ``default_height_m``; the bottom from
    ``min_height`` else ``building:min_level`` x storey height, else 0. A bottom tagged at or above
    an untagged top puts the roof height (else a storey) on the bottom; a bottom at or above a
    tagged top is a tagging error and becomes 0.
    """
    height = parse_length_m(tags.get("height"))
    if height is not None and not 0 < height <= MAX_HEIGHT_M:
        height = None
    explicit = height is not None
    if height is None:
        levels = number(tags.get("building:levels"))
        if levels is not None:
            roof_levels = number(tags.get("roof:levels"))
            roof_h = parse_length_m(tags.get("roof:height"))
            height = levels * storey_height_m + (roof_levels * storey_height_m if roof_levels is not None
                                                 else (roof_h or 0.0))
    if height is None or not 0 < height <= MAX_HEIGHT_M:
        height = default_height_m
    low = parse_length_m(tags.get("min_height"))
    if low is None:
        min_level = number(tags.get("building:min_level"))
        low = min_level * storey_height_m if min_level is not None else 0.0
    if low >= height and not explicit:
        # Only the bottom is tagged (a dome on a tower, a bridge part): its roof, else a storey, on top.
        roof_h = parse_length_m(tags.get("roof:height"))
        height = low + (roof_h if roof_h and roof_h > 0 else storey_height_m)
    return (low if 0 <= low < height else 0.0), height


def roof_of(tags, height_m: float, min_height_m: float, storey_height_m: float) -> tuple[str, float, bool]:
    """(roof shape, roof height in m or NaN for the mesher's default, ridge across) from the tags."""
    shape = ROOF_SHAPE_APPROX.get(tags.get("roof:shape", "flat"), "flat")
    if shape == "flat":
        return "flat", 0.0, False
    roof_h = parse_length_m(tags.get("roof:height"))
    if roof_h is None:
        roof_levels = number(tags.get("roof:levels"))
        roof_h = roof_levels * storey_height_m if roof_levels else None
    span = height_m - min_height_m
    roof_h = float("nan") if roof_h is None or roof_h <= 0 else min(roof_h, span)
    return shape, roof_h, tags.get("roof:orientation") == "across"


def landcover_class(tags) -> str | None:
    """``water``, ``vegetation``, ``parking`` or ``road`` (a highway area) for an area's tags; None otherwise."""
    for key, values in WATER.items():
        if tags.get(key) in values:
            return "water"
    if "water" in tags and tags.get("natural") in (None, "water"):
        return "water"
    if tags.get("amenity") == "parking" and tags.get("parking", "surface") in ("surface", "lane"):
        return "parking"
    if "area:highway" in tags or (tags.get("highway") and tags.get("area") == "yes"
                                  and tags.get("highway") not in NOT_A_ROAD):
        return "road"
    for key, values in VEGETATION.items():
        if tags.get(key) in values:
            return "vegetation"
    return None


def material_of(tags, feature_class: str, materials: Materials, rules: dict) -> str:
    """The first tag rule the feature's tags match, else its class's material."""
    for key, values in rules.items():
        mat = values.get(tags.get(key, ""))
        if mat is not None:
            return mat
    default = {"building": materials.building, "building_part": materials.building, "road": materials.road,
               "parking": materials.road, "water": materials.water, "vegetation": materials.vegetation}
    return default.get(feature_class, materials.ground)


def is_underground(tags) -> bool:
    """Tunnels and underground buildings: not part of the street-level scene."""
    return tags.get("location") == "underground" or tags.get("tunnel", "no") != "no"


def road_width_m(tags) -> float:
    """``width`` (with units), else ``lanes`` x :data:`LANE_WIDTH_M`, else the class's typical width."""
    width = parse_length_m(tags.get("width"))
    if width is None or width <= 0:
        lanes = number(tags.get("lanes"))
        width = lanes * LANE_WIDTH_M if lanes else HIGHWAY_WIDTH_M.get(tags.get("highway"), DEFAULT_ROAD_WIDTH_M)
    return float(width)
