"""Scene construction: building solids and roofs, facade detail, paired meshes of the real extracts,
Sionna RT on them, the ``simart scene build`` command and its refusals."""

import json
import math

import numpy as np
import pytest
import scipy.constants as const
import shapely
import trimesh
from scipy.spatial import cKDTree

from conftest import REPO, SHARED_DATA
from simart_pipeline.vocabulary import SemanticClass
from simart_pipeline.cli import main
from simart_pipeline.config import load_scene_config
from simart_pipeline.radio import materials as radio_materials
from simart_pipeline.scene import build, extrude, geometry, meshes, source
from simart_pipeline.scene.osm import OsmReadError, read_extract
from simart_pipeline.validation import scene_problems

OSM = SHARED_DATA / "osm"
EXTRACTS = ["small_block.osm", "neukolln.osm", "taipei.osm", "helsinki.osm.pbf"]


def _solid_mesh(s: extrude.Solid) -> trimesh.Trimesh:
    return trimesh.Trimesh(s.vertices, s.faces, process=False)


L, W, H, R = 20.0, 10.0, 12.0, 3.0
# Volume under each roof of an L x W footprint, H high, roof rise R (prisms and pyramids).
ROOF_VOLUMES = {"flat": L * W * H, "gabled": L * W * (H - R / 2), "skillion": L * W * (H - R / 2),
                "pyramidal": L * W * (H - 2 * R / 3), "hipped": L * W * (H - R) + R * W * (3 * L - W) / 6}


@pytest.mark.parametrize("shape", sorted(ROOF_VOLUMES))
@pytest.mark.parametrize("angle_deg", [0.0, 37.0])
def test_roof_solids_are_closed_outward_and_have_the_analytic_volume(shape, angle_deg):
    poly = shapely.affinity.rotate(shapely.box(100, 50, 100 + L, 50 + W), angle_deg, origin=(0, 0))
    m = _solid_mesh(extrude.building_solid(poly, 0.0, H, shape, R if shape != "flat" else 0.0))
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume == pytest.approx(ROOF_VOLUMES[shape], rel=1e-9)
    assert m.vertices[:, 2].max() == pytest.approx(H) and m.vertices[:, 2].min() == 0.0
    # the walls stand on the footprint: every footprint corner is a vertex at the bottom and at the eaves
    tree = cKDTree(m.vertices)
    for x, y in poly.exterior.coords:
        assert tree.query([x, y, 0.0])[0] < 1e-9
        assert tree.query([x, y, H - (R if shape in ("gabled", "hipped", "pyramidal") else 0.0)])[0] < 1e-9 \
            or shape == "skillion"


@pytest.mark.parametrize("shape", ["flat", "gabled", "hipped", "pyramidal", "skillion"])
def test_concave_and_courtyard_footprints_stay_watertight_under_any_roof(shape):
    ell = shapely.Polygon([(0, 0), (30, 0), (30, 8), (8, 8), (8, 25), (0, 25)])
    court = shapely.box(0, 0, 30, 24).difference(shapely.box(9, 7, 21, 17))
    for poly in (ell, court):
        m = _solid_mesh(extrude.building_solid(poly, 2.0, 14.0, shape))
        assert m.is_watertight and m.is_winding_consistent
        flat = poly.area * 12.0
        assert 0.5 * flat < m.volume <= flat * (1 + 1e-12)   # the roof only removes, at most half


