"""User meshes to paired visual and radio meshes: import, rules, simplification, deviation, paths."""

from __future__ import annotations

import base64
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from simart_pipeline.vocabulary import SemanticClass
from simart_pipeline import stores
from simart_pipeline.config import ConfigError, MeshImportRules, load_scene_config, resolve_source_path
from simart_pipeline.scene import geometry, meshes, mesh_import, simplify
from simart_pipeline.scene.mesh_import import MeshImportError, build_from_mesh, source_geometry_from_mesh

REPO = Path(__file__).resolve().parent.parent
ENU_TO_GLTF = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])


def box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(hi - lo, trimesh.transformations.translation_matrix((lo + hi) / 2))


# A detailed block: a 30 x 20 x 15 m building tessellated in 1 m triangles, 4-bar window frames
# standing 15 cm out of every facade, rooftop units, an antenna mast, and the ground.
L, W, H = 30.0, 20.0, 15.0
FRAME_W, FRAME_H, BAR, DEPTH = 1.4, 1.6, 0.12, 0.15


def _frame(x, y, z, axis, sign) -> list[trimesh.Trimesh]:
    bars = []
    for du, dz, eu, ez in ((0, FRAME_H / 2, FRAME_W, BAR), (0, -FRAME_H / 2, FRAME_W, BAR),
                           (-FRAME_W / 2, 0, BAR, FRAME_H), (FRAME_W / 2, 0, BAR, FRAME_H)):
        if axis == "y":  # facade y = const: bars stand out along y
            c, e = (x + du, y + sign * DEPTH / 2, z + dz), (eu, DEPTH, ez)
        else:
            c, e = (x + sign * DEPTH / 2, y + du, z + dz), (DEPTH, eu, ez)
        bars.append(trimesh.creation.box(e, trimesh.transformations.translation_matrix(c)))
    return bars


def detailed_block() -> tuple[trimesh.Scene, dict]:
    s = trimesh.Scene()
    s.add_geometry(box((-L / 2, -W / 2, 0), (L / 2, W / 2, H)).subdivide_to_size(1.0), node_name="block",
                   geom_name="block")
    s.add_geometry(trimesh.Trimesh([[-60, -60, 0], [60, -60, 0], [60, 60, 0], [-60, 60, 0]], [[0, 1, 2], [0, 2, 3]]),
                   node_name="ground", geom_name="ground")
    n_frames = 0
    for z in np.arange(2.5, H - 1, 3.0):
        for x in np.arange(-L / 2 + 2.5, L / 2 - 1, 3.0):
            for sign in (-1, 1):
                frame = trimesh.util.concatenate(_frame(x, sign * W / 2, z, "y", sign))
                s.add_geometry(frame, node_name=f"window_frame_{n_frames}", geom_name=f"window_frame_{n_frames}")
                n_frames += 1
        for y in np.arange(-W / 2 + 2.5, W / 2 - 1, 3.0):
            for sign in (-1, 1):
                frame = trimesh.util.concatenate(_frame(sign * L / 2, y, z, "x", sign))
                s.add_geometry(frame, node_name=f"window_frame_{n_frames}", geom_name=f"window_frame_{n_frames}")
                n_frames += 1
    units = [(-8, -4), (-3, 5), (6, -2), (10, 6)]
    for i, (x, y) in enumerate(units):
        s.add_geometry(box((x - 0.45, y - 0.45, H), (x + 0.45, y + 0.45, H + 0.8)).subdivide_to_size(0.2),
                       node_name=f"hvac_{i}", geom_name=f"hvac_{i}")
    mast = trimesh.creation.cylinder(0.05, 3.0, sections=16)
    mast.apply_translation((12, -8, H + 1.5))
    s.add_geometry(mast, node_name="antenna_mast", geom_name="antenna_mast")
    return s, {"frames": n_frames, "bars": 4 * n_frames, "units": len(units)}


RULES = MeshImportRules(up_axis="z", min_part_extent_m=2.0, parts=[
    {"match": "ground", "semantic_class": "ground", "radio_material": "medium_dry_ground"},
    {"match": "antenna_*", "drop": True},
    {"match": "window_frame_*", "radio_material": "metal"},
])


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    scene, facts = detailed_block()
    path = tmp_path_factory.mktemp("block") / "block.glb"
    scene.export(path)
    return path, facts


