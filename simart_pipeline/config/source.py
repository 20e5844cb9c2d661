"""Scene source: the world origin and where the geometry comes from (procedural layout, an OSM
extract, a user mesh with its import rules, or a Mitsuba/Sionna scene XML with its radio materials)."""

from __future__ import annotations

import re
from typing import Annotated, Literal, Union

from pydantic import Field, field_validator, model_validator

from simart_pipeline.config.base import Vec2, _inside_scene_dir, _Model
from simart_pipeline.vocabulary import RADIO_MATERIALS, SEMANTIC_CLASS_NAMES


class WorldOrigin(_Model):
    """Geodetic origin of the local ENU world frame (WGS84)."""

    latitude_deg: float = Field(ge=-90, le=90)
    longitude_deg: float = Field(ge=-180, le=180)
    altitude_m: float = 0.0


class ProceduralSource(_Model):
    """The project's own city-block layout: a grid of blocks with one building each."""

    kind: Literal["procedural"]
    blocks: tuple[int, int] = (3, 3)
    block_size_m: Vec2 = (40.0, 30.0)
    street_width_m: float = Field(20.0, gt=0)
    building_height_m: Vec2 = (10.0, 30.0)
    building_inset_m: float = Field(3.0, ge=0)
    seed: int = 7

    @field_validator("blocks")
    @classmethod
    def _blocks_positive(cls, v):
        if min(v) < 1:
            raise ValueError("both block counts must be >= 1")
        return v


class OsmSource(_Model):
    """An OpenStreetMap extract (.osm XML or .osm.pbf), path relative to the scene directory."""

    kind: Literal["osm"]
    path: str
    bbox_deg: tuple[float, float, float, float] | None = Field(
        None, description="min_lon, min_lat, max_lon, max_lat; whole extract when absent")
    default_building_height_m: float = Field(10.0, gt=0)
    storey_height_m: float = Field(3.0, gt=0)
    facade_detail: bool = Field(True, description="window frames on the visual mesh's facades")

    _inside = field_validator("path")(classmethod(lambda cls, v: _inside_scene_dir(v, "the extract")))

    @field_validator("bbox_deg")
    @classmethod
    def _bbox_ordered(cls, v):
        if v is not None and not (-180 <= v[0] < v[2] <= 180 and -90 <= v[1] < v[3] <= 90):
            raise ValueError("expected min_lon < max_lon and min_lat < max_lat, in degrees")
        return v


def check_pattern(v: str) -> str:
    """A part or material pattern: a case-insensitive glob, or ``re:`` and a regular expression."""
    if not v:
        raise ValueError("an empty pattern matches nothing")
    if v.startswith("re:"):
        try:
            re.compile(v[3:])
        except re.error as exc:
            raise ValueError(f"{v!r}: not a valid regular expression: {exc}") from None
    return v


class MeshPartRule(_Model):
    """How the parts that ``match`` are labelled and simplified (``docs/user-meshes.md``).

    ``match`` is a case-insensitive glob (``window_frame*``) or, prefixed ``re:``, a regular
    expression (full match), tried against a part's node name, node path (``Room/Desk``), mesh
    name, visual material name and tags. For each field, the first matching rule that sets it wins.
    """

    match: str = Field(min_length=1)
    semantic_class: str | None = None
    radio_material: str | None = None
    drop: bool | None = Field(None, description="remove from the radio mesh (the visual mesh keeps it)")
    keep: bool | None = Field(None, description="never removed by the size threshold")

    _pattern = field_validator("match")(classmethod(lambda cls, v: check_pattern(v)))

    @model_validator(mode="after")
    def _known_names(self):
        check_mesh_labels(self.semantic_class, self.radio_material)
        return self


def check_mesh_labels(semantic_class: str | None = None, radio_material: str | None = None) -> None:
    """Raise ValueError for a semantic class or radio material the project does not know."""
    if semantic_class is not None and semantic_class not in SEMANTIC_CLASS_NAMES:
        raise ValueError(f"unknown semantic class {semantic_class!r}; known: {', '.join(SEMANTIC_CLASS_NAMES)}")
    if radio_material is not None and radio_material not in RADIO_MATERIALS:
        raise ValueError(f"unknown radio material {radio_material!r}; known: {', '.join(RADIO_MATERIALS)}")


