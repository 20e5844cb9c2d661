"""The solids of a triangle mesh and which points lie inside them (the CKM's indoor test).

A *solid* is a connected part of the mesh (faces that share a vertex; vertices closer than
:data:`MERGE_TOLERANCE_M` are one, so that a building split into a wall and a roof shape is one
part) that encloses a volume:

- closed: every edge of it is used by two faces or more;
- or open only at its bottom: its open edges (used by one face) form horizontal rings from which
  its faces rise, each ring capped at its height. So walls and a roof without a floor (Sionna's
  city scenes) are a solid, and so is a tower that stands open on a roof, or a building part that
  hangs open above a street (its volume starts at its open bottom).

Everything else encloses nothing: flat layers (ground, roads, water: no height), a sheet (a single
wall, a canopy), a surface open at its top or along a side. A slab, a ceiling box, a ship's deck
or an overhang are solids of their own, so a point under them is outdoors, and a room between
separate wall and slab boxes (``scenes/indoor``) is not inside any of them.

A point is inside a solid when a vertical line from it upwards crosses the solid's faces and caps
an odd number of times (:func:`inside_solids`). Crossings are counted per solid, every face of it
once, so faces that two solids share in space (buildings sharing a wall, a part standing on a
roof) count for each; vertical faces are never crossed, so an inner wall two blocks of Sionna's
Munich share (three faces on one edge) does not matter. Whatever way the faces point (Sionna's
bundled scenes face inwards) the count is the same. Not handled: a horizontal face that two
stacked volumes of one part share as a single face (the count above the lower one is even).
"""

from __future__ import annotations

import gc
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from simart_pipeline.scene import simplify

MERGE_TOLERANCE_M = 1e-3  # vertices this close are one; also the flatness of a ring, the least height of a solid
# The query points move by this much (m), in a direction no axis-aligned or 45-degree edge follows,
# so that a point on the shared edge of two triangles' shadows is counted in exactly one of them.
NUDGE_M = 1e-6
_NUDGE = NUDGE_M * np.array([np.cos(1.0), np.sin(1.0)])
_MIN_SHADOW_M2 = 1e-12  # twice the area below which a face's shadow is a line: a vertical face


@dataclass(frozen=True)
class Solids:
    """The solids of a mesh as the vertical crossing count needs them.

    ``faces [F, 3, 3]`` (m): the solids' faces that are not vertical; ``face_solid [F]``: the solid
    each belongs to; ``caps [K]`` (shapely polygons, xy in m) at ``cap_height_m [K]`` of solid
    ``cap_solid [K]``; ``num_solids``; ``num_open_parts``: connected parts that enclose nothing.
    """

    faces: np.ndarray
    face_solid: np.ndarray
    caps: np.ndarray
    cap_height_m: np.ndarray
    cap_solid: np.ndarray
    num_solids: int
    num_open_parts: int


def merged_vertices(triangles: np.ndarray, tolerance_m: float = MERGE_TOLERANCE_M) -> tuple[np.ndarray, np.ndarray]:
    """Vertices closer than ``tolerance_m`` joined: (positions ``[V, 3]``, faces ``[F, 3]``)."""
    v = np.asarray(triangles, np.float64).reshape(-1, 3)
    n = len(v)
    pairs = cKDTree(v).query_pairs(tolerance_m, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, vid = connected_components(graph, directed=False)
    pos = np.zeros((int(vid.max()) + 1 if n else 0, 3))
    pos[vid] = v
    return pos, vid.reshape(-1, 3).astype(np.int64)


def _open_rings(pos: np.ndarray, faces: np.ndarray, part: np.ndarray, tolerance_m: float):
    """Rings of open edges: per ring its part, whether it is a flat bottom (horizontal, every face
    on it rising from it), its height (m) and its edges ``[e, 2, 2]`` in xy."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e.sort(axis=1)
    third = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    # an edge's two vertices are one key (both are in the same part: parts share no vertex)
    _, inv, count = np.unique(e[:, 0] * len(pos) + e[:, 1], return_inverse=True, return_counts=True)
    open_ = count[inv] == 1
    oe, o3, op = e[open_], third[open_], np.tile(part, 3)[open_]
    if len(oe) == 0:
        return []
    n = len(pos)
    graph = coo_matrix((np.ones(len(oe), np.int8), (oe[:, 0], oe[:, 1])), shape=(n, n))
    _, vring = connected_components(graph, directed=False)
    ring = vring[oe[:, 0]]
    rings = []
    for r in np.unique(ring):
        sel = ring == r
        z = pos[oe[sel].ravel(), 2]
        height = float(z.mean())
        flat = z.max() - z.min() <= tolerance_m and bool(np.all(pos[o3[sel], 2] >= height - tolerance_m))
        rings.append((int(op[sel][0]), flat, height, pos[oe[sel]][:, :, :2]))
    return rings


@contextmanager
def _collector_paused():
    """Python's cyclic garbage collector paused: making some 10^5 shapely geometries otherwise
    sets it off over the whole heap again and again (189,000 points: 0.22 s, paused 0.06 s)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _shadow2(tri: np.ndarray) -> np.ndarray:
    """Twice the signed area of each triangle's shadow on the ground ``[F]`` (m^2)."""
    a, b = tri[:, 1, :2] - tri[:, 0, :2], tri[:, 2, :2] - tri[:, 0, :2]
    return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]