@pytest.fixture(scope="module")
def block_built(block):
    path, facts = block
    return (*build_from_mesh(path, RULES), facts)


# --- simplification primitives -------------------------------------------------------------------


def test_surface_distance_is_exact_against_trimesh_reference():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    mesh = trimesh.util.concatenate([mesh, box((3, -1, -1), (9, 1, 0))])
    rng = np.random.default_rng(3)
    pts = rng.uniform(-6, 12, size=(1000, 3))
    ours = simplify.surface_distance_m(mesh, pts)
    _, ref, _ = trimesh.proximity.closest_point(mesh, pts)
    np.testing.assert_allclose(ours, ref, atol=1e-9)


def test_components_and_extents_of_separate_boxes():
    parts = [box((0, 0, 0), (1, 1, 1)), box((5, 0, 0), (6, 0.5, 1)), box((10, 0, 0), (11, 1, 3))]
    m = trimesh.util.concatenate(parts)
    v, inv = simplify.merge_vertices(m.vertices, 1e-6)
    assert len(v) == 24  # 8 corners each, nothing shared
    n, label = simplify.face_components(inv[m.faces], len(v))
    assert n == 3
    ext = simplify.component_extents_m(v, inv[m.faces], label, n)
    assert sorted(np.round(ext, 12)) == [1.0, 1.0, 3.0]


def test_lossless_decimation_keeps_the_solid_and_the_border():
    solid = box((0, 0, 0), (30, 20, 15)).subdivide_to_size(0.5)
    v, inv = simplify.merge_vertices(solid.vertices, 1e-6)
    out = simplify.decimate(trimesh.Trimesh(v, inv[solid.faces], process=False), "lossless")
    assert len(out.faces) == 12 and out.is_watertight
    assert out.volume == pytest.approx(30 * 20 * 15, rel=1e-9)
    # An open plane: preserve_border keeps its outline, so its area and bounds stay exact.
    plane = trimesh.creation.box((10, 10, 1)).subdivide_to_size(0.5)
    top = plane.submesh([np.flatnonzero(plane.face_normals[:, 2] > 0.9)], append=True)
    v, inv = simplify.merge_vertices(top.vertices, 1e-6)
    flat = simplify.decimate(trimesh.Trimesh(v, inv[top.faces], process=False), "lossless")
    assert len(flat.faces) < len(top.faces) / 4
    assert flat.area == pytest.approx(100.0, rel=1e-9)
    np.testing.assert_allclose(flat.bounds, top.bounds, atol=1e-12)


def test_quadric_decimation_keeps_sharp_edges_and_bounds_the_deviation():
    # A box with a spherical cap on top: the cap may lose detail, the box's creases may not.
    base = box((-2, -2, 0), (2, 2, 2)).subdivide_to_size(0.25)
    cap = trimesh.creation.icosphere(subdivisions=4, radius=1.5)
    cap.apply_translation((0, 0, 2.0))
    cap = cap.slice_plane((0, 0, 2.0), (0, 0, 1), cap=False)
    m = trimesh.util.concatenate([base, cap])
    v, inv = simplify.merge_vertices(m.vertices, 1e-9)
    mesh = trimesh.Trimesh(v, inv[m.faces], process=False)
    out = simplify.decimate(mesh, "quadric", target_fraction=0.25, sharp_edge_angle_deg=30.0)
    assert len(out.faces) < 0.35 * len(mesh.faces)
    corners = np.array([[x, y, z] for x in (-2, 2) for y in (-2, 2) for z in (0, 2)], float)
    assert np.all(simplify.surface_distance_m(out, corners) < 1e-9)
    dev = simplify.hausdorff_m(mesh, out, samples=5000)
    assert dev["hausdorff_max_m"] < 0.05  # 3 % of the cap radius


# --- the detailed block: reduction, deviation, labels --------------------------------------------


