"""Source geometry: the ``osm_extract`` asset's dataset, whatever the scene's source.

Features are 2D shapes in the local ENU frame (x east, y north, m) with the attributes the mesher
needs: buildings and building parts (footprint, heights, roof), roads (centre line and width, or
an area), parking, vegetation, water, and the ground. They are stored as CF contiguous ragged
arrays (CF 1.8 section 7.5 geometries): every ring's nodes one after another along ``node``,
``node_count`` nodes per feature, ``part_node_count`` nodes per ring (part) and ``interior_ring``
saying which rings are holes, so multipolygons with courtyards round-trip exactly.

Building outlines and their parts follow the Simple 3D Buildings convention: an outline whose 3D
shape its ``building:part`` children carry has ``has_parts`` set and is not extruded; each part
names its outline in ``parent_id``. :func:`SourceGeometry.volumes` lists what gets extruded.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
import xarray as xr
from shapely.geometry import LineString, MultiPolygon, Polygon


FEATURE_CLASSES = ("building", "building_part", "road", "parking", "water", "vegetation", "ground")
ROOF_SHAPES = ("flat", "gabled", "hipped", "pyramidal", "skillion")


@dataclass
class Feature:
    """One source feature. Heights in m above the ground plane; NaN where not applicable."""

    feature_class: str
    geometry: Polygon | MultiPolygon | LineString
    source_id: int
    height_m: float = np.nan
    min_height_m: float = np.nan
    width_m: float = np.nan
    radio_material: str = ""
    roof_shape: str = ""             # buildings and parts: one of ROOF_SHAPES
    roof_height_m: float = np.nan    # part of height_m; NaN: the mesher's default for the shape
    roof_across: bool = False        # ridge across the footprint's long side (roof:orientation=across)
    levels: float = np.nan           # storeys below the roof (building:levels), NaN if untagged
    parent_id: int = 0               # building parts: the source id of their outline (0: none)
    has_parts: bool = False          # building outlines whose 3D shape their parts carry

    @property
    def instance_id(self) -> int:
        """The id a visual face of this feature carries: a part's outline, else its own."""
        return self.parent_id or self.source_id


@dataclass
class SourceGeometry:
    features: list[Feature] = field(default_factory=list)
    origin: tuple[float, float, float] | None = None  # WGS84 latitude, longitude (deg), altitude (m)
    attribution: str = ""
    warnings: list[str] = field(default_factory=list)
    # [N, 3] m: vertices of the ground surface (ground, road and water faces) of a mesh or Sionna
    # scene whose ground is not the plane z = 0 (terrain: Sionna's san_francisco rises 0-104 m);
    # None: the plane z = 0. In memory only (validation); the stores keep the features.
    ground_surface_m: np.ndarray | None = None

    def of_class(self, cls: str) -> list[Feature]:
        return [f for f in self.features if f.feature_class == cls]

    def volumes(self) -> list[Feature]:
        """What is extruded: building parts, and building outlines that have no parts."""
        return [f for f in self.features if f.feature_class == "building_part"
                or (f.feature_class == "building" and not f.has_parts)]


def polygons_of(geom) -> list[Polygon]:
    """The non-empty polygons of a Polygon, MultiPolygon or collection."""
    if isinstance(geom, Polygon):
        return [geom] if not geom.is_empty else []
    return [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon) and not g.is_empty]


def _rings(geom) -> list[tuple[np.ndarray, bool]]:
    """(coords [n, 2], is_interior) of every ring of a polygonal geometry, or the line itself."""
    if isinstance(geom, LineString):
        return [(np.asarray(geom.coords)[:, :2], False)]
    out = []
    for poly in polygons_of(geom):
        out.append((np.asarray(poly.exterior.coords)[:, :2], False))
        out += [(np.asarray(r.coords)[:, :2], True) for r in poly.interiors]
    return out


