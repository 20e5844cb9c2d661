"""A Mitsuba/Sionna scene XML as a scene source (``kind: sionna_xml``, docs/sionna-scenes.md): the
shapes become the visual and the radio mesh with their own radio materials, and the radio scene the
pipeline writes traces like the original file."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from simart_pipeline import stores, validation, versions
from simart_pipeline.config import ConfigError, SionnaXmlSource, load_scene_config
from simart_pipeline.scene import geometry, meshes
from simart_pipeline.scene.source import build_source_geometry
from simart_pipeline.scene.sionna_xml import (SionnaXmlError, build_from_sionna_xml, referenced_files,
                                              source_geometry_from_sionna_xml)
from simart_pipeline.vocabulary import SPEED_OF_LIGHT_MPS, SemanticClass

FREQUENCY_HZ = 3.5e9
CLASSES = {"car*": "vehicle", "floor": "ground", "itu_brick": "building"}


def _box(lo, hi) -> trimesh.Trimesh:
    return trimesh.creation.box(bounds=np.array([lo, hi], float))


def _plane(half: float) -> trimesh.Trimesh:
    v = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


# shape id -> (mesh, BSDF id); the BSDFs show every form the reader accepts
SHAPES = {
    "tower": (_box((-20, 5, 0), (-5, 20, 30)), "concrete"),      # itu-radio-material, $default thickness
    "hall": (_box((5, 5, 0), (25, 20, 12)), "mat-itu_brick"),    # Blender: named itu_, twosided diffuse
    "car_1": (_box((0, -4, 0), (4.5, -2, 1.5)), "paint"),        # radio-material, explicit parameters
    "floor": (_plane(40.0), "ground"),                           # itu type wet ground
}
BSDFS = """
  <default name="wall" value="0.25"/>
  <bsdf type="itu-radio-material" id="concrete">
    <string name="type" value="concrete"/><float name="thickness" value="$wall"/>
  </bsdf>
  <bsdf type="twosided" id="mat-itu_brick">
    <bsdf type="diffuse"><rgb name="reflectance" value="0.6 0.2 0.1"/></bsdf>
  </bsdf>
  <bsdf type="radio-material" id="paint">
    <float name="relative_permittivity" value="3.5"/><float name="conductivity" value="0.02"/>
    <float name="thickness" value="0.01"/><float name="scattering_coefficient" value="0.3"/>
    <float name="xpd_coefficient" value="0.1"/>
  </bsdf>
  <bsdf type="itu-radio-material" id="ground"><string name="type" value="wet_ground"/></bsdf>
"""


def write_tiny_xml(d: Path, bsdfs: str = BSDFS, shapes: dict = SHAPES, filename=None) -> Path:
    """A scene XML of a few PLY boxes (written with trimesh) in ``d``; ``filename``: {shape: the
    value written for its file} to break it."""
    (d / "meshes").mkdir(parents=True, exist_ok=True)
    lines = ['<scene version="2.1.0">', bsdfs]
    for name, (mesh, bsdf) in shapes.items():
        mesh.export(d / "meshes" / f"{name}.ply", encoding="binary")
        f = (filename or {}).get(name, f"meshes/{name}.ply")
        lines.append(f'  <shape type="ply" id="{name}"><string name="filename" value="{f}"/>'
                     f'<ref id="{bsdf}" name="bsdf"/></shape>')
    lines.append("</scene>")
    (d / "scene.xml").write_text("\n".join(lines))
    return d / "scene.xml"


def _src(path="scene.xml", **kw) -> SionnaXmlSource:
    return SionnaXmlSource(kind="sionna_xml", path=path, semantic_classes=kw.pop("classes", CLASSES), **kw)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    d = tmp_path_factory.mktemp("tiny_xml")
    xml = write_tiny_xml(d)
    m, report = build_from_sionna_xml(xml, _src(), d)
    return d, xml, m, report


def _sionna_materials(scene) -> dict:
    """(eps_r, sigma S/m, thickness m, scattering coefficient, xpd) of every object's material."""
    out = {}
    for name, obj in scene.objects.items():
        rm = obj.radio_material
        out[name] = tuple(round(float(np.array(v).ravel()[0]), 6) for v in (
            rm.relative_permittivity, rm.conductivity, rm.thickness, rm.scattering_coefficient,
            rm.xpd_coefficient))
    return out