def _ring_areas(edges: np.ndarray) -> list:
    """The areas a flat ring of open edges ``[e, 2, 2]`` (xy, m) encloses, as polygons. Zero-area
    leftovers (edges that meet no ring, rings folded onto themselves: a T-junction, where an edge of
    one face runs along two edges of others) enclose nothing a vertical line could cross."""
    polys, _cuts, _dangles, invalid = shapely.polygonize_full(shapely.linestrings(edges))
    out = list(shapely.get_parts(polys))
    for ring in shapely.get_parts(invalid):  # self-touching rings: their valid parts
        fixed = shapely.make_valid(shapely.Polygon(shapely.get_coordinates(ring)))
        out += [g for g in shapely.get_parts(fixed) if isinstance(g, shapely.Polygon) and g.area > 0]
    return out


def enclosing_parts(pos: np.ndarray, faces: np.ndarray, part: np.ndarray, num_parts: int,
                    tolerance_m: float = MERGE_TOLERANCE_M, with_caps: bool = True) -> tuple[np.ndarray, list]:
    """Which parts of a mesh enclose a volume (module docstring): ``[num_parts]`` bool, and the
    caps of those that do, as (part, height m, polygon) triples (none unless ``with_caps``).

    :param pos: ``[V, 3]`` vertex positions, m; ``faces``: ``[F, 3]`` vertex indices (shared
        vertices already joined); ``part``: ``[F]`` part of each face
    :param tolerance_m: how far from flat a ring of open edges may be, and the least height of a
        part that encloses anything
    """
    tri = pos[faces]
    lo = np.full(num_parts, np.inf)
    hi = np.full(num_parts, -np.inf)
    np.minimum.at(lo, part, tri[:, :, 2].min(axis=1))
    np.maximum.at(hi, part, tri[:, :, 2].max(axis=1))
    encloses = hi - lo > tolerance_m  # flat layers enclose nothing
    caps = []
    for p, flat, height, edges in _open_rings(pos, faces, part, tolerance_m):
        if encloses[p] and not flat:
            encloses[p] = False  # open at a side or at the top
        elif encloses[p] and with_caps:
            caps += [(p, height, poly) for poly in _ring_areas(edges)]
    return encloses, [c for c in caps if encloses[c[0]]]


def mesh_solids(triangles: np.ndarray, tolerance_m: float = MERGE_TOLERANCE_M) -> Solids:
    """The solids of a triangle soup ``[F, 3, 3]`` (m, z up), as the module docstring defines them."""
    triangles = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    pos, faces = merged_vertices(triangles, tolerance_m)
    faces = faces[~simplify.degenerate_faces(pos, faces)] if len(faces) else faces
    num_parts, part = simplify.face_components(faces, len(pos))
    solid, caps = enclosing_parts(pos, faces, part, num_parts, tolerance_m)
    index = np.full(num_parts, -1)
    index[solid] = np.arange(int(solid.sum()))
    tri = pos[faces]
    sel = solid[part] & (np.abs(_shadow2(tri)) > _MIN_SHADOW_M2)
    return Solids(faces=tri[sel], face_solid=index[part[sel]],
                  caps=np.array([c[2] for c in caps] + [None], object)[:-1],
                  cap_height_m=np.array([c[1] for c in caps], np.float64),
                  cap_solid=index[np.array([c[0] for c in caps], np.int64)],
                  num_solids=int(solid.sum()), num_open_parts=int(num_parts - solid.sum()))


def inside_solids(solids: Solids, points: np.ndarray, walls_outside: bool = False) -> np.ndarray:
    """``[N]`` bool: which of ``points [N, 3]`` (m) lie inside one of ``solids`` (odd number of
    crossings of its faces and caps on the vertical line upwards). A point on a face may go either
    way; with ``walls_outside``, one on a wall (a point moved :data:`NUDGE_M` to either side of it
    is inside on one side only) is outside, as footprints have it (twice the work)."""
    if walls_outside:
        return _inside(solids, points, _NUDGE) & _inside(solids, points, -_NUDGE)
    return _inside(solids, points, _NUDGE)


def _inside(solids: Solids, points: np.ndarray, nudge: np.ndarray) -> np.ndarray:
    points = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros(len(points), bool)
    if not len(points) or not solids.num_solids:
        return out
    low = points[:, 2].min()  # faces and caps no higher than every point are above none of them
    keep = np.flatnonzero(solids.faces[:, :, 2].max(axis=1) > low)
    f = solids.faces[keep]
    cap = np.flatnonzero(solids.cap_height_m > low)
    xy = f[:, :, :2]
    a, b = xy[:, 1] - xy[:, 0], xy[:, 2] - xy[:, 0]
    det = _shadow2(f)
    q = points[:, :2] + nudge
    with _collector_paused():
        shapes = np.concatenate([shapely.polygons(xy), solids.caps[cap]])
        pi, si = shapely.STRtree(shapes).query(shapely.points(q), predicate="intersects")
        del shapes
    is_face = si < len(f)
    fi = si[is_face]
    r = q[pi[is_face]] - xy[fi, 0]
    u = (r[:, 0] * b[fi, 1] - r[:, 1] * b[fi, 0]) / det[fi]
    w = (a[fi, 0] * r[:, 1] - a[fi, 1] * r[:, 0]) / det[fi]
    z = np.empty(len(si))
    z[is_face] = f[fi, 0, 2] + u * (f[fi, 1, 2] - f[fi, 0, 2]) + w * (f[fi, 2, 2] - f[fi, 0, 2])
    ci = cap[si[~is_face] - len(f)]
    z[~is_face] = solids.cap_height_m[ci]
    owner = np.empty(len(si), np.int64)
    owner[is_face] = solids.face_solid[keep[fi]]
    owner[~is_face] = solids.cap_solid[ci]
    above = z > points[pi, 2]
    key = pi[above] * solids.num_solids + owner[above]
    keys, count = np.unique(key, return_counts=True)
    out[keys[count % 2 == 1] // solids.num_solids] = True
    return out
