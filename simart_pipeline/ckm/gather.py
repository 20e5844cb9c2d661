"""Diffuse gathering: the last diffuse reflection of few-hit cells, estimated from the cell.

The one-pass solver reaches a cell's diffusely scattered power from the scatter points: a
scattered ray that crosses the cell, or a hit's connection drawn to it (next-event estimation,
:meth:`simart_pipeline.ckm.shoot_bounce.Tracer._connect`). Both weigh a scatter point ``x`` by
``f_s / r^2`` (``r`` its distance to the cell): a wall two metres from a cell counts hundreds of
times more than one fifty metres away, so where no strong path reaches a cell (behind the
station's array, deep in a side street) a few samples that happen to fall near it carry the cell.
That is a heavy-tailed sum, in PathSolver as in the one-pass (docs/ckm-one-pass.md, "Session
34"), and more rays barely tame it.

Written over the solid angle seen from the cell instead, the same power has no such weight:

``P(o) = integral over surfaces E_d(x) f_s(x -> o) / r^2 dA = integral over directions
E_d(x(w)) f_s(x(w) -> o) / |cos theta_x| dw``,

``E_d`` the diffuse part of the irradiance at the first surface point ``x(w)`` seen from ``o`` in
direction ``w``, ``theta_x`` the angle at ``x`` between its face normal and ``o``. For a
Lambertian face ``f_s = cos theta_x / pi`` and the integrand is ``E_d / pi``: bounded. This module
estimates it in few-hit cells (final gathering, as in photon mapping, Jensen 1996):

1. **Gather rays.** From the cell's outdoor sample points (those of :mod:`.outdoor`, 4 x 4 a
   cell) ``directions_per_point`` directions each, a spherical Fibonacci set turned by a random
   rotation per point (seeded: deterministic), cast to their first hit on a face that scatters
   (``S > 0``).
2. **Photons.** A second pass of ``photon_rays`` transmitter rays (a Fibonacci lattice of its own,
   with every mechanism as in the main pass, :attr:`Tracer.photons`) records each hit within the
   gather radius ``R`` of a gather point: point, face, incident field and direction, diffuse energy
   ``w_diff = S^2 |R E|^2``, path length and departure direction; it deposits nothing.
3. **Density estimate.** At each gather point the :data:`DEFAULT_GATHER_NEIGHBOURS` photons
   nearest to it within ``R`` (:func:`gather_pairs`; the kernel's radius shrinks to the farthest
   one's distance where all lie within ``R``) on the same face plane and side (normals within
   :data:`SAME_SIDE_COS`, plane offset within :data:`PLANE_TOLERANCE_M`) each give a connection
   to the gather ray's origin, Sionna's scattered field of that photon (``_scattered_field``,
   ``_received``: pattern, XPD, receiver polarisation as every deposit), weighted by the 2-D
   Epanechnikov kernel (:func:`epanechnikov`) and ``w_sr / |cos theta_x|``, ``w_sr`` the gather
   ray's solid angle (``4 pi / directions`` for uniform rays). Its delay is the photon's path
   length plus the distance to the cell centre, its arrival direction from the gather point to the
   centre, its departure the photon's: the same layers as any deposit.

**Guided rays** (:func:`guide_faces`, :func:`guided_directions`). Where the light comes from a lit
face that fills a small part of the cell's sky, uniform rays rarely meet it and a few carry the
cell. So pilot rays from each point find the faces the transmitter lights directly (the lattice
rays' first hits, :meth:`Tracer.collect_lit`); a cell's guide is what the pilots of its neighbours
found and the lit faces near those; half a point's rays go to points drawn on the guide's faces,
half stay uniform, each weighted by multiple importance sampling (the balance heuristic over
both), so the estimate stays unbiased whatever the guide (docs/ckm-one-pass.md, "Session 43").

In the chosen cells these deposits and the main pass's deposits whose last interaction was a
lattice ray's diffuse reflection (first crossings after it and connections, tagged
``diffuse_last`` by the tracer) are weighed by their relative variances
(``one_pass._gather_diffuse``); everything else of the cell stays (specular paths, paths that
scatter and then reflect, diffracted rays). The estimate is biased by the kernel (irradiance
blurred over ``R``; a disc that overhangs a face's edge misses its outer part) and consistent as
``R`` shrinks with more photons; its noise no longer depends on how close a scatter point lies.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from simart_pipeline.ckm.compiled import compiled

from simart_pipeline.ckm.outdoor import OUTDOOR_SAMPLES_PER_AXIS, cell_sample_points, points_inside

# x 16 outdoor sample points: 256 gather rays a cell. On Munich at 1e7 rays against 1e8, 32 took
# the map's p95 to 12.1 dB (16.5 without), 16 to 12.5, at 44 % of the gather's time (docs/ckm-one-pass.md
# "Session 36")
DEFAULT_GATHER_DIRECTIONS_PER_POINT = 16
DEFAULT_GATHER_RADIUS_CELLS = 1.0  # the kernel radius R, in cell sizes
DEFAULT_PHOTON_RAY_SHARE = 0.25  # photon rays per main-pass ray
DEFAULT_GATHER_NEIGHBOURS = 16  # photons examined per gather point at most (gather_pairs)
DEFAULT_GATHER_BELOW_EFFECTIVE_HITS = 10.0  # cells whose effective count is below this are gathered
# diffuse_gather="auto" gathers where the few-hit cells are at least this share of the cells outside
# the mask (counted at GATHER_AUTO_REFERENCE_RAYS): Munich's 29-54 % at 3e6-1e8 rays (at 1e7 the
# map's mean error -1.8 -> -0.6 dB, p95 16.5 -> 12.5 dB for 1.2x the time; 1.2x the rays: -1.7,
# 15.6 dB), not urban's 11-22 % at 3e6-1e7 (1.3x the rays do better in less time) nor the street
# canyon's 4-8 % (docs/ckm-one-pass.md "Session 36")
DEFAULT_GATHER_AUTO_MIN_SHARE = 0.25
# ... counting the cells that would be few-hit cells at this many rays (effective count below
# threshold x num_rays / this): the shares above are those at 1e7 rays, whatever the call's rays
GATHER_AUTO_REFERENCE_RAYS = 10**7
# Guided gathering (guide_faces, guided_directions): per gather point this many pilot rays find the
# faces it sees that the transmitter lights directly (the lattice rays' first hits, Tracer.
# collect_lit); the gather rays then go, DEFAULT_GATHER_GUIDED_SHARE of them, to points drawn on those faces
# (multi-sample importance sampling with the balance heuristic, the rest uniform: unbiased whatever
# the guide). A lit wall that fills 0.5 % of a cell's sky gets ~1 of 256 uniform rays (Munich's
# (107.5, -84) m: -154 dB against PathSolver's -133, docs/ckm-one-pass.md "Session 43").
# Half the rays guided and 6 photons a guided point (below): on Munich at 1e7 rays the same errors
# on the settled benchmark cells as 3/4 of them and 8 or 16 photons, and the fastest: side by side
# with RadioMapSolver 1.92x its time against 1.98-2.01x in one run (uniform rays 1.72x), 2.03x
# against uniform rays' 1.85x in another (runs differ by about 0.1x)
DEFAULT_GATHER_PILOT_DIRECTIONS = 8
DEFAULT_GATHER_GUIDED_SHARE = 0.5
# photons examined per gather point where the rays are guided: guided rays meet lit faces, where
# photons are dense (16: 4.3x the pairs of uniform rays, and their deposits' time)
GUIDED_GATHER_NEIGHBOURS = 6
GUIDE_NEIGHBOUR_CELLS = 1  # a cell's guide: the lit faces the pilots of the cells this near found
GUIDE_EXPAND_M = 15.0  # ... and the lit faces whose centroids lie this near a found one's
GUIDE_MAX_FACES = 16  # per cell at most (the largest expected shares, see guide_faces)
# faces larger than this are not aimed at: area sampling spreads over all of a face, and the ground
# plane of a city scene (two triangles of ~1 km^2 on Munich) is lit somewhere but rarely near the cell
GUIDE_MAX_FACE_AREA_M2 = 5000.0
_PILOT_SEED = 0x9117
_GUIDE_SEED = 0x6D1D
PLANE_TOLERANCE_M = 0.05  # a photon's point lies this close to the gather point's face plane
SAME_SIDE_COS = 0.999  # and its face normal (incoming side) within 2.6 deg of the gather face's
MAX_RECORDER_VOXELS = 1 << 26  # the photon recorder's voxel grid: 64 MB at most
_GATHER_SEED = 0x5EED
_PAIRS_PER_CHUNK = 1 << 22
GATHER_RAYS_PER_BATCH = 1 << 21


class PhotonRecorder:
    """Keeps the photons that lie within ``radius_m`` of any gather point and stores them as numpy.
    The test is a boolean voxel grid over the gather points' bounding box: voxels of at least the
    radius (coarser where the box would need more than :data:`MAX_RECORDER_VOXELS`), the gather
    points' voxels dilated by one (half-radius voxels dilated by two kept 96 % of Munich's photons
    at five times the grid's cost)."""

    def __init__(self, gather_points_m: np.ndarray, radius_m: float):
        pts = np.ascontiguousarray(gather_points_m, np.float64)
        box = np.array([[np.inf] * 3, [-np.inf] * 3])
        _grow_box(pts, box)
        self.lo = box[0] - radius_m
        extent = box[1] + radius_m - self.lo
        self.voxel = max(float(radius_m), float(np.cbrt(np.prod(extent + radius_m) / MAX_RECORDER_VOXELS)))
        self.shape = np.maximum(np.ceil(extent / self.voxel).astype(np.int64) + 1, 1)
        occupied = np.zeros(self.shape, bool)
        occupied.reshape(-1)[self._keys(pts)] = True
        for axis in range(3):  # dilated by one voxel: the 3 x 3 x 3 cube, one axis at a time
            moved = np.moveaxis(occupied, axis, 0)
            grown = moved.copy()
            grown[1:] |= moved[:-1]
            grown[:-1] |= moved[1:]
            occupied = np.moveaxis(grown, 0, axis)
        self.occupied = np.ascontiguousarray(occupied).reshape(-1)
        self.parts: list[dict] = []

    def _keys(self, points_m: np.ndarray) -> np.ndarray:
        """Flat voxel indices (C order), -1 outside the box (compiled: numpy's temporaries of a
        few million points cost more than the arithmetic)."""
        keys = np.empty(len(points_m), np.int64)
        _voxel_keys(np.ascontiguousarray(points_m), self.lo, self.voxel, self.shape, keys)
        return keys

    def keep(self, points_m: np.ndarray) -> np.ndarray:
        keys = self._keys(points_m)
        out = keys >= 0
        out[out] = self.occupied[keys[out]]
        return out

    def store(self, photons: dict) -> None:
        self.parts.append(photons)

    def photons(self) -> dict | None:
        if not self.parts:
            return None
        return {k: np.concatenate([p[k] for p in self.parts]) for k in self.parts[0]}


