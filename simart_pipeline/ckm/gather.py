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

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from simart_pipeline.ckm.outdoor import OUTDOOR_SAMPLES_PER_AXIS, cell_sample_points, points_inside

DEFAULT_GATHER_DIRECTIONS_PER_POINT = 32  # x 16 outdoor sample points: 512 gather rays a cell
DEFAULT_GATHER_RADIUS_CELLS = 1.0  # the kernel radius R, in cell sizes
DEFAULT_PHOTON_RAY_SHARE = 0.25  # photon rays per main-pass ray
DEFAULT_GATHER_NEIGHBOURS = 16  # photons examined per gather point at most (gather_pairs)
DEFAULT_GATHER_BELOW_EFFECTIVE_HITS = 10.0  # cells whose effective count is below this are gathered
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
    points' voxels dilated by one."""

    def __init__(self, gather_points_m: np.ndarray, radius_m: float):
        from scipy.ndimage import binary_dilation

        pts = np.asarray(gather_points_m, np.float64)
        self.lo = pts.min(axis=0) - radius_m
        extent = pts.max(axis=0) + radius_m - self.lo
        self.voxel = max(float(radius_m), float(np.cbrt(np.prod(extent + radius_m) / MAX_RECORDER_VOXELS)))
        shape = np.maximum(np.ceil(extent / self.voxel).astype(np.int64) + 1, 1)
        occupied = np.zeros(shape, bool)
        occupied[tuple(self._index(pts).T)] = True
        self.occupied = binary_dilation(occupied, np.ones((3, 3, 3), bool))
        self.parts: list[dict] = []

    def _index(self, points_m: np.ndarray) -> np.ndarray:
        return np.floor((points_m - self.lo) / self.voxel).astype(np.int64)

    def keep(self, points_m: np.ndarray) -> np.ndarray:
        v = self._index(np.asarray(points_m, np.float64))
        inside = ((v >= 0) & (v < np.array(self.occupied.shape))).all(axis=1)
        out = np.zeros(len(v), bool)
        out[inside] = self.occupied[tuple(v[inside].T)]
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
    and side are paired with it."""
    # a tree built without balancing or shrinking its nodes: half the build time, queries about as fast
    tree = cKDTree(photons["p"].astype(np.float64), balanced_tree=False, compact_nodes=False)
    rows, cols, dists = [], [], []
    radius = np.full(len(hits["x"]), float(radius_m))
    step = max(1, _PAIRS_PER_CHUNK // neighbours)
    for lo in range(0, len(hits["x"]), step):
        x = hits["x"][lo:lo + step]
        dist, k = tree.query(x, k=neighbours, distance_upper_bound=radius_m, workers=-1)
        dist, k = dist.reshape(len(x), -1), k.reshape(len(x), -1)
        full = np.isfinite(dist[:, -1])
        radius[lo:lo + len(x)][full] = dist[full, -1]
        inside = np.isfinite(dist)
        inside[full, -1] = False  # on the kernel's rim: weight 0
        j = np.broadcast_to(np.arange(lo, lo + len(x))[:, None], dist.shape)[inside]
        k, d = k[inside], dist[inside]
        n_j = hits["n"][j]
        same = (np.einsum("ij,ij->i", n_j, photons["n"][k]) > SAME_SIDE_COS) & (
            np.abs(np.einsum("ij,ij->i", n_j, photons["p"][k] - hits["x"][j])) < PLANE_TOLERANCE_M)
        rows.append(j[same])
        cols.append(k[same])
        dists.append(d[same])
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), radius
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(dists), radius


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
        ko_np /= np.linalg.norm(ko_np, axis=1, keepdims=True)
        v_c = c - x
        r_c = np.linalg.norm(v_c, axis=1)
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
