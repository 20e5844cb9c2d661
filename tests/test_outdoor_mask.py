"""The fast CKM's outdoor mask against an independent point-in-solid test, on every bundled scene and
on Sionna's Munich (issue 17: "the outdoor mask agrees with an independent test ... on every cell
of every bundled scene and of Munich").

The mask (``ckm.outdoor.outdoor_fraction``, ``scene/solids.py``) counts a point indoors when the
vertical line above it crosses one solid of the radio mesh an odd number of times (shapely shadows
of the faces, per solid, caps from ``shapely.polygonize``). The independent test here shares none
of that code, only what a building is (``scene/solids.py``'s docstring: a part of the mesh that is
closed, or open only at its bottom, its open edges on horizontal rings its faces rise from): trimesh
joins the vertices (``grouping.clusters``) and finds the parts (``graph.connected_components``)
and their open edges; each open ring is closed by a fan of triangles from its centre (a fan covers
what a ring encloses an odd number of times, whatever its shape); and trimesh's ray-triangle
intersector casts rays from the point, every face hit counted, coincident faces each. A point is
inside a part when two of three rays cross it an odd number of times. The rays are tilted 1e-4 rad
from the vertical, in three directions: a ray from a point on a shared roof edge's shadow would
count both faces, and an oblique ray would cross the partition two of Munich's blocks share (one
face on edges of three) and miscount, where a nearly vertical one passes it within millimetres.
A point within 1 um of a face may go either way in both tests; such points are counted and listed.

Checked on every sample point of every cell (``OUTDOOR_SAMPLES_PER_AXIS**2`` per cell, the points
``outdoor_fraction`` averages), at every height of the scene's own CKM grid; Munich on the grid of
``benchmarks/ckm_solver.py`` (the project's Munich CKM grid: 300 m x 300 m around its base station,
2 m cells, 1.5 m; 22,500 cells, 360,000 points). Then the cells: the fast mode masks a cell whose
outdoor share is below ``min_outdoor_fraction`` or whose centre is ``inside_building`` (as
``ckm_layers`` computes it: ``tile_grid`` with the paired meshes' solids); the same rule on the
independent points and centres must give the same cells.
"""

import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml
from trimesh.ray.ray_triangle import RayMeshIntersector

from simart_pipeline import stores
from simart_pipeline.ckm import outdoor
from simart_pipeline.ckm.grid import cell_centres, scene_tiles
from simart_pipeline.ckm.layers import tile_grid
from simart_pipeline.ckm.outdoor import DEFAULT_MIN_OUTDOOR_FRACTION
from simart_pipeline.config import load_scene_config
from simart_pipeline.radio.tracer import RadioScene
from simart_pipeline.scene import build, meshes, source

REPO = Path(__file__).resolve().parents[1]
BUNDLED = ["scenes/demo", "scenes/urban", "scenes/indoor", "scenes/maritime", "scenes/beam_study",
           "tests/scenes/tiny", "tests/scenes/beam_tiny"]
S = outdoor.OUTDOOR_SAMPLES_PER_AXIS
JOIN_M = 1e-3  # vertices closer than this are one (walls and roof of a Sionna building are two shapes)
TILT_RAD = 1e-4
ON_FACE_M = 1e-6
RAYS = np.array([[np.sin(TILT_RAD) * np.cos(a), np.sin(TILT_RAD) * np.sin(a), np.cos(TILT_RAD)]
                 for a in (0.3, 0.3 + 2 * np.pi / 3, 0.3 + 4 * np.pi / 3)])