# --- known answers: geometry and labels ---------------------------------------------------------
def test_triangles_bounds_and_classes_equal_the_input_shapes(tiny):
    _, _, m, report = tiny
    assert report["shapes"] == 4 and report["visual_triangles"] == sum(len(s.faces) for s, _ in SHAPES.values())
    assert report["radio_triangles"] == report["visual_triangles"]  # no decimation by default
    assert report["hausdorff_max_m"] == 0.0 and report["hausdorff_samples"] == 0  # so nothing to measure
    want = {"tower": "building", "hall": "building", "car_1": "vehicle", "floor": "ground"}
    for i, (name, (mesh, _)) in enumerate(SHAPES.items()):
        sel = m.face_instance == i + 1  # instance id: the shape's position in the file
        assert sel.sum() == len(mesh.faces), name
        np.testing.assert_allclose(m.visual.vertices[np.unique(m.visual.faces[sel])].min(axis=0), mesh.bounds[0])
        np.testing.assert_allclose(m.visual.vertices[np.unique(m.visual.faces[sel])].max(axis=0), mesh.bounds[1])
        assert set(m.face_class[sel]) == {SemanticClass[want[name].upper()]}, name
    assert {(c, mat): len(x.faces) for (c, mat), x in m.radio.items()} == {
        ("building", "xml-concrete"): 12, ("building", "xml-mat-itu_brick"): 12,
        ("vehicle", "xml-paint"): 12, ("ground", "xml-ground"): 2}
    assert report["materials"]["xml-mat-itu_brick"] == {"bsdf_id": "mat-itu_brick", "kind": "itu-radio-material",
                                                       "itu_type": "brick", "shapes": 1}


def test_default_mapping_and_first_match_wins(tmp_path):
    xml = write_tiny_xml(tmp_path)
    m, _ = build_from_sionna_xml(xml, SionnaXmlSource(kind="sionna_xml", path="scene.xml"), tmp_path)
    cls = {i + 1: SemanticClass(m.face_class[m.face_instance == i + 1][0]).name.lower() for i in range(4)}
    assert cls == {1: "building", 2: "building", 3: "vehicle", 4: "ground"}  # *car*, *floor*, default
    # patterns see the BSDF id and the ITU type too; the first match wins
    m, _ = build_from_sionna_xml(xml, _src(classes={"concrete": "water", "brick": "road", "re:t.*": "vegetation"},
                                           default_semantic_class="unlabeled"), tmp_path)
    cls = [SemanticClass(m.face_class[m.face_instance == i + 1][0]).name.lower() for i in range(4)]
    assert cls == ["water", "road", "unlabeled", "unlabeled"]


def test_up_axis_and_scale(tmp_path):
    xml = write_tiny_xml(tmp_path)
    m, _ = build_from_sionna_xml(xml, _src(up_axis="y", scale_m_per_unit=0.5), tmp_path)
    tower = m.visual.vertices[np.unique(m.visual.faces[m.face_instance == 1])]
    lo, hi = SHAPES["tower"][0].bounds  # (x, y, z) -> (x, -z, y), halved
    np.testing.assert_allclose(tower.min(axis=0), 0.5 * np.array([lo[0], -hi[2], lo[1]]))
    np.testing.assert_allclose(tower.max(axis=0), 0.5 * np.array([hi[0], -lo[2], hi[1]]))


def test_footprints_come_from_the_obstacle_shapes(tiny):
    d, xml, _, _ = tiny
    geom = source_geometry_from_sionna_xml(xml, _src(), d, (48.0, 11.0, 500.0))
    b = sorted(geom.of_class("building"), key=lambda f: f.instance_id)
    assert [f.instance_id for f in b] == [1, 2]  # the car (a vehicle) is no obstacle
    np.testing.assert_allclose(b[0].geometry.bounds, (-20, 5, -5, 20))
    np.testing.assert_allclose(b[0].geometry.area, 15 * 15)
    assert b[1].height_m == pytest.approx(12.0) and b[0].radio_material == "xml-concrete"
    assert geom.origin == (48.0, 11.0, 500.0)