def test_window_frames_count_face_out_and_stay_off_a_neighbour():
    a, b = shapely.box(0, 0, 12, 9), shapely.box(12, 0, 24, 9)   # sharing the wall x = 12
    sa, sb = extrude.building_solid(a, 0, 9), extrude.building_solid(b, 0, 6)
    walls = np.concatenate([sa.walls, sb.walls])
    inst = np.repeat([1, 2], [len(sa.walls), len(sb.walls)])
    v, f, face_inst = extrude.window_frames(walls, np.full(len(walls), 3.0), inst, [a, b],
                                            np.array([[0, 9], [0, 6]]))
    n = len(f) // 10
    # A: 4 + 3 + 4 + 3 columns x 3 storeys, less the 2 storeys of its shared wall under B's roof;
    # B: (4 + 3) x 2 x 2 storeys, less its whole shared wall (A is taller)
    assert n == (14 * 3 - 3 * 2) + (14 * 2 - 3 * 2)
    assert (np.bincount(face_inst)[1:] == np.array([36, 22]) * 10).all()
    tri = v[f]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    box_centre = v.reshape(n, 8, 3).mean(1)
    out = (tri.mean(1) - np.repeat(box_centre, 10, axis=0))
    assert np.all(np.einsum("ij,ij->i", normals, out) > 0)             # every face points away from its box
    feet = shapely.points(v[:, :2])
    # nothing inside a building: A's top row looks out over B's roof
    assert not np.any(shapely.contains(a, feet) | (shapely.contains(b, feet) & (v[:, 2] < 6.0)))
    assert np.all(shapely.distance(shapely.union_all([a, b]), feet) <= extrude.WINDOW_DEPTH_M + 1e-9)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """Every shared extract built by ``build_scene`` into a temporary directory."""
    root = tmp_path_factory.mktemp("built")
    out = {}
    for name in EXTRACTS:
        assert (OSM / name).is_file(), f"shared test data missing: {OSM / name}"
        d = root / name.split(".")[0]
        info = build.build_scene(OSM / name, d)
        out[name] = (d, info, read_extract(OSM / name))
    return out


@pytest.mark.parametrize("name", EXTRACTS)
def test_extracts_build_with_origin_counts_and_attribution(built, name):
    d, info, geom = built[name]
    assert json.loads((d / "scene.json").read_text()) == info
    assert (info["origin"]["latitude_deg"], info["origin"]["longitude_deg"]) == geom.origin[:2]
    assert "OpenStreetMap contributors" in info["attribution"] and "ODbL" in info["attribution"]
    outlines = geom.of_class("building")
    orphans = [p for p in geom.of_class("building_part") if not p.parent_id]
    assert info["counts"]["buildings"] == len(outlines) + len(orphans)
    assert info["source_features"]["building"] == len(outlines)
    per_mesh = info["counts"]["radio_triangles_per_mesh"]
    assert sum(per_mesh.values()) == info["counts"]["radio_triangles"]
    assert sorted(p.stem for p in (d / "radio" / "meshes").glob("*.ply")) == sorted(per_mesh)
    xml = (d / "radio" / "scene.xml").read_text()
    assert f"latitude {geom.origin[0]!r} deg" in xml and f"longitude {geom.origin[1]!r} deg" in xml
    labels = meshes.load(d)
    assert len(labels.face_class) == len(labels.visual.faces) == info["counts"]["visual_triangles"]


def test_radio_scenes_load_in_plain_sionna_with_their_materials(built):
    import sionna.rt as rt

    from simart_pipeline import engine

    engine.init()
    for name in EXTRACTS:
        d, info, _ = built[name]
        scene = rt.load_scene(str(meshes.radio_scene_file(d)), merge_shapes=False)
        assert set(scene.objects) == set(info["counts"]["radio_triangles_per_mesh"])
        for obj_name, obj in scene.objects.items():
            mat = obj_name.split("_", 1)[1]
            assert radio_materials.material_name(obj.radio_material) == mat
            if mat == "fresh_water":    # a Debye-model material, written at the carrier frequency
                eps, sigma = radio_materials.permittivity_conductivity(mat, info["carrier_frequency_hz"])
                assert float(np.array(obj.radio_material.relative_permittivity).ravel()[0]) == pytest.approx(eps, rel=1e-6)
    assert "water_fresh_water" in info["counts"]["radio_triangles_per_mesh"] or name != "neukolln.osm"


@pytest.mark.parametrize("name", EXTRACTS)
def test_radio_buildings_are_watertight_solids_one_per_footprint(built, name):
    d, _, geom = built[name]
    parts = []
    for ply in (d / "radio" / "meshes").glob("building_*.ply"):
        parts += trimesh.load(ply, process=False, force="mesh").split(only_watertight=False)
    assert len(parts) == sum(len(geometry.polygons_of(f.geometry)) for f in geom.volumes())
    for p in parts:
        assert p.is_watertight and p.is_winding_consistent and p.volume > 0


