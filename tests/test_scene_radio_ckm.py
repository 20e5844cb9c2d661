"""Scene meshes, Sionna RT tracing and CKM tiles against geometry with known answers."""

from pathlib import Path

import numpy as np
import pytest
import scipy.constants as const
import shapely
import yaml

from simart_pipeline import stores
from simart_pipeline.ckm.grid import cell_centres, scene_tiles, tile_slices
from simart_pipeline.ckm.layers import tile_layers
from simart_pipeline.config import SceneConfig, load_scene_config
from simart_pipeline.radio.tracer import RadioScene
from simart_pipeline.scene import geometry, meshes


def _cfg(scene_dir, edit=None) -> SceneConfig:
    raw = yaml.safe_load((Path(scene_dir) / "scene.yaml").read_text())
    if edit:
        edit(raw)
    return SceneConfig.model_validate(raw)


def _iso(raw):
    for b in raw["base_stations"]:
        b["array"] = {"rows": 1, "cols": 1, "pattern": "iso"}


@pytest.fixture(scope="module")
def tiny_built(tmp_path_factory):
    from conftest import TESTS

    cfg = load_scene_config(TESTS / "scenes" / "tiny")
    geom = geometry.build_source_geometry(cfg, None)
    m = meshes.build_meshes(geom)
    out = tmp_path_factory.mktemp("pm") / "tiny"
    stores.write_directory(out, lambda d: meshes.save(m, d, {"name": "tiny"}, cfg.materials.thickness_m))
    return cfg, geom, m, out


def test_extruded_buildings_have_footprint_times_height_volume(tiny_built):
    _, geom, m, _ = tiny_built
    buildings = m.radio[("building", "concrete")]
    expected = sum(f.geometry.area * (f.height_m - f.min_height_m) for f in geom.of_class("building"))
    assert buildings.is_watertight
    assert buildings.volume == pytest.approx(expected, rel=1e-9)


def test_ground_and_roads_tile_the_ground_without_overlap(tiny_built):
    _, geom, m, _ = tiny_built
    flat_area = sum(mesh.area for (cls, _), mesh in m.radio.items() if cls in ("road", "ground"))
    ground = shapely.union_all([g.geometry for g in geom.of_class("ground")])
    footprints = shapely.union_all([b.geometry for b in geom.of_class("building")])
    assert flat_area == pytest.approx(ground.area - footprints.area, rel=1e-9)
    for (cls, _), mesh in m.radio.items():
        if cls in ("road", "ground"):
            assert np.all(mesh.face_normals[:, 2] > 0.999)  # facing up, at z = 0
            assert np.allclose(mesh.vertices[:, 2], 0.0)


def test_visual_faces_carry_class_and_instance(tiny_built):
    _, geom, m, _ = tiny_built
    assert len(m.face_class) == len(m.visual.faces) == len(m.face_instance)
    ids = {f.source_id for f in geom.of_class("building")}
    bld = m.face_class == meshes.SemanticClass.BUILDING
    assert set(np.unique(m.face_instance[bld])) == ids
    # every building face lies inside (or on) its own footprint
    centres = m.visual.triangles_center
    for f in geom.of_class("building"):
        sel = bld & (m.face_instance == f.source_id)
        assert np.all(shapely.distance(f.geometry, shapely.points(centres[sel, :2])) < 1e-9)


def test_geometry_dataset_round_trip(tiny_built):
    _, geom, _, _ = tiny_built
    back = geometry.from_dataset(geometry.to_dataset(geom))
    assert [f.source_id for f in back.features] == [f.source_id for f in geom.features]
    for a, b in zip(back.features, geom.features):
        assert a.geometry.equals_exact(b.geometry, 1e-12) and a.feature_class == b.feature_class


def test_radio_scene_loads_in_plain_sionna_with_materials(tiny_built):
    _, _, _, out = tiny_built
    import sionna.rt as rt

    from simart_pipeline import engine

    engine.init()
    scene = rt.load_scene(str(meshes.radio_scene_file(out)), merge_shapes=False)
    types = {n: o.radio_material.itu_type for n, o in scene.objects.items()}
    assert types == {"building_concrete": "concrete", "ground_medium_dry_ground": "medium_dry_ground",
                     "road_concrete": "concrete"}


def test_free_space_los_matches_friis_and_light_delay(tiny_scene):
    cfg = _cfg(tiny_scene, _iso)
    radio = RadioScene(None, cfg)  # empty scene: only the line of sight
    tx = np.array([[0.0, 0.0, 10.0]])
    d = np.array([5.0, 50.0, 500.0, 2000.0])
    rx = np.column_stack([d, np.zeros_like(d), np.full_like(d, 10.0)])
    p = radio.trace(tx, np.zeros((1, 3)), rx)
    assert p.valid.sum(-1).ravel().tolist() == [1, 1, 1, 1] and p.los[..., 0].all()
    lam = const.c / cfg.ofdm.carrier_frequency_hz
    gain = np.abs(p.a[:, 0, 0, 0, 0]) ** 2
    np.testing.assert_allclose(gain, (lam / (4 * np.pi * d)) ** 2, rtol=1e-5)
    np.testing.assert_allclose(p.tau_s[:, 0, 0], d / const.c, rtol=1e-6)