def test_a_building_split_into_wall_and_roof_shapes_is_one_solid(tmp_path):
    b = _box((0, 0, 0), (10, 6, 8))
    nz = b.face_normals[:, 2]
    wall, roof = b.submesh([np.flatnonzero(np.abs(nz) < 0.5)], append=True), b.submesh([np.flatnonzero(nz > 0.5)],
                                                                                       append=True)
    xml = write_tiny_xml(tmp_path, BSDFS, {"mesh-b-wall": (wall, "concrete"), "mesh-b-roof": (roof, "paint")})
    fp = source_geometry_from_sionna_xml(xml, _src(), tmp_path).of_class("building")
    assert len(fp) == 1 and fp[0].geometry.area == pytest.approx(60.0)  # the shadow, not two thin walls
    assert fp[0].height_m == pytest.approx(8.0)


# --- radio materials ----------------------------------------------------------------------------
def test_written_radio_scene_has_the_xml_radio_materials(tiny, tmp_path):
    import sionna.rt as rt

    from simart_pipeline import engine

    engine.init()
    d, xml, m, _ = tiny
    meshes.save(m, tmp_path / "pm", {"origin": None}, thickness_m=0.2, frequency_hz=FREQUENCY_HZ)
    written = rt.load_scene(str(tmp_path / "pm" / "radio" / "scene.xml"), merge_shapes=False)
    original = rt.load_scene(str(xml), merge_shapes=False)
    for s in (written, original):
        s.frequency = FREQUENCY_HZ
    got, want = _sionna_materials(written), _sionna_materials(original)
    # each original shape's material equals that of the written object holding it
    holder = {"tower": "building_xml-concrete", "hall": "building_xml-mat-itu_brick",
              "car_1": "vehicle_xml-paint", "floor": "ground_xml-ground"}
    assert {k: got[v] for k, v in holder.items()} == want
    assert want["tower"][2] == 0.25 and want["car_1"][:2] == (3.5, 0.02)  # $wall, explicit values
    paint = written.objects["vehicle_xml-paint"].radio_material
    assert want["car_1"][3:] == (0.3, 0.1) and type(paint.scattering_pattern).__name__ == "LambertianPattern"
    assert written.objects["building_xml-concrete"].radio_material.itu_type == "concrete"


def test_rain_wets_itu_materials_and_leaves_explicit_ones(tiny, tmp_path):
    from simart_pipeline.config import Array
    from simart_pipeline.radio.tracer import RadioScene

    _, _, m, _ = tiny
    meshes.save(m, tmp_path / "pm", {"origin": None}, thickness_m=0.2, frequency_hz=FREQUENCY_HZ)
    rs = RadioScene(tmp_path / "pm" / "radio" / "scene.xml", frequency_hz=FREQUENCY_HZ, bandwidth_hz=1e7,
                    tx_array=Array(), rx_array=Array(), weather="rainy")
    assert rs.material_overrides == {"building_xml-concrete": "concrete -> wet_concrete",
                                     "building_xml-mat-itu_brick": "brick -> wet_brick"}
    assert rs.radio_materials()["vehicle_xml-paint"] == "mat_xml-paint"  # unchanged
    assert rs.radio_materials()["ground_xml-ground"] == "wet_ground"      # already wet


def test_twosided_around_a_radio_material_is_that_material(tmp_path):
    bsdfs = BSDFS.replace('<bsdf type="itu-radio-material" id="ground"><string name="type" value="wet_ground"/></bsdf>',
                          '<bsdf type="twosided" id="ground"><bsdf type="itu-radio-material">'
                          '<string name="type" value="wet_ground"/></bsdf></bsdf>')
    assert bsdfs != BSDFS
    m, report = build_from_sionna_xml(write_tiny_xml(tmp_path, bsdfs), _src(), tmp_path)
    assert report["materials"]["xml-ground"]["itu_type"] == "wet_ground"
    assert 'type="itu-radio-material" id="mat_xml-ground"' in m.material_xml["xml-ground"]