# --- the independent test -----------------------------------------------------------------------
def closed_parts(triangles: np.ndarray) -> tuple[list[trimesh.Trimesh], int]:
    """The parts of a triangle soup that enclose a volume, each closed: (meshes, parts left out).
    A part is the faces joined by shared vertices; it encloses a volume when its open edges lie
    on horizontal rings from which its faces rise; those rings get caps."""
    soup = trimesh.Trimesh(triangles.reshape(-1, 3), np.arange(3 * len(triangles)).reshape(-1, 3), process=False)
    groups = trimesh.grouping.clusters(soup.vertices, JOIN_M)
    vid = np.arange(len(soup.vertices))
    for g in groups:
        vid[g] = g[0]
    mesh = trimesh.Trimesh(soup.vertices, vid[soup.faces], process=False)
    mesh.update_faces(mesh.nondegenerate_faces(height=1e-8))
    parts, skipped = [], 0
    for nodes in trimesh.graph.connected_components(mesh.edges, min_len=1):
        faces = mesh.faces[np.isin(mesh.faces[:, 0], nodes)]
        part = trimesh.Trimesh(mesh.vertices, faces, process=False)
        z = part.vertices[np.unique(part.faces), 2]
        if np.ptp(z) <= JOIN_M:
            skipped += 1  # flat: ground, roads, water
            continue
        open_ = trimesh.grouping.group_rows(part.edges_sorted, require_count=1)
        caps, closes = [], True
        for ring in trimesh.graph.connected_components(part.edges_sorted[open_], min_len=1):
            sel = open_[np.isin(part.edges_sorted[open_, 0], ring)]
            rz = part.vertices[part.edges_sorted[sel].ravel(), 2]
            third = part.faces[part.edges_face[sel]].ravel()
            if np.ptp(rz) > JOIN_M or part.vertices[third, 2].min() < rz.mean() - JOIN_M:
                closes = False  # open at a side or at the top
                break
            # A fan from the ring's centre to each of its edges covers the points the ring
            # encloses an odd number of times and the others an even number (Jordan), whatever the
            # ring's shape: the parity a ray needs, without rebuilding polygons.
            ends = part.vertices[part.edges_sorted[sel]]
            apex = np.broadcast_to(ends.reshape(-1, 3).mean(axis=0), (len(sel), 3))
            fan = np.stack([apex, ends[:, 0], ends[:, 1]], axis=1)
            fan[:, :, 2] = rz.mean()
            fan = fan[trimesh.triangles.area(fan) > 1e-9]
            caps.append(trimesh.Trimesh(fan.reshape(-1, 3), np.arange(3 * len(fan)).reshape(-1, 3), process=False))
        if not closes:
            skipped += 1
            continue
        parts.append(trimesh.util.concatenate([part] + caps))
    return parts, skipped


def point_in_solid(parts: list[trimesh.Trimesh], points: np.ndarray) -> tuple[np.ndarray, int]:
    """Which points lie inside one of ``parts`` (odd crossings on two of three tilted rays: the
    third is cast only where the first two disagree), and how many (point, part) pairs had their
    rays disagree."""
    inside = np.zeros(len(points), bool)
    split = 0
    for part in parts:
        lo, hi = part.bounds
        sel = np.flatnonzero(np.all((points >= lo) & (points <= hi), axis=1))
        if not len(sel):
            continue
        hits = RayMeshIntersector(part)

        def odd(idx, d):
            _, ray = hits.intersects_id(points[idx], np.tile(d, (len(idx), 1)), multiple_hits=True)
            return np.bincount(ray, minlength=len(idx)) % 2 == 1

        a, b = odd(sel, RAYS[0]), odd(sel, RAYS[1])
        vote = a & b
        tie = np.flatnonzero(a != b)
        if len(tie):
            vote[tie] = odd(sel[tie], RAYS[2])
        inside[sel[vote]] = True
        split += len(tie)
    return inside, split


# --- the scenes, built by the pipeline's own code ------------------------------------------------
def _munich_dir(tmp: Path) -> Path:
    import sionna.rt as rt

    from benchmarks.ckm_solver import CELL_M, HEIGHT_M, SCENES

    spec = SCENES["munich"]
    d = tmp / "munich"
    shutil.copytree(Path(rt.scene.munich).parent, d)
    (d / "scene.yaml").write_text(yaml.safe_dump({
        "name": "munich", "origin": {"latitude_deg": 48.1372, "longitude_deg": 11.5755},
        "source": {"kind": "sionna_xml", "path": "munich.xml"},
        "base_stations": [{"name": "bs0", "position_m": list(spec["tx"]), "array": {"rows": 1, "cols": 1}}],
        "platforms": [{"name": "p", "kind": "pedestrian", "sensors": [],
                       "trajectory": {"waypoints_m": [[0, 0, 1.5], [1, 0, 1.5]], "speed_mps": 1.0}}],
        "clock": {"duration_s": 1.0},
        "ckm": {"center_m": list(spec["centre"]), "size_m": list(spec["size"]), "cell_size_m": CELL_M,
                "height_m": HEIGHT_M, "tiles": [1, 1]}}))
    return d


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    return {}, tmp_path_factory.mktemp("outdoor")


