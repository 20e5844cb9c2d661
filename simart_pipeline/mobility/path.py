"""Corner-blended paths through waypoints: straight segments joined by clothoid pairs.

A waypoint path is a polyline. At each interior vertex the platform either

- **passes a blend**: a symmetric pair of clothoids (Euler spirals) tangent to both segments, in
  the plane the two segments span. Curvature rises linearly from 0 to ``theta / Lc`` over the first
  clothoid and falls back to 0 over the second (``theta`` the turning angle, ``Lc`` the length of
  one clothoid), so curvature is continuous along the whole path and its rate of change is the
  constant ``theta / Lc**2``. The blend's point nearest the vertex lies on the bisector at
  ``deviation = tolerance`` or less, and a blend uses at most half of each adjacent segment;
- **or stops** there: when the vertex's tolerance is zero, when the path turns back on itself
  (``theta`` within 1e-6 rad of pi), or when the blend's horizontal tangent would come near zero
  (a nearly vertical climb or descent on either side, where the heading along the velocity is
  undefined). A stop lets the platform turn in place.

Vertices within 1e-6 rad of a straight line are dropped: the path runs straight through them.

Geometry is evaluated in closed form (Fresnel integrals, ``scipy.special.fresnel``): position, unit
tangent ``T``, and its arc-length derivatives ``T' = kappa N`` and ``T''`` (which the jerk needs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import fresnel

LINE, BLEND = 0, 1
STRAIGHT_ANGLE_RAD = 1e-6       # below: the vertex is dropped, the path runs straight through it
REVERSAL_ANGLE_RAD = np.pi - 1e-6  # above: the path turns back, the platform stops and turns in place
MIN_HORIZONTAL_FRACTION = 0.2   # blends whose horizontal tangent shrinks below this (of 1) stop instead


@dataclass(frozen=True)
class CornerPath:
    """Pieces along the path in order: lines, and blends between lines. Two consecutive lines
    meet at a stop. Arrays are ``[num_pieces]`` unless noted; lengths in m, angles in rad."""

    kind: np.ndarray          # LINE or BLEND
    length_m: np.ndarray
    origin_m: np.ndarray      # [num_pieces, 3]: start point of the piece
    e1: np.ndarray            # [num_pieces, 3]: line direction; blend: incoming direction
    e2: np.ndarray            # [num_pieces, 3]: blend: unit normal in the turn plane, towards the turn
    turn_rad: np.ndarray      # blend turning angle theta (0 for lines)
    half_length_m: np.ndarray  # blend: length Lc of one clothoid (0 for lines)
    heading_rad: np.ndarray   # unwrapped heading of the horizontal direction at the piece's start
    vertices_m: np.ndarray    # [num_vertices, 3]: the polyline after dropping straight-through vertices
    vertex_kept: np.ndarray   # [num_input_vertices] bool: which input vertices are corners or ends
    deviation_m: np.ndarray   # [num_vertices]: distance from each vertex to the path (0: exact)
    stop: np.ndarray          # [num_vertices] bool: the platform is at rest at the vertex

    @property
    def total_length_m(self) -> float:
        return float(self.length_m.sum())


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def blend_shape(theta):
    """Tangent length and deviation of a blend turning by ``theta`` (rad, scalar or array), per
    metre of ``Lc``.

    The tangent length is the distance from the vertex to where the blend leaves each segment;
    the deviation is the distance from the vertex to the blend's midpoint, its nearest point.
    """
    k = np.sqrt(np.pi / theta)
    sz, cz = fresnel(np.sqrt(theta / np.pi))
    xm, ym = k * cz, k * sz                      # end of the first clothoid, per unit Lc
    return xm + ym * np.tan(theta / 2), ym / np.cos(theta / 2)


def _heading(u: np.ndarray) -> float | None:
    return float(np.arctan2(u[1], u[0])) if np.hypot(u[0], u[1]) > 1e-9 else None


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def corner_path(vertices_m: np.ndarray, tolerance_m: np.ndarray) -> CornerPath:
    """The corner-blended path through ``vertices_m`` ``[n, 3]`` (m).

    :param tolerance_m: ``[n]`` largest distance (m) the path may keep from each vertex (the first
        and last are always reached exactly); 0 makes the platform stop at the vertex.
    """
    pts = np.asarray(vertices_m, dtype=np.float64)
    tol = np.asarray(tolerance_m, dtype=np.float64)
    if len(pts) < 2:
        raise ValueError("a path needs at least two vertices")
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    if np.any(seg <= 1e-9):
        i = int(np.argmax(seg <= 1e-9))
        raise ValueError(f"vertices {i} and {i + 1} coincide")
    # Drop straight-through vertices.
    keep = [0]
    for i in range(1, len(pts) - 1):
        u_in = _unit(pts[i] - pts[keep[-1]])
        u_out = _unit(pts[i + 1] - pts[i])
        if np.arccos(np.clip(u_in @ u_out, -1.0, 1.0)) >= STRAIGHT_ANGLE_RAD:
            keep.append(i)
    keep.append(len(pts) - 1)
    kept = np.zeros(len(pts), bool)
    kept[keep] = True
    v, tv = pts[keep], tol[keep]
    n = len(v)
    u = _unit(np.diff(v, axis=0))                       # [n - 1, 3] segment directions
    seg = np.linalg.norm(np.diff(v, axis=0), axis=1)
    # Headings of the segments, unwrapped; a vertical segment keeps its neighbour's heading.
    raw = [_heading(d) for d in u]
    known = [h for h in raw if h is not None]
    prev = known[0] if known else 0.0
    filled = []
    for h in raw:
        prev = h if h is not None else prev
        filled.append(prev)
    heading = np.unwrap(np.asarray(filled))
    # Corners: tangent length d (m) cut from each adjacent segment, or a stop.
    d = np.zeros(n)
    theta = np.zeros(n)
    lc = np.zeros(n)
    dev = np.zeros(n)
    stop = np.ones(n, bool)
    normal = np.zeros((n, 3))
    for i in range(1, n - 1):
        a, b = u[i - 1], u[i]
        th = float(np.arccos(np.clip(a @ b, -1.0, 1.0)))
        if tv[i] <= 0 or th > REVERSAL_ANGLE_RAD:
            continue
        w = _unit(b - (a @ b) * a)
        phi = np.linspace(0.0, th, 33)
        tang = np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * w
        if np.hypot(tang[:, 0], tang[:, 1]).min() < MIN_HORIZONTAL_FRACTION:
            continue
        d_hat, e_hat = (float(x) for x in blend_shape(th))
        lc_i = min(tv[i] / e_hat, 0.5 * min(seg[i - 1], seg[i]) / d_hat)
        theta[i], lc[i], d[i], dev[i] = th, lc_i, lc_i * d_hat, lc_i * e_hat
        normal[i] = w
        stop[i] = False
    kinds, lengths, origins, e1s, e2s, turns, halves, heads = ([] for _ in range(8))
    for k in range(n - 1):
        kinds.append(LINE)
        lengths.append(max(seg[k] - d[k] - d[k + 1], 0.0))
        origins.append(v[k] + d[k] * u[k])
        e1s.append(u[k])
        e2s.append(np.zeros(3))
        turns.append(0.0)
        halves.append(0.0)
        heads.append(heading[k])
        if k + 1 < n - 1 and not stop[k + 1]:
            kinds.append(BLEND)
            lengths.append(2 * lc[k + 1])
            origins.append(v[k + 1] - d[k + 1] * u[k])
            e1s.append(u[k])
            e2s.append(normal[k + 1])
            turns.append(theta[k + 1])
            halves.append(lc[k + 1])
            heads.append(heading[k])
    return CornerPath(np.array(kinds), np.array(lengths), np.array(origins), np.array(e1s), np.array(e2s),
                      np.array(turns), np.array(halves), np.array(heads), v, kept, dev, stop)


def evaluate(path: CornerPath, piece: np.ndarray, s_m: np.ndarray) -> tuple[np.ndarray, ...]:
    """Position, unit tangent ``T``, ``dT/ds`` and ``d2T/ds2`` at arc length ``s_m`` [q] (m, from
    each piece's start) on pieces ``piece`` [q]; each result ``[q, 3]`` (m, 1, m-1, m-2)."""
    piece = np.asarray(piece)
    s = np.clip(np.asarray(s_m, np.float64), 0.0, path.length_m[piece])
    o, e1, e2 = path.origin_m[piece], path.e1[piece], path.e2[piece]
    pos = o + s[:, None] * e1
    tan = e1.copy()
    k1 = np.zeros_like(pos)
    k2 = np.zeros_like(pos)
    b = path.kind[piece] == BLEND
    if b.any():
        th, lc, sb = path.turn_rad[piece][b], path.half_length_m[piece][b], s[b]
        alpha = th / (2 * lc**2)                       # heading = alpha s**2 on the first clothoid
        kk = lc * np.sqrt(np.pi / th)                  # Fresnel scale: alpha r**2 = (pi / 2) (r / kk)**2
        first = sb <= lc
        r = np.where(first, sb, 2 * lc - sb)           # distance from the nearer blend end
        fs, fc = fresnel(r / kk)
        x1, y1 = kk * fc, kk * fs
        d = lc * blend_shape(th)[0]
        # Second clothoid: the first one mirrored, measured back from the blend's end point.
        ex, ey = d + d * np.cos(th), d * np.sin(th)
        c, sn = np.cos(th), np.sin(th)
        x2 = ex - (c * x1 + sn * y1)
        y2 = ey - (sn * x1 - c * y1)
        x, y = np.where(first, x1, x2), np.where(first, y1, y2)
        phi = np.where(first, alpha * r**2, th - alpha * r**2)
        dphi = 2 * alpha * r                           # curvature
        ddphi = np.where(first, 2 * alpha, -2 * alpha)  # its rate of change along s
        t2 = np.stack([np.cos(phi), np.sin(phi)], -1)
        n2 = np.stack([-np.sin(phi), np.cos(phi)], -1)
        k1_2 = dphi[:, None] * n2
        k2_2 = ddphi[:, None] * n2 - (dphi**2)[:, None] * t2

        def lift(xy):
            return xy[:, :1] * e1[b] + xy[:, 1:] * e2[b]

        pos[b] = o[b] + lift(np.stack([x, y], -1))
        tan[b] = lift(t2)
        k1[b] = lift(k1_2)
        k2[b] = lift(k2_2)
    return pos, tan, k1, k2


def blend_curvature(path: CornerPath) -> tuple[np.ndarray, np.ndarray]:
    """Peak curvature ``theta / Lc`` (m-1) and curvature rate ``theta / Lc**2`` (m-2) per piece
    (0 for lines)."""
    b = path.kind == BLEND
    kmax = np.zeros(len(path.kind))
    krate = np.zeros(len(path.kind))
    kmax[b] = path.turn_rad[b] / path.half_length_m[b]
    krate[b] = path.turn_rad[b] / path.half_length_m[b] ** 2
    return kmax, krate


def blend_heading(path: CornerPath, piece: np.ndarray, tangent: np.ndarray, dtangent: np.ndarray):
    """Heading (rad, unwrapped from the piece's entry heading) and its rate per metre of arc
    (rad m-1) along blends, from the horizontal tangent."""
    e1 = path.e1[piece]
    rel = _wrap(np.arctan2(tangent[:, 1], tangent[:, 0]) - np.arctan2(e1[:, 1], e1[:, 0]))
    h2 = tangent[:, 0] ** 2 + tangent[:, 1] ** 2
    rate = (tangent[:, 0] * dtangent[:, 1] - tangent[:, 1] * dtangent[:, 0]) / np.maximum(h2, 1e-12)
    return path.heading_rad[piece] + rel, rate