@pytest.mark.parametrize("name", ["neukolln.osm", "helsinki.osm.pbf"])
def test_building_corners_have_the_same_enu_coordinates_in_both_meshes(built, name):
    d, _, geom = built[name]
    radio = np.concatenate([trimesh.load(p, process=False, force="mesh").vertices
                            for p in (d / "radio" / "meshes").glob("building_*.ply")])
    visual = trimesh.load(d / "visual" / "visual.ply", process=False, force="mesh").vertices
    corners = []
    for f in geom.volumes():
        bottom = 0.0 if np.isnan(f.min_height_m) else f.min_height_m
        for poly in geometry.polygons_of(f.geometry):
            xy = np.asarray(poly.exterior.coords)[:-1]
            corners.append(np.column_stack([xy, np.full(len(xy), bottom)]))
            if f.roof_shape == "flat":
                corners.append(np.column_stack([xy, np.full(len(xy), f.height_m)]))
    corners = np.concatenate(corners)
    # PLY stores float32: the same rounding in both meshes, within 1e-4 m of the source up to 1 km out
    d_radio, i_radio = cKDTree(radio).query(corners)
    d_visual, i_visual = cKDTree(visual).query(corners)
    assert np.max(d_radio) < 1e-4 and np.max(d_visual) < 1e-4
    assert np.array_equal(radio[i_radio], visual[i_visual])
    # and the visual mesh holds every radio vertex: the radio mesh is a simplification of it
    assert np.max(cKDTree(visual).query(radio)[0]) == 0.0


def test_visual_mesh_is_the_radio_mesh_plus_facade_detail(built):
    d, info, geom = built["taipei.osm"]
    m = meshes.load(d)
    bld = m.face_class == SemanticClass.BUILDING
    radio_bld = sum(len(v.faces) for (c, _), v in m.radio.items() if c == "building")
    assert bld.sum() > 5 * radio_bld      # window frames
    assert set(np.unique(m.face_instance[bld])) == {f.instance_id for f in geom.volumes()}
    assert len(m.visual.faces) - bld.sum() == info["counts"]["radio_triangles"] - radio_bld  # same ground


def _street_points(geom, height_m: float, min_length_m: float = 40.0):
    """Two points over the longest straight road segment clear of every building."""
    feet = shapely.union_all(geometry.building_footprints(geom)).buffer(1.0)
    best = None
    for f in geom.of_class("road"):
        if not isinstance(f.geometry, shapely.LineString) or f.width_m < 6:
            continue
        xy = np.asarray(f.geometry.coords)
        for a, b in zip(xy[:-1], xy[1:]):
            length = float(np.hypot(*(b - a)))
            seg = shapely.LineString([a + 0.1 * (b - a), a + 0.9 * (b - a)])
            if length >= min_length_m and not seg.intersects(feet) and (best is None or length > best[0]):
                best = (length, seg)
    assert best is not None, "no straight street segment clear of buildings"
    (x0, y0), (x1, y1) = best[1].coords
    return np.array([x0, y0, height_m]), np.array([x1, y1, 1.5])


def test_sionna_finds_the_los_path_and_the_ground_reflection_in_a_real_street(built):
    import sionna.rt as rt

    from simart_pipeline import engine

    engine.init()
    d, info, geom = built["neukolln.osm"]
    tx, rx = _street_points(geom, 10.0)
    scene = rt.load_scene(str(meshes.radio_scene_file(d)), merge_shapes=False)
    scene.frequency = info["carrier_frequency_hz"]
    scene.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    scene.add(rt.Transmitter("tx", position=[float(c) for c in tx]))
    scene.add(rt.Receiver("rx", position=[float(c) for c in rx]))
    paths = rt.PathSolver()(scene, max_depth=1, samples_per_src=10**5, synthetic_array=True, los=True,
                            specular_reflection=True, diffuse_reflection=False, refraction=False, seed=1)
    valid = np.array(paths.valid).ravel().astype(bool)
    tau = np.array(paths.tau).ravel()[valid]
    inter = np.array(paths.interactions).reshape(1, -1)[0][valid]
    horizontal = np.hypot(*(rx[:2] - tx[:2]))
    los = np.hypot(horizontal, tx[2] - rx[2]) / const.c
    ground = np.hypot(horizontal, tx[2] + rx[2]) / const.c     # the image of tx under z = 0
    assert np.any((inter == 0) & np.isclose(tau, los, rtol=1e-6))
    assert np.any((inter == 1) & np.isclose(tau, ground, rtol=1e-6))