def to_dataset(geom: SourceGeometry) -> xr.Dataset:
    """The CF ragged-array dataset of ``geom``."""
    xs, ys, counts, part_counts, interior = [], [], [], [], []
    for f in geom.features:
        rings = _rings(f.geometry)
        for coords, hole in rings:
            xs.append(coords[:, 0])
            ys.append(coords[:, 1])
            part_counts.append(len(coords))
            interior.append(hole)
        counts.append(sum(len(c) for c, _ in rings))
    nan_attr = "not applicable to this feature class"
    fs = geom.features

    def col(name, dtype):
        return np.asarray([getattr(f, name) for f in fs], dtype)

    empty = np.zeros(0)
    ds = xr.Dataset(
        {
            "node_x_m": ("node", np.concatenate(xs) if xs else empty,
                         {"units": "m", "long_name": "node east (ENU)"}),
            "node_y_m": ("node", np.concatenate(ys) if ys else empty,
                         {"units": "m", "long_name": "node north (ENU)"}),
            "node_count": ("feature", np.asarray(counts, np.int64),
                           {"long_name": "nodes of each feature, in order along node",
                            "sample_dimension": "node"}),
            "part_node_count": ("part", np.asarray(part_counts, np.int64),
                                {"long_name": "nodes of each ring (polygon) or line, in order along node"}),
            "interior_ring": ("part", np.asarray(interior, np.int8),
                              {"long_name": "1 where the part is a hole of the polygon before it",
                               "flag_values": np.array([0, 1], np.int8),
                               "flag_meanings": "exterior_ring interior_ring"}),
            "feature_class": ("feature", np.asarray([f.feature_class for f in fs], dtype=str),
                              {"long_name": "source feature class", "flag_values": " ".join(FEATURE_CLASSES)}),
            "geometry_type": ("feature", np.asarray(["line" if isinstance(f.geometry, LineString)
                                                     else "polygon" for f in fs], dtype=str),
                              {"long_name": "polygon (closed rings, holes flagged) or line (centre line)"}),
            "source_id": ("feature", col("source_id", np.int64),
                          {"long_name": "OSM id (ways positive, relations negative), or a generated id"}),
            "parent_id": ("feature", col("parent_id", np.int64),
                          {"long_name": "building parts: source_id of their building outline; 0 otherwise"}),
            "has_parts": ("feature", col("has_parts", bool),
                          {"long_name": "building outline whose 3D shape its building parts carry"}),
            "height_m": ("feature", col("height_m", np.float64),
                         {"units": "m", "long_name": "top of the building (roof included) above ground",
                          "nan_means": nan_attr}),
            "min_height_m": ("feature", col("min_height_m", np.float64),
                             {"units": "m", "long_name": "bottom of the extruded footprint",
                              "nan_means": nan_attr}),
            "roof_height_m": ("feature", col("roof_height_m", np.float64),
                              {"units": "m", "long_name": "roof height (part of height_m)",
                               "nan_means": "not a building, or untagged (the mesher's default)"}),
            "roof_shape": ("feature", np.asarray([f.roof_shape for f in fs], dtype=str),
                           {"long_name": "roof shape", "flag_values": " ".join(ROOF_SHAPES)}),
            "roof_across": ("feature", col("roof_across", bool),
                            {"long_name": "ridge across the long side of the footprint"}),
            "levels": ("feature", col("levels", np.float64),
                       {"units": "1", "long_name": "storeys below the roof (building:levels)",
                        "nan_means": "untagged or not a building"}),
            "width_m": ("feature", col("width_m", np.float64),
                        {"units": "m", "long_name": "road width", "nan_means": nan_attr + " (or a road area)"}),
            "radio_material": ("feature", np.asarray([f.radio_material for f in fs], dtype=str),
                               {"long_name": "radio material (simart_pipeline.radio.materials)"}),
        },
        coords={"feature": np.arange(len(fs))},
    )
    if geom.origin is not None:
        ds.attrs.update(origin_latitude_deg=geom.origin[0], origin_longitude_deg=geom.origin[1],
                        origin_altitude_m=geom.origin[2])
    if geom.attribution:
        ds.attrs["attribution"] = geom.attribution
    if geom.warnings:
        ds.attrs["source_warnings"] = "\n".join(geom.warnings)
    return ds