def test_ground_reflection_delay_and_sorting(tiny_scene, tmp_path):
    """Flat ground only: two paths, LoS then the specular ground bounce at the image distance."""
    cfg = _cfg(tiny_scene, _iso)
    geom = geometry.SourceGeometry([geometry.Feature("ground", shapely.box(-500, -500, 500, 500), 1,
                                                     radio_material="medium_dry_ground")])
    m = meshes.build_meshes(geom)
    meshes.save(m, tmp_path / "flat", {}, 0.2)
    radio = RadioScene(meshes.radio_scene_file(tmp_path / "flat"), cfg)
    h_tx, h_rx, d = 20.0, 1.5, 100.0
    p = radio.trace(np.array([[0, 0, h_tx]]), np.zeros((1, 3)), np.array([[d, 0, h_rx]]))
    assert int(p.valid.sum()) == 2
    tau = p.tau_s[0, 0, :2]
    np.testing.assert_allclose(tau, [np.hypot(d, h_tx - h_rx) / const.c, np.hypot(d, h_tx + h_rx) / const.c],
                               rtol=1e-6)
    assert p.los[0, 0, 0] and not p.los[0, 0, 1]
    assert p.interaction[0, 0, 0, 1] == 1  # specular reflection
    assert np.isnan(p.tau_s[0, 0, 2:]).all() and (p.a[..., 2:] == 0).all()


def test_tracing_is_reproducible_and_sorted(tiny_built, tiny_scene):
    cfg, _, _, out = tiny_built
    radio = RadioScene(meshes.radio_scene_file(out), cfg)
    tx = np.array([b.position_m for b in cfg.base_stations])
    rx = np.array([[-30.0, -18.0, 1.5], [0.0, -18.0, 1.5], [25.0, 10.0, 1.5]])
    p1 = radio.trace(tx, np.zeros((2, 3)), rx)
    p2 = radio.trace(tx, np.zeros((2, 3)), rx)
    assert np.array_equal(p1.a, p2.a) and np.array_equal(p1.tau_s, p2.tau_s, equal_nan=True)
    assert p1.valid.sum() > 6
    for i in range(3):
        for j in range(2):
            v = p1.valid[i, j]
            assert not np.any(v[1:] & ~v[:-1])  # valid paths first
            assert np.all(np.diff(p1.tau_s[i, j][v]) >= 0)  # then by delay


def test_rain_wets_the_ground_only(tiny_built):
    cfg, _, _, out = tiny_built
    dry = RadioScene(meshes.radio_scene_file(out), cfg, "sunny").radio_materials()
    wet = RadioScene(meshes.radio_scene_file(out), cfg, "rainy").radio_materials()
    assert dry["ground_medium_dry_ground"] == "medium_dry_ground"
    assert wet["ground_medium_dry_ground"] == "wet_ground"
    assert wet["building_concrete"] == dry["building_concrete"] == "concrete"


def test_ckm_tiles_partition_the_grid_and_match_one_full_tile(tiny_built, tiny_scene):
    cfg, geom, _, out = tiny_built
    radio = RadioScene(meshes.radio_scene_file(out), cfg)
    rows, cols = cfg.ckm.shape
    seen = np.zeros((rows, cols), int)
    tiles = {}
    for key in reversed(scene_tiles(cfg.ckm)):  # order must not matter
        sl = tile_slices(cfg.ckm, key)
        seen[sl] += 1
        tiles[key] = tile_layers(radio, cfg, geom, key)
    assert np.all(seen == 1)
    full_cfg = _cfg(tiny_scene, lambda raw: raw["ckm"].update(tiles=[1, 1]))
    full = tile_layers(RadioScene(meshes.radio_scene_file(out), full_cfg), full_cfg, geom, "r0c0")
    for key, ds in tiles.items():
        sl = tile_slices(cfg.ckm, key)
        ref = full.isel(y=sl[0], x=sl[1])
        np.testing.assert_array_equal(ds["path_gain_db"].values, ref["path_gain_db"].values)
        np.testing.assert_array_equal(ds["los"].values, ref["los"].values)
    # indoor cells are masked and never traced
    y, x = cell_centres(cfg.ckm)
    indoor = full["cell_inside_building"].values
    assert indoor.any() and full.attrs["cells_traced"] == int((~indoor).sum())
    assert np.isnan(full["path_gain_db"].values[:, indoor]).all()
    assert not full["has_path"].values[:, indoor].any()


def test_ckm_tile_outside_scene_tiling_is_empty_and_needs_no_tracer(tiny_built):
    cfg, geom, _, _ = tiny_built
    ds = tile_layers(None, cfg, geom, "r3c3")
    assert ds.sizes["y"] == 0 and ds.sizes["x"] == 0 and ds.attrs["in_scene_tiling"] == 0


def test_ckm_free_space_gain_is_friis(tiny_scene):
    cfg = _cfg(tiny_scene, lambda raw: (_iso(raw), raw["ckm"].update(tiles=[1, 1])))
    geom = geometry.SourceGeometry()
    ds = tile_layers(RadioScene(None, cfg), cfg, geom, "r0c0")
    lam = const.c / cfg.ofdm.carrier_frequency_hz
    for i, b in enumerate(cfg.base_stations):
        xx, yy = np.meshgrid(ds["x"].values, ds["y"].values)
        d = np.sqrt((xx - b.position_m[0]) ** 2 + (yy - b.position_m[1]) ** 2 + (cfg.ckm.height_m - b.position_m[2]) ** 2)
        np.testing.assert_allclose(ds["path_gain_db"].values[i], 20 * np.log10(lam / (4 * np.pi * d)), atol=1e-3)
        np.testing.assert_allclose(ds["toa_s"].values[i], d / const.c, rtol=1e-6)
    assert ds["los"].values.all()
