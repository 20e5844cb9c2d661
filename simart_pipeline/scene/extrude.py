"""Buildings as closed solids (walls, roof, floor) and the facade detail of the visual mesh.

**Roofs.** A roof is a height field over the footprint, piecewise planar in the frame of the
footprint's minimum rotated rectangle (length ``L`` along the ridge direction ``u``, width ``W``
across it, ``v``), with ``t`` the top and ``r`` the roof height:

- flat: ``z = t``
- gabled: ``z = t - r |v| / (W/2)`` (ridge along ``u``; ``roof:orientation=across`` turns it)
- hipped: ``z = t - r max(|v|, |u| - (L - W)/2) / (W/2)``
- pyramidal: ``z = t - r max(|u| / (L/2), |v| / (W/2))``
- skillion: ``z = t - r (v + W/2) / W``

The footprint is split along the lines where the height field bends (ridge, hips, diagonals), so
each piece lies in one plane; pieces are triangulated (earcut, no new vertices) and lifted. Walls
stand under every piece edge on the footprint's boundary, from the bottom up to the roof, so the
wall tops and the roof share their vertices and each building is a closed, consistently oriented
(outward) surface: watertight whatever the footprint (concave, with courtyards), because the roof
is a graph over it.

**Facade detail** (visual mesh only): window frames, one per storey and per
:data:`WINDOW_PITCH_M` of facade, standing :data:`WINDOW_DEPTH_M` proud of the wall below the
eaves. Frames that would sit inside a neighbouring building (shared walls) are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mapbox_earcut
import numpy as np
import shapely
import shapely.ops
from shapely.geometry import MultiLineString, Polygon
from shapely.geometry.polygon import orient

DEFAULT_ROOF_PITCH_DEG = 30.0       # gabled, hipped, pyramidal roofs without roof:height
DEFAULT_SKILLION_PITCH_DEG = 15.0
WINDOW_WIDTH_M = 1.2
WINDOW_PITCH_M = 3.0                # facade length per window column
WINDOW_HEIGHT_M = 1.5               # at most half the storey height
WINDOW_DEPTH_M = 0.08               # how far a frame stands out of its wall
SNAP_M = 1e-7                       # vertices closer than this are one


def triangulate(poly: Polygon) -> tuple[np.ndarray, np.ndarray]:
    """Earcut triangulation of a polygon (holes included), triangles counter-clockwise seen from +z.

    :return: (vertices [n, 2] m, triangles [m, 3] int64 into them); no vertex is added
    """
    poly = orient(poly, 1.0)
    rings = [np.asarray(poly.exterior.coords)[:-1, :2]] + [np.asarray(r.coords)[:-1, :2] for r in poly.interiors]
    v = np.concatenate(rings)
    ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
    tri = mapbox_earcut.triangulate_float64(v, ends).astype(np.int64).reshape(-1, 3)
    if len(tri):
        a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
        cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        tri[cross < 0] = tri[cross < 0][:, ::-1]
    return v, tri


@dataclass
class RoofFrame:
    """The roof's frame: centre [2], ridge direction ``u`` [2] (unit), length and width in m."""

    centre: np.ndarray
    u: np.ndarray
    length_m: float
    width_m: float

    @property
    def v(self) -> np.ndarray:
        return np.array([-self.u[1], self.u[0]])

    def local(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = np.asarray(xy, float) - self.centre
        return d @ self.u, d @ self.v

    def world(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, float)
        return self.centre + uv[:, :1] * self.u + uv[:, 1:] * self.v


def roof_frame(poly: Polygon, across: bool = False) -> RoofFrame:
    """The minimum rotated rectangle of ``poly``: ridge along its long side (short side if ``across``)."""
    c = np.asarray(shapely.oriented_envelope(poly).exterior.coords)[:4, :2]
    e0, e1 = c[1] - c[0], c[2] - c[1]
    l0, l1 = float(np.hypot(*e0)), float(np.hypot(*e1))
    if (l0 >= l1) != across:
        u, length, width = e0 / l0, l0, l1
    else:
        u, length, width = e1 / l1, l1, l0
    return RoofFrame(c.mean(0), u, length, width)


def default_roof_height_m(shape: str, frame: RoofFrame) -> float:
    if shape == "skillion":
        return frame.width_m * math.tan(math.radians(DEFAULT_SKILLION_PITCH_DEG))
    return frame.width_m / 2 * math.tan(math.radians(DEFAULT_ROOF_PITCH_DEG))


def roof_z(shape: str, frame: RoofFrame, top: float, rise: float, xy: np.ndarray) -> np.ndarray:
    """Roof height (m) at points ``xy`` [n, 2] (see the module docstring)."""
    u, v = frame.local(xy)
    half_l, half_w = frame.length_m / 2, max(frame.width_m / 2, 1e-9)
    if shape == "gabled":
        s = np.abs(v) / half_w
    elif shape == "hipped":
        s = np.maximum(np.abs(v), np.abs(u) - (frame.length_m - frame.width_m) / 2) / half_w
    elif shape == "pyramidal":
        s = np.maximum(np.abs(u) / max(half_l, 1e-9), np.abs(v) / half_w)
    elif shape == "skillion":
        s = (v + half_w) / (2 * half_w)
    else:
        return np.full(len(xy), top)
    return top - rise * np.clip(s, 0.0, 1.0)


def _fold_lines(shape: str, frame: RoofFrame) -> list[np.ndarray]:
    """Where the roof's height field bends, as line strings [k, 2] in world coordinates."""
    hl, hw = frame.length_m / 2 + 1.0, frame.width_m / 2 + 1.0  # a metre beyond the rectangle
    if shape == "gabled":
        lines = [[(-hl, 0.0), (hl, 0.0)]]
    elif shape == "hipped":
        r = max((frame.length_m - frame.width_m) / 2, 0.0)
        lines = [[(-r, 0.0), (r, 0.0)]] if r > 0 else []
        lines += [[(sx * r, 0.0), (sx * (r + hw), sy * hw)] for sx in (-1, 1) for sy in (-1, 1)]
    elif shape == "pyramidal":
        k = 1.0 + 2.0 / max(min(frame.length_m, frame.width_m), 1e-3)
        a, b = frame.length_m / 2 * k, frame.width_m / 2 * k
        lines = [[(-a, -b), (a, b)], [(-a, b), (a, -b)]]
    else:
        return []
    return [frame.world(np.asarray(seg)) for seg in lines if np.hypot(*np.subtract(*seg)) > 1e-9]


@dataclass
class Solid:
    """A closed building surface and its facade edges."""

    vertices: np.ndarray   # [n, 3] m
    faces: np.ndarray      # [m, 3] int64, outward
    walls: np.ndarray      # [k, 6]: ax, ay, bx, by (outside on the right of a->b), bottom, eave (m)


def building_solid(poly: Polygon, bottom: float, top: float, shape: str = "flat",
                   roof_height_m: float = float("nan"), across: bool = False) -> Solid:
    """A closed, outward-oriented solid: ``poly`` extruded from ``bottom`` to ``top`` under its roof.

    :param roof_height_m: the roof's rise (part of ``top - bottom``); NaN: a 30 degree pitch
        (15 degrees for skillion), at most half the building's height
    """
    poly = shapely.remove_repeated_points(poly, 1e-6)
    # Hipped and pyramidal roofs are symmetric: only gabled and skillion ridges can turn.
    frame = roof_frame(poly, across and shape in ("gabled", "skillion")) if shape != "flat" else None
    span = top - bottom
    if frame is None:
        rise = 0.0
    elif math.isnan(roof_height_m):
        rise = min(default_roof_height_m(shape, frame), span / 2)
    else:
        rise = min(max(roof_height_m, 0.0), span)
    lines = _fold_lines(shape, frame) if rise > 0 else []
    pieces = [poly]
    if lines:
        pieces = [g for g in shapely.ops.split(poly, MultiLineString([ln.tolist() for ln in lines])).geoms
                  if isinstance(g, Polygon) and g.area > 0]
    pieces = [orient(p, 1.0) for p in pieces]
    # Every piece ring's edge a->b with the piece on its left; internal edges come in both directions.
    verts2, tris, edges = [], [], []
    offset = 0
    for piece in pieces:
        v2, tri = triangulate(piece)
        verts2.append(v2)
        tris.append(tri + offset)
        ring_sizes = [len(piece.exterior.coords) - 1] + [len(r.coords) - 1 for r in piece.interiors]
        start = offset
        for n in ring_sizes:
            idx = np.arange(start, start + n)
            edges.append(np.column_stack([idx, np.roll(idx, -1)]))
            start += n
        offset += len(v2)
    v2 = np.concatenate(verts2)
    tri = np.concatenate(tris)
    edges = np.concatenate(edges)
    # One index per distinct point (pieces share their cut vertices exactly).
    uniq, inv = np.unique(v2, axis=0, return_inverse=True)
    inv = inv.ravel()
    tri, edges = inv[tri], inv[edges]
    # Boundary edges: those whose reverse is not an edge of another piece.
    n = len(uniq)
    key = edges[:, 0] * n + edges[:, 1]
    boundary = edges[~np.isin(edges[:, 1] * n + edges[:, 0], key)]
    z_top = roof_z(shape, frame, top, rise, uniq) if frame is not None else np.full(n, top)
    vertices = np.concatenate([np.column_stack([uniq, np.full(n, bottom)]), np.column_stack([uniq, z_top])])
    a, b = boundary[:, 0], boundary[:, 1]
    faces = np.concatenate([
        tri + n,                      # roof, facing up
        tri[:, ::-1],                 # floor, facing down
        np.column_stack([a, b, b + n]),   # walls, facing out (the piece is on the left of a->b)
        np.column_stack([a, b + n, a + n]),
    ])
    walls = np.column_stack([uniq[a], uniq[b], np.full(len(a), bottom), np.minimum(z_top[a], z_top[b])])
    vertices, faces = _weld(vertices, faces)
    return Solid(vertices, faces, walls)


def _weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident vertices (a roof meeting the floor) and drop the faces that collapse."""
    keys = np.round(vertices / SNAP_M).astype(np.int64)
    _, first, inv = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    faces = inv.ravel()[faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return vertices[first], faces[keep]


# Frame box: vertex k = (along, up, out) bits (k & 1, k >> 1 & 1, k >> 2 & 1); the face against
# the wall is left out. Outward winding checked in the tests.
_BOX_FACES = np.array([[4, 5, 7], [4, 7, 6], [2, 7, 3], [2, 6, 7], [0, 1, 5], [0, 5, 4],
                       [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5]], np.int64)
_BOX_BITS = np.array([[k & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)], float)


def window_frames(walls: np.ndarray, storey_m: np.ndarray, instance: np.ndarray,
                  blockers: list | None = None, blocker_bands: np.ndarray | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Window frames on facade edges, vectorised over all of them.

    :param walls: [k, 6] from :attr:`Solid.walls` (ax, ay, bx, by, bottom, eave), m
    :param storey_m: [k] storey height of each edge's building, m
    :param instance: [k] instance id of each edge's building
    :param blockers: footprints (shapely polygons) in which no frame may stand, with
        ``blocker_bands`` [len(blockers), 2] their (bottom, top) in m
    :return: (vertices [8 w, 3], faces [10 w, 3], face instance [10 w]) for ``w`` frames
    """
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64))
    if len(walls) == 0:
        return empty
    a, b, z0, z1 = walls[:, 0:2], walls[:, 2:4], walls[:, 4], walls[:, 5]
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    cols = np.floor(length / WINDOW_PITCH_M).astype(np.int64)
    band = np.maximum(z1 - z0, 0.0)
    rows = np.floor(band / storey_m + 1e-6).astype(np.int64)
    n = cols * rows
    if n.sum() == 0:
        return empty
    e = np.repeat(np.arange(len(walls)), n)
    k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    col, row = k % cols[e], k // cols[e]
    unit = d[e] / length[e, None]
    out = np.column_stack([unit[:, 1], -unit[:, 0]])
    storey = band[e] / rows[e]
    t = (col + 0.5) * length[e] / cols[e]
    centre = a[e] + unit * t[:, None]
    zc = z0[e] + (row + 0.5) * storey
    h = np.minimum(WINDOW_HEIGHT_M, storey / 2)
    keep = np.ones(len(e), bool)
    if blockers:
        probe = centre + out * (WINDOW_DEPTH_M + 0.2)
        pi, bi = shapely.STRtree(blockers).query(shapely.points(probe), predicate="within")
        hidden = (zc[pi] >= blocker_bands[bi, 0]) & (zc[pi] <= blocker_bands[bi, 1])
        keep[pi[hidden]] = False
    e, unit, out, centre, zc, h = e[keep], unit[keep], out[keep], centre[keep], zc[keep], h[keep]
    w = len(e)
    if w == 0:
        return empty
    bits = _BOX_BITS[None]  # [1, 8, 3]
    xy = (centre[:, None, :] + unit[:, None, :] * ((bits[..., 0:1] - 0.5) * WINDOW_WIDTH_M)
          + out[:, None, :] * (bits[..., 2:3] * WINDOW_DEPTH_M))
    z = zc[:, None] + (bits[..., 1] - 0.5) * h[:, None]
    vertices = np.concatenate([xy, z[..., None]], axis=-1).reshape(-1, 3)
    faces = (_BOX_FACES[None] + 8 * np.arange(w)[:, None, None]).reshape(-1, 3)
    return vertices, faces, np.repeat(instance[e], len(_BOX_FACES))
