"""Source geometry: the ``osm_extract`` asset's dataset, whatever the scene's source.

Features (buildings, roads, ground) are 2D shapes in the local ENU frame, stored as CF contiguous
ragged arrays (CF 1.8 section 7.5): every polygon ring's nodes one after another along ``node``,
``node_count`` nodes per feature. Polygons are stored as their exterior ring (holes are a later
refinement of the OSM reader); roads as their centre line with a width.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
import xarray as xr
from shapely.geometry import LineString, Polygon

from simart_pipeline.config import ProceduralSource, SceneConfig

FEATURE_CLASSES = ("building", "road", "ground")


@dataclass
class Feature:
    feature_class: str
    geometry: Polygon | LineString
    source_id: int
    height_m: float = np.nan
    min_height_m: float = np.nan
    width_m: float = np.nan
    radio_material: str = ""


@dataclass
class SourceGeometry:
    features: list[Feature] = field(default_factory=list)

    def of_class(self, cls: str) -> list[Feature]:
        return [f for f in self.features if f.feature_class == cls]


def procedural_layout(src: ProceduralSource, cfg: SceneConfig) -> SourceGeometry:
    """A grid of blocks centred on the origin, one building per block, streets between blocks."""
    rng = np.random.default_rng(src.seed)
    nx, ny = src.blocks
    bw, bh = src.block_size_m
    sw = src.street_width_m
    pitch_x, pitch_y = bw + sw, bh + sw
    x0 = -(nx * pitch_x - sw) / 2
    y0 = -(ny * pitch_y - sw) / 2
    out = SourceGeometry()
    fid = 1
    for j in range(ny):
        for i in range(nx):
            cx0, cy0 = x0 + i * pitch_x, y0 + j * pitch_y
            inset = src.building_inset_m
            poly = shapely.box(cx0 + inset, cy0 + inset, cx0 + bw - inset, cy0 + bh - inset)
            h = float(rng.uniform(*src.building_height_m))
            out.features.append(Feature("building", poly, fid, height_m=round(h, 2), min_height_m=0.0,
                                        radio_material=cfg.materials.building))
            fid += 1
    half_x, half_y = nx * pitch_x / 2, ny * pitch_y / 2
    # Streets: the centre lines between and around blocks, full length.
    for k in range(nx + 1):
        x = x0 - sw / 2 + k * pitch_x
        out.features.append(Feature("road", LineString([(x, -half_y), (x, half_y)]), fid, width_m=sw,
                                    radio_material=cfg.materials.road))
        fid += 1
    for k in range(ny + 1):
        y = y0 - sw / 2 + k * pitch_y
        out.features.append(Feature("road", LineString([(-half_x, y), (half_x, y)]), fid, width_m=sw,
                                    radio_material=cfg.materials.road))
        fid += 1
    margin = sw
    out.features.append(Feature("ground", shapely.box(-half_x - margin, -half_y - margin,
                                                      half_x + margin, half_y + margin), fid,
                                radio_material=cfg.materials.ground))
    return out


def to_dataset(geom: SourceGeometry) -> xr.Dataset:
    """The CF ragged-array dataset of ``geom``."""
    xs, ys, counts = [], [], []
    for f in geom.features:
        coords = np.asarray(f.geometry.exterior.coords if isinstance(f.geometry, Polygon)
                            else f.geometry.coords)[:, :2]
        xs.append(coords[:, 0])
        ys.append(coords[:, 1])
        counts.append(len(coords))
    nan_attr = "not applicable to this feature class"
    fs = geom.features
    ds = xr.Dataset(
        {
            "node_x_m": ("node", np.concatenate(xs), {"units": "m", "long_name": "node east (ENU)"}),
            "node_y_m": ("node", np.concatenate(ys), {"units": "m", "long_name": "node north (ENU)"}),
            "node_count": ("feature", np.asarray(counts, np.int64),
                           {"long_name": "nodes of each feature, in order along node",
                            "sample_dimension": "node"}),
            "feature_class": ("feature", np.asarray([f.feature_class for f in fs]),
                              {"long_name": "semantic class", "flag_values": " ".join(FEATURE_CLASSES)}),
            "geometry_type": ("feature", np.asarray(["polygon" if isinstance(f.geometry, Polygon)
                                                     else "line" for f in fs]),
                              {"long_name": "polygon (closed exterior ring) or line (centre line)"}),
            "source_id": ("feature", np.asarray([f.source_id for f in fs], np.int64),
                          {"long_name": "OSM id, or generated id for procedural scenes"}),
            "height_m": ("feature", np.asarray([f.height_m for f in fs], np.float64),
                         {"units": "m", "long_name": "top of the extruded footprint above ground",
                          "nan_means": nan_attr}),
            "min_height_m": ("feature", np.asarray([f.min_height_m for f in fs], np.float64),
                             {"units": "m", "long_name": "bottom of the extruded footprint",
                              "nan_means": nan_attr}),
            "width_m": ("feature", np.asarray([f.width_m for f in fs], np.float64),
                        {"units": "m", "long_name": "road width", "nan_means": nan_attr}),
            "radio_material": ("feature", np.asarray([f.radio_material for f in fs]),
                               {"long_name": "ITU-R P.2040 radio material"}),
        },
        coords={"feature": np.arange(len(fs))},
    )
    return ds


def from_dataset(ds: xr.Dataset) -> SourceGeometry:
    """Inverse of :func:`to_dataset`."""
    ends = np.cumsum(ds["node_count"].values)
    starts = ends - ds["node_count"].values
    x, y = ds["node_x_m"].values, ds["node_y_m"].values
    out = SourceGeometry()
    for i in range(ds.sizes["feature"]):
        pts = np.column_stack([x[starts[i]:ends[i]], y[starts[i]:ends[i]]])
        geom = Polygon(pts) if str(ds["geometry_type"].values[i]) == "polygon" else LineString(pts)
        out.features.append(Feature(
            str(ds["feature_class"].values[i]), geom, int(ds["source_id"].values[i]),
            float(ds["height_m"].values[i]), float(ds["min_height_m"].values[i]),
            float(ds["width_m"].values[i]), str(ds["radio_material"].values[i])))
    return out


def build_source_geometry(cfg: SceneConfig, scene_dir) -> SourceGeometry:
    """Dispatch on the scene's source kind."""
    if cfg.source.kind == "procedural":
        return procedural_layout(cfg.source, cfg)
    if cfg.source.kind == "osm":
        from simart_pipeline.scene.osm import read_osm
        return read_osm(cfg, scene_dir)
    raise NotImplementedError(
        f"scene {cfg.name}: source kind 'mesh' is not supported yet (the scene-construction issue adds "
        "the user-mesh pipeline); use 'procedural' or 'osm'")


def building_footprints(geom: SourceGeometry) -> list[Polygon]:
    return [f.geometry for f in geom.of_class("building")]


def inside_buildings(geom: SourceGeometry, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """True where a point lies inside a building's extruded volume (footprint and height band)."""
    inside = np.zeros(np.shape(x), dtype=bool)
    for f in geom.of_class("building"):
        hit = shapely.contains_xy(f.geometry, x, y)
        lo = 0.0 if np.isnan(f.min_height_m) else f.min_height_m
        inside |= hit & (z >= lo) & (z <= f.height_m)
    return inside
