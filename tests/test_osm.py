"""The first OSM reader on a real extract (../shared/data/osm, ODbL): heights, projection, errors."""

import numpy as np
import osmium
import pymap3d
import pytest
import yaml

from conftest import SHARED_DATA
from simart_pipeline.config import load_scene_config
from simart_pipeline.scene import geometry, meshes
from simart_pipeline.scene.osm import building_heights, parse_length_m

SMALL_BLOCK = SHARED_DATA / "osm" / "small_block.osm"


@pytest.mark.parametrize("text,metres", [("12", 12.0), ("12 m", 12.0), ("12.5m", 12.5), ("40'", 12.192),
                                         ("40 ft", 12.192), ("3,5", 3.5), ("tall", None), (None, None)])
def test_parse_length(text, metres):
    assert parse_length_m(text) == (pytest.approx(metres) if metres is not None else None)


def test_height_rules():
    assert building_heights({"height": "21 m"}, 10, 3) == (0.0, 21.0)
    assert building_heights({"building:levels": "4", "roof:levels": "1"}, 10, 3) == (0.0, 15.0)
    assert building_heights({"building:levels": "4", "building:min_level": "1"}, 10, 3) == (3.0, 12.0)
    assert building_heights({}, 10, 3) == (0.0, 10.0)


def _osm_scene(tmp_path, osm_path):
    d = tmp_path / "osm_scene"
    d.mkdir()
    (d / "scene.yaml").write_text(yaml.safe_dump({
        "name": "osm_scene", "source": {"kind": "osm", "path": str(osm_path)},
        "origin": {"latitude_deg": 48.136, "longitude_deg": 10.069, "altitude_m": 0.0},
        "base_stations": [{"name": "bs0", "position_m": [0, 0, 50]}],
        "platforms": [{"name": "p0", "kind": "pedestrian",
                       "trajectory": {"waypoints_m": [[0, 0, 60], [1, 0, 60]], "speed_mps": 1}}],
        "clock": {"duration_s": 1}}))
    return d


def test_small_block_buildings_heights_and_projection(tmp_path):
    assert SMALL_BLOCK.is_file(), f"shared test data missing: {SMALL_BLOCK}"
    d = _osm_scene(tmp_path, SMALL_BLOCK)
    cfg = load_scene_config(d)
    geom = geometry.build_source_geometry(cfg, d)
    buildings = {f.source_id: f for f in geom.of_class("building")}
    assert len(buildings) >= 30 and geom.of_class("road")
    # cross-check against the raw file: closed building ways, their levels and first node position
    checked = 0
    for obj in osmium.FileProcessor(str(SMALL_BLOCK)).with_locations():
        if obj.is_way() and "building" in obj.tags and obj.id in buildings:
            f = buildings[obj.id]
            levels = obj.tags.get("building:levels")
            expected_h = float(levels) * cfg.source.storey_height_m if levels else cfg.source.default_building_height_m
            if "height" not in obj.tags:
                assert f.height_m == pytest.approx(expected_h)
            node = obj.nodes[0]
            e, n, _ = pymap3d.geodetic2enu(node.lat, node.lon, 0.0, 48.136, 10.069, 0.0)
            ring = np.asarray(f.geometry.exterior.coords)
            assert np.min(np.hypot(ring[:, 0] - e, ring[:, 1] - n)) < 1e-6
            checked += 1
    assert checked >= 25
    m = meshes.build_meshes(geom)
    assert m.counts()["buildings"] == len(buildings)


def test_malformed_osm_is_refused_with_the_file_name(tmp_path):
    bad = tmp_path / "broken.osm"
    bad.write_text("<osm version='0.6'><node id='1' lat='48.1' lon='10.0'><tag k='a'")
    d = _osm_scene(tmp_path, bad)
    cfg = load_scene_config(d)
    with pytest.raises(ValueError, match="broken.osm"):
        geometry.build_source_geometry(cfg, d)