# --- Sionna's own street canyon -----------------------------------------------------------------
@pytest.fixture(scope="module")
def canyon(tmp_path_factory):
    import sionna.rt as rt

    d = tmp_path_factory.mktemp("canyon") / "canyon"
    shutil.copytree(Path(rt.scene.simple_street_canyon).parent, d)
    xml = d / "simple_street_canyon.xml"
    m, report = build_from_sionna_xml(xml, SionnaXmlSource(kind="sionna_xml", path=xml.name), d)
    meshes.save(m, d / "pm", {"origin": None}, thickness_m=0.2, frequency_hz=FREQUENCY_HZ)
    return d, xml, m, report


def test_street_canyon_geometry_and_footprints(canyon):
    d, xml, m, report = canyon
    plys = {p.stem: trimesh.load(p, process=False) for p in (d / "meshes").glob("*.ply")}
    assert report["visual_triangles"] == report["radio_triangles"] == sum(len(p.faces) for p in plys.values()) == 74
    lo = np.min([p.bounds[0] for p in plys.values()], axis=0)
    hi = np.max([p.bounds[1] for p in plys.values()], axis=0)
    np.testing.assert_allclose(m.visual.bounds, [lo, hi], atol=1e-5)
    assert report["parts_per_class"] == {"building": 6, "ground": 1}  # mesh-floor: *floor*
    geom = source_geometry_from_sionna_xml(xml, SionnaXmlSource(kind="sionna_xml", path=xml.name), d)
    fp = geom.of_class("building")
    assert len(fp) == 6
    order = ["building_1", "building_6", "building_5", "building_4", "building_3", "building_2"]  # in the file
    for f in fp:  # each footprint is its building's shadow; instance ids follow the file's order
        b = plys[order[f.instance_id - 1]].bounds
        np.testing.assert_allclose(f.geometry.bounds, (b[0][0], b[0][1], b[1][0], b[1][1]), atol=1e-4)
        assert f.height_m == pytest.approx(b[1][2], abs=1e-4)
    assert referenced_files(d, xml.name)[0] == "meshes/building_1.ply"


def test_street_canyon_paths_equal_the_original_scene_and_friis(canyon):
    import sionna.rt as rt

    d, xml, _, _ = canyon
    rx_pos = [[-40.0, 0.0, 1.5], [0.0, 2.0, 1.5], [35.0, -3.0, 1.5], [70.0, 1.0, 1.5]]
    tx_pos = [-70.0, 0.0, 10.0]

    def strongest(path):
        s = rt.load_scene(str(path), merge_shapes=False)
        s.frequency = FREQUENCY_HZ
        s.tx_array = s.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
        s.add(rt.Transmitter("tx", position=tx_pos))
        for i, p in enumerate(rx_pos):
            s.add(rt.Receiver(f"rx{i}", position=p))
        paths = rt.PathSolver(deterministic=True)(s, max_depth=2, samples_per_src=10**4, seed=1)
        a_re, a_im = (np.array(x) for x in paths.a)
        g = (a_re**2 + a_im**2).reshape(len(rx_pos), -1, a_re.shape[-1])  # [rx, ..., paths]
        return 10 * np.log10(g.sum(axis=1).max(axis=-1))

    ours, theirs = strongest(d / "pm" / "radio" / "scene.xml"), strongest(xml)
    np.testing.assert_allclose(ours, theirs, atol=0.1)
    dist = np.linalg.norm(np.array(rx_pos) - tx_pos, axis=1)
    friis = 20 * np.log10(SPEED_OF_LIGHT_MPS / FREQUENCY_HZ / (4 * np.pi * dist))
    np.testing.assert_allclose(ours, friis, atol=0.1)  # the line of sight is the strongest path