def test_block_is_reduced_by_more_than_tenfold(block_built):
    m, report, facts = block_built
    assert report["visual_triangles"] == len(m.visual.faces)
    assert report["radio_triangles"] == sum(len(r.faces) for r in m.radio.values())
    assert report["triangle_reduction"] >= 10
    # Lossless decimation turns the tessellated block back into its 12 triangles, volume exact.
    blk = m.radio[("building", "concrete")]
    assert len(blk.faces) == 12 and blk.is_watertight
    assert blk.volume == pytest.approx(L * W * H, rel=1e-6)
    assert len(m.radio[("ground", "medium_dry_ground")].faces) == 2
    # Every frame bar (1.6 m at most) and rooftop unit is a small part; the mast goes by its rule.
    assert report["removed"]["small_part"]["components"] == facts["bars"] + facts["units"]
    assert report["removed"]["pattern"] == {"parts": 1, "triangles": 64, "parts_per_rule": {"antenna_*": 1}}
    assert ("building", "metal") not in m.radio


def test_block_deviation_is_bounded_by_what_was_removed(block_built):
    m, report, _ = block_built
    # The radio surfaces lie on visual ones; removed parts stand at most 3 m (the mast) off them.
    assert report["radio_to_visual_max_m"] < 1e-5
    assert report["visual_to_radio_max_m"] <= 3.0 + 1e-5
    assert report["visual_to_radio_max_m"] >= DEPTH - 1e-6  # frame fronts were sampled and measured
    assert report["hausdorff_p95_m"] < 0.05
    assert report["hausdorff_max_m"] == max(report["visual_to_radio_max_m"], report["radio_to_visual_max_m"])


def test_visual_faces_carry_class_instance_and_full_detail(block_built, block):
    m, report, facts = block_built
    parts, _ = mesh_import.read_parts(block[0], RULES)
    assert report["parts"] == len(parts) == 1 + 1 + facts["frames"] + facts["units"] + 1
    assert len(m.visual.faces) == sum(len(p.mesh.faces) for p in parts)
    assert m.visual.area == pytest.approx(sum(p.mesh.area for p in parts), rel=1e-9)
    ids = {p.name: p.part_id for p in parts}
    ground = m.face_instance == ids["ground"]
    assert np.all(m.face_class[ground] == SemanticClass.GROUND)
    assert np.all(m.face_class[~ground] == SemanticClass.BUILDING)
    assert set(np.unique(m.face_instance)) == set(ids.values())


def test_paired_outputs_round_trip_through_the_writer(block_built, tmp_path):
    m, report, _ = block_built
    out = tmp_path / "pm"
    stores.write_directory(out, lambda d: meshes.save(m, d, {"mesh_import": report}, 0.2))
    back = meshes.load(out)
    np.testing.assert_array_equal(back.face_class, m.face_class)
    np.testing.assert_array_equal(back.face_instance, m.face_instance)
    assert {k: len(v.faces) for k, v in back.radio.items()} == {k: len(v.faces) for k, v in m.radio.items()}
    info = json.loads((out / "scene.json").read_text())
    assert info["mesh_import"]["hausdorff_p95_m"] == pytest.approx(report["hausdorff_p95_m"])


def _trace(m: meshes.SceneMeshes, out: Path, tx, rxs) -> list[list[tuple[float, float, tuple]]]:
    """Paths of plain Sionna RT on the written radio scene: per receiver [(gain dB, delay ns, hits)]."""
    from simart_pipeline import engine

    engine.init()
    import sionna.rt as rt

    stores.write_directory(out, lambda d: meshes.save(m, d, {}, 0.2))
    scene = rt.load_scene(str(meshes.radio_scene_file(out)), merge_shapes=False)
    scene.frequency = 3.5e9
    scene.tx_array = scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    scene.add(rt.Transmitter("tx", position=list(tx)))
    for i, p in enumerate(rxs):
        scene.add(rt.Receiver(f"rx{i}", position=list(p)))
    depth = 2
    paths = rt.PathSolver()(scene, max_depth=depth, samples_per_src=100_000, max_num_paths_per_src=100_000,
                            los=True, specular_reflection=True, diffuse_reflection=False, refraction=False,
                            seed=1)
    names = {o.object_id: n for n, o in scene.objects.items()}
    n = len(rxs)
    a = (np.array(paths.a[0]) + 1j * np.array(paths.a[1])).reshape(n, -1)
    tau = np.array(paths.tau).reshape(n, -1)
    valid = np.array(paths.valid).reshape(n, -1)
    inter = np.array(paths.interactions).reshape(depth, n, -1)
    obj = np.array(paths.objects).reshape(depth, n, -1)
    out_paths = []
    for r in range(n):
        found = []
        for k in np.flatnonzero(valid[r]):
            hits = tuple((int(inter[d, r, k]), names[int(obj[d, r, k])]) for d in range(depth) if inter[d, r, k])
            found.append((10 * np.log10(abs(a[r, k]) ** 2), float(tau[r, k]) * 1e9, hits))
        out_paths.append(sorted(found, key=lambda p: -p[0]))
    return out_paths