def _built(scenes, name):
    cache, tmp = scenes
    if name not in cache:
        d = _munich_dir(tmp) if name == "munich" else REPO / name
        cfg = load_scene_config(d)
        geom = source.build_source_geometry(cfg, d)
        out = tmp / (name.replace("/", "_") + "_pm")
        stores.write_directory(out, build.paired_meshes_for_scene(cfg, d, geom).save)
        cache[name] = cfg, geom, RadioScene.from_config(meshes.radio_scene_file(out), cfg), meshes.load(out)
    return cache[name]


def _grid(cfg):
    """Cell centres (y, x), heights, and the sample points' axes (yf, xf): S x S per cell."""
    y, x = cell_centres(cfg.ckm)
    off = ((np.arange(S) + 0.5) / S - 0.5) * cfg.ckm.cell_size_m
    return y, x, np.asarray(cfg.ckm.heights, float), (y[:, None] + off).ravel(), (x[:, None] + off).ravel()


def _points(h, y, x):
    hh, yy, xx = np.meshgrid(h, y, x, indexing="ij")
    return np.column_stack([xx.ravel(), yy.ravel(), hh.ravel()])


def _inside_building(cfg, geom, paired, shape):
    """``inside_building`` of every tile, as the ``ckm_layers`` asset computes it."""
    solids = outdoor.mesh_solids_of(paired)
    ib = np.zeros(shape, bool)
    for t in scene_tiles(cfg.ckm):
        g = tile_grid(cfg, geom, t, solids)
        ib[np.ix_(np.arange(shape[0]), g.rows, g.cols)] = g.inside_building
    return ib


def _on_a_face(parts: list[trimesh.Trimesh], points: np.ndarray) -> np.ndarray:
    """Points within ON_FACE_M of a face of ``parts``: inside or outside is theirs to choose."""
    if not len(points) or not parts:
        return np.zeros(len(points), bool)
    _, dist, _ = trimesh.proximity.closest_point(trimesh.util.concatenate(parts), points)
    return dist < ON_FACE_M


def _checked(scenes, name) -> dict:
    """The mask and the independent test of scene ``name`` (computed once per module)."""
    cache, _ = scenes
    if ("checked", name) not in cache:
        cfg, geom, radio, paired = _built(scenes, name)
        y, x, h, yf, xf = _grid(cfg)
        c = cfg.ckm.cell_size_m
        solids = outdoor.radio_solids(radio)
        parts, skipped = closed_parts(outdoor.radio_triangles(radio))
        samples = _points(h, yf, xf)
        truth, split = point_in_solid(parts, samples)
        centre, _ = point_in_solid(parts, _points(h, y, x))
        cache[("checked", name)] = dict(
            cfg=cfg, radio=radio, parts=parts, skipped=skipped, split=split, samples=samples,
            shape=(len(h), len(y), len(x)), truth=truth, centre=centre, centres=_points(h, y, x),
            mask_in=outdoor.outdoor_fraction(radio, xf, yf, h, samples_per_axis=1, cell_size_m=c / S,
                                             solids=solids).ravel() == 0,
            frac=outdoor.outdoor_fraction(radio, x, y, h, cell_size_m=c, solids=solids),
            inside_building=_inside_building(cfg, geom, paired, (len(h), len(y), len(x))))
    return cache[("checked", name)]