# --- errors -------------------------------------------------------------------------------------
@pytest.mark.parametrize("case, problem", [
    ("malformed", "malformed XML: mismatched tag"),
    ("missing_mesh", "shape 'hall': mesh file not found"),
    ("outside", "shape 'hall': mesh file '../outside.ply' lies outside the scene directory"),
    ("absolute", "lies outside the scene directory"),
    ("unknown_itu", "material 'concrete': unknown ITU material type 'adamantium'"),
    ("not_radio", "material 'plastic' is a 'diffuse' BSDF, not a radio material"),
    ("not_scene", "not a Mitsuba scene"),
])
def test_bad_files_name_the_file_and_the_problem_and_write_nothing(tmp_path, case, problem):
    d = tmp_path / "scene"
    d.mkdir()
    if case == "malformed":
        xml = write_tiny_xml(d)
        xml.write_text(xml.read_text().replace("</shape>", "</shap>", 1))
    elif case == "missing_mesh":
        xml = write_tiny_xml(d, filename={"hall": "meshes/nowhere.ply"})
    elif case == "outside":
        _box((0, 0, 0), (1, 1, 1)).export(tmp_path / "outside.ply")
        xml = write_tiny_xml(d, filename={"hall": "../outside.ply"})
    elif case == "absolute":
        xml = write_tiny_xml(d, filename={"hall": str(d / "meshes" / "hall.ply")})
    elif case == "unknown_itu":
        xml = write_tiny_xml(d, BSDFS.replace('value="concrete"', 'value="adamantium"'))
    elif case == "not_radio":
        xml = write_tiny_xml(d, BSDFS + '<bsdf type="diffuse" id="plastic"/>',
                             {**SHAPES, "car_1": (SHAPES["car_1"][0], "plastic")})
    else:
        xml = d / "scene.xml"
        xml.write_text("<mesh/>")
    out = tmp_path / "out"
    with pytest.raises(SionnaXmlError) as err:
        stores.write_directory(out, lambda o: meshes.save(*build_from_sionna_xml(xml, _src(), d)[:1], o, {}, 0.2))
    assert str(err.value).startswith(f"{xml}: ") and problem in str(err.value), str(err.value)
    assert not out.exists()


def test_config_names_unknown_keys_classes_and_unsafe_paths(tmp_path):
    d = tmp_path / "s"
    d.mkdir()
    write_tiny_xml(d)
    base = {"name": "s", "origin": {"latitude_deg": 48.0, "longitude_deg": 11.0},
            "base_stations": [{"name": "bs0", "position_m": [0, 0, 20]}],
            "platforms": [{"name": "p", "kind": "uav",
                           "trajectory": {"waypoints_m": [[0, 0, 40], [10, 0, 40]], "speed_mps": 5.0}}],
            "clock": {"duration_s": 1.0}}
    cases = [({"kind": "sionna_xml", "path": "scene.xml", "semantic_class": {}}, "source.semantic_class: Extra inputs are not permitted"),
             ({"kind": "sionna_xml", "path": "scene.xml", "semantic_classes": {"car*": "boat"}},
              "unknown semantic class 'boat'"),
             ({"kind": "sionna_xml", "path": "scene.xml", "semantic_classes": {"re:(": "road"}},
              "not a valid regular expression"),
             ({"kind": "sionna_xml", "path": "scene.xml", "obstacle_classes": ["tree"]},
              "source.obstacle_classes: Value error, unknown semantic class 'tree'"),
             ({"kind": "sionna_xml", "path": "../x.xml"}, "must lie inside the scene directory"),
             ({"kind": "sionna_xml", "path": "meshes/tower.ply"}, "ending in .xml"),
             ({"kind": "sionna_xml", "path": "nowhere.xml"}, "source.path: file not found")]
    for source, problem in cases:
        (d / "scene.yaml").write_text(yaml.safe_dump({**base, "source": source}))
        with pytest.raises(ConfigError) as err:
            load_scene_config(d)
        assert problem in str(err.value) and "scene.yaml" in str(err.value), str(err.value)
    (d / "scene.yaml").write_text(yaml.safe_dump({**base, "source": {"kind": "sionna_xml", "path": "scene.xml"}}))
    cfg = load_scene_config(d)
    assert cfg.source.kind == "sionna_xml"
    # simart validate reports a broken XML on one line naming scene.yaml, the XML and the problem
    (d / "scene.xml").write_text((d / "scene.xml").read_text().replace('value="concrete"', 'value="unobtainium"'))
    _, problems = validation.scene_problems(d)
    assert problems == [f"{d / 'scene.yaml'}: source: cannot read the scene's source: {d / 'scene.xml'}: material "
                        f"'concrete': unknown ITU material type 'unobtainium'; known: " + problems[0].split("known: ")[1]]
    write_tiny_xml(d)
    # the scene XML and every mesh it names decide whether osm_extract is stale
    assert sorted(versions.source_files(cfg, "osm_extract", d)) == [
        "meshes/car_1.ply", "meshes/floor.ply", "meshes/hall.ply", "meshes/tower.ply", "scene.xml"]


