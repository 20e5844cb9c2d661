"""Road following: shortest routes between waypoints along the scene's road centre lines.

The road graph comes from the source geometry's ``road`` features that are centre lines (a
LineString with ``width_m``); road areas (polygons) carry no direction and are left out. Centre
lines are noded where they cross or touch (``shapely.union_all``), every noded piece is an
undirected edge weighted by its length (one-way streets and turn restrictions are not in the
source geometry), and routes are Dijkstra shortest paths (``scipy.sparse.csgraph``). Crossings
without a junction (bridges, tunnels) cannot be told apart from junctions: the source geometry
keeps no layers.

Each waypoint is snapped to the nearest point of a usable road; a waypoint farther than the
platform's ``max_road_snap_distance_m`` is an error. The route follows the centre line (no lane
offset). Its corners may be cut by at most half the narrower adjacent road's width, so a blend
never leaves the road surface (the centre line buffered by half its width); at the snapped
waypoints the platform's own ``waypoint_tolerance_m`` applies as well. Heights are interpolated
linearly along the route between consecutive waypoints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from shapely.geometry import LineString, Point
from shapely.ops import substring


class RoadError(ValueError):
    """A route that cannot be found; the message names the platform and the waypoint."""


@dataclass(frozen=True)
class Route:
    """A route through snapped waypoints.

    ``points_m`` ``[m, 3]`` the polyline (m, world); ``tolerance_m`` ``[m]`` how far the path may
    cut each vertex's corner; ``waypoint_index`` ``[n]`` the vertex of each configured waypoint;
    ``snapped_m`` ``[n, 3]`` the waypoints moved onto their roads; ``length_m`` the route's length.
    """

    points_m: np.ndarray
    tolerance_m: np.ndarray
    waypoint_index: np.ndarray
    snapped_m: np.ndarray
    length_m: float


def road_lines(geom, min_width_m: float = 0.0) -> tuple[list[LineString], np.ndarray]:
    """Centre lines of the roads at least ``min_width_m`` wide, and their widths (m)."""
    lines, widths = [], []
    for f in geom.of_class("road"):
        if isinstance(f.geometry, LineString) and np.isfinite(f.width_m) and f.width_m >= min_width_m \
                and f.geometry.length > 0:
            lines.append(f.geometry)
            widths.append(float(f.width_m))
    return lines, np.asarray(widths, np.float64)


def noded_pieces(lines: list[LineString], widths: np.ndarray) -> tuple[list[LineString], np.ndarray]:
    """The road lines split where they cross or touch, each piece with its road's width."""
    merged = shapely.union_all(lines)
    pieces = [g for g in getattr(merged, "geoms", [merged]) if isinstance(g, LineString) and g.length > 0]
    mids = shapely.line_interpolate_point(pieces, 0.5, normalized=True)
    src, _ = shapely.STRtree(lines).query_nearest(mids, all_matches=False, return_distance=True)
    # query_nearest returns (input index, tree index) pairs
    which = np.asarray(src)[1]
    return pieces, widths[which]


def _split(pieces, widths, at: dict[int, list[float]]):
    """Pieces split at the given distances along them."""
    out, w = [], []
    for i, (g, wi) in enumerate(zip(pieces, widths)):
        cuts = sorted({c for c in at.get(i, []) if 0 < c < g.length})
        bounds = [0.0] + cuts + [g.length]
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b - a > 1e-9:
                out.append(g if (a, b) == (0.0, g.length) else substring(g, a, b))
                w.append(wi)
    return out, np.asarray(w)


def _key(xy) -> tuple[float, float]:
    return (round(float(xy[0]), 6), round(float(xy[1]), 6))