def test_cli_builds_refuses_to_overwrite_and_replaces_with_force(tmp_path, capsys):
    out = tmp_path / "block"
    assert main(["scene", "build", str(OSM / "small_block.osm"), "--out", str(out)]) == 0
    first = (out / "scene.json").read_text()
    assert "OpenStreetMap contributors" in capsys.readouterr().out
    assert main(["scene", "build", str(OSM / "small_block.osm"), "--out", str(out), "--origin", "48.136,10.07"]) == 1
    assert "not empty" in capsys.readouterr().err and (out / "scene.json").read_text() == first
    assert main(["scene", "build", str(OSM / "small_block.osm"), "--out", str(out), "--origin", "48.136,10.07",
                 "--bbox", "10.068,48.135,10.071,48.137", "--force"]) == 0
    info = json.loads((out / "scene.json").read_text())
    assert info["origin"] == {"latitude_deg": 48.136, "longitude_deg": 10.07, "altitude_m": 0.0}
    assert info["bbox_deg"] == [10.068, 48.135, 10.071, 48.137]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["block"]     # nothing left aside


def test_bad_sources_leave_nothing_behind_and_keep_the_old_build(tmp_path, capsys):
    bad = tmp_path / "broken.osm"
    bad.write_text("<osm version='0.6'><node id='1' lat='48.1' lon='10.0'><tag k='a'")
    out = tmp_path / "new"
    assert main(["scene", "build", str(bad), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "XML parsing error" in err and not out.exists()
    good = tmp_path / "good"
    build.build_scene(OSM / "small_block.osm", good)
    before = (good / "scene.json").read_text()
    with pytest.raises(OsmReadError, match="broken.osm"):
        build.build_scene(bad, good, force=True)
    assert (good / "scene.json").read_text() == before and meshes.load(good).counts()["buildings"] > 20
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.osm", "good"]   # nothing aside
    with pytest.raises(build.SceneBuildError, match="unknown source type"):
        build.build_scene(tmp_path / "scene.txt", tmp_path / "x")
    with pytest.raises(build.SceneBuildError, match="no such file"):
        build.build_scene(tmp_path / "missing.osm", tmp_path / "x")


def test_cli_dispatches_a_mesh_file_to_the_mesh_importer(tmp_path):
    box = trimesh.creation.box(extents=(20.0, 12.0, 15.0))
    box.apply_translation([0, 0, 7.5])
    src = tmp_path / "block.obj"
    box.export(src)
    assert main(["scene", "build", str(src), "--out", str(tmp_path / "out"), "--origin", "60.17,24.94"]) == 0
    info = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert info["source"]["kind"] == "mesh" and info["origin"]["latitude_deg"] == 60.17
    assert meshes.radio_scene_file(tmp_path / "out").is_file()


def test_urban_scene_validates_and_the_asset_builds_what_the_cli_builds(tmp_path):
    scene_dir = REPO / "scenes" / "urban"
    cfg, problems = scene_problems(scene_dir)
    assert problems == [], problems
    cfg = load_scene_config(scene_dir)
    geom = source.build_source_geometry(cfg, scene_dir)
    assert {"building", "building_part", "road", "parking", "water", "vegetation"} <= {f.feature_class for f in geom.features}
    assert {f.roof_shape for f in geom.volumes()} >= {"flat", "gabled", "hipped", "pyramidal", "skillion"}
    asset = build.paired_meshes_for_scene(cfg, scene_dir, geometry.from_dataset(geometry.to_dataset(geom)))
    origin = (cfg.origin.latitude_deg, cfg.origin.longitude_deg, cfg.origin.altitude_m)
    info = build.build_scene(scene_dir / cfg.source.path, tmp_path / "urban", origin=origin,
                             frequency_hz=cfg.ofdm.carrier_frequency_hz)
    assert asset.meshes.counts() == info["counts"]
    # the tower: an outline whose parts carry its shape is not extruded itself
    tower = [f for f in geom.of_class("building") if f.has_parts]
    assert len(tower) == 1 and tower[0] not in geom.volumes()
    bld = asset.meshes.face_class == SemanticClass.BUILDING
    top = asset.meshes.visual.vertices[asset.meshes.visual.faces[bld & (asset.meshes.face_instance
                                                                        == tower[0].source_id)]][..., 2].max()
    assert top == pytest.approx(max(p.height_m for p in geom.of_class("building_part")
                                    if p.parent_id == tower[0].source_id))
    assert math.isclose(geom.origin[0], cfg.origin.latitude_deg)