class MeshImportRules(_Model):
    """Import, labelling and simplification of a user mesh into paired visual and radio meshes."""

    up_axis: Literal["auto", "y", "z"] = Field(
        "auto", description="the file's up axis; auto: y for glTF/GLB (the glTF spec), z otherwise")
    scale_m_per_unit: float = Field(1.0, gt=0, description="metres per file unit (glTF is metres)")
    parts: tuple[MeshPartRule, ...] = ()
    default_semantic_class: str = "building"
    default_radio_material: str = "concrete"
    min_part_extent_m: float = Field(
        1.0, ge=0, description="connected parts whose bounding box is smaller than this along every "
        "axis are removed from the radio mesh")
    merge_tolerance_m: float = Field(1e-4, gt=0, le=0.1, description="vertices closer than this merge")
    decimation: Literal["lossless", "quadric", "none"] = "lossless"
    decimation_target_fraction: float = Field(
        0.5, gt=0, le=1, description="quadric only: triangles kept per smooth patch, after lossless")
    sharp_edge_angle_deg: float = Field(
        30.0, gt=0, lt=180, description="quadric only: edges bending more than this are kept exactly")
    drop_degenerate_faces: bool = Field(
        False, description="drop zero-area faces instead of refusing the mesh")
    obstacle_classes: tuple[str, ...] = Field(
        ("building",), description="semantic classes whose parts become building footprints of the "
        "source geometry (device placement and trajectory clearance checks, indoor masks)")
    wall_sheet_thickness_m: float = Field(
        0.1, gt=0, description="thickness given to open (sheet) walls in building footprints")
    hausdorff_samples: int = Field(20_000, ge=100, le=10_000_000)
    seed: int = 0

    @model_validator(mode="after")
    def _known_defaults(self):
        check_mesh_labels(self.default_semantic_class, self.default_radio_material)
        for c in self.obstacle_classes:
            check_mesh_labels(semantic_class=c)
        return self


class MeshSource(_Model):
    """A user-built mesh (OBJ, PLY, STL, glTF/GLB), path relative to the scene directory."""

    kind: Literal["mesh"]
    path: str
    rules: MeshImportRules = Field(default_factory=lambda: MeshImportRules())

    _inside = field_validator("path")(classmethod(lambda cls, v: _inside_scene_dir(v, "the mesh")))


def _word(*words: str) -> str:
    """A pattern matching any of ``words`` as a whole word of a name (``mesh-car_3``, not ``Carlo``)."""
    return f"re:(.*[^a-z])?({'|'.join(words)})([^a-z].*)?"


# Shape id / material patterns -> semantic class, tried in order (docs/sionna-scenes.md).
DEFAULT_XML_SEMANTIC_CLASSES: dict[str, str] = {
    _word("floor", "ground", "terrain", "plane"): "ground",
    _word("roads?", "streets?"): "road",
    _word("cars?", "vehicles?", "trucks?", "bus"): "vehicle",
    _word("trees?", "vegetation", "grass"): "vegetation",
    _word("water", "river", "lake"): "water",
}


class SionnaXmlSource(_Model):
    """A Mitsuba/Sionna RT scene XML (Sionna's bundled scenes, Blender exports), path relative to
    the scene directory; its radio materials are kept (``docs/sionna-scenes.md``)."""

    kind: Literal["sionna_xml"]
    path: str
    semantic_classes: dict[str, str] = Field(
        default_factory=lambda: dict(DEFAULT_XML_SEMANTIC_CLASSES),
        description="case-insensitive glob (or re:regex) -> semantic class, tried in order against "
        "each shape's id, its BSDF's id and its ITU material type; the first match wins")
    default_semantic_class: str = "building"
    obstacle_classes: tuple[str, ...] = Field(
        ("building",), description="semantic classes whose shapes become building footprints")
    up_axis: Literal["y", "z"] = Field("z", description="the file's up axis (Sionna scenes: z)")
    scale_m_per_unit: float = Field(1.0, gt=0, description="metres per file unit (Sionna scenes: m)")
    merge_tolerance_m: float = Field(1e-4, gt=0, le=0.1, description="vertices closer than this merge")
    decimation: Literal["none", "lossless"] = Field(
        "none", description="radio mesh simplification: none (the shapes as they are) or lossless")
    wall_sheet_thickness_m: float = Field(
        0.1, gt=0, description="thickness given to open (sheet) walls in building footprints")
    hausdorff_samples: int = Field(20_000, ge=100, le=10_000_000)

    _inside = field_validator("path")(classmethod(lambda cls, v: _inside_scene_dir(v, "the scene XML")))

    @field_validator("path")
    @classmethod
    def _xml_suffix(cls, v):
        if not v.lower().endswith(".xml"):
            raise ValueError(f"{v!r}: expected a Mitsuba scene file ending in .xml")
        return v

    @field_validator("semantic_classes")
    @classmethod
    def _classes(cls, v):
        for pattern, name in v.items():
            check_pattern(pattern)
            try:
                check_mesh_labels(semantic_class=name)
            except ValueError as exc:
                raise ValueError(f"{pattern!r}: {exc}") from None
        return v

    @field_validator("default_semantic_class")
    @classmethod
    def _known_default(cls, v):
        check_mesh_labels(semantic_class=v)
        return v

    @field_validator("obstacle_classes")
    @classmethod
    def _known_obstacles(cls, v):
        for c in v:
            check_mesh_labels(semantic_class=c)
        return v


Source = Annotated[Union[ProceduralSource, OsmSource, MeshSource, SionnaXmlSource], Field(discriminator="kind")]