def route_through(geom, waypoints_m: np.ndarray, *, min_width_m: float, max_snap_m: float,
                  waypoint_tolerance_m: float, where: str = "") -> Route:
    """The shortest road route through ``waypoints_m`` ``[n, 3]`` in order.

    :raises RoadError: no usable road, a waypoint farther than ``max_snap_m`` (m) from every road,
        or two consecutive waypoints that no road connects.
    """
    wp = np.asarray(waypoints_m, np.float64)
    lines, widths = road_lines(geom, min_width_m)
    if not lines:
        raise RoadError(f"{where}: the scene has no road centre line at least {min_width_m} m wide to follow")
    pieces, pw = noded_pieces(lines, widths)
    tree = shapely.STRtree(pieces)
    pts = shapely.points(wp[:, 0], wp[:, 1])
    (_, near), dist = tree.query_nearest(pts, all_matches=False, return_distance=True)
    cuts: dict[int, list[float]] = {}
    snapped = np.empty_like(wp)
    for i, (p, d) in enumerate(zip(near, dist)):
        if d > max_snap_m:
            raise RoadError(f"{where}: waypoint {i} at {np.round(wp[i], 2).tolist()} m is {d:.1f} m from the "
                            f"nearest road (at least {min_width_m} m wide); the limit is max_road_snap_distance_m "
                            f"= {max_snap_m} m: move it onto a road or set follow_roads: false")
        g = pieces[p]
        c = g.project(Point(wp[i, :2]))
        cuts.setdefault(int(p), []).append(c)
        xy = g.interpolate(c)
        snapped[i] = (xy.x, xy.y, wp[i, 2])
    pieces, pw = _split(pieces, pw, cuts)
    # Graph: nodes at piece ends (coordinates to the micrometre), edges both ways.
    nodes: dict[tuple[float, float], int] = {}
    ends = []
    for g in pieces:
        c = np.asarray(g.coords)
        ends.append((nodes.setdefault(_key(c[0]), len(nodes)), nodes.setdefault(_key(c[-1]), len(nodes))))
    ends = np.asarray(ends)
    lengths = np.array([g.length for g in pieces])
    # Parallel edges: the shorter one (csgraph sums duplicates, so keep one per pair first).
    best: dict[tuple[int, int], int] = {}
    for e, (a, b) in enumerate(ends):
        key = (min(a, b), max(a, b))
        if a != b and (key not in best or lengths[e] < lengths[best[key]]):
            best[key] = e
    sel = np.array(sorted(best.values()), np.int64)
    n = len(nodes)
    graph = coo_matrix((np.concatenate([lengths[sel]] * 2),
                        (np.concatenate([ends[sel, 0], ends[sel, 1]]), np.concatenate([ends[sel, 1], ends[sel, 0]]))),
                       shape=(n, n)).tocsr()
    snap_node = []
    for i in range(len(wp)):
        k = _key(snapped[i])
        if k not in nodes:  # a snap that landed on an existing node up to rounding: the nearest node
            allxy = np.array(list(nodes))
            k = tuple(allxy[np.argmin(np.hypot(*(allxy - snapped[i, :2]).T))])
        snap_node.append(nodes[k])
    pts_out: list[np.ndarray] = [snapped[:1]]
    seg_width: list[float] = []
    wp_index = [0]
    cache: dict[int, np.ndarray] = {}
    for i in range(len(wp) - 1):
        a, b = snap_node[i], snap_node[i + 1]
        if a not in cache:
            cache[a] = dijkstra(graph, indices=a, return_predecessors=True)[1]
        pred = cache[a]
        if a != b and pred[b] < 0:
            raise RoadError(f"{where}: no road (at least {min_width_m} m wide) connects waypoint {i} "
                            f"to waypoint {i + 1}")
        chain = [b]
        while chain[-1] != a:
            chain.append(int(pred[chain[-1]]))
        chain.reverse()
        leg_xy, leg_w = [], []
        for u, v in zip(chain[:-1], chain[1:]):
            e = best[(min(u, v), max(u, v))]
            c = np.asarray(pieces[e].coords)[:, :2]
            if ends[e, 0] != u:
                c = c[::-1]
            leg_xy.append(c[1:])
            leg_w += [pw[e]] * (len(c) - 1)
        if leg_xy:
            xy = np.vstack([snapped[i:i + 1, :2], np.vstack(leg_xy)])
            xy[-1] = snapped[i + 1, :2]
            # Heights linear in arc length between the two waypoints.
            s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
            frac = s / s[-1] if s[-1] > 0 else np.zeros_like(s)
            z = wp[i, 2] + frac * (wp[i + 1, 2] - wp[i, 2])
            pts_out.append(np.column_stack([xy[1:], z[1:]]))
            seg_width += leg_w
        wp_index.append(sum(len(p) for p in pts_out) - 1)
    pts = np.vstack(pts_out)
    # Drop repeated vertices (a waypoint snapped onto a junction, two waypoints on one point).
    keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9])
    new_index = np.cumsum(keep) - 1
    widths_out = np.asarray(seg_width)[keep[1:]] if len(seg_width) else np.zeros(0)
    pts = pts[keep]
    tol = np.zeros(len(pts))
    if len(pts) > 2:
        tol[1:-1] = 0.5 * np.minimum(widths_out[:-1], widths_out[1:])
    idx = new_index[np.asarray(wp_index)]
    inner = idx[(idx > 0) & (idx < len(pts) - 1)]
    tol[inner] = np.minimum(tol[inner], waypoint_tolerance_m)
    length = float(np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1).sum()) if len(pts) > 1 else 0.0
    return Route(pts, tol, idx, snapped, length)