# --- the pipeline -------------------------------------------------------------------------------
def test_sionna_xml_scene_materialises_through_dagster(canyon, tmp_path):
    import dagster as dg

    from simart_pipeline import registry
    from simart_pipeline.assets import ALL_ASSETS
    from simart_pipeline.definitions import build_definitions
    from simart_pipeline.partitions import scene_partitions

    src = canyon[0]
    scene = tmp_path / "canyon"
    shutil.copytree(src, scene, ignore=shutil.ignore_patterns("pm"))
    (scene / "scene.yaml").write_text(yaml.safe_dump({
        "name": "canyon", "origin": {"latitude_deg": 48.137, "longitude_deg": 11.575},
        "source": {"kind": "sionna_xml", "path": "simple_street_canyon.xml"},
        "base_stations": [{"name": "bs0", "position_m": [-70.0, 0.0, 10.0], "array": {"rows": 1, "cols": 1}}],
        "platforms": [{"name": "car0", "kind": "ground_vehicle",
                       "trajectory": {"waypoints_m": [[-40.0, 0.0, 1.5], [0.0, 0.0, 1.5]], "speed_mps": 10.0},
                       "sensors": []}],
        "clock": {"duration_s": 0.4, "radio_rate_hz": 5.0, "pose_rate_hz": 10.0},
        "ray_tracing": {"max_depth": 1, "samples_per_src": 10000},
        "ofdm": {"numerology_mu": 1, "num_resource_blocks": 1},
        "weathers": ["sunny"]}))
    data = tmp_path / "data"
    cfg = registry.register(scene, data)
    instance = dg.DagsterInstance.ephemeral()
    instance.add_dynamic_partitions(scene_partitions.name, [cfg.name])
    resources = build_definitions(data_root=str(data)).resources
    result = dg.materialize(ALL_ASSETS, selection=["osm_extract", "paired_meshes", "trajectory"],
                            partition_key=cfg.name, instance=instance, resources=resources)
    assert result.success
    result = dg.materialize(ALL_ASSETS, selection=["cirs"], instance=instance, resources=resources,
                            partition_key=dg.MultiPartitionKey({"scene": cfg.name, "weather": "sunny"}))
    assert result.success
    pm = data / "paired_meshes" / "canyon"
    info = json.loads((pm / "scene.json").read_text())
    assert info["sionna_xml"]["visual_triangles"] == 74 and info["counts"]["radio_triangles"] == 74
    assert info["origin"]["latitude_deg"] == 48.137
    src_ds = stores.open_store(data / "osm_extract" / "canyon.zarr")
    assert int((src_ds["feature_class"].values == "building").sum()) == 6
    cirs = stores.open_store(next((data / "cirs" / "canyon").glob("*.zarr")))
    assert cirs.sizes["time"] == 3 and bool(cirs["valid"].any())


def _ridge(half_x: float, top_m: float, half_y: float) -> trimesh.Trimesh:
    """A ground rising linearly from z = 0 at x = -half_x to ``top_m`` at x = 0 and down again."""
    v = np.array([[-half_x, -half_y, 0], [0, -half_y, top_m], [0, half_y, top_m], [-half_x, half_y, 0],
                  [half_x, -half_y, 0], [half_x, half_y, 0]], float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]], process=False)