@pytest.mark.parametrize("name", BUNDLED + ["munich"])
def test_outdoor_mask_agrees_with_point_in_solid_at_every_sample_point(scenes, name):
    r = _checked(scenes, name)
    H, Y, X = r["shape"]
    truth, mask_in, frac, ib, centre = r["truth"], r["mask_in"], r["frac"], r["inside_building"].ravel(), r["centre"]
    odd = np.flatnonzero(mask_in != truth)
    odd_on_face = _on_a_face(r["parts"], r["samples"][odd])
    differ = np.flatnonzero(ib != centre)
    on_face = _on_a_face(r["parts"], r["centres"][differ])
    # Points on a face may go either way: take the mask's word there, once checked they are on one.
    truth, centre = truth.copy(), centre.copy()
    truth[odd[odd_on_face]] = mask_in[odd[odd_on_face]]
    centre[differ[on_face]] = ib[differ[on_face]]
    truth_frac = 1.0 - truth.reshape(H, Y, S, X, S).mean(axis=(2, 4))
    masked = (frac < DEFAULT_MIN_OUTDOOR_FRACTION).ravel() | ib
    truth_masked = (truth_frac < DEFAULT_MIN_OUTDOOR_FRACTION).ravel() | centre
    print(f"\n{name}: {len(r['parts'])} closed parts ({r['skipped']} left out), {r['split']} ray ties; "
          f"{truth.size} sample points, {int(truth.sum())} inside, {len(odd)} differ "
          f"({int(odd_on_face.sum())} on a face); {frac.size} cells, {int(masked.sum())} masked, "
          f"{int((masked != truth_masked).sum())} differ; cell centres: {int(ib.sum())} inside_building, "
          f"{len(differ)} differ ({int(on_face.sum())} on a face)")
    assert r["truth"].any() or name == "tests/scenes/beam_tiny", "no sample point inside a building: a vacuous check"
    assert odd_on_face.all(), f"sample points off every face where the mask is wrong: {r['samples'][odd[~odd_on_face]]}"
    assert on_face.all(), f"cell centres off every face where inside_building is wrong: {r['centres'][differ[~on_face]]}"
    np.testing.assert_array_equal(frac.ravel(), truth_frac.ravel())
    np.testing.assert_array_equal(masked, truth_masked)


@pytest.mark.parametrize("name, wrong", [("scenes/indoor", 5560), ("munich", 135)])
def test_the_check_fails_the_old_anything_above_rule(scenes, name, wrong):
    """The rule the mask had before (a point is indoors when anything lies above it) fails the same
    check: every room of the office (its ceiling is above them all), Munich's streets under
    building parts that hang over them."""
    r = _checked(scenes, name)
    old = outdoor.anything_above(r["radio"], r["samples"])
    assert int((old != r["truth"]).sum()) == wrong
    assert not (r["truth"] & ~old).any()  # nothing inside a solid lacks a face above it


# --- known answers ------------------------------------------------------------------------------
def _shell(lo, hi, drop=()) -> trimesh.Trimesh:
    """A box's surface without the faces named in ``drop`` ("bottom", "x+", ...)."""
    box = trimesh.creation.box(bounds=np.array([lo, hi], float))
    n = box.face_normals
    keep = np.ones(len(n), bool)
    for name, axis, sign in (("bottom", 2, -1), ("x+", 0, 1), ("x-", 0, -1)):
        if name in drop:
            keep &= ~(n[:, axis] * sign > 0.9)
    box.update_faces(keep)
    box.remove_unreferenced_vertices()
    return box


