"""The project's own procedural city: a grid of blocks with one building each, streets between them."""

from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import LineString

from simart_pipeline.config import ProceduralSource, SceneConfig
from simart_pipeline.scene.geometry import Feature, SourceGeometry


def procedural_layout(src: ProceduralSource, cfg: SceneConfig) -> SourceGeometry:
    """A grid of blocks centred on the origin, one building per block, streets between blocks."""
    rng = np.random.default_rng(src.seed)
    nx, ny = src.blocks
    bw, bh = src.block_size_m
    sw = src.street_width_m
    pitch_x, pitch_y = bw + sw, bh + sw
    x0 = -(nx * pitch_x - sw) / 2
    y0 = -(ny * pitch_y - sw) / 2
    out = SourceGeometry(origin=(cfg.origin.latitude_deg, cfg.origin.longitude_deg, cfg.origin.altitude_m))
    fid = 1
    for j in range(ny):
        for i in range(nx):
            cx0, cy0 = x0 + i * pitch_x, y0 + j * pitch_y
            inset = src.building_inset_m
            poly = shapely.box(cx0 + inset, cy0 + inset, cx0 + bw - inset, cy0 + bh - inset)
            h = float(rng.uniform(*src.building_height_m))
            out.features.append(Feature("building", poly, fid, height_m=round(h, 2), min_height_m=0.0,
                                        radio_material=cfg.materials.building, roof_shape="flat"))
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
