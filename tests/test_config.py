"""The scene config schema: defaults, every problem reported with file and key path."""

import pytest
import yaml

from simart_pipeline.config import ConfigError, load_scene_config
from simart_pipeline.validation import scene_problems


def _edit(scene_dir, fn):
    path = scene_dir / "scene.yaml"
    raw = yaml.safe_load(path.read_text())
    fn(raw)
    path.write_text(yaml.safe_dump(raw))
    return path


def test_demo_and_tiny_scenes_validate(tiny_scene):
    from conftest import REPO

    for d in (REPO / "scenes" / "demo", tiny_scene):
        cfg, problems = scene_problems(d)
        assert problems == [], problems
        assert cfg.ofdm.num_subcarriers == 12 * cfg.ofdm.num_resource_blocks


def test_numerology_derives_bandwidth(tiny_scene):
    cfg = load_scene_config(tiny_scene)
    # TS 38.211: 15 * 2**mu kHz; mu = 1 -> 30 kHz; 4 RBs x 12 subcarriers
    assert cfg.ofdm.subcarrier_spacing_hz == 30e3
    assert cfg.ofdm.bandwidth_hz == 48 * 30e3


def test_unknown_key_and_bad_values_all_reported_with_paths(tiny_scene):
    def bad(raw):
        raw["platforms"][0]["sensors"][0]["rate_hz"] = -1
        raw["ray_tracing"]["max_dept"] = 3          # typo
        raw["materials"] = {"building": "unobtainium"}
        raw["base_stations"][0]["array"]["rows"] = 0

    path = _edit(tiny_scene, bad)
    with pytest.raises(ConfigError) as err:
        load_scene_config(tiny_scene)
    text = str(err.value)
    assert all(line.startswith(f"{path}: ") for line in err.value.problems)
    assert "platforms.0.sensors.0.rate_hz" in text
    assert "ray_tracing.max_dept" in text and "Extra inputs are not permitted" in text
    assert "materials" in text and "unobtainium" in text
    assert "base_stations.0.array.rows" in text
    assert len(err.value.problems) == 4


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(ConfigError, match="no scene.yaml"):
        load_scene_config(tmp_path)
    (tmp_path / "scene.yaml").write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_scene_config(tmp_path)
    (tmp_path / "scene.yaml").write_text("- a list\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_scene_config(tmp_path)


def test_name_must_match_directory_and_osm_source_must_exist(tiny_scene):
    def bad(raw):
        raw["name"] = "other"
        raw["source"] = {"kind": "osm", "path": "missing.osm"}

    _edit(tiny_scene, bad)
    with pytest.raises(ConfigError) as err:
        load_scene_config(tiny_scene)
    assert any("name:" in p and "'other'" in p for p in err.value.problems)
    assert any("source.path: file not found" in p and "missing.osm" in p for p in err.value.problems)


def test_devices_inside_buildings_are_problems(tiny_scene):
    cfg = load_scene_config(tiny_scene)

    def bad(raw):
        # The first block's building spans x in [-37, -9] (blocks 30 m wide, 16 m streets, 2 m inset).
        raw["base_stations"][0]["position_m"] = [-20.0, 0.0, 5.0]
        raw["platforms"][0]["trajectory"]["waypoints_m"][1] = [-20.0, 0.0, 1.5]

    _edit(tiny_scene, bad)
    _, problems = scene_problems(tiny_scene)
    assert any(p.endswith("is inside a building") and "base_stations.0.position_m" in p for p in problems)
    assert any("platforms.0.trajectory.waypoints_m.1" in p for p in problems)
    assert cfg.name == "tiny"


def test_devices_and_grid_beyond_the_ground_are_problems(tiny_scene):
    import shapely

    from simart_pipeline.scene import source

    cfg = load_scene_config(tiny_scene)
    ground = shapely.union_all([g.geometry for g in source.build_source_geometry(cfg, tiny_scene).of_class("ground")])
    x0, y0, x1, y1 = ground.bounds
    ckm_w, ckm_h = cfg.ckm.size_m
    assert ckm_h < y1 - y0  # the grid's rows stay inside: half of it beyond x1 is half its area

    def beyond(raw):
        raw["base_stations"][0]["position_m"] = [x1 + 1.0, 0.0, 5.0]
        raw["base_stations"][1]["position_m"] = [x1, 0.0, 5.0]  # on the edge: held
        raw["platforms"][0]["trajectory"]["waypoints_m"][1] = [0.0, y0 - 2.0, 1.5]
        raw["ckm"]["center_m"] = [x1, (y0 + y1) / 2]

    _edit(tiny_scene, beyond)
    _, problems = scene_problems(tiny_scene)
    ours = [p for p in problems if "beyond the scene's ground" in p]
    assert len(ours) == 3, problems
    assert "base_stations.0.position_m" in ours[0] and f"{x1 + 1.0}" in ours[0]
    assert "platforms.0.trajectory.waypoints_m.1" in ours[1]
    assert "ckm: 50 % of the grid" in ours[2] and "ckm.size_m" in ours[2]
    assert all(str(tiny_scene / "scene.yaml") in p for p in ours)


def test_config_digest_is_stable_and_sensitive(tiny_scene):
    a = load_scene_config(tiny_scene).digest()
    assert a == load_scene_config(tiny_scene).digest()
    _edit(tiny_scene, lambda raw: raw["ray_tracing"].update(seed=7))
    assert load_scene_config(tiny_scene).digest() != a


def test_devices_must_share_one_array(tiny_scene):
    _edit(tiny_scene, lambda raw: raw["base_stations"][1]["array"].update(rows=4))
    with pytest.raises(ConfigError, match="same array"):
        load_scene_config(tiny_scene)
