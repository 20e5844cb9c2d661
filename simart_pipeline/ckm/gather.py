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
   Epanechnikov kernel (:func:`epanechnikov`) and ``4 pi / (directions) / |cos theta_x|``. Its
   delay is the photon's path length plus the distance to the cell centre, its arrival direction
   from the gather point to the centre, its departure the photon's: the same layers as any deposit.

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


def cast_gather_rays(tracer, origins: np.ndarray, directions: np.ndarray) -> dict:
    """First hits of the gather rays (``directions [P, K, 3]`` from ``origins [P, 3]``) on faces
    that scatter (``S > 0``): per hit its point, the unit normal of its face towards the origin,
    ``|cos|`` of the ray at the face, and the origin's row."""
    dr, mi = tracer.dr, tracer.mi
    num_points, k = directions.shape[:2]
    o = np.repeat(origins, k, axis=0)
    d = directions.reshape(-1, 3)
    ray = mi.Ray3f(mi.Point3f(*(o[:, c].astype(np.float32) for c in range(3))),
                   mi.Vector3f(*(d[:, c].astype(np.float32) for c in range(3))))
    pi = tracer.scene.ray_intersect_preliminary(ray, False)
    hit = pi.is_valid()
    ids = dr.reinterpret_array(mi.UInt32, pi.shape)
    _, n = tracer.face_at(ids, pi.prim_index, hit)
    s_coef = dr.gather(mi.Float, tracer.scat[0], ids, hit)
    hit &= s_coef > 0
    dr.eval(hit, n, pi.t)
    keep = np.asarray(hit.numpy(), bool)
    t = pi.t.numpy()[keep].astype(np.float64)
    d = d[keep]
    normal = np.stack([c.numpy()[keep] for c in (n.x, n.y, n.z)], -1).astype(np.float64)
    cos = np.einsum("ij,ij->i", d, normal)
    normal *= -np.sign(cos)[:, None]  # towards the origin
    row = np.repeat(np.arange(num_points), k)[keep]
    return dict(x=o[keep] + t[:, None] * d, n=normal, cos=np.abs(cos), row=row)


def trace_photons(tracer, recorder: PhotonRecorder, photon_rays: int, batch_rays: int) -> dict | None:
    """The photon pass: ``photon_rays`` rays of their own Fibonacci lattice (each ``4 pi /
    photon_rays`` sr, random streams numbered from 0 like the main lattice's, different rays)
    traced with the tracer's mechanisms, no deposits; returns the recorder's photons."""
    saved = (tracer.num_rays, tracer.lattice_bins, tracer._lit_face_mask, tracer.tag_diffuse_last)
    tracer.num_rays, tracer.lattice_bins, tracer._lit_face_mask = int(photon_rays), None, None
    tracer.tag_diffuse_last, tracer.photons = False, recorder
    tracer.set_solid_angle(4 * np.pi / int(photon_rays))
    try:
        for start in range(0, int(photon_rays), int(batch_rays)):
            tracer.trace(start, min(start + int(batch_rays), int(photon_rays)), lambda *_: None)
    finally:
        tracer.num_rays, tracer.lattice_bins, tracer._lit_face_mask, tracer.tag_diffuse_last = saved
        tracer.photons = None
        tracer.set_solid_angle(4 * np.pi / tracer.num_rays)
    return recorder.photons()