def test_dominant_paths_are_the_same_on_the_visual_and_the_radio_mesh(block, block_built, tmp_path):
    """The paper's claim: >= 10x fewer triangles, the strongest paths unchanged."""
    path, _ = block
    radio, report, _ = block_built
    # The visual-derived radio scene: every part, no removal, no decimation.
    full_rules = RULES.model_copy(update={"min_part_extent_m": 0.0, "decimation": "none",
                                          "parts": (RULES.parts[0], RULES.parts[2])})
    full, full_report = build_from_mesh(path, full_rules)
    assert full_report["radio_triangles"] == report["visual_triangles"]
    assert full_report["radio_triangles"] >= 10 * report["radio_triangles"]
    tx = (-19.0, -30.0, 6.0)
    rxs = [(21.0, -30.0, 2.0), (10.0, -25.0, 1.5), (-5.0, -40.0, 3.0), (25.0, -15.0, 1.5)]
    on_full = _trace(full, tmp_path / "full", tx, rxs)
    on_radio = _trace(radio, tmp_path / "radio", tx, rxs)
    wall_reflections = 0
    for r, (pf, pr) in enumerate(zip(on_full, on_radio)):
        assert len(pr) >= 2, f"rx {r}: expected LoS and a ground reflection"
        for strongest, other in ((pr[:3], pf), (pf[:3], pr)):
            for gain, delay, hits in strongest:
                match = [p for p in other if p[2] == hits and abs(p[1] - delay) < 0.1]
                assert match, f"rx {r}: path {hits} at {delay:.2f} ns has no counterpart"
                assert abs(match[0][0] - gain) < 1.0
        wall_reflections += any(hits == ((1, "building_concrete"),) for _, _, hits in pr[:3])
        total = [10 * np.log10(sum(10 ** (g / 10) for g, _, _ in p)) for p in (pf, pr)]
        assert abs(total[0] - total[1]) < 1.0
    assert wall_reflections >= 2  # the facade with its frames is a dominant reflector for 2+ receivers


# --- import: formats, names, tags, rules ---------------------------------------------------------