def gather_origins(radio, grid, cells: np.ndarray, solids) -> tuple[np.ndarray, np.ndarray]:
    """The outdoor sample points of the flat ``cells`` (those of :func:`.outdoor.outdoor_fraction`:
    the centres of a 4 x 4 finer grid per cell, points inside a solid left out): (points ``[P, 3]``
    m, their cell). The same points and test as the cells' outdoor share, which the gather's
    normalisation relies on (:func:`gather_deposits`)."""
    pts = cell_sample_points(grid, cells)
    cell_of = np.repeat(cells, OUTDOOR_SAMPLES_PER_AXIS**2)
    inside = points_inside(radio, pts, solids)
    return pts[~inside], cell_of[~inside]


def gather_rotations(num_points: int, seed: int = _GATHER_SEED) -> np.ndarray:
    """``[num_points, 3, 3]`` uniformly random rotations, one per gather point (seeded)."""
    return Rotation.random(num_points, random_state=seed).as_matrix()


def gather_directions(rotations: np.ndarray, per_point: int) -> np.ndarray:
    """``[len(rotations), per_point, 3]`` unit directions: a spherical Fibonacci set of
    ``per_point`` turned by each point's rotation (:func:`gather_rotations`), so each point's set
    is stratified and the points' sets independent."""
    i = np.arange(per_point, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / per_point
    phi = 2.0 * np.pi * np.modf(i / ((1.0 + 5.0**0.5) / 2.0))[0]
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    base = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    return np.einsum("pij,kj->pki", rotations, base)


def cast_gather_rays(tracer, origins: np.ndarray, directions: np.ndarray, w_sr: np.ndarray | None = None) -> dict:
    """First hits of the gather rays (``directions [P, K, 3]`` from ``origins [P, 3]``) on faces
    that scatter (``S > 0``): per hit its point, the unit normal of its face towards the origin,
    ``|cos|`` of the ray at the face, the origin's row, the global face and the ray's weight in
    steradians (``w_sr [P, K]``: one over the density of its direction, :func:`guided_directions`;
    default ``4 pi / K``, uniform directions)."""
    dr, mi = tracer.dr, tracer.mi
    num_points, k = directions.shape[:2]
    o = np.repeat(origins, k, axis=0)
    d = directions.reshape(-1, 3)
    ray = mi.Ray3f(mi.Point3f(*(o[:, c].astype(np.float32) for c in range(3))),
                   mi.Vector3f(*(d[:, c].astype(np.float32) for c in range(3))))
    pi = tracer.scene.ray_intersect_preliminary(ray, False)
    hit = pi.is_valid()
    ids = dr.reinterpret_array(mi.UInt32, pi.shape)
    face_id, n = tracer.face_at(ids, pi.prim_index, hit)
    s_coef = dr.gather(mi.Float, tracer.scat[0], ids, hit)
    hit &= s_coef > 0
    dr.eval(hit, n, pi.t, face_id)
    keep = np.asarray(hit.numpy(), bool)
    t = pi.t.numpy()[keep].astype(np.float64)
    d = d[keep]
    normal = np.stack([c.numpy()[keep] for c in (n.x, n.y, n.z)], -1).astype(np.float64)
    cos = np.einsum("ij,ij->i", d, normal)
    normal *= -np.sign(cos)[:, None]  # towards the origin
    row = np.repeat(np.arange(num_points), k)[keep]
    w = np.full(num_points * k, 4 * np.pi / k) if w_sr is None else np.asarray(w_sr, np.float64).reshape(-1)
    face = np.asarray(face_id.numpy(), np.int64)[keep]
    return dict(x=o[keep] + t[:, None] * d, n=normal, cos=np.abs(cos), row=row, face=face, w_sr=w[keep])


def trace_photons(tracer, recorder: PhotonRecorder, photon_rays: int, batch_rays: int) -> dict | None:
    """The photon pass: ``photon_rays`` rays of their own Fibonacci lattice (each ``4 pi /
    photon_rays`` sr, random streams numbered from 0 like the main lattice's, different rays)
    traced with the tracer's mechanisms, no deposits; returns the recorder's photons."""
    saved = (tracer.num_rays, tracer.lattice_bins, tracer._lit_face_hits, tracer.tag_diffuse_last)
    tracer.num_rays, tracer.lattice_bins, tracer._lit_face_hits = int(photon_rays), None, None
    tracer.tag_diffuse_last, tracer.photons = False, recorder
    tracer.set_solid_angle(4 * np.pi / int(photon_rays))
    try:
        for start in range(0, int(photon_rays), int(batch_rays)):
            tracer.trace(start, min(start + int(batch_rays), int(photon_rays)), lambda *_: None)
    finally:
        tracer.num_rays, tracer.lattice_bins, tracer._lit_face_hits, tracer.tag_diffuse_last = saved
        tracer.photons = None
        tracer.set_solid_angle(4 * np.pi / tracer.num_rays)
    return recorder.photons()


def gather_pairs(hits: dict, photons: dict, radius_m: float, neighbours: int | np.ndarray = DEFAULT_GATHER_NEIGHBOURS):
    """(gather hit, photon) index pairs and each gather hit's kernel radius: the ``neighbours``
    photons (a number, or one per hit) nearest to the hit within ``radius_m`` are examined; where
    all of them lie within it the radius shrinks to the farthest one's distance, which is left out (``(K - 1) / (pi r_K^2)``
    estimates a uniform density without bias, Jensen's k-nearest photon estimate), else it stays
    ``radius_m`` and every photon within it counts; of those, the photons on the hit's face plane
    and side are paired with it.

    The search is a voxel grid of side ``radius_m`` (a hash table of the photons' voxels: a city's
    box would hold millions of empty ones), the 27 voxels around a hit searched in a compiled loop,
    the hits in voxel order (neighbouring hits read the same photons: 1.8x faster than in ray
    order, 0.72 -> 0.39 s on one thread) and split between threads; its own voxel first, and a voxel
    no nearer than the k-th nearest photon found so far is skipped (Munich's 1.1 M guided gather
    hits at 1e7 rays: the same pairs in 0.63 s against 1.15 s for all 27). A k-d tree
    (``scipy.spatial.cKDTree``) found the same pairs in 2.2x the time on Munich's 2.1 M gather hits
    (1.5 against 0.69 s). Pairs come in the hits'
    voxel order, each hit's by distance."""
    x_hits = np.ascontiguousarray(hits["x"], np.float64)
    n_hits = np.ascontiguousarray(hits["n"], np.float64)
    radius = np.full(len(x_hits), float(radius_m))
    if not len(x_hits) or not len(photons["p"]):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), radius
    p = np.ascontiguousarray(photons["p"])  # float32 as recorded: the loop's arithmetic is float64
    box = np.array([[np.inf] * 3, [-np.inf] * 3])
    _grow_box(x_hits, box)
    _grow_box(p, box)
    lo = box[0] - radius_m
    dims = np.floor((box[1] + radius_m - lo) / radius_m).astype(np.int64) + 1
    if float(np.prod(dims.astype(np.float64))) >= 2.0**62:
        raise ValueError(f"gather_pairs: a box of {dims.tolist()} voxels of {radius_m} m does not fit 64-bit keys")
    keys = np.empty(len(p), np.int64)
    _voxel_keys(p, lo, float(radius_m), dims, keys)
    order = np.argsort(keys)  # introsort: deterministic, twice as fast as a stable sort here
    keys = keys[order]
    first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    starts = np.append(first, len(keys)).astype(np.int64)
    bits = max(4, int(np.ceil(np.log2(2 * len(first)))))
    table_keys, table_voxels = _voxel_table(keys[first], bits)
    p_sorted = np.ascontiguousarray(p[order])
    n_sorted = np.ascontiguousarray(np.asarray(photons["n"])[order])
    hit_keys = np.empty(len(x_hits), np.int64)
    _voxel_keys(x_hits, lo, float(radius_m), dims, hit_keys)
    hit_order = np.argsort(hit_keys)

    k_of = np.broadcast_to(np.asarray(neighbours, np.int64), (len(x_hits),))
    most = int(k_of.max())

    def part(rows_of):
        q, qn = np.ascontiguousarray(x_hits[rows_of]), np.ascontiguousarray(n_hits[rows_of])
        r = np.empty(len(rows_of))
        rows = np.empty(len(rows_of) * most, np.int64)
        cols = np.empty(len(rows_of) * most, np.int64)
        dists = np.empty(len(rows_of) * most)
        n = _pairs_in_voxels(q, qn, p_sorted, n_sorted, order, starts, table_keys, table_voxels, bits, lo,
                             float(radius_m), dims, float(radius_m), _VOXEL_OFFSETS,
                             np.ascontiguousarray(k_of[rows_of]), most, SAME_SIDE_COS, PLANE_TOLERANCE_M, r, rows,
                             cols, dists)
        radius[rows_of] = r
        return rows_of[rows[:n]], cols[:n].copy(), dists[:n].copy()

    threads = os.cpu_count() or 1
    step = max(1, min(_PAIRS_PER_CHUNK // most, -(-len(hit_order) // threads)))
    chunks = [hit_order[lo_:lo_ + step] for lo_ in range(0, len(hit_order), step)]
    with ThreadPoolExecutor(threads) as pool:  # the loop runs without the GIL
        parts = list(pool.map(part, chunks))
    return (np.concatenate([q[0] for q in parts]), np.concatenate([q[1] for q in parts]),
            np.concatenate([q[2] for q in parts]), radius)


@compiled
def _grow_box(points, box):
    """``box`` ([min, max] x 3) grown to hold ``points`` (a strided numpy reduction per axis is slower)."""
    for t in range(points.shape[0]):
        for c in range(3):
            box[0, c] = min(box[0, c], points[t, c])
            box[1, c] = max(box[1, c], points[t, c])


@compiled
def _voxel_keys(points, lo, voxel, dims, out):
    """Each point's voxel of the box from ``lo`` with ``dims`` voxels as one int64 key ``(i * ny +
    j) * nz + k`` (C order), -1 outside the box."""
    for t in range(points.shape[0]):
        i = np.floor((points[t, 0] - lo[0]) / voxel)
        j = np.floor((points[t, 1] - lo[1]) / voxel)
        k = np.floor((points[t, 2] - lo[2]) / voxel)
        if i < 0 or j < 0 or k < 0 or i >= dims[0] or j >= dims[1] or k >= dims[2] or not (i == i and j == j and k == k):
            out[t] = -1
        else:
            out[t] = (np.int64(i) * dims[1] + np.int64(j)) * dims[2] + np.int64(k)


@compiled
def _slot(key, bits):
    """Fibonacci hashing of a voxel key to a slot of a table of ``2**bits``."""
    return np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(64 - bits))


@compiled
def _voxel_table(keys, bits):
    """An open-addressing table (linear probing) from each distinct voxel key to its index in ``keys``."""
    size = 1 << bits
    table_keys = np.full(size, -1, np.int64)
    table_voxels = np.zeros(size, np.int64)
    for u in range(len(keys)):
        s = _slot(keys[u], bits)
        while table_keys[s] != -1:
            s = (s + 1) & (size - 1)
        table_keys[s] = keys[u]
        table_voxels[s] = u
    return table_keys, table_voxels


# the 27 voxels around a gather hit's, its own first and the corners last: the nearest photons are
# found early, and the voxels beyond the k-th nearest's distance are skipped (_pairs_in_voxels)
_VOXEL_OFFSETS = np.array(sorted(((a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)),
                                 key=lambda o: o[0] ** 2 + o[1] ** 2 + o[2] ** 2), np.int64)


@compiled
def _pairs_in_voxels(q, qn, p, pn, order, starts, table_keys, table_voxels, bits, lo, voxel, dims, radius,
                     offsets, k_of, most, cos_min, plane_tol, out_radius, rows, cols, dists):
    """:func:`gather_pairs` for the hits ``q`` (normals ``qn``) against the photons ``p`` (normals
    ``pn``) sorted by voxel (``order``: their indices before; ``starts``: each voxel's first), the
    voxels around a hit's visited in the order of ``offsets`` (:data:`_VOXEL_OFFSETS`): each hit's
    ``k_of[j]`` (at most ``most``) nearest within ``radius`` by insertion into a sorted list, its
    kernel radius, its pairs on its plane and side. Returns the number of pairs written."""
    size_mask = (1 << bits) - 1
    r2 = radius * radius
    best_d2 = np.empty(most)
    best = np.empty(most, np.int64)
    n = 0
    for j in range(q.shape[0]):
        k = k_of[j]
        m = 0
        c0 = np.int64(np.floor((q[j, 0] - lo[0]) / voxel))
        c1 = np.int64(np.floor((q[j, 1] - lo[1]) / voxel))
        c2 = np.int64(np.floor((q[j, 2] - lo[2]) / voxel))
        for o in range(offsets.shape[0]):
            a0, a1, a2 = c0 + offsets[o, 0], c1 + offsets[o, 1], c2 + offsets[o, 2]
            if a0 < 0 or a1 < 0 or a2 < 0 or a0 >= dims[0] or a1 >= dims[1] or a2 >= dims[2]:
                continue
            # a voxel no nearer than the search's bound holds no photon it would keep: skipped (a
            # micrometre's slack: a photon's voxel came from a division, its bounds here from a product)
            g0 = max(lo[0] + a0 * voxel - q[j, 0], q[j, 0] - (lo[0] + (a0 + 1) * voxel), 1e-6) - 1e-6
            g1 = max(lo[1] + a1 * voxel - q[j, 1], q[j, 1] - (lo[1] + (a1 + 1) * voxel), 1e-6) - 1e-6
            g2 = max(lo[2] + a2 * voxel - q[j, 2], q[j, 2] - (lo[2] + (a2 + 1) * voxel), 1e-6) - 1e-6
            if g0 * g0 + g1 * g1 + g2 * g2 >= (best_d2[k - 1] if m == k else r2):
                continue
            key = (a0 * dims[1] + a1) * dims[2] + a2
            s = _slot(key, bits)
            while table_keys[s] != -1 and table_keys[s] != key:
                s = (s + 1) & size_mask
            if table_keys[s] == -1:
                continue
            u = table_voxels[s]
            for t in range(starts[u], starts[u + 1]):
                e0, e1, e2 = p[t, 0] - q[j, 0], p[t, 1] - q[j, 1], p[t, 2] - q[j, 2]
                d2 = e0 * e0 + e1 * e1 + e2 * e2
                if d2 >= r2:
                    continue
                if m < k:
                    pos = m
                    m += 1
                elif d2 < best_d2[k - 1]:
                    pos = k - 1
                else:
                    continue
                while pos > 0 and best_d2[pos - 1] > d2:
                    best_d2[pos] = best_d2[pos - 1]
                    best[pos] = best[pos - 1]
                    pos -= 1
                best_d2[pos] = d2
                best[pos] = t
        use = m
        out_radius[j] = radius
        if m == k:  # the k-th nearest sets the radius and lies on the kernel's rim: weight 0
            out_radius[j] = np.sqrt(best_d2[k - 1])
            use = k - 1
        for h in range(use):
            t = best[h]
            if qn[j, 0] * pn[t, 0] + qn[j, 1] * pn[t, 1] + qn[j, 2] * pn[t, 2] <= cos_min:
                continue
            off = qn[j, 0] * (p[t, 0] - q[j, 0]) + qn[j, 1] * (p[t, 1] - q[j, 1]) + qn[j, 2] * (p[t, 2] - q[j, 2])
            if abs(off) >= plane_tol:
                continue
            rows[n] = j
            cols[n] = order[t]
            dists[n] = np.sqrt(best_d2[h])
            n += 1
    return n


def epanechnikov(distance_m, radius_m):
    """The 2-D Epanechnikov kernel ``2 (1 - d^2 / r^2) / (pi r^2)`` (unit integral over the disc):
    smooth at its rim, so the photon at the k-nearest radius, and the regular spacing of photons
    from a lattice, bias it less than a flat disc (Silverman 1986; a flat disc with ``(K - 1) /
    (pi r_K^2)`` read 3 % low on the Lambertian ground of the tests)."""
    return 2.0 * np.maximum(1.0 - (distance_m / radius_m) ** 2, 0.0) / (np.pi * radius_m**2)


def gather_deposits(tracer, hits: dict, photons: dict, rows, cols, dists, radius_m: np.ndarray, origins: np.ndarray,
                    cell_of: np.ndarray, centres: np.ndarray, photon_rays: int,
                    points_per_cell: int, sink) -> np.ndarray:
    """The gathered deposits of the pairs (``rows``: gather hits, ``cols``: photons, ``dists``: their
    distances; ``radius_m``: each gather hit's kernel radius, :func:`epanechnikov`) handed to ``sink`` in chunks, in the tracer's deposit form
    (see the module docstring); returns each gather hit's power (the sum of its pairs')."""
    from simart_pipeline.ckm.shoot_bounce import direction_terms

    dr, mi = tracer.dr, tracer.mi
    # per pair: (1 / points a cell) w_sr kernel (lambda / 4 pi)^2 (4 pi / photons) |E_s|^2 /
    # |cos theta_x|, w_sr the gather ray's solid angle (4 pi / directions where they are uniform,
    # cast_gather_rays); the solver divides each cell by its outdoor share (outdoor points / points
    # a cell), which makes the sum over outdoor points their mean
    scale = 1.0 / points_per_cell * (4 * np.pi / photon_rays) * (
        tracer._power_per_sr * tracer.grid.dx * tracer.grid.dy)

    def vec(a):
        return mi.Vector3f(*(np.ascontiguousarray(a[:, c], np.float32) for c in range(3)))

    per_hit = np.zeros(len(hits["x"]))
    for lo in range(0, len(rows), _PAIRS_PER_CHUNK):
        j, k = rows[lo:lo + _PAIRS_PER_CHUNK], cols[lo:lo + _PAIRS_PER_CHUNK]
        row = hits["row"][j]
        x = hits["x"][j]
        o = origins[row]
        c = centres[cell_of[row]]
        ko_np = o - x
        ko_np /= np.sqrt(np.einsum("ij,ij->i", ko_np, ko_np))[:, None]  # np.linalg.norm: 3x slower
        v_c = c - x
        r_c = np.sqrt(np.einsum("ij,ij->i", v_c, v_c))
        d, n = vec(photons["d"][k]), vec(photons["n"][k])
        d_r = d - 2.0 * dr.dot(d, n) * n
        ko = vec(ko_np)
        fs, _ = tracer._scattering_density(d, n, d_r, mi.UInt32(photons["pat"][k]), ko)
        e_re, e_im = tracer._scattered_field(d, ko, vec(photons["e_re"][k]), vec(photons["e_im"][k]),
                                             mi.Float(photons["kx"][k]), mi.Float(photons["w_diff"][k]) * fs)
        weight = scale * hits["w_sr"][j] * epanechnikov(dists[lo:lo + _PAIRS_PER_CHUNK], radius_m[j]) / np.maximum(
            hits["cos"][j], 1e-3)
        power = tracer._received(e_re, e_im, ko) * mi.Float(weight.astype(np.float32))
        out = dict(cell=mi.UInt32(cell_of[row].astype(np.uint32)), power=power,
                   dist=mi.Float((photons["length"][k] + r_c).astype(np.float32)))
        out.update(direction_terms(vec(v_c / r_c[:, None]), vec(photons["dep"][k]), tracer.rot, tracer.with_beams))
        dr.eval(*out.values())
        per_hit += np.bincount(j, power.numpy().astype(np.float64), len(per_hit))
        sink(out if tracer.device_deposits else {key: v.numpy() for key, v in out.items()}, False)
    return per_hit


def triangle_vertices(tracer) -> np.ndarray:
    """``[num faces, 3, 3]`` m: every face's vertices, numbered as the tracer's global faces
    (:func:`.shoot_bounce.face_table`: shape by shape in ``mi_scene.shapes()`` order); kept on the
    tracer after the first call."""
    tri = getattr(tracer, "_triangle_vertices", None)
    if tri is None:
        parts = [shape.vertex_positions_buffer().numpy().reshape(-1, 3).astype(np.float64)[
                 shape.faces_buffer().numpy().reshape(-1, 3).astype(np.int64)] for shape in tracer.scene.shapes()]
        tri = np.concatenate(parts) if parts else np.zeros((0, 3, 3))
        tracer._triangle_vertices = tri
    return tri


def triangle_solid_angle(tri: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Solid angle (sr) of each triangle ``tri [N, 3, 3]`` seen from ``points [N, 3]`` (Van
    Oosterom and Strackee 1983: ``tan(omega / 2) = |a . (b x c)| / (abc + (a . b) c + (a . c) b
    + (b . c) a)``, ``a, b, c`` the vectors to the vertices and their lengths)."""
    a, b, c = (tri[:, k] - points for k in range(3))
    la, lb, lc = (np.sqrt(np.einsum("ij,ij->i", v, v)) for v in (a, b, c))
    num = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb + np.einsum(
        "ij,ij->i", b, c) * la
    return 2.0 * np.arctan2(num, den)


def _cast_in_batches(tracer, origins: np.ndarray, per_point: int, directions_of) -> dict:
    """:func:`cast_gather_rays` over the points in batches of about GATHER_RAYS_PER_BATCH rays
    (a city's few-hit cells can ask for tens of millions); ``directions_of(rows)``: the
    directions ``[n, per_point, 3]`` and weights (sr, or None) of the points ``rows``."""
    step = max(1, GATHER_RAYS_PER_BATCH // int(per_point))
    parts = []
    for lo in range(0, len(origins), step):
        rows = np.arange(lo, min(lo + step, len(origins)))
        d, w = directions_of(rows)
        part = cast_gather_rays(tracer, origins[rows], d, w)
        part["row"] = part["row"] + lo
        parts.append(part)
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def guide_faces(tracer, grid, cells: np.ndarray, origins: np.ndarray, cell_of: np.ndarray,
                pilot_directions: int) -> dict | None:
    """The faces each gathered cell's rays aim at, or None where the tracer collected no lit
    faces (:meth:`Tracer.collect_lit`) or ``pilot_directions`` is 0.

    ``pilot_directions`` uniform rays from each gather point (a Fibonacci set of their own
    rotation) find the faces they first hit that scatter and that a lattice ray hit first (lit by
    the transmitter directly), at most :data:`GUIDE_MAX_FACE_AREA_M2` large. A cell's guide is what
    the pilots of the cells within :data:`GUIDE_NEIGHBOUR_CELLS` found (a wall that fills 0.5 % of
    the sky is found by 47 % of one cell's 16 x 8 pilots, by 99.7 % of nine cells'), each face
    with the share ``q ∝ (lattice hits / area) x solid angle from the cell centre`` (its direct
    irradiance times its size in the cell's sky: its expected part of the gather, Lambertian and
    unobstructed), the :data:`GUIDE_MAX_FACES` largest. Returns ``start`` (``[len(cells) + 1]``,
    CSR over ``cells`` in their order), ``face``, ``q`` (summing to 1 per cell), and per gather
    point its cell's row in ``cells`` (``cell_pos``) and whether that cell has a guide
    (``point_has_guide``)."""
    lit_hits = tracer.lit_face_hits
    if lit_hits is None or int(pilot_directions) <= 0:
        return None
    tri = triangle_vertices(tracer)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    lit = (lit_hits > 0) & (area > 0) & (area <= GUIDE_MAX_FACE_AREA_M2)
    rotations = gather_rotations(len(origins), seed=_PILOT_SEED)
    k = int(pilot_directions)
    pilots = _cast_in_batches(tracer, origins, k, lambda rows: (gather_directions(rotations[rows], k), None))
    keep = lit[pilots["face"]]
    size = grid.nx * grid.ny * len(grid.heights)
    position = np.full(size, -1, np.int64)
    position[cells] = np.arange(len(cells))
    h, iy, ix = np.unravel_index(cell_of[pilots["row"][keep]], grid.shape)
    face = pilots["face"][keep]
    keys = []
    r = GUIDE_NEIGHBOUR_CELLS
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            ny_, nx_ = iy + dy, ix + dx
            ok = (ny_ >= 0) & (ny_ < grid.ny) & (nx_ >= 0) & (nx_ < grid.nx)
            pos = position[np.ravel_multi_index((h[ok], ny_[ok], nx_[ok]), grid.shape)]
            keys.append(pos[pos >= 0] * len(tri) + face[ok][pos >= 0])
    keys = np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)
    pos, face = keys // len(tri), keys % len(tri)
    # a pilot that found one face of a lit building found the building: its other lit faces
    # (a small one can carry a cell and be missed by every pilot) within GUIDE_EXPAND_M
    lit_faces = np.flatnonzero(lit)
    if len(face) and GUIDE_EXPAND_M > 0:
        centroid = tri[lit_faces].mean(axis=1)
        found = np.unique(face)
        near = cKDTree(centroid).query_ball_point(tri[found].mean(axis=1), GUIDE_EXPAND_M)
        counts = np.array([len(v) for v in near])  # CSR over `found`: the lit faces near each
        offsets = np.concatenate([[0], np.cumsum(counts)])
        members = lit_faces[np.concatenate([np.asarray(v, np.int64) for v in near])]
        which = np.searchsorted(found, face)
        reps = counts[which]
        idx = np.repeat(offsets[which] - np.concatenate([[0], np.cumsum(reps)[:-1]]), reps) + np.arange(reps.sum())
        keys = np.unique(np.concatenate([keys, np.repeat(pos, reps) * len(tri) + members[idx]]))
        pos, face = keys // len(tri), keys % len(tri)
    q = lit_hits[face] / area[face] * triangle_solid_angle(tri[face], grid.centres()[cells[pos]])
    # the GUIDE_MAX_FACES largest shares of each cell: by cell, then share, largest first
    order = np.lexsort((-q, pos))
    pos, face, q = pos[order], face[order], q[order]
    first = np.searchsorted(pos, np.arange(len(cells) + 1))
    rank = np.arange(len(pos)) - first[pos]
    sel = (rank < GUIDE_MAX_FACES) & (q > 0)
    pos, face, q = pos[sel], face[sel], q[sel]
    start = np.searchsorted(pos, np.arange(len(cells) + 1))
    q = q / np.bincount(pos, q, len(cells))[pos]
    cell_pos = position[cell_of]
    return {"start": start, "face": face, "q": q, "cell_pos": cell_pos,
            "point_has_guide": start[cell_pos + 1] > start[cell_pos], "pilot_hits": int(len(pilots["face"])),
            "lit_pilot_hits": int(keep.sum())}


def guided_directions(rows: np.ndarray, origins: np.ndarray, guide: dict, tri: np.ndarray,
                      rotations: np.ndarray, per_point: int, guided_share: float) -> tuple[np.ndarray, np.ndarray]:
    """Directions ``[len(rows), per_point, 3]`` of the gather points ``rows`` and each ray's
    weight (sr): one over the density of all the point's techniques at its direction.

    A point whose cell has a guide (:func:`guide_faces`) casts ``round(guided_share x
    per_point)`` rays at points drawn uniformly on its guide's faces (the face by stratified
    draws from the shares ``q``), the rest uniform (the Fibonacci set of that many, turned by the
    point's rotation, as without a guide). Multi-sample importance sampling with the balance
    heuristic (Veach and Guibas 1995): a ray in direction ``w`` weighs ``1 / (n_u / 4 pi + n_g
    sum_t q_t pdf_t(w))``, ``pdf_t(w) = r^2 / (A_t |cos theta_t|)`` where the ray meets face
    ``t`` (at ``r``) and 0 elsewhere, whichever technique drew it; the sum of a point's rays times
    those weights is unbiased for the integral over the sphere whatever the guide, and the uniform
    rays keep every direction reachable. A point without a guide: ``per_point`` uniform rays of
    ``4 pi / per_point`` sr each, as without guiding. The draws hash the point's index: the same
    whatever the batch."""
    k = int(per_point)
    n_g = int(round(float(guided_share) * k))
    n_u = k - n_g
    pos = guide["cell_pos"][rows]
    start = guide["start"]
    has = guide["point_has_guide"][rows] & (n_g > 0)
    d = np.empty((len(rows), k, 3))
    w = np.full((len(rows), k), 4 * np.pi / k)
    if (~has).any():
        d[~has] = gather_directions(rotations[rows[~has]], k)
    g = np.flatnonzero(has)
    if len(g):
        if n_u:
            d[g, :n_u] = gather_directions(rotations[rows[g]], n_u)
        dg, wg = d[g], w[g]
        _guided_rays(np.ascontiguousarray(origins[rows[g]]), rows[g].astype(np.int64), pos[g].astype(np.int64), start,
                     guide["face"], guide["q"], tri, n_u, n_g, _GUIDE_SEED, dg, wg)
        d[g], w[g] = dg, wg
    return d, w


def _guided_rays_py(o, point_id, pos, start, face, q, tri, n_u, n_g, seed, d, w):
    """:func:`guided_directions`' draws and weights for points that have a guide (compiled
    below): ``d [P, n_u + n_g, 3]`` holds the uniform directions in its first ``n_u`` columns;
    the guided ones are drawn into the rest; ``w`` gets every ray's weight."""
    for p in range(o.shape[0]):
        a, b = start[pos[p]], start[pos[p] + 1]
        for j in range(n_g):
            u = (j + _hash01(seed, point_id[p], j, 0)) / n_g  # stratified over the shares
            t = a
            acc = q[a]
            while acc < u and t < b - 1:
                t += 1
                acc += q[t]
            r1 = np.sqrt(_hash01(seed, point_id[p], j, 1))
            r2 = _hash01(seed, point_id[p], j, 2)
            f = face[t]
            x0 = (1.0 - r1) * tri[f, 0, 0] + r1 * (1.0 - r2) * tri[f, 1, 0] + r1 * r2 * tri[f, 2, 0] - o[p, 0]
            x1 = (1.0 - r1) * tri[f, 0, 1] + r1 * (1.0 - r2) * tri[f, 1, 1] + r1 * r2 * tri[f, 2, 1] - o[p, 1]
            x2 = (1.0 - r1) * tri[f, 0, 2] + r1 * (1.0 - r2) * tri[f, 1, 2] + r1 * r2 * tri[f, 2, 2] - o[p, 2]
            n = max(np.sqrt(x0 * x0 + x1 * x1 + x2 * x2), 1e-12)
            d[p, n_u + j, 0], d[p, n_u + j, 1], d[p, n_u + j, 2] = x0 / n, x1 / n, x2 / n
        for j in range(n_u + n_g):
            dens = n_u / (4.0 * np.pi)
            for t in range(a, b):
                dens += n_g * q[t] * _face_density(o[p, 0], o[p, 1], o[p, 2], d[p, j, 0], d[p, j, 1], d[p, j, 2],
                                                   tri, face[t])
            w[p, j] = 1.0 / dens


def _face_density_py(ox, oy, oz, dx, dy, dz, tri, f):
    """Density (per sr) of the direction ``d`` from ``o`` when a point is drawn uniformly on the
    triangle ``tri[f]``: ``r^2 / (A |cos theta|)`` where the ray meets it (Moeller and Trumbore
    1997), else 0."""
    e1x, e1y, e1z = tri[f, 1, 0] - tri[f, 0, 0], tri[f, 1, 1] - tri[f, 0, 1], tri[f, 1, 2] - tri[f, 0, 2]
    e2x, e2y, e2z = tri[f, 2, 0] - tri[f, 0, 0], tri[f, 2, 1] - tri[f, 0, 1], tri[f, 2, 2] - tri[f, 0, 2]
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if abs(det) < 1e-12:
        return 0.0
    inv = 1.0 / det
    tx, ty, tz = ox - tri[f, 0, 0], oy - tri[f, 0, 1], oz - tri[f, 0, 2]
    uu = (tx * px + ty * py + tz * pz) * inv
    if uu < 0.0 or uu > 1.0:
        return 0.0
    qx, qy, qz = ty * e1z - tz * e1y, tz * e1x - tx * e1z, tx * e1y - ty * e1x
    vv = (dx * qx + dy * qy + dz * qz) * inv
    if vv < 0.0 or uu + vv > 1.0:
        return 0.0
    r = (e2x * qx + e2y * qy + e2z * qz) * inv
    if r <= 0.0:
        return 0.0
    nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
    twice_area = np.sqrt(nx * nx + ny * ny + nz * nz)
    cos = abs(dx * nx + dy * ny + dz * nz) / twice_area
    return r * r / (0.5 * twice_area * max(cos, 1e-9))


def _hash01_py(seed, a, b, c):
    """A uniform number in [0, 1) from the integers (``seed, a, b, c``): splitmix64 of their
    mix, so a draw depends on its point and index alone (not on the batch)."""
    x = np.uint64(seed) ^ (np.uint64(a) * np.uint64(0x9E3779B97F4A7C15)) ^ (
        np.uint64(b) * np.uint64(0xC2B2AE3D27D4EB4F)) ^ (np.uint64(c) * np.uint64(0x165667B19E3779F9))
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    x = x ^ (x >> np.uint64(31))
    return float(x >> np.uint64(11)) * (1.0 / 9007199254740992.0)


_hash01 = compiled(_hash01_py)
_face_density = compiled(_face_density_py)
_guided_rays = compiled(_guided_rays_py)


def diffuse_gather(radio, tracer, grid, cells: np.ndarray, solids, sink, *, photon_rays: int,
                   batch_rays: int, directions_per_point: int = DEFAULT_GATHER_DIRECTIONS_PER_POINT,
                   radius_m: float | None = None, pilot_directions: int = DEFAULT_GATHER_PILOT_DIRECTIONS,
                   guided_share: float = DEFAULT_GATHER_GUIDED_SHARE) -> tuple[dict, np.ndarray | None]:
    """Gathered deposits of the last diffuse reflection for the flat ``cells`` into ``sink``
    (module docstring), the rays guided towards the faces the transmitter lights
    (:func:`guide_faces`, :func:`guided_directions`; ``pilot_directions=0``: uniform rays); returns
    what it did and the variance of each cell's gathered power (the gather rays as independent
    samples; None where nothing was gathered)."""
    radius = float(radius_m) if radius_m is not None else DEFAULT_GATHER_RADIUS_CELLS * min(grid.dx, grid.dy)
    k = int(directions_per_point)
    out = {"cells": int(len(cells)), "photon_rays": int(photon_rays), "radius_m": radius,
           "directions_per_point": k, "gather_points": 0, "gather_hits": 0, "photons": 0, "pairs": 0}
    if not len(cells):
        return out, None
    origins, cell_of = gather_origins(radio, grid, cells, solids)
    out["gather_points"] = int(len(origins))
    if not len(origins):
        return out, None
    rotations = gather_rotations(len(origins))  # each point's own, whatever its batch
    guide = guide_faces(tracer, grid, cells, origins, cell_of, pilot_directions)
    if guide is None:
        hits = _cast_in_batches(tracer, origins, k, lambda rows: (gather_directions(rotations[rows], k), None))
    else:
        tri = triangle_vertices(tracer)
        hits = _cast_in_batches(tracer, origins, k, lambda rows: guided_directions(
            rows, origins, guide, tri, rotations, k, guided_share))
        out.update(pilot_directions=int(pilot_directions), guided_share=float(guided_share),
                   guided_cells=int(np.count_nonzero(np.diff(guide["start"]))), guide_faces=int(len(guide["face"])),
                   pilot_hits=guide["pilot_hits"], lit_pilot_hits=guide["lit_pilot_hits"])
    out["gather_hits"] = int(len(hits["x"]))
    if not len(hits["x"]):
        return out, None
    photons = trace_photons(tracer, PhotonRecorder(hits["x"], radius), int(photon_rays), int(batch_rays))
    if photons is None:
        return out, None
    out["photons"] = int(len(photons["p"]))
    neighbours = DEFAULT_GATHER_NEIGHBOURS
    if guide is not None and int(round(float(guided_share) * k)) > 0:  # guided points' hits: fewer photons
        neighbours = np.where(guide["point_has_guide"][hits["row"]], GUIDED_GATHER_NEIGHBOURS,
                              DEFAULT_GATHER_NEIGHBOURS)
    rows, cols, dists, radii = gather_pairs(hits, photons, radius, neighbours)
    out["pairs"] = int(len(rows))
    per_hit = gather_deposits(tracer, hits, photons, rows, cols, dists, radii, origins, cell_of, grid.centres(),
                              int(photon_rays), OUTDOOR_SAMPLES_PER_AXIS**2, sink)
    # each gather ray is one sample of its cell's sum (a ray without a hit: a zero sample): the
    # variance of the sum over a cell's rays
    size = grid.nx * grid.ny * len(grid.heights)
    rays = np.bincount(cell_of, minlength=size) * k
    total = np.bincount(cell_of[hits["row"]], per_hit, size)
    sq = np.bincount(cell_of[hits["row"]], per_hit**2, size)
    variance = np.maximum(sq - total**2 / np.maximum(rays, 1), 0.0)
    return out, variance