def test_devices_paths_and_ckm_planes_below_a_terrain_are_named_with_the_ground_there(tmp_path):
    # a ridge z = 0.4 (50 - |x|): a station 4 m below it; a UAV whose waypoints are above it and
    # whose straight path between them crosses the ridge 4.86 m below its top (at x = 0: z = 22 -
    # 12 x 40 / 70); the CKM plane at 7 m under the ground in the six middle cell columns of ten
    # (centres x = -45 .. 45: ground 2, 6, 10, 14, 18, 18, 14, 10, 6, 2 m): 60 % of the cells
    d = tmp_path / "hill"
    d.mkdir()
    shapes = {"tower": SHAPES["tower"], "floor": (_ridge(50.0, 20.0, 40.0), "ground")}
    write_tiny_xml(d, shapes=shapes)
    raw = {"name": "hill", "origin": {"latitude_deg": 48.0, "longitude_deg": 11.0},
           "source": {"kind": "sionna_xml", "path": "scene.xml"},
           "base_stations": [{"name": "bs0", "position_m": [10.0, 0.0, 12.0]}],   # ground 16 m
           "platforms": [{"name": "p", "kind": "uav",
                          "trajectory": {"waypoints_m": [[-40.0, -30.0, 22.0], [30.0, -30.0, 10.0]],  # ground 4, 8 m
                                         "speed_mps": 5.0}}],
           "clock": {"duration_s": 1.0},
           "ckm": {"center_m": [0.0, -30.0], "size_m": [100.0, 20.0], "cell_size_m": 10.0, "height_m": 7.0}}
    (d / "scene.yaml").write_text(yaml.safe_dump(raw))
    cfg = load_scene_config(d)
    geom = build_source_geometry(cfg, d)
    np.testing.assert_allclose(geometry.ground_elevation_m(geom, [-50.0, 0.0, 25.0, 49.0], [0.0, 10.0, -5.0, 39.0]),
                               [0.0, 20.0, 10.0, 0.4], atol=1e-6)
    _, problems = validation.scene_problems(d)
    where = f"{d / 'scene.yaml'}"
    assert [p.split(": ")[1] for p in problems] == ["base_stations.0.position_m", "platforms.0.trajectory",
                                                   "ckm.height_m"]
    assert problems[0].startswith(f"{where}: base_stations.0.position_m: bs0 at [10.0, 0.0, 12.0] lies 4.0 m below "
                                  "the ground surface there (16.0 m)")
    depth = float(problems[1].split("runs up to ")[1].split(" m below")[0])
    assert depth == pytest.approx(4.86, abs=0.15) and "add waypoints over the rise" in problems[1]
    assert "the plane at 7 m lies below the ground surface in 60 % of the grid's cells (the ground there: " \
           "2.0 .. 18.0 m)" in problems[2]
    assert all("not above ground (the ground rises 0.0 .. 20.0 m)" in p for p in problems)
    # raised above it (and a waypoint over the ridge), nothing to say
    raw["base_stations"][0]["position_m"][2] = 17.0
    raw["platforms"][0]["trajectory"]["waypoints_m"].insert(1, [0.0, -30.0, 25.0])
    raw["ckm"]["height_m"] = 21.0
    (d / "scene.yaml").write_text(yaml.safe_dump(raw))
    assert validation.scene_problems(d)[1] == []
    # a waypoint itself below the ground is named as such
    raw["platforms"][0]["trajectory"]["waypoints_m"][1][2] = 19.0
    (d / "scene.yaml").write_text(yaml.safe_dump(raw))
    assert "platforms.0.trajectory.waypoints_m.1: [0.0, -30.0, 19.0] lies 1.0 m below the ground surface there " \
           "(20.0 m)" in validation.scene_problems(d)[1][0]
    # a flat ground at z = 0 keeps no surface at all
    write_tiny_xml(d, shapes={"tower": SHAPES["tower"], "floor": SHAPES["floor"]})
    assert build_source_geometry(load_scene_config(d), d).ground_surface_m is None
