"""Scene meshes, Sionna RT tracing and CKM tiles against geometry with known answers."""


import numpy as np
import pytest
import shapely

from conftest import scene_config

from simart_pipeline.vocabulary import SemanticClass
from simart_pipeline.scene import extrude, geometry, meshes


_cfg = scene_config  # the scene's config after an edit of its raw YAML


def _iso(raw):
    for b in raw["base_stations"]:
        b["array"] = {"rows": 1, "cols": 1, "pattern": "iso"}


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
    bld = m.face_class == SemanticClass.BUILDING
    assert set(np.unique(m.face_instance[bld])) == ids
    # every building face lies inside (or on) its own footprint, window frames at most their depth out
    centres = m.visual.triangles_center
    for f in geom.of_class("building"):
        sel = bld & (m.face_instance == f.source_id)
        dist = shapely.distance(f.geometry, shapely.points(centres[sel, :2]))
        assert np.all(dist < extrude.WINDOW_DEPTH_M + 1e-9) and (dist > 0).any()


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