def gather_pairs(hits: dict, photons: dict, radius_m: float, neighbours: int = DEFAULT_GATHER_NEIGHBOURS):
    """(gather hit, photon) index pairs and each gather hit's kernel radius: the ``neighbours``
    photons nearest to the hit within ``radius_m`` are examined; where all of them lie within it
    the radius shrinks to the farthest one's distance, which is left out (``(K - 1) / (pi r_K^2)``
    estimates a uniform density without bias, Jensen's k-nearest photon estimate), else it stays
    ``radius_m`` and every photon within it counts; of those, the photons on the hit's face plane
    and side are paired with it.

    The search is a voxel grid of side ``radius_m`` (a hash table of the photons' voxels: a city's
    box would hold millions of empty ones), the 27 voxels around a hit searched in a compiled loop,
    the hits in voxel order (neighbouring hits read the same photons: 1.8x faster than in ray
    order, 0.72 -> 0.39 s on one thread) and split between threads. A k-d tree (``scipy.spatial.cKDTree``) found the same pairs
    in 2.2x the time on Munich's 2.1 M gather hits (1.5 against 0.69 s). Pairs come in the hits'
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

    def part(rows_of):
        q, qn = np.ascontiguousarray(x_hits[rows_of]), np.ascontiguousarray(n_hits[rows_of])
        r = np.empty(len(rows_of))
        rows = np.empty(len(rows_of) * neighbours, np.int64)
        cols = np.empty(len(rows_of) * neighbours, np.int64)
        dists = np.empty(len(rows_of) * neighbours)
        n = _pairs_in_voxels(q, qn, p_sorted, n_sorted, order, starts, table_keys, table_voxels, bits, lo,
                             float(radius_m), dims, float(radius_m), int(neighbours), SAME_SIDE_COS,
                             PLANE_TOLERANCE_M, r, rows, cols, dists)
        radius[rows_of] = r
        return rows_of[rows[:n]], cols[:n].copy(), dists[:n].copy()

    threads = os.cpu_count() or 1
    step = max(1, min(_PAIRS_PER_CHUNK // neighbours, -(-len(hit_order) // threads)))
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


@compiled
def _pairs_in_voxels(q, qn, p, pn, order, starts, table_keys, table_voxels, bits, lo, voxel, dims, radius,
                     k, cos_min, plane_tol, out_radius, rows, cols, dists):
    """:func:`gather_pairs` for the hits ``q`` (normals ``qn``) against the photons ``p`` (normals
    ``pn``) sorted by voxel (``order``: their indices before; ``starts``: each voxel's first):
    each hit's ``k`` nearest within ``radius`` by insertion into a sorted list, its kernel radius,
    its pairs on its plane and side. Returns the number of pairs written."""
    size_mask = (1 << bits) - 1
    r2 = radius * radius
    best_d2 = np.empty(k)
    best = np.empty(k, np.int64)
    n = 0
    for j in range(q.shape[0]):
        m = 0
        c0 = np.int64(np.floor((q[j, 0] - lo[0]) / voxel))
        c1 = np.int64(np.floor((q[j, 1] - lo[1]) / voxel))
        c2 = np.int64(np.floor((q[j, 2] - lo[2]) / voxel))
        for a0 in range(max(c0 - 1, 0), min(c0 + 2, dims[0])):
            for a1 in range(max(c1 - 1, 0), min(c1 + 2, dims[1])):
                for a2 in range(max(c2 - 1, 0), min(c2 + 2, dims[2])):
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
                    cell_of: np.ndarray, centres: np.ndarray, directions_per_point: int, photon_rays: int,
                    points_per_cell: int, sink) -> np.ndarray:
    """The gathered deposits of the pairs (``rows``: gather hits, ``cols``: photons, ``dists``: their
    distances; ``radius_m``: each gather hit's kernel radius, :func:`epanechnikov`) handed to ``sink`` in chunks, in the tracer's deposit form
    (see the module docstring); returns each gather hit's power (the sum of its pairs')."""
    from simart_pipeline.ckm.shoot_bounce import direction_terms

    dr, mi = tracer.dr, tracer.mi
    # per pair: (1 / points a cell) (4 pi / directions) kernel (lambda / 4 pi)^2 (4 pi / photons)
    # |E_s|^2 / |cos theta_x|; the solver divides each cell by its outdoor share (outdoor points /
    # points a cell), which makes the sum over outdoor points their mean
    scale = (4 * np.pi / directions_per_point) / points_per_cell * (
        4 * np.pi / photon_rays) * (tracer._power_per_sr * tracer.grid.dx * tracer.grid.dy)

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
        weight = scale * epanechnikov(dists[lo:lo + _PAIRS_PER_CHUNK], radius_m[j]) / np.maximum(hits["cos"][j], 1e-3)
        power = tracer._received(e_re, e_im, ko) * mi.Float(weight.astype(np.float32))
        out = dict(cell=mi.UInt32(cell_of[row].astype(np.uint32)), power=power,
                   dist=mi.Float((photons["length"][k] + r_c).astype(np.float32)))
        out.update(direction_terms(vec(v_c / r_c[:, None]), vec(photons["dep"][k]), tracer.rot, tracer.with_beams))
        dr.eval(*out.values())
        per_hit += np.bincount(j, power.numpy().astype(np.float64), len(per_hit))
        sink(out if tracer.device_deposits else {key: v.numpy() for key, v in out.items()}, False)
    return per_hit


def diffuse_gather(radio, tracer, grid, cells: np.ndarray, solids, sink, *, photon_rays: int,
                   batch_rays: int, directions_per_point: int = DEFAULT_GATHER_DIRECTIONS_PER_POINT,
                   radius_m: float | None = None) -> tuple[dict, np.ndarray | None]:
    """Gathered deposits of the last diffuse reflection for the flat ``cells`` into ``sink``
    (module docstring); returns what it did and the variance of each cell's gathered power (the
    gather rays as independent samples; None where nothing was gathered)."""
    radius = float(radius_m) if radius_m is not None else DEFAULT_GATHER_RADIUS_CELLS * min(grid.dx, grid.dy)
    out = {"cells": int(len(cells)), "photon_rays": int(photon_rays), "radius_m": radius,
           "directions_per_point": int(directions_per_point), "gather_points": 0, "gather_hits": 0,
           "photons": 0, "pairs": 0}
    if not len(cells):
        return out, None
    origins, cell_of = gather_origins(radio, grid, cells, solids)
    out["gather_points"] = int(len(origins))
    if not len(origins):
        return out, None
    # the gather rays in batches of about GATHER_RAYS_PER_BATCH (a city's few-hit cells can ask for
    # tens of millions)
    step = max(1, GATHER_RAYS_PER_BATCH // int(directions_per_point))
    rotations = gather_rotations(len(origins))  # each point's own, whatever its batch
    parts = []
    for lo in range(0, len(origins), step):
        rows = slice(lo, min(lo + step, len(origins)))
        part = cast_gather_rays(tracer, origins[rows], gather_directions(rotations[rows], int(directions_per_point)))
        part["row"] = part["row"] + lo
        parts.append(part)
    hits = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    out["gather_hits"] = int(len(hits["x"]))
    if not len(hits["x"]):
        return out, None
    photons = trace_photons(tracer, PhotonRecorder(hits["x"], radius), int(photon_rays), int(batch_rays))
    if photons is None:
        return out, None
    out["photons"] = int(len(photons["p"]))
    rows, cols, dists, radii = gather_pairs(hits, photons, radius)
    out["pairs"] = int(len(rows))
    per_hit = gather_deposits(tracer, hits, photons, rows, cols, dists, radii, origins, cell_of, grid.centres(),
                              int(directions_per_point), int(photon_rays), OUTDOOR_SAMPLES_PER_AXIS**2, sink)
    # each gather ray is one sample of its cell's sum (a ray without a hit: a zero sample): the
    # variance of the sum over a cell's rays
    size = grid.nx * grid.ny * len(grid.heights)
    rays = np.bincount(cell_of, minlength=size) * int(directions_per_point)
    total = np.bincount(cell_of[hits["row"]], per_hit, size)
    sq = np.bincount(cell_of[hits["row"]], per_hit**2, size)
    variance = np.maximum(sq - total**2 / np.maximum(rays, 1), 0.0)
    return out, variance