def from_dataset(ds: xr.Dataset) -> SourceGeometry:
    """Inverse of :func:`to_dataset`."""
    x, y = ds["node_x_m"].values, ds["node_y_m"].values
    part_counts = ds["part_node_count"].values
    interior = ds["interior_ring"].values.astype(bool)
    part_end = np.cumsum(part_counts)
    part_start = part_end - part_counts
    counts = ds["node_count"].values
    part = 0
    node = 0
    v = {k: ds[k].values for k in ds.data_vars if ds[k].dims == ("feature",)}
    out = SourceGeometry()
    for i in range(ds.sizes["feature"]):
        rings = []
        end = node + counts[i]
        while node < end:
            s, e = part_start[part], part_end[part]
            rings.append((np.column_stack([x[s:e], y[s:e]]), interior[part]))
            node = e
            part += 1
        if str(v["geometry_type"][i]) == "line":
            geom = LineString(rings[0][0])
        else:
            polys = []
            for coords, hole in rings:
                if hole:
                    polys[-1][1].append(coords)
                else:
                    polys.append((coords, []))
            shapes = [Polygon(s, h) for s, h in polys]
            geom = shapes[0] if len(shapes) == 1 else MultiPolygon(shapes)
        out.features.append(Feature(
            str(v["feature_class"][i]), geom, int(v["source_id"][i]),
            height_m=float(v["height_m"][i]), min_height_m=float(v["min_height_m"][i]),
            width_m=float(v["width_m"][i]), radio_material=str(v["radio_material"][i]),
            roof_shape=str(v["roof_shape"][i]), roof_height_m=float(v["roof_height_m"][i]),
            roof_across=bool(v["roof_across"][i]), levels=float(v["levels"][i]),
            parent_id=int(v["parent_id"][i]), has_parts=bool(v["has_parts"][i])))
    if "origin_latitude_deg" in ds.attrs:
        out.origin = (float(ds.attrs["origin_latitude_deg"]), float(ds.attrs["origin_longitude_deg"]),
                      float(ds.attrs["origin_altitude_m"]))
    out.attribution = str(ds.attrs.get("attribution", ""))
    out.warnings = [w for w in str(ds.attrs.get("source_warnings", "")).split("\n") if w]
    return out


def building_footprints(geom: SourceGeometry) -> list[Polygon]:
    """Footprint polygons of every extruded volume."""
    return [p for f in geom.volumes() for p in polygons_of(f.geometry)]


def ground_elevation_m(geom: SourceGeometry, x, y) -> np.ndarray:
    """The ground surface's height (m, ENU z) at points ``(x, y)``: 0 where the source's ground is
    the plane z = 0; else interpolated linearly over the surface's vertices (the highest one where
    several share an (x, y): a road on the terrain), the nearest vertex's outside their hull."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

    x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    pts = geom.ground_surface_m
    if pts is None or not len(pts):
        return np.zeros(x.shape)
    xy, inv = np.unique(np.round(pts[:, :2], 3), axis=0, return_inverse=True)
    z = np.full(len(xy), -np.inf)
    np.maximum.at(z, inv.ravel(), pts[:, 2])
    q = np.column_stack([x.ravel(), y.ravel()])
    out = LinearNDInterpolator(xy, z)(q) if len(xy) >= 3 else np.full(len(q), np.nan)
    miss = ~np.isfinite(out)
    if miss.any():
        out[miss] = NearestNDInterpolator(xy, z)(q[miss])
    return out.reshape(x.shape)


def inside_buildings(geom: SourceGeometry, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """True where a point lies inside a building's extruded volume (footprint and height band).

    The band runs from ``min_height_m`` to ``height_m``, roof included: under a pitched roof it is
    conservative (a point just above the eaves but outside the roof counts as inside).
    """
    x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
    inside = np.zeros(x.shape, dtype=bool)
    vols = geom.volumes()
    if not vols or x.size == 0:
        return inside
    shapes = [f.geometry for f in vols]
    lo = np.array([0.0 if np.isnan(f.min_height_m) else f.min_height_m for f in vols])
    hi = np.array([f.height_m for f in vols])
    pts = shapely.points(x.ravel(), y.ravel())
    # Spatial index: each point is tested only against the footprints around it.
    pi, vi = shapely.STRtree(shapes).query(pts, predicate="within")
    zf = z.ravel()[pi]
    hit = (zf >= lo[vi]) & (zf <= hi[vi])
    flat = inside.ravel()
    flat[pi[hit]] = True
    return flat.reshape(x.shape)
