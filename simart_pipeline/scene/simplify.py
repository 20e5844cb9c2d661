"""Mesh simplification for radio meshes: merge, drop small parts, decimate, measure the deviation.

The order follows what was measured on extruded city blocks (ARCHITECTURE.md): merge vertices
first; dropping small connected parts is the big win (window frames, furniture, clutter); then
decimate. Lossless decimation (``fast_simplification`` with ``lossless=True``) collapses only edges
whose collapse leaves the surface unchanged, so sharp building edges stay exact by construction;
borders are always preserved, since a lossless collapse of an open plane's border shrinks it.
Quadric (lossy) decimation runs per smooth patch, the patches cut along sharp edges, so that
creases become patch borders and stay where they are.
"""

from __future__ import annotations

import math

import fast_simplification
import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree
from scipy.sparse.csgraph import connected_components


def merge_vertices(vertices: np.ndarray, tolerance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices that fall into the same ``tolerance_m`` grid cell.

    :param vertices: [n, 3] float, m
    :return: (unique vertices [k, 3], m; inverse [n] int64 such that ``unique[inverse]`` ~ ``vertices``)
    """
    keys = np.floor(np.asarray(vertices, np.float64) / tolerance_m + 0.5).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return np.asarray(vertices, np.float64)[first], inverse.ravel().astype(np.int64)


def face_components(faces: np.ndarray, num_vertices: int) -> tuple[int, np.ndarray]:
    """Connected components of faces that share a vertex.

    :return: (number of components, label [num_faces] int64)
    """
    faces = np.asarray(faces, np.int64)
    if len(faces) == 0:
        return 0, np.zeros(0, np.int64)
    a = np.concatenate([faces[:, 0], faces[:, 1]])
    b = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(num_vertices, num_vertices))
    n, vertex_label = connected_components(graph, directed=False)
    used, face_label = np.unique(vertex_label[faces[:, 0]], return_inverse=True)
    return len(used), face_label.ravel().astype(np.int64)


def component_extents_m(vertices: np.ndarray, faces: np.ndarray, label: np.ndarray,
                        num_components: int) -> np.ndarray:
    """Largest axis-aligned bounding-box side of each component: [num_components], m."""
    lo = np.full((num_components, 3), np.inf)
    hi = np.full((num_components, 3), -np.inf)
    tri = vertices[faces]  # [f, 3 corners, 3 axes]
    np.minimum.at(lo, label, tri.min(axis=1))
    np.maximum.at(hi, label, tri.max(axis=1))
    return (hi - lo).max(axis=1)


def edge_use_counts(faces: np.ndarray, group: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (optionally keyed by a per-face group) and how many faces use each.

    :return: (edges [e, 3] int64 as (group, v_min, v_max), count [e])
    """
    faces = np.asarray(faces, np.int64)
    g = np.zeros(len(faces), np.int64) if group is None else np.asarray(group, np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e.sort(axis=1)
    keyed = np.column_stack([np.tile(g, 3), e])
    edges, count = np.unique(keyed, axis=0, return_counts=True)
    return edges, count


def degenerate_faces(vertices: np.ndarray, faces: np.ndarray, rel_area: float = 1e-10) -> np.ndarray:
    """Faces with a repeated vertex or (near) zero area relative to their longest edge squared."""
    faces = np.asarray(faces, np.int64)
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    tri = vertices[faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    longest2 = np.max([np.sum((tri[:, i] - tri[:, j]) ** 2, axis=1) for i, j in ((0, 1), (1, 2), (2, 0))],
                      axis=0)
    return repeated | (area2 <= rel_area * longest2)


def _clean(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    mesh.remove_unreferenced_vertices()
    return mesh


def decimate(mesh: trimesh.Trimesh, mode: str = "lossless", target_fraction: float = 0.5,
             sharp_edge_angle_deg: float = 30.0) -> trimesh.Trimesh:
    """Decimate ``mesh`` (vertices already merged) keeping borders and sharp edges.

    :param mode: ``none``, ``lossless`` (only collapses that leave the surface unchanged) or
        ``quadric`` (lossless, then quadric error per smooth patch down to ``target_fraction`` of
        the patch's triangles; edges bending more than ``sharp_edge_angle_deg`` are patch borders)
    """
    if mode == "none" or len(mesh.faces) == 0:
        return mesh
    v, f = fast_simplification.simplify(mesh.vertices, mesh.faces.astype(np.int64), lossless=True,
                                        preserve_border=True)
    out = _clean(v, f)
    if mode == "lossless":
        return out
    if mode != "quadric":
        raise ValueError(f"unknown decimation mode {mode!r}; expected none, lossless or quadric")
    adjacency = out.face_adjacency
    smooth = out.face_adjacency_angles < math.radians(sharp_edge_angle_deg)
    n, label = connected_components(
        coo_matrix((np.ones(int(smooth.sum()), np.int8), (adjacency[smooth, 0], adjacency[smooth, 1])),
                   shape=(len(out.faces), len(out.faces))), directed=False)
    pieces = []
    for k in range(n):
        sel = np.flatnonzero(label == k)
        patch = _clean(out.vertices, out.faces[sel])
        target = max(1, int(math.ceil(target_fraction * len(sel))))
        if target < len(sel) and len(sel) > 4:
            pv, pf = fast_simplification.simplify(patch.vertices, patch.faces.astype(np.int64),
                                                  target_count=target, preserve_border=True)
            patch = _clean(pv, pf)
        pieces.append(patch)
    joined = trimesh.util.concatenate(pieces)
    uv, inv = merge_vertices(joined.vertices, 1e-9 * max(1.0, float(np.ptp(joined.vertices))))
    faces = inv[joined.faces]
    keep = ~degenerate_faces(uv, faces)
    return _clean(uv, faces[keep])


def surface_distance_m(mesh: trimesh.Trimesh, points: np.ndarray, seed: int = 0,
                       chunk: int = 20_000) -> np.ndarray:
    """Exact distance (m) from each point [n, 3] to the surface of ``mesh``.

    An upper bound per point (the nearest of the mesh's vertices and of dense area samples, so it
    stays tight where triangles are large) limits the triangles searched to those whose bounding
    box meets the ball (rtree); the closest point on each candidate is exact
    (``trimesh.triangles.closest_point``).
    """
    points = np.asarray(points, np.float64)
    ref, _ = trimesh.sample.sample_surface(mesh, max(4 * len(points), 10_000), seed=seed)
    ref = np.concatenate([mesh.vertices, ref])
    bound = cKDTree(ref).query(points)[0] + 1e-9
    tree = mesh.triangles_tree
    triangles = mesh.triangles
    out = np.empty(len(points))
    for start in range(0, len(points), chunk):
        p, u = points[start:start + chunk], bound[start:start + chunk, None]
        ids, counts = tree.intersection_v(p - u, p + u)
        ids, counts = np.asarray(ids, np.int64), np.asarray(counts, np.int64)
        owner = np.repeat(np.arange(len(p)), counts)
        close = trimesh.triangles.closest_point(triangles[ids], p[owner])
        d = np.linalg.norm(close - p[owner], axis=1)
        best = np.full(len(p), np.inf)
        np.minimum.at(best, owner, d)
        out[start:start + chunk] = np.minimum(best, u[:, 0])
    return out


def _directed_distances(src: trimesh.Trimesh, dst: trimesh.Trimesh, samples: int, seed: int) -> np.ndarray:
    """Distances (m) from area-uniform random points of ``src`` to the surface of ``dst``."""
    if len(src.faces) == 0 or src.area <= 0:
        return np.zeros(0)
    pts, _ = trimesh.sample.sample_surface(src, samples, seed=seed)
    return surface_distance_m(dst, pts, seed=seed + 1)


def hausdorff_m(visual: trimesh.Trimesh, radio: trimesh.Trimesh, samples: int = 20_000,
                seed: int = 0) -> dict:
    """Geometric deviation between two surfaces, both directions, from sampled points.

    Points are drawn uniformly by area on one surface; their exact distance to the other surface is
    measured. ``*_p95_m`` is the 95th percentile, ``*_max_m`` the largest sampled distance (a lower
    bound of the true Hausdorff distance that tightens with ``samples``).

    :return: dict with ``visual_to_radio_p95_m``, ``visual_to_radio_max_m``, ``radio_to_visual_p95_m``,
        ``radio_to_visual_max_m``, ``hausdorff_p95_m`` and ``hausdorff_max_m`` (the larger of the
        two directions), ``samples``
    """
    if len(radio.faces) == 0 or len(visual.faces) == 0:
        raise ValueError("cannot measure the deviation: one of the meshes has no triangle")
    out = {"samples": int(samples)}
    for name, (a, b) in {"visual_to_radio": (visual, radio), "radio_to_visual": (radio, visual)}.items():
        d = _directed_distances(a, b, samples, seed)
        out[f"{name}_p95_m"] = float(np.percentile(d, 95)) if len(d) else 0.0
        out[f"{name}_max_m"] = float(d.max()) if len(d) else 0.0
    out["hausdorff_p95_m"] = max(out["visual_to_radio_p95_m"], out["radio_to_visual_p95_m"])
    out["hausdorff_max_m"] = max(out["visual_to_radio_max_m"], out["radio_to_visual_max_m"])
    return out