def _known_scene():
    """Shapes with a known inside, and that inside as a function of (x, y, z)."""
    from conftest import ground_square

    shapes = {
        "ground": (ground_square(400.0), "medium_dry_ground"),
        # walls and roof without a floor, a tower open on its roof sharing a roof corner
        "block": (_shell((0, 0, 0), (20, 20, 10), ["bottom"]), "concrete"),
        "tower": (_shell((0, 0, 10), (5, 5, 30), ["bottom"]), "concrete"),
        # a room of separate wall boxes under a ceiling slab: the room is outdoors
        "slab": (_shell((30, 30, 3), (40, 40, 3.4)), "concrete"),
        # a part hanging open above the street from 6 m
        "oriel": (_shell((65, 0, 6), (75, 10, 12), ["bottom"]), "concrete"),
        # two halves without floors, each missing its wall at x = 50, and the one partition both share
        "west": (_shell((40, 0, 0), (50, 10, 10), ["bottom", "x+"]), "brick"),
        "east": (_shell((50, 0, 0), (60, 10, 10), ["bottom", "x-"]), "brick"),
        "partition": (trimesh.Trimesh([[50, 0, 0], [50, 10, 0], [50, 10, 10], [50, 0, 10]],
                                      [[0, 1, 2], [0, 2, 3]], process=False), "brick"),
    }
    for k, (lo, hi) in enumerate([((30, 30, 0), (31, 40, 3)), ((39, 30, 0), (40, 40, 3)),
                                  ((31, 30, 0), (39, 31, 3)), ((31, 39, 0), (39, 40, 3))]):
        shapes[f"wall{k}"] = (_shell(lo, hi), "concrete")

    def inside(X, Y, Z):
        def box(x0, x1, y0, y1, z0, z1):
            return (X > x0) & (X < x1) & (Y > y0) & (Y < y1) & (Z > z0) & (Z < z1)
        walls = box(30, 40, 30, 40, 0, 3) & ~box(31, 39, 31, 39, 0, 3)
        return (box(0, 20, 0, 20, 0, 10) | box(0, 5, 0, 5, 10, 30) | box(30, 40, 30, 40, 3, 3.4) | walls
                | box(65, 75, 0, 10, 6, 12) | box(40, 60, 0, 10, 0, 10))

    return shapes, inside


def test_known_answers_slab_oriel_tower_on_a_roof_and_a_shared_partition(tmp_path):
    """Regression: a room under a ceiling slab and the street under an oriel are outdoors (the old
    rule masked them), a block whose tower stands open on its roof is indoors below the tower (the
    old footprint rule took the block for wall sheets), and so are two halves of a building that
    share one partition (three faces on its edges). The mask and the independent test agree with
    the construction at every cell centre, and so do the Sionna-XML footprints at street level
    outside the room."""
    from conftest import write_radio_scene

    from simart_pipeline.config import SionnaXmlSource
    from simart_pipeline.scene.geometry import inside_buildings
    from simart_pipeline.scene.sionna_xml import source_geometry_from_sionna_xml

    shapes, inside = _known_scene()
    xml = write_radio_scene(tmp_path / "known", shapes, 3.5e9, 0.2)
    cfg = load_scene_config(REPO / "tests" / "scenes" / "tiny")
    radio = RadioScene.from_config(xml, cfg)
    x, y, h = np.arange(-4.5, 80), np.arange(-4.5, 45), np.array([1.5, 3.2, 5.0, 9.0, 20.0])
    pts = _points(h, y, x)
    expected = inside(pts[:, 0], pts[:, 1], pts[:, 2])
    assert expected.sum() > 2000
    mask = outdoor.outdoor_fraction(radio, x, y, h, samples_per_axis=1).ravel() == 0
    np.testing.assert_array_equal(mask, expected)
    parts, _ = closed_parts(outdoor.radio_triangles(radio))
    np.testing.assert_array_equal(point_in_solid(parts, pts)[0], expected)
    old = outdoor.anything_above(radio, pts)
    room = (pts[:, 0] > 31) & (pts[:, 0] < 39) & (pts[:, 1] > 31) & (pts[:, 1] < 39) & (pts[:, 2] < 3)
    street = (pts[:, 0] > 65) & (pts[:, 0] < 75) & (pts[:, 1] > 0) & (pts[:, 1] < 10) & (pts[:, 2] < 6)
    assert old[room].all() and old[street].all() and not expected[room | street].any()
    # Footprints (the reference of ckm_layers without solids, and of CIR and trajectory checks)
    # are shadows: the room's walls and slab are one part, whose shadow covers the room.
    geom = source_geometry_from_sionna_xml(xml, SionnaXmlSource(kind="sionna_xml", path=xml.name), xml.parent)
    low = (pts[:, 2] == 1.5) & ~room
    np.testing.assert_array_equal(inside_buildings(geom, *pts[low].T), expected[low])