def _gltf_with_primitives_and_extras(path: Path) -> None:
    """A hand-written glTF: node Room > node Desk (extras) holding one mesh of two primitives."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    f1, f2 = np.array([0, 1, 2], np.uint32), np.array([0, 1, 3], np.uint32)
    buf = v.tobytes() + f1.tobytes() + f2.tobytes()
    doc = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"name": "Room", "children": [1], "extras": {"tags": ["office"]}},
                  {"name": "Desk", "mesh": 0, "translation": [1, 2, 3],
                   "extras": {"tags": ["furniture"], "semantic_class": "vehicle"}}],
        "meshes": [{"name": "desk_mesh", "primitives": [
            {"attributes": {"POSITION": 0}, "indices": 1, "material": 0},
            {"attributes": {"POSITION": 0}, "indices": 2, "material": 1}]}],
        "materials": [{"name": "oak"}, {"name": "steel_leg"}],
        "buffers": [{"byteLength": len(buf),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(buf).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48},
                        {"buffer": 0, "byteOffset": 48, "byteLength": 12},
                        {"buffer": 0, "byteOffset": 60, "byteLength": 12}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 1]},
                      {"bufferView": 1, "componentType": 5125, "count": 3, "type": "SCALAR"},
                      {"bufferView": 2, "componentType": 5125, "count": 3, "type": "SCALAR"}],
    }
    path.write_text(json.dumps(doc))


def test_gltf_parts_keep_node_names_paths_materials_and_inherited_tags(tmp_path):
    src = tmp_path / "desk.gltf"
    _gltf_with_primitives_and_extras(src)
    parts, _ = mesh_import.read_parts(src, MeshImportRules())
    assert [(p.name, p.path, p.material_name) for p in parts] == [
        ("Desk", "Room/Desk", "oak"), ("Desk", "Room/Desk", "steel_leg")]
    for p in parts:
        assert set(p.tags) == {"office", "furniture"}
        assert p.extras == {"semantic_class": "vehicle"}
    # glTF is +y up: the node's translation (1, 2, 3) is ENU (1, -3, 2).
    np.testing.assert_allclose(parts[0].mesh.vertices[0], [1, -3, 2])


def test_rules_first_match_wins_then_extras_then_defaults(tmp_path):
    src = tmp_path / "desk.gltf"
    _gltf_with_primitives_and_extras(src)
    rules = MeshImportRules(default_radio_material="brick", parts=[
        {"match": "steel*", "radio_material": "metal"},          # the material name
        {"match": "re:room/d.sk", "radio_material": "wood"},     # the node path, regex
        {"match": "office", "semantic_class": "building", "keep": True},  # an inherited tag
    ])
    parts, _ = mesh_import.read_parts(src, rules)
    mesh_import.label_parts(parts, rules, src)
    by_mat = {p.material_name: p for p in parts}
    assert by_mat["steel_leg"].radio_material == "metal"
    assert by_mat["oak"].radio_material == "wood"
    assert all(p.semantic_class == "building" and p.keep for p in parts)  # the rule beats the extras
    plain = MeshImportRules(default_radio_material="brick")
    parts, _ = mesh_import.read_parts(src, plain)
    mesh_import.label_parts(parts, plain, src)
    assert all(p.semantic_class == "vehicle" and p.radio_material == "brick" for p in parts)


def test_obj_objects_and_materials_stl_solids_ply_file(tmp_path):
    (tmp_path / "m.mtl").write_text("newmtl glass_pane\nKd 1 1 1\nnewmtl concrete_wall\nKd 1 1 1\n")
    wall = box((0, 0, 0), (4, 0.2, 3))
    pane = box((5, 0, 0), (7, 0.02, 2))
    lines = ["mtllib m.mtl"]
    base = 0
    for name, mat, m in (("wall", "concrete_wall", wall), ("pane", "glass_pane", pane)):
        lines += [f"o {name}"] + [f"v {x} {y} {z}" for x, y, z in m.vertices] + [f"usemtl {mat}"]
        lines += [f"f {a + base + 1} {b + base + 1} {c + base + 1}" for a, b, c in m.faces]
        base += len(m.vertices)
    (tmp_path / "m.obj").write_text("\n".join(lines) + "\n")
    rules = MeshImportRules(parts=[{"match": "glass_*", "radio_material": "glass"}])
    m, report = build_from_mesh(tmp_path / "m.obj", rules)
    assert set(m.radio) == {("building", "concrete"), ("building", "glass")}
    assert m.radio[("building", "glass")].volume == pytest.approx(2 * 0.02 * 2)
    stl = trimesh.exchange.stl.export_stl_ascii(wall).replace("solid ", "solid left", 1)
    stl += trimesh.exchange.stl.export_stl_ascii(pane).replace("solid ", "solid right", 1)
    (tmp_path / "two.stl").write_text(stl)
    parts, _ = mesh_import.read_parts(tmp_path / "two.stl", MeshImportRules())
    assert sorted(p.name for p in parts) == ["left", "right"]
    wall.export(tmp_path / "wall.ply")
    m, _ = build_from_mesh(tmp_path / "wall.ply")
    assert m.radio[("building", "concrete")].volume == pytest.approx(4 * 0.2 * 3)


def test_up_axis_and_scale(tmp_path):
    s = trimesh.Scene()
    s.add_geometry(box((100, 200, 0), (300, 400, 500)), node_name="b", geom_name="b")  # cm, ENU
    s.graph.update(frame_to="b", frame_from=s.graph.base_frame, matrix=ENU_TO_GLTF, geometry="b")
    s.export(tmp_path / "b.glb")
    parts, _ = mesh_import.read_parts(tmp_path / "b.glb", MeshImportRules(scale_m_per_unit=0.01))
    np.testing.assert_allclose(parts[0].mesh.bounds, [[1, 2, 0], [3, 4, 5]], atol=1e-5)
    box((1, 2, 0), (3, 4, 5)).export(tmp_path / "b.stl")
    parts, _ = mesh_import.read_parts(tmp_path / "b.stl", MeshImportRules())  # auto: z up
    np.testing.assert_allclose(parts[0].mesh.bounds, [[1, 2, 0], [3, 4, 5]], atol=1e-6)


# --- bad input -----------------------------------------------------------------------------------


def _obj(path: Path, vertices, faces) -> Path:
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in vertices)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    return path


@pytest.mark.parametrize("name, content, problem", [
    ("scene.fbx", b"whatever", "unsupported mesh format"),
    ("missing.obj", None, "file not found"),
    ("broken.glb", b"glTF\x02\x00\x00\x00garbage-not-a-glb", "cannot read"),
    ("empty.obj", b"# nothing\n", "no triangle"),
])
def test_unreadable_unsupported_or_empty_files_are_named(tmp_path, name, content, problem):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(MeshImportError, match=problem) as err:
        build_from_mesh(path)
    assert str(path) in str(err.value)


def test_degenerate_faces_are_refused_or_dropped_on_request(tmp_path):
    b = box((0, 0, 0), (3, 3, 3))
    faces = np.vstack([b.faces, [[0, 0, 1]], [[0, 1, 1]]])
    path = _obj(tmp_path / "degenerate.obj", b.vertices, faces)
    with pytest.raises(MeshImportError, match=r"2 degenerate") as err:
        build_from_mesh(path)
    assert str(path) in str(err.value)
    m, report = build_from_mesh(path, MeshImportRules(drop_degenerate_faces=True))
    assert report["removed"]["degenerate"]["triangles"] == 2
    assert len(m.visual.faces) == 12


def test_non_manifold_edges_are_refused(tmp_path):
    # Three triangles on one edge (a fin on a sheet).
    v = [[0, 0, 0], [2, 0, 0], [1, 1, 0], [1, -1, 0], [1, 0, 1]]
    path = _obj(tmp_path / "fin.obj", v, [[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(MeshImportError, match="non-manifold") as err:
        build_from_mesh(path)
    assert str(path) in str(err.value)


def test_nothing_left_for_the_radio_mesh_is_an_error(tmp_path):
    path = tmp_path / "small.stl"
    box((0, 0, 0), (0.5, 0.5, 0.5)).export(path)
    with pytest.raises(MeshImportError, match="every part was removed"):
        build_from_mesh(path)


def test_extras_with_an_unknown_class_name_the_node(tmp_path):
    src = tmp_path / "desk.gltf"
    _gltf_with_primitives_and_extras(src)
    doc = json.loads(src.read_text())
    doc["nodes"][1]["extras"]["semantic_class"] = "spaceship"
    src.write_text(json.dumps(doc))
    with pytest.raises(MeshImportError, match=r"Room/Desk.*spaceship"):
        build_from_mesh(src)


def test_config_rejects_unknown_names_and_paths_outside_the_scene(tmp_path):
    scene = tmp_path / "indoor"
    shutil.copytree(REPO / "scenes" / "indoor", scene, ignore=shutil.ignore_patterns("*.py"))
    raw = yaml.safe_load((scene / "scene.yaml").read_text())
    raw["source"]["rules"]["parts"][0]["radio_material"] = "unobtainium"
    raw["source"]["rules"]["min_part_extent_m"] = -1
    (scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError) as err:
        load_scene_config(scene)
    text = str(err.value)
    assert "source.rules.parts.0" in text and "unobtainium" in text
    assert "source.rules.min_part_extent_m" in text
    raw = yaml.safe_load((REPO / "scenes" / "indoor" / "scene.yaml").read_text())
    raw["source"]["path"] = "../maritime/harbour.glb"
    (scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match="source.path.*inside the scene directory"):
        load_scene_config(scene)


# --- source geometry for a mesh source -----------------------------------------------------------


def test_footprints_from_solids_and_sheets_match_the_mesh(tmp_path):
    s = trimesh.Scene()
    s.add_geometry(box((-5, -5, -0.2), (5, 5, 0)), node_name="floor", geom_name="floor")
    s.add_geometry(box((-5, -5, 3), (5, 5, 3.2)), node_name="ceiling", geom_name="ceiling")
    s.add_geometry(box((-5, 1, 0), (5, 1.2, 3)), node_name="wall_solid", geom_name="wall_solid")
    sheet = trimesh.Trimesh([[-5, -2, 0], [5, -2, 0], [5, -2, 3], [-5, -2, 3]], [[0, 1, 2], [0, 2, 3]])
    s.add_geometry(sheet, node_name="wall_sheet", geom_name="wall_sheet")
    s.export(tmp_path / "room.glb")
    rules = MeshImportRules(up_axis="z", wall_sheet_thickness_m=0.1,
                            parts=[{"match": "floor", "semantic_class": "ground"}])
    geom = source_geometry_from_mesh(tmp_path / "room.glb", rules, origin=(1.0, 2.0, 3.0))
    assert geom.origin == (1.0, 2.0, 3.0)
    assert len(geom.of_class("building")) == 3 and len(geom.of_class("ground")) == 1
    pts = np.array([[0, 0, 1.5],     # in the room: free
                    [0, 1.1, 1.5],   # inside the solid wall
                    [0, -2.03, 1.5],  # within half the sheet's thickness
                    [0, -2.2, 1.5],  # beside the sheet
                    [0, 0, 3.1],     # inside the ceiling slab
                    [0, 1.1, 3.5]])  # above everything
    expected = [False, True, True, False, True, False]
    for g in (geom, geometry.from_dataset(geometry.to_dataset(geom))):
        assert geometry.inside_buildings(g, pts[:, 0], pts[:, 1], pts[:, 2]).tolist() == expected
    ground = geom.of_class("ground")[0].geometry
    assert ground.bounds == pytest.approx((-5, -5, 5, 5))


# --- the example scenes --------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["indoor", "maritime"])
def test_example_scenes_validate_and_simplify(name):
    from simart_pipeline.validation import scene_problems

    cfg, problems = scene_problems(REPO / "scenes" / name)
    assert problems == []
    m, report = build_from_mesh(resolve_source_path(REPO / "scenes" / name, cfg), cfg.source.rules)
    assert report["triangle_reduction"] >= 10
    assert (REPO / "scenes" / name / cfg.source.path).stat().st_size < 1_000_000
    if name == "indoor":
        assert report["removed"]["small_part"]["components"] >= 10 * 10  # furniture of ten rooms
        assert all(cls != "unlabeled" for cls, _ in m.radio)             # no furniture left
        assert (m.face_class == SemanticClass.UNLABELED).any()    # but the visual has it
    else:
        assert ("water", "sea_water") in m.radio and ("vehicle", "metal") in m.radio


def test_mesh_scene_assets_materialise_through_dagster(tmp_path):
    import dagster as dg

    from simart_pipeline import registry
    from simart_pipeline.assets import ALL_ASSETS
    from simart_pipeline.definitions import build_definitions
    from simart_pipeline.partitions import scene_partitions

    data = tmp_path / "data"
    cfg = registry.register(REPO / "scenes" / "indoor", data)
    instance = dg.DagsterInstance.ephemeral()
    instance.add_dynamic_partitions(scene_partitions.name, [cfg.name])
    result = dg.materialize(ALL_ASSETS, selection=["osm_extract", "paired_meshes", "trajectory"],
                            partition_key=cfg.name, instance=instance,
                            resources=build_definitions(data_root=str(data)).resources)
    assert result.success
    pm = data / "paired_meshes" / "indoor"
    info = json.loads((pm / "scene.json").read_text())
    assert info["mesh_import"]["triangle_reduction"] >= 10
    assert (pm / "radio" / "scene.xml").is_file()
    back = meshes.load(pm)
    assert len(back.visual.faces) == info["mesh_import"]["visual_triangles"]
    src = stores.open_store(data / "osm_extract" / "indoor.zarr")
    assert int((src["feature_class"].values == "building").sum()) > 0


def test_mirrored_nodes_keep_outward_faces(tmp_path):
    s = trimesh.Scene()
    s.add_geometry(box((1, 1, 0), (3, 4, 5)), node_name="mirrored", geom_name="b",
                   transform=np.diag([-1.0, 1.0, 1.0, 1.0]))
    s.export(tmp_path / "m.glb")
    m, _ = build_from_mesh(tmp_path / "m.glb", MeshImportRules(up_axis="z"))
    solid = m.radio[("building", "concrete")]
    np.testing.assert_allclose(solid.bounds, [[-3, 1, 0], [-1, 4, 5]], atol=1e-6)
    assert solid.volume == pytest.approx(2 * 3 * 5, rel=1e-6)  # positive: normals point out
