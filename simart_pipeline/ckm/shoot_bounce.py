"""Shoot and bounce on Mitsuba and Dr.Jit: the ray side of the one-pass CKM solver.

:class:`Tracer` launches rays from a transmitter on a Fibonacci lattice, carries each ray's
polarised field (a complex world-frame 3-vector started from the transmit element pattern of the
Sionna scene's ``tx_array``), intersects the radio mesh (Mitsuba's preliminary intersection plus
our own face-normal table, a third of the cost of a full surface interaction), and at each hit
either reflects specularly with the ITU-R P.2040 slab TE/TM coefficients of the hit object's radio
material (specular reflection alone: the original path, deterministic) or, where diffuse
reflection or refraction is on, splits or draws the interaction (:meth:`Tracer._interact`). It
hands every crossing of a grid height plane to a sink as numpy arrays (one call per segment and
height). Which cells lie indoors is :mod:`simart_pipeline.ckm.outdoor`'s business.
Everything that depends on the scene, the grid, the device or the ray count enters the kernels
as opaque variables, so compiled kernels are reused across grids, tiles, transmitters and ray
counts.

With ``E`` the incident field, ``R``/``T`` the slab reflection and transmission (TE/TM) of the
hit material, ``S`` its scattering coefficient, the energies are ``w_spec = (1 - S^2) |R E|^2``,
``w_diff = S^2 |R E|^2``, ``w_refr = |T E|^2`` (only the enabled mechanisms).

- With refraction and a reflection both on, every hit is split: the transmitted ray goes on
  with ``T E`` exactly, and the reflected one is drawn between specular and diffuse with
  probability ``w_k / W_r`` (``W_r = w_spec + w_diff``), its field divided by ``sqrt(w_k / W_r)``.
  Drawing reflection against transmission too (Sionna RT's RadioMapSolver,
  ``RadioMaterial.sample``) leaves a path behind a thin wall, whose reflection is the unlikely
  draw, to a few rays of full weight: at 1e7 rays whole cells of the street canyon were 5-11 dB
  low, and 1e8 were needed. Split, the transmitted rays cost about 2.4x the traced segments at
  depth 3. A side of a split with less than ``SPLIT_MIN_SHARE`` of the hit's energy goes on by
  Russian roulette (with probability ``share / SPLIT_MIN_SHARE``, its field weighted by the
  inverse square root).
- Otherwise one interaction per ray and hit is drawn with probability ``w_k / W`` (``W`` their
  sum) and its field divided by ``sqrt(w_k / W)``.

Either way the estimator is unbiased. Sionna draws with the unpolarised ``|R_TE|^2 + |R_TM|^2``
and ``|T_TE|^2 + |T_TM|^2``; the ray's own polarised energies give the same mean with less
variance. Random numbers are a counter-based hash of (lattice index, depth, purpose), so a ray's
draws do not depend on the batch that holds it; a transmitted ray of a split takes a stream of
its own, hashed from its parent's.

- Refraction: straight through (``T`` of the ITU-R P.2040 single-layer slab, eq. 43b as Sionna
  computes it, on the TE/TM basis of the face); direction, image source and departure direction
  are unchanged.
- Diffuse reflection: the scattered field of Sionna's model (``|E_s|^2 = (S Gamma)^2 |E|^2 f_s
  * solid angle``, ``Gamma = |R E| / |E|``, polarisation rotated by the XPD matrix
  ``[[sqrt(1 - K_x), -sqrt(K_x)], [sqrt(K_x), sqrt(1 - K_x)]]`` from the incident to the
  scattered ``(theta-hat, phi-hat)`` basis). The direction is importance-sampled with a density
  ``q``: cosine-weighted for the Lambertian pattern (``f_s / q = 1``), the pattern's own lobes
  for the directive and backscattering patterns (``q = lambda (a_R + 1) v_R / 4 pi + (1 -
  lambda) (a_I + 1) v_I / 4 pi``, directions below the face dropped), cosine-weighted for any
  other registered pattern; the field is weighted by ``sqrt(f_s / q)`` (``f_s`` evaluated by
  the material's own pattern object), which replaces Sionna's uniform hemisphere and its solid
  angle ``2 pi``. The ray's delay restarts from the hit point: it carries ``anchor``, its path
  length there, and deposits measure ``anchor + |c - s'|`` with ``s'`` the hit point's image
  through the later specular reflections. Its departure direction is fixed at the launch
  direction (the mirror columns become the rank-1 ``m_k = dep_k d``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.constants import epsilon_0

# Departure directions are quantised for the beam gains on a grid of 2**-13 in direction cosines
# (device frame): a phase error below pi * 2**-13 * sqrt(3) * (largest element offset in
# wavelengths) per element, 1.2e-3 rad for an 8 x 8 half-wavelength array. 15 bits per component.
Q_BITS = 15
DIRECTION_QUANTUM = 2.0**-13
Q_OFFSET = 1 << 13
# A path whose departure is a ray's own launch direction (after a diffuse reflection or a
# diffraction: no cell-centre correction applies) takes it on a coarser grid of 2**-7 in direction
# cosines (< 0.45 deg, a thirtieth of an 8 x 8 half-wavelength array's beamwidth), so that
# neighbouring rays share one beam factor: at 1e7 rays every ray's launch direction is distinct
# on the 2**-13 grid, and their beam factors were most of a diffuse run's host time
DEPARTURE_QUANTUM = 2.0**-7
_GOLDEN_RATIO = (1.0 + 5.0**0.5) / 2.0
_SPAWN_EPSILON = 89.0 * 2.0**-24  # Mitsuba's RayEpsilon for float32
# Purposes of the per-ray random numbers (hashed with the lattice index and the depth)
_DRAW_EVENT, _DRAW_DIR1, _DRAW_DIR2, _DRAW_LOBE, _DRAW_SPLIT, _DRAW_ROULETTE = range(6)
# a diffuse hit's connections to cells (Tracer._connect): taken or not, which cell, where in it
_DRAW_NEE_TAKE, _DRAW_NEE_CELL, _DRAW_NEE_X, _DRAW_NEE_Y = range(6, 10)
_RNG_SEED = 0x2545F491
# the share of a hit's energy below which a ray of a split goes on by Russian roulette
SPLIT_MIN_SHARE = 0.03
_TUBE = ("tube_c", "tube_l0")  # a diffracted ray's own ray tube (Tracer._footprint)
# carried unchanged through every interaction: the tube, and the stretch of edge a diffracted ray
# came from or the lattice bin a lattice ray left through, which its deposits report when they are
# tagged (the second passes on undersampled cells, one_pass)
TAGS = ("stretch", "lattice_bin")
# the lattice_bin tag of a deposit made after a diffuse reflection (or by a diffuse hit's
# connection): such a deposit falls where the scattering sent it, not where its launch bin points,
# so the lattice's second pass leaves it out of its bins and of its swap
NOT_A_BIN = 0xFFFFFFFF
_CARRIED = _TUBE + TAGS


@dataclass(frozen=True)
class Grid:
    """A regular grid of cells on one or more horizontal planes: lower-left corner (m), cell size
    (m), cell counts, plane heights (m); cell ``(h, row, col)`` is flat index ``(h * ny + row) * nx + col``."""

    x_lo: float
    y_lo: float
    dx: float
    dy: float
    nx: int
    ny: int
    heights: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self.heights), self.ny, self.nx)

    def centres(self) -> np.ndarray:
        """``[H * ny * nx, 3]`` cell centres, flat in C order of :attr:`shape`."""
        h, y, x = np.meshgrid(self.heights, self.y_lo + (np.arange(self.ny) + 0.5) * self.dy,
                              self.x_lo + (np.arange(self.nx) + 0.5) * self.dx, indexing="ij")
        return np.stack([x.ravel(), y.ravel(), h.ravel()], -1)


def _regular_axis(v, name: str) -> tuple[float, float | None]:
    v = np.asarray(v, np.float64)
    if v.ndim != 1 or v.size == 0 or not np.isfinite(v).all():
        raise ValueError(f"{name}: expected a non-empty 1-D array of finite cell-centre coordinates")
    if v.size == 1:
        return float(v[0]), None
    step = np.diff(v)
    if step[0] <= 0 or not np.allclose(step, step[0], rtol=1e-6, atol=0):
        raise ValueError(f"{name}: cell centres must be increasing and equally spaced")
    return float(v[0]), float(step[0])


def grid_from_centres(x_m, y_m, heights_m, cell_size_m: float | None = None) -> Grid:
    """:class:`Grid` from cell-centre coordinates ``x_m [nx]``, ``y_m [ny]`` (increasing, equally
    spaced; the spacing is the cell size) and ``heights_m [num_heights]``. ``cell_size_m`` (m)
    gives the size of square cells where an axis has one cell, and must match the spacing
    elsewhere."""
    x0, dx = _regular_axis(x_m, "x_m")
    y0, dy = _regular_axis(y_m, "y_m")
    if cell_size_m is not None:
        for name, step in (("x_m", dx), ("y_m", dy)):
            if step is not None and not np.isclose(step, cell_size_m, rtol=1e-6, atol=0):
                raise ValueError(f"{name}: spacing {step!r} m differs from cell_size_m {cell_size_m!r} m")
        dx, dy = dx or float(cell_size_m), dy or float(cell_size_m)
    if dx is None and dy is None:
        raise ValueError("x_m, y_m: a single cell has no spacing to take the cell size from; "
                         "pass cell_size_m")
    dx, dy = dx or dy, dy or dx  # one-cell axis: square cells
    h = np.atleast_1d(np.asarray(heights_m, np.float64))
    if h.ndim != 1 or h.size == 0 or not np.isfinite(h).all():
        raise ValueError("heights_m: expected one or more finite heights, m")
    return Grid(x0 - dx / 2, y0 - dy / 2, dx, dy, len(np.atleast_1d(x_m)), len(np.atleast_1d(y_m)), h)


def fibonacci_directions(start: int, stop: int, num_rays: int, indices=None):
    """Unit vectors (``mi.Vector3f``) of lattice points ``start..stop-1`` (or of the ``indices``,
    ``mi.UInt32``, where given) of the ``num_rays``-point
    spherical Fibonacci lattice (Gonzalez 2010, Math. Geosci. 42: 49-64): ``z = 1 - 2 i / (N - 1)``,
    azimuth ``2 pi frac(i / golden ratio)``, lattice arithmetic in float64 (exact indices up to
    2**53), so a ray is the same whatever the batch that holds it."""
    import drjit as dr
    import mitsuba as mi

    i = mi.Float64(dr.arange(mi.UInt32, start, stop) if indices is None else indices)
    if indices is not None:
        start, stop = 0, dr.width(indices)
    # the lattice size enters as an opaque variable, not a literal: a new ray count (the adaptive
    # rule's, a benchmark's) reuses the compiled kernels (a literal cost 1.5-2.5 s of compilation
    # per new count on the urban scene); IEEE division is exactly rounded either way
    span = dr.opaque(mi.Float64, float(max(num_rays - 1, 1)))
    z = mi.Float(1.0 - 2.0 * i / span) if num_rays > 1 else dr.zeros(mi.Float, stop - start)
    frac = i / _GOLDEN_RATIO
    phi = mi.Float(2.0 * np.pi * (frac - dr.floor(frac)))
    r = dr.sqrt(dr.maximum(1.0 - z * z, 0.0))
    sp, cp = dr.sincos(phi)
    return mi.Vector3f(r * cp, r * sp, z)


def _mix64(x: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser on uint64 (a counter-based hash: the same bits in any order)."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


class LatticeBins:
    """The sphere of launch directions cut into ``num_z`` bands of equal height in ``z`` and
    ``num_phi`` sectors of equal azimuth: equal-area bins (area ``dz dphi``), about ``rays_per_bin``
    points of the ``num_rays``-point Fibonacci lattice each (the bands as wide in angle at the
    horizon as the sectors). The lattice's second pass (``one_pass``) re-traces the lattice rays of
    chosen bins and traces new, finer rays over the same bins: a bin is a region of the sphere both
    sets of rays cover exactly, which a Fibonacci point's own (irregular) Voronoi cell is not.

    A lattice point's bin is computed here alone, in float64 from its index (``z`` and the azimuth
    fraction exactly as :func:`fibonacci_directions` forms them), both to tag the first pass's rays
    and to find the rays of a bin again."""

    def __init__(self, num_rays: int, rays_per_bin: int):
        if int(rays_per_bin) < 1:
            raise ValueError(f"rays_per_bin must be >= 1, got {rays_per_bin}")
        self.num_rays = int(num_rays)
        bins = max(self.num_rays / int(rays_per_bin), 1.0)
        self.num_z = max(1, int(round(np.sqrt(bins / np.pi))))
        self.num_phi = max(1, int(round(bins / self.num_z)))
        self.num_bins = self.num_z * self.num_phi

    def bin_of(self, index: np.ndarray) -> np.ndarray:
        """Bins (uint32) of lattice points ``index``."""
        i = np.asarray(index, np.float64)
        span = float(max(self.num_rays - 1, 1))
        u = i / span if self.num_rays > 1 else np.zeros_like(i)  # (1 - z) / 2
        frac = i / _GOLDEN_RATIO
        frac -= np.floor(frac)
        bz = np.minimum((u * self.num_z).astype(np.int64), self.num_z - 1)
        bp = np.minimum((frac * self.num_phi).astype(np.int64), self.num_phi - 1)
        return (bz * self.num_phi + bp).astype(np.uint32)

    def with_neighbours(self, bins: np.ndarray) -> np.ndarray:
        """``bins`` and the bins beside them (sorted, unique): the 8 around each (the azimuth wraps
        round), and a whole polar band where one of its bins is chosen (its bins meet at the pole).
        A cell's directions seen from the transmitter can straddle a bin's border while the few
        first-pass rays that reached it came through one bin; the finer rays need every bin that
        reaches the cell, or the swap would leave out the part of the bins beside it."""
        bz, bp = np.divmod(np.asarray(bins, np.int64), self.num_phi)
        dz, dp = np.meshgrid([-1, 0, 1], [-1, 0, 1], indexing="ij")
        nz = bz[:, None] + dz.ravel()
        np_ = np.mod(bp[:, None] + dp.ravel(), self.num_phi)
        inside = (nz >= 0) & (nz < self.num_z)
        out = [(nz * self.num_phi + np_)[inside]]
        for band in {0, self.num_z - 1} & set(np.unique(bz).tolist()):
            out.append(band * self.num_phi + np.arange(self.num_phi))
        return np.unique(np.concatenate(out)).astype(np.int64)

    def rays_in(self, bins: np.ndarray, chunk: int = 1 << 22) -> np.ndarray:
        """The lattice indices (sorted, uint32) whose bin is one of ``bins``."""
        chosen = np.zeros(self.num_bins, bool)
        chosen[np.asarray(bins, np.int64)] = True
        out = [lo + np.flatnonzero(chosen[self.bin_of(np.arange(lo, min(lo + chunk, self.num_rays)))])
               for lo in range(0, self.num_rays, chunk)]
        return np.concatenate(out).astype(np.uint32)

    def finer_directions(self, bins: np.ndarray, per_bin: int, seed: int = 0) -> np.ndarray:
        """``per_bin`` directions in each of ``bins`` (``[len(bins) * per_bin, 3]`` float64, bin by
        bin): a rank-1 lattice over the bin's ``(z, azimuth)`` rectangle (``((k + 1/2) / M,
        frac(k / golden ratio))``) shifted at random per bin (Cranley and Patterson 1976; the shift
        a hash of the bin and ``seed``), so each direction is uniform over its bin (equal area in
        ``(z, azimuth)``) and the set an unbiased, stratified estimate of the bin's integral."""
        b = np.asarray(bins, np.uint64)
        h1 = _mix64(b * np.uint64(2) + np.uint64(int(seed) * 0x9E3779B97F4A7C15 % 2**64))
        h2 = _mix64(h1 ^ np.uint64(0xD1B54A32D192ED03))
        s = np.stack([(h >> np.uint64(11)).astype(np.float64) * 2.0**-53 for h in (h1, h2)], -1)
        k = np.arange(int(per_bin), dtype=np.float64)
        u = (k[None, :] + 0.5) / per_bin + s[:, :1]
        v = k[None, :] / _GOLDEN_RATIO + s[:, 1:]
        u, v = u - np.floor(u), v - np.floor(v)
        bz, bp = np.divmod(np.asarray(bins, np.int64), self.num_phi)
        z = 1.0 - 2.0 * (bz[:, None] + u) / self.num_z
        phi = 2.0 * np.pi * (bp[:, None] + v) / self.num_phi
        r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1).reshape(-1, 3)


def direction_terms(d_c, d_dep, rotation, with_beams: bool) -> dict:
    """The direction part of a deposit: cos and sin of azimuth and zenith, arrival then departure
    (ANGLES order; arrival angles are those of ``-d_c``, towards where the wave comes from, as
    PathSolver's), and with ``with_beams`` the departure direction in the device frame quantised
    to :data:`DIRECTION_QUANTUM` (the key of ``one_pass._Accumulator._add_beams``). ``d_c``: unit
    propagation direction into the cell centre; ``d_dep``: unit departure direction (world);
    ``rotation``: device-to-world rotation (rows indexable, numbers or opaque floats)."""
    import drjit as dr
    import mitsuba as mi

    out = {}
    for k, u in enumerate((-d_c, d_dep)):
        rho = dr.sqrt(dr.maximum(u.x * u.x + u.y * u.y, 0.0))
        safe = rho > 0
        out[f"cos{2 * k}"] = dr.select(safe, u.x / rho, 1.0)
        out[f"sin{2 * k}"] = dr.select(safe, u.y / rho, 0.0)
        out[f"cos{2 * k + 1}"] = dr.clip(u.z, -1.0, 1.0)
        out[f"sin{2 * k + 1}"] = rho
    if with_beams:
        key = mi.UInt64(0)
        for k in range(3):
            c = sum(rotation[i][k] * d_dep[i] for i in range(3))
            q = mi.UInt64(mi.Int32(dr.round(c * (1.0 / DIRECTION_QUANTUM))) + Q_OFFSET)
            key = (key << Q_BITS) | q
        out["dkey"] = key
    return out


def on_departure_grid(u):
    """Unit directions ``u`` (Mitsuba Vector3f) moved to :data:`DEPARTURE_QUANTUM`'s grid of
    direction cosines, unit length again."""
    import drjit as dr

    return dr.normalize(dr.round(u * (1.0 / DEPARTURE_QUANTUM)) * DEPARTURE_QUANTUM)


def _material_tables(radio) -> tuple[np.ndarray, ...]:
    """Per Mitsuba shape id: complex relative permittivity (re, im), thickness m and the specular
    amplitude factor ``sqrt(1 - S^2)``, from the Sionna scene's radio materials (weather applied).
    Every shape the rays can hit must have a row (the kernels gather without bounds checks)."""
    import drjit as dr
    import mitsuba as mi

    omega = 2 * np.pi * float(radio.scene.frequency[0])
    rows = {}
    for name, obj in radio.scene.objects.items():
        m = obj.radio_material
        try:
            eps, sigma, d = (float(np.array(getattr(m, k)).ravel()[0])
                             for k in ("relative_permittivity", "conductivity", "thickness"))
        except AttributeError:
            raise ValueError(f"{radio.scene_xml}: object {name!r} has radio material {m.name!r} of type "
                             f"{type(m).__name__}, which has no permittivity, conductivity and thickness; "
                             "the one-pass solver knows only RadioMaterial / ITURadioMaterial") from None
        s = float(np.array(getattr(m, "scattering_coefficient", 0.0)).ravel()[0])
        rows[int(obj.object_id)] = (eps, -sigma / (epsilon_0 * omega), d, np.sqrt(max(1.0 - s * s, 0.0)))
    for shape in radio.scene.mi_scene.shapes():
        if int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0]) not in rows:
            raise ValueError(f"{radio.scene_xml}: shape {shape.id()!r} is not a Sionna scene object with a "
                             "radio material")
    size = max(rows, default=0) + 1
    table = np.zeros((4, size))
    table[:, 0] = (1.0, 0.0, 0.0, 0.0)  # id 0 (no shape) never reflects: vacuum, no thickness
    for k, row in rows.items():
        table[:, k] = row
    return tuple(table)


def _scattering_tables(radio) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """Per Mitsuba shape id: the scattering coefficient ``S``, the XPD coefficient ``K_x`` and the
    index of the scattering pattern in the returned list of distinct pattern objects (index 0:
    Lambertian, also for every material with ``S = 0``, which never scatters)."""
    from sionna.rt.radio_materials.scattering_pattern import LambertianPattern

    patterns: list = [None]  # 0: Lambertian, sampled in closed form
    rows = {}
    for obj in radio.scene.objects.values():
        m = obj.radio_material
        s = float(np.array(getattr(m, "scattering_coefficient", 0.0)).ravel()[0])
        kx = float(np.array(getattr(m, "xpd_coefficient", 0.0)).ravel()[0])
        pat = getattr(m, "scattering_pattern", None)
        k = 0
        if s > 0 and pat is not None and not isinstance(pat, LambertianPattern):
            k = next((i for i, q in enumerate(patterns) if q is pat), len(patterns))
            if k == len(patterns):
                patterns.append(pat)
        rows[int(obj.object_id)] = (s, kx, k)
    size = max(rows, default=0) + 1
    s_tab, kx_tab, pat_tab = np.zeros(size), np.zeros(size), np.zeros(size, np.uint32)
    for k, (s, kx, p) in rows.items():
        s_tab[k], kx_tab[k], pat_tab[k] = s, kx, p
    return s_tab, kx_tab, pat_tab, patterns


@dataclass(frozen=True)
class FaceTable:
    """Every triangle of the radio scene, numbered shape by shape in ``mi_scene.shapes()`` order
    (the global face index): unit geometric normals ``[total_faces, 3]`` (Mitsuba's
    ``normalize(cross(p1 - p0, p2 - p0))``), the first vertex of each ``[total_faces, 3]`` m, and
    per shape its Mitsuba id and first global face (``shape_ids``, ``shape_first_face``)."""

    normals: np.ndarray
    first_vertex: np.ndarray
    shape_ids: np.ndarray
    shape_first_face: np.ndarray

    def offsets_by_shape_id(self) -> np.ndarray:
        """First global face per Mitsuba shape id (0 for ids that are no shape)."""
        offsets = np.zeros(int(self.shape_ids.max(initial=0)) + 1, np.int64)
        offsets[self.shape_ids] = self.shape_first_face
        return offsets

    def shape_and_primitive(self, faces) -> np.ndarray:
        """``[n, 2]`` (Mitsuba shape id, primitive) of global face indices."""
        f = np.asarray(faces, np.int64)
        k = np.searchsorted(self.shape_first_face, f, side="right") - 1
        return np.column_stack([self.shape_ids[k], f - self.shape_first_face[k]])


def face_table(mi_scene, source) -> FaceTable:
    """:class:`FaceTable` of a Mitsuba scene whose shapes are all triangle meshes."""
    import drjit as dr
    import mitsuba as mi

    normals, first_vertex, ids, first = [], [], [], []
    total = 0
    for shape in mi_scene.shapes():
        if not shape.is_mesh():
            raise ValueError(f"{source}: shape {shape.id()!r} is not a triangle mesh; the one-pass solver "
                             "reflects on meshes only")
        v = shape.vertex_positions_buffer().numpy().reshape(-1, 3).astype(np.float64)
        f = shape.faces_buffer().numpy().reshape(-1, 3).astype(np.int64)
        nrm = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        ids.append(int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0]))
        first.append(total)
        normals.append(nrm)
        first_vertex.append(v[f[:, 0]])
        total += len(f)
    if not normals:
        return FaceTable(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64))
    return FaceTable(np.concatenate(normals), np.concatenate(first_vertex), np.array(ids, np.int64),
                     np.array(first, np.int64))


def _complex_sqrt(dr, re, im):
    """Principal square root of ``re + j im`` (Dr.Jit floats)."""
    r = dr.sqrt(re * re + im * im)
    out_re = dr.sqrt(dr.maximum(0.5 * (r + re), 0.0))
    out_im = dr.sqrt(dr.maximum(0.5 * (r - re), 0.0))
    return out_re, dr.select(im < 0, -out_im, out_im)


def _cdiv(dr, ar, ai, br, bi):
    den = dr.rcp(br * br + bi * bi)
    return (ar * br + ai * bi) * den, (ai * br - ar * bi) * den


def _cmul(ar, ai, br, bi):
    return ar * br - ai * bi, ar * bi + ai * br


def _slab_reflection(dr, cos_i, eta_re, eta_im, thickness, wavelength):
    """ITU-R P.2040-3 single-layer slab reflection coefficients (eqs. 37, 43a, 44): returns
    (R_TE, R_TM) as (re, im) pairs. Half-space Fresnel ``R'`` then
    ``R = R' (1 - e^{-j2q}) / (1 - R'^2 e^{-j2q})``, ``q = 2 pi d / lambda sqrt(eta - sin^2)``."""
    sr, si = _complex_sqrt(dr, eta_re - (1.0 - cos_i * cos_i), eta_im)
    te = _cdiv(dr, cos_i - sr, -si, cos_i + sr, si)
    ec_re, ec_im = eta_re * cos_i, eta_im * cos_i
    tm = _cdiv(dr, ec_re - sr, ec_im - si, ec_re + sr, ec_im + si)
    k = 2.0 * dr.pi * thickness / wavelength
    # exp(-j 2 q) with q = k (sr + j si): magnitude exp(2 k si) (si <= 0: decays), phase -2 k sr
    mag = dr.exp(2.0 * k * si)
    s2, c2 = dr.sincos(2.0 * k * sr)
    xr, xi = mag * c2, -mag * s2
    out = []
    for rr, ri in (te, tm):
        num = _cmul(rr, ri, 1.0 - xr, -xi)
        r2r, r2i = _cmul(rr, ri, rr, ri)
        pr, pi_ = _cmul(r2r, r2i, xr, xi)
        out.append(_cdiv(dr, num[0], num[1], 1.0 - pr, -pi_))
    return out


def _slab_transmission(dr, cos_i, eta_re, eta_im, thickness, wavelength):
    """ITU-R P.2040-3 single-layer slab transmission coefficients (eq. 43b, as Sionna RT's
    ``itu_coefficients_single_layer_slab``): returns (T_TE, T_TM) as (re, im) pairs,
    ``T = (1 - R'^2) e^{-jq} / (1 - R'^2 e^{-j2q})`` with the half-space ``R'`` and ``q`` of
    :func:`_slab_reflection`."""
    sr, si = _complex_sqrt(dr, eta_re - (1.0 - cos_i * cos_i), eta_im)
    te = _cdiv(dr, cos_i - sr, -si, cos_i + sr, si)
    ec_re, ec_im = eta_re * cos_i, eta_im * cos_i
    tm = _cdiv(dr, ec_re - sr, ec_im - si, ec_re + sr, ec_im + si)
    k = 2.0 * dr.pi * thickness / wavelength
    mag = dr.exp(k * si)  # e^{-jq}: magnitude exp(k si), phase -k sr
    s1, c1 = dr.sincos(k * sr)
    yr, yi = mag * c1, -mag * s1
    xr, xi = _cmul(yr, yi, yr, yi)  # e^{-j2q}
    out = []
    for rr, ri in (te, tm):
        r2r, r2i = _cmul(rr, ri, rr, ri)
        num = _cmul(1.0 - r2r, -r2i, yr, yi)
        pr, pi_ = _cmul(r2r, r2i, xr, xi)
        out.append(_cdiv(dr, num[0], num[1], 1.0 - pr, -pi_))
    return out


# _unique_keys: a batch's keys are thinned on the device above this many lanes, into a table of
# 2**_DEDUP_TABLE_BITS slots (4 MiB)
_DEDUP_MIN_LANES = 1 << 16
_DEDUP_TABLE_BITS = 20
_DEDUP_PURPOSE = 15


def _hash32(x):
    """lowbias32 (C. Wellons' integer hash): a bijective avalanche mix of UInt32 (mod 2**32)."""
    x = x ^ (x >> 16)
    x = x * 0x7FEB352D
    x = x ^ (x >> 15)
    x = x * 0x846CA68B
    return x ^ (x >> 16)


def _key(depth: int, purpose: int) -> int:
    """The hashed (depth, purpose) part of a random number's counter (Python int, UInt32)."""
    x = (depth * 16 + purpose + _RNG_SEED) & 0xFFFFFFFF
    for shift, mul in ((16, 0x7FEB352D), (15, 0x846CA68B)):
        x = ((x ^ (x >> shift)) * mul) & 0xFFFFFFFF
    return x ^ (x >> 16)


def _theta_phi_hat(dr, mi, k):
    """Spherical unit vectors theta-hat, phi-hat of direction ``k`` (phi = 0 on the z-axis)."""
    rho = dr.sqrt(k.x * k.x + k.y * k.y)
    safe = rho > 1e-7
    cphi = dr.select(safe, k.x / rho, 1.0)
    sphi = dr.select(safe, k.y / rho, 0.0)
    return mi.Vector3f(k.z * cphi, k.z * sphi, -rho), mi.Vector3f(-sphi, cphi, 0.0)


def reflection_terms(dr, mi, d, n, e_re, e_im, eta_re, eta_im, thick, wavelength):
    """A field ``(e_re, e_im)`` travelling along ``d`` onto a face of unit normal ``n`` (facing
    the incoming side): the incidence basis (``e_s`` normal to the plane of incidence, ``e_pi``
    / ``e_pr`` in it for the incident / reflected wave), the reflected direction, ``cos_i``, the
    field's TE / TM components ``(s_r, s_i, p_r, p_i)`` and those components times the ITU-R
    P.2040 slab coefficients ``(a_r, a_i, b_r, b_i)``: the reflected field is
    ``a e_s + b e_pr``."""
    cos_i = dr.clip(-dr.dot(d, n), 0.0, 1.0)
    e_s = dr.cross(d, n)
    ls = dr.norm(e_s)
    e_s = dr.select(ls > 1e-6, e_s / dr.maximum(ls, 1e-30), mi.coordinate_system(n)[0])
    d_r = d + 2.0 * cos_i * n
    e_pi, e_pr = dr.cross(e_s, d), dr.cross(e_s, d_r)
    s_r, s_i = dr.dot(e_re, e_s), dr.dot(e_im, e_s)
    p_r, p_i = dr.dot(e_re, e_pi), dr.dot(e_im, e_pi)
    (te_r, te_i), (tm_r, tm_i) = _slab_reflection(dr, cos_i, eta_re, eta_im, thick, wavelength)
    a_r, a_i = _cmul(te_r, te_i, s_r, s_i)
    b_r, b_i = _cmul(tm_r, tm_i, p_r, p_i)
    return dict(cos_i=cos_i, e_s=e_s, e_pi=e_pi, e_pr=e_pr, d_r=d_r, s_r=s_r, s_i=s_i, p_r=p_r, p_i=p_i,
                a_r=a_r, a_i=a_i, b_r=b_r, b_i=b_i)


class Tracer:
    """Dr.Jit side: launch, intersect, deposit, reflect; hands deposits to numpy per segment."""

    def __init__(self, radio, tx_position_m, tx_rotation: np.ndarray, grid: Grid, num_rays: int,
                 max_depth: int, los: bool, rx_polarization: str | None, with_beams: bool = False, *,
                 specular: bool = True, diffuse: bool = False, refraction: bool = False,
                 max_footprint_cells: float = 1.0, outdoor_fraction: np.ndarray | None = None,
                 diffuse_last_only: bool = False, diffuse_connections: float = 0.0):
        import drjit as dr
        import mitsuba as mi

        self.dr, self.mi = dr, mi
        self.scene = radio.scene.mi_scene
        patterns = radio.scene.tx_array.antenna_pattern.patterns
        if len(patterns) != 1:
            raise ValueError(f"{radio.scene_xml}: the transmit array has {len(patterns)} polarisation "
                             "directions; the one-pass solver supports single-polarised arrays (V or H)")
        self.pattern = patterns[0]
        # Scene-, grid- and device-dependent numbers enter the kernels as opaque variables, not
        # literals, so the compiled kernels are reused across grids, tiles and transmitters.
        def opaque(v, t=mi.Float):
            return dr.opaque(t, v)

        self.tx = [opaque(float(v)) for v in np.asarray(tx_position_m, np.float64)]
        self.rot = [[opaque(float(v)) for v in row] for row in np.asarray(tx_rotation, np.float64)]
        self.grid = grid
        self.g = dict(x_lo=opaque(grid.x_lo), y_lo=opaque(grid.y_lo), dx=opaque(grid.dx), dy=opaque(grid.dy),
                      nx=opaque(float(grid.nx)), ny=opaque(float(grid.ny)), nx_int=opaque(grid.nx, mi.UInt32))
        self.heights = [(opaque(float(h)), opaque(k * grid.ny * grid.nx, mi.UInt32))
                        for k, h in enumerate(grid.heights)]
        self.num_rays = num_rays
        self.max_depth = max_depth
        self.los = los
        self.rx_polarization = rx_polarization
        self.with_beams = with_beams
        self.wavelength = opaque(radio.wavelength_m)
        eta_re, eta_im, thick, spec = _material_tables(radio)
        self.faces = face_table(self.scene, radio.scene_xml)
        self.face_normals = mi.Vector3f(*(self.faces.normals[:, k].astype(np.float32) for k in range(3)))
        self.face_offset = mi.UInt32(self.faces.offsets_by_shape_id().astype(np.uint32))
        self.mat = tuple(mi.Float(np.asarray(a, np.float32)) for a in (eta_re, eta_im, thick, spec))
        self.specular, self.diffuse, self.refraction = bool(specular), bool(diffuse), bool(refraction)
        # PathSolver's diffuse model (one_pass_moments' diffuse_last_only): nothing after a diffuse
        # reflection, no diffuse reflection of a diffracted ray
        self.diffuse_last_only = bool(diffuse_last_only)
        # [num faces] uint32: the lattice rays that hit each face first (lit: > 0), see collect_lit;
        # None: nothing is collected
        self._lit_face_hits = None
        self.lit_pairs: list | None = None
        # a split or drawn interaction per hit where diffuse reflection or refraction is on; specular
        # reflection alone keeps the deterministic _reflect
        self.sampled = self.diffuse or self.refraction
        if self.sampled:
            s_tab, kx_tab, pat_tab, self.patterns = _scattering_tables(radio)
            self.scat = (mi.Float(s_tab.astype(np.float32)), mi.Float(kx_tab.astype(np.float32)),
                         mi.UInt32(pat_tab))
        # p = |E|^2 * solid angle / |cos| * (lambda / 4 pi)^2 / cell area (RadioMapSolver's estimator)
        self.lattice_bins: LatticeBins | None = None  # set: the lattice rays' deposits are tagged with their bin
        # True: rays stop at a diffuse reflection and diffuse hits make no connections (the
        # lattice's second pass re-traces the part of its bins that never scattered diffusely)
        self.undiffused_only = False
        self.max_footprint_cells = float(max_footprint_cells)
        # True: deposits handed to the sink as evaluated Dr.Jit arrays (one_pass._DeviceAccumulator),
        # False: as numpy arrays
        self.device_deposits = False
        # a spread crossing's share of a cell is the part of the cell outside buildings (the
        # solver divides each cell's sums by that part): [num_heights, ny, nx], None: all outside
        self.outdoor = None if outdoor_fraction is None else mi.Float(
            np.asarray(outdoor_fraction, np.float32).reshape(-1))
        # A ray going down from at or below the lowest point of the scene and of the grid planes
        # meets nothing and crosses no plane: the rays transmitted through the ground are culled
        # (a fifth of the first hits' transmitted rays in the street canyon)
        self.floor_z = opaque(min(float(self.scene.bbox().min.z) + 1e-3, float(np.min(grid.heights))))
        self._power_per_sr = (radio.wavelength_m / (4 * np.pi)) ** 2 / (grid.dx * grid.dy)
        self.set_solid_angle(4 * np.pi / num_rays)  # a lattice ray's: 4 pi / N sr (tube_c, power_scale)
        self.nee = None
        if self.diffuse and diffuse_connections > 0:
            self._setup_connections(float(diffuse_connections))
        # True: every deposit says whether a lattice ray's diffuse reflection was its last
        # interaction (``diffuse_last``: the first crossings after it and the hit's connections),
        # the part the diffuse gather (.gather) estimates again in few-hit cells
        self.tag_diffuse_last = False
        # set (a .gather.PhotonRecorder): a photon pass, no deposits; every hit's diffuse part is
        # handed to it instead (point, face, incident field, path length, departure)
        self.photons = None

    def _setup_connections(self, per_hit: float) -> None:
        """The candidate cells of the diffuse hits' connections (:meth:`_connect`): every cell
        with a part outside buildings, on every plane, each drawn with the same probability."""
        dr, mi, grid = self.dr, self.mi, self.grid
        frac = (np.ones(int(np.prod(grid.shape))) if self.outdoor is None
                else np.asarray(self.outdoor.numpy(), np.float64))
        cand = np.flatnonzero(frac > 0)
        if not len(cand):
            return
        h, rc = np.divmod(cand, grid.ny * grid.nx)
        row, col = np.divmod(rc, grid.nx)
        density = per_hit / (len(cand) * grid.dx * grid.dy)  # connections per m^2 of candidate plane
        self.nee = dict(
            per_hit=per_hit, cell=mi.UInt32(cand.astype(np.uint32)),
            x0=mi.Float((grid.x_lo + col * grid.dx).astype(np.float32)),
            y0=mi.Float((grid.y_lo + row * grid.dy).astype(np.float32)),
            z=mi.Float(np.asarray(grid.heights, np.float64)[h].astype(np.float32)),
            num=dr.opaque(mi.UInt64, len(cand)),
            density=dr.opaque(mi.Float, density),
            # density per candidate cell (0 elsewhere): the MIS weight of a scattered ray's crossing
            cell_density=mi.Float(np.where(frac > 0, density, 0.0).astype(np.float32)))

    def set_solid_angle(self, solid_angle_sr: float) -> None:
        """The solid angle each launched ray stands for from now on (``4 pi / num_rays`` for the
        lattice; the second pass's finer rays less): the power of its deposits and its tube."""
        self.tube_c = self.dr.opaque(self.mi.Float, float(solid_angle_sr))
        self.power_scale = self.dr.opaque(self.mi.Float, float(solid_angle_sr) * self._power_per_sr)

    def launch(self, start: int, stop: int, indices: np.ndarray | None = None, directions: np.ndarray | None = None):
        """Ray state of lattice points ``start..stop-1``, or of the lattice points ``indices``
        (uint32), or of unit ``directions`` ``[n, 3]`` (float64, world) whose random numbers are
        keyed by ``indices`` (numbers outside the lattice's ``0..num_rays-1``: streams of their
        own). With :attr:`lattice_bins` set every lattice ray carries its bin
        (:meth:`LatticeBins.bin_of`) as the tag ``lattice_bin``."""
        dr, mi = self.dr, self.mi
        if directions is not None:
            u = np.asarray(directions, np.float64)
            d = mi.Vector3f(*(u[:, k].astype(np.float32) for k in range(3)))
            start, stop = 0, len(u)
        elif indices is not None:
            d = fibonacci_directions(0, 0, self.num_rays, indices=mi.UInt32(np.asarray(indices, np.uint32)))
            start, stop = 0, len(indices)
        else:
            d = fibonacci_directions(start, stop, self.num_rays)
        # field from the element pattern, evaluated in the transmitter's own frame
        R = self.rot
        dl = [sum(R[i][k] * d[i] for i in range(3)) for k in range(3)]  # R^T d
        theta = dr.acos(dr.clip(dl[2], -1.0, 1.0))
        phi = dr.atan2(dl[1], dl[0])
        c_theta, c_phi = self.pattern(theta, phi)
        st, ct = dr.sincos(theta)
        sp, cp = dr.sincos(phi)
        th_l, ph_l = (ct * cp, ct * sp, -st), (-sp, cp, mi.Float(0.0))
        th_w = mi.Vector3f(*(sum(R[k][i] * th_l[i] for i in range(3)) for k in range(3)))
        ph_w = mi.Vector3f(*(sum(R[k][i] * ph_l[i] for i in range(3)) for k in range(3)))
        e_re = dr.real(c_theta) * th_w + dr.real(c_phi) * ph_w
        e_im = dr.imag(c_theta) * th_w + dr.imag(c_phi) * ph_w
        n = stop - start
        o = dr.zeros(mi.Point3f, n) + mi.Point3f(*self.tx)
        eye = [mi.Vector3f(*(1.0 if i == k else 0.0 for i in range(3))) for k in range(3)]
        mirror = [dr.zeros(mi.Vector3f, n) + e for e in eye]  # columns of the reflection product
        st = dict(o=o, d=d, e_re=e_re, e_im=e_im, length=dr.zeros(mi.Float, n), m0=mirror[0],
                  m1=mirror[1], m2=mirror[2])
        if self.sampled:  # the lattice index keys the ray's random numbers; anchor: see _interact
            idx = dr.arange(mi.UInt32, start, stop) if indices is None else mi.UInt32(np.asarray(indices, np.uint32))
            st.update(idx=idx, anchor=dr.zeros(mi.Float, n))
        if self.lattice_bins is not None:
            if directions is not None:
                raise ValueError("launch: rays of given directions belong to no lattice bin (unset lattice_bins)")
            bins = self.lattice_bins.bin_of(np.arange(start, stop) if indices is None else indices)
            st["lattice_bin"] = mi.UInt32(bins)
        return st

    def _footprint(self, st, t_h):
        """The ray tube's footprint on the plane at ``t_h`` along each ray, as the half-widths
        (m) of a tent kernel along the ray's horizontal direction and across it, and the
        half-extents (cells) of the box that holds it; zero half-extents where the footprint is
        smaller than a cell (the crossing stays a point). The tube's cross-section at path length
        ``L`` is ``c (L - l0) L`` (``c = 4 pi / num_rays``, ``l0 = 0`` for the lattice rays, a cone
        from the transmitter unfolded through specular reflections; a diffracted ray carries its
        own ``tube_c``, ``tube_l0``, :mod:`.diffraction`; after a diffuse bounce: not tracked, a
        point); on the plane it is that square stretched by ``1 / |cos theta_z|`` along the ray.

        Back along the ray it stops at the plane of the face the segment left (``back_reach``, in
        the ray's state after an interaction, :func:`_back_reach`): a grazing ray's stretched
        footprint otherwise reached back through the wall it had just left, and its deposits
        there took the image source's delay (on taipei.osm up to 200 ns before the line of
        sight, behind a building). A horizontal face (the ground) bounds no part of the plane
        above it. Where the footprint then spans less than a cell, the crossing stays a point.
        (Ahead it is not bounded by the face the segment meets next: the last segments are cast
        only as far as their last crossing, :meth:`_reach`, so that face is not known there.)"""
        dr, mi, g = self.dr, self.mi, self.g
        d = st["d"]
        length = st["length"] + t_h
        if "tube_c" in st:
            c, l0 = st["tube_c"], st["tube_l0"]
        else:
            c, l0 = self.tube_c, mi.Float(0.0)
        if self.sampled:  # diffused since launch (or since the diffraction): no tube
            c = dr.select(st["anchor"] == l0, c, 0.0)
        cz = dr.abs(d.z)
        side = dr.sqrt(dr.maximum(c * (length - l0) * length, 0.0))  # across the ray, m
        cell = dr.minimum(g["dx"], g["dy"])
        wide = side * side > g["dx"] * g["dy"] * cz  # the footprint is larger than a cell
        cap = self.max_footprint_cells * cell
        a_v = dr.minimum(dr.maximum(side, cell), cap)
        a_u = dr.minimum(dr.maximum(side / cz, cell), cap)
        rho = dr.sqrt(dr.maximum(d.x * d.x + d.y * d.y, 0.0))
        if "back_reach" in st:  # the face the segment left bounds it (see above, _back_reach)
            a_u = dr.minimum(a_u, t_h * st["back_reach"])
        wide &= a_u >= cell
        ux = dr.select(rho > 0, d.x / rho, 1.0)
        uy = dr.select(rho > 0, d.y / rho, 0.0)
        hx = dr.select(wide, (a_u * dr.abs(ux) + a_v * dr.abs(uy)) / g["dx"], 0.0)
        hy = dr.select(wide, (a_u * dr.abs(uy) + a_v * dr.abs(ux)) / g["dy"], 0.0)
        return dict(a_u=a_u, a_v=a_v, ux=ux, uy=uy, hx=hx, hy=hy)

    def _deposits(self, st, t_hit, height, cell_offset, spread: bool = True) -> dict[str, np.ndarray] | None:
        dr, mi, g = self.dr, self.mi, self.g
        o, d = st["o"], st["d"]
        t_h = (height - o.z) / d.z
        cross = (d.z != 0) & (t_h > 0) & (t_h < t_hit)
        px = (o.x + t_h * d.x - g["x_lo"]) / g["dx"]  # crossing point, in cells
        py = (o.y + t_h * d.y - g["y_lo"]) / g["dy"]
        if spread and self.max_footprint_cells > 1:
            fp = self._footprint(st, t_h)
            hx, hy = fp["hx"], fp["hy"]
        else:
            fp, hx, hy = None, mi.Float(0.0), mi.Float(0.0)
        # the crossing's footprint (a point where hx = hy = 0) overlaps the grid
        cross &= (px + hx >= 0) & (px - hx < g["nx"]) & (py + hy >= 0) & (py - hy < g["ny"])
        # one kernel for the mask and what the crossings read (a gather from a lazy array
        # evaluates it, and all it depends on, in a kernel of its own)
        dr.eval(cross, px, py, *(fp.values() if fp is not None else ()))
        idx = dr.compress(cross)
        if dr.width(idx) == 0:
            return None
        px, py = dr.gather(mi.Float, px, idx), dr.gather(mi.Float, py, idx)
        weight = None
        if fp is not None:
            spread_out = self._spread(px, py, {k: dr.gather(mi.Float, v, idx) for k, v in fp.items()}, cell_offset)
            if spread_out is None:
                return None
            source, col, row, weight = spread_out
            if source is not None:
                idx = dr.gather(mi.UInt32, idx, source)
        else:
            col, row = dr.floor(px), dr.floor(py)
        take = {k: dr.gather(type(v), v, idx) for k, v in st.items()}  # the state of each deposit
        d = take["d"]
        centre = mi.Point3f(g["x_lo"] + (col + 0.5) * g["dx"], g["y_lo"] + (row + 0.5) * g["dy"], height)
        if not self.sampled:
            v = centre - (take["o"] - take["length"] * d)  # cell centre minus the image source
            dist = dr.norm(v)
            d_c = v / dist
            # normalised: a diffracted ray's mirror columns are rank one (DiffractionSampler)
            d_dep = dr.normalize(mi.Vector3f(dr.dot(take["m0"], d_c), dr.dot(take["m1"], d_c),
                                             dr.dot(take["m2"], d_c)))
        else:
            # after a diffuse bounce the path restarts at the hit point: its image s' through the
            # later reflections lies (length - anchor) behind the segment's origin, and the delay
            # is anchor + |c - s'|; anchor = 0 (never diffused): the image source as above
            anchor = take["anchor"]
            v = centre - (take["o"] - (take["length"] - anchor) * d)
            r = dr.norm(v)
            dist = anchor + r
            d_c = v / r
            # a diffused ray's mirror columns are rank 1 (m_k = dep_k d): its departure is fixed,
            # read along its own direction; unit length restored for both kinds
            d_sel = dr.select(anchor > 0, d, d_c)
            d_dep = dr.normalize(mi.Vector3f(dr.dot(take["m0"], d_sel), dr.dot(take["m1"], d_sel),
                                             dr.dot(take["m2"], d_sel)))
        # No path is shorter than the straight line. The image source's distance is, to a cell
        # centre behind the mirror the ray last left (a cell that straddles the wall: the crossing
        # lies in front of it, the centre behind): 1-6 ns before the line of sight on taipei.osm
        dist = dr.maximum(dist, dr.norm(centre - mi.Point3f(*self.tx)))
        power = self._received(take["e_re"], take["e_im"], d) * self.power_scale / dr.abs(d.z)
        if weight is not None:
            power *= weight
        cell = cell_offset + mi.UInt32(row) * g["nx_int"] + mi.UInt32(col)
        if "dir_pdf" in take and self.nee is not None:
            # the first segment after a diffuse reflection: the balance heuristic's share of the
            # scattered ray (density dir_pdf per sr, |d_z| / t^2 per m^2 of the plane) beside the
            # hit's connections to cells (Tracer._connect), which estimate the same crossings
            t_c = dr.gather(mi.Float, t_h, idx)
            p_ray = take["dir_pdf"] * dr.abs(d.z) / dr.maximum(t_c * t_c, 1e-12)
            p_conn = dr.gather(mi.Float, self.nee["cell_density"], cell)
            power *= dr.select(take["dir_pdf"] > 0, p_ray / (p_ray + p_conn), 1.0)
        out = dict(cell=cell, power=power, dist=dist)
        if self.tag_diffuse_last:  # a lattice ray's first segment after its diffuse reflection
            out["diffuse_last"] = ((take["dir_pdf"] > 0) if "dir_pdf" in take and "tube_c" not in take
                                   else dr.zeros(mi.Bool, dr.width(power)))
        out.update({k: take[k] for k in TAGS if k in take})
        if "lattice_bin" in out and self.sampled:  # diffused since launch: no bin's
            out["lattice_bin"] = dr.select(take["anchor"] == 0, out["lattice_bin"], NOT_A_BIN)
        out.update(direction_terms(d_c, d_dep, self.rot, self.with_beams))
        dr.eval(*out.values())
        return out if self.device_deposits else {k: v.numpy() for k, v in out.items()}

    def _received(self, e_re, e_im, d):
        """``|E|^2`` of a field travelling along ``d`` that the receiver collects: all of it
        (``rx_polarization`` None), or for an isotropic element of one polarisation its projection
        on theta-hat (V) or phi-hat (H) of the arrival direction (the power is the cell mean, so is
        its projection)."""
        dr = self.dr
        if self.rx_polarization is None:
            return dr.squared_norm(e_re) + dr.squared_norm(e_im)
        theta_hat, phi_hat = _theta_phi_hat(dr, self.mi, d)
        u = theta_hat if self.rx_polarization == "V" else phi_hat
        return dr.square(dr.dot(e_re, u)) + dr.square(dr.dot(e_im, u))

    def _spread(self, px, py, fp, cell_offset):
        """The crossings repeated once per grid cell their footprint (:meth:`_footprint`) covers,
        with a tent kernel's weight at the cell's centre, normalised over the whole box (cells off
        the grid included, then dropped: a footprint that crosses the grid's border leaves that
        share outside): (the crossing of each deposit, column, row, weight; the first and last
        None where every footprint is a point), or None where no covered cell lies on the grid."""
        dr, mi, g = self.dr, self.mi, self.g
        wide = fp["hx"] > 0
        c0 = dr.floor(px - fp["hx"])
        r0 = dr.floor(py - fp["hy"])
        ncol = dr.floor(px + fp["hx"]) - c0 + 1.0
        n = mi.UInt32(ncol * (dr.floor(py + fp["hy"]) - r0 + 1.0))
        dr.eval(n)
        # lane k of the output is cell `local` of crossing `parent`: a cumulative index
        if self.device_deposits:  # on the device: one number comes back, not the index
            lanes = _cumulative_lanes(dr, mi, n)
            if lanes is None:
                return None, c0, r0, None
            parent, local = lanes
        else:  # numpy, in lane order: the same weights in any batch and any run
            n_np = n.numpy().astype(np.int64)
            if not (n_np > 1).any():
                return None, c0, r0, None
            parent_np = np.repeat(np.arange(len(n_np), dtype=np.uint32), n_np)
            local_np = np.arange(len(parent_np), dtype=np.int64) - np.repeat(np.cumsum(n_np) - n_np, n_np)
            parent, local = mi.UInt32(parent_np), mi.Float(local_np.astype(np.float32))
        gat = lambda v: dr.gather(type(v), v, parent)  # noqa: E731
        nc = gat(ncol)
        r_off = dr.floor((local + 0.5) / nc)  # float: exact for these small integers, no integer division
        col, row = gat(c0) + (local - r_off * nc), gat(r0) + r_off
        # the cell centre relative to the crossing, m, along the ray's horizontal direction and across
        ex, ey = (col + 0.5 - gat(px)) * g["dx"], (row + 0.5 - gat(py)) * g["dy"]
        ux, uy = gat(fp["ux"]), gat(fp["uy"])
        du, dv = ex * ux + ey * uy, ey * ux - ex * uy
        w = dr.maximum(1.0 - dr.abs(du) / gat(fp["a_u"]), 0.0) * dr.maximum(1.0 - dr.abs(dv) / gat(fp["a_v"]), 0.0)
        w = dr.select(gat(wide), w, 1.0)
        dr.eval(w)
        if self.device_deposits:  # float32 atomics: the last bits vary with their order
            total = dr.zeros(mi.Float, dr.width(n))
            dr.scatter_reduce(dr.ReduceOp.Add, total, w, parent)
            w = w / dr.gather(mi.Float, total, parent)
        else:
            w_np = w.numpy().astype(np.float64)
            total = np.bincount(parent_np, w_np, len(n_np))  # in lane order: deterministic
            w = mi.Float((w_np / total[parent_np]).astype(np.float32))
        dr.eval(col, row, w)
        keep = (col >= 0) & (col < g["nx"]) & (row >= 0) & (row < g["ny"]) & (w > 0)
        sel = dr.compress(keep)
        if dr.width(sel) == 0:
            return None
        col, row, w = (dr.gather(mi.Float, a, sel) for a in (col, row, w))
        if self.outdoor is not None:
            # the part of a footprint that falls inside a building never reaches the plane: a cell
            # gets its outdoor part of the kernel's share (the density after the solver's division
            # by that part is the unobstructed one); a point crossing did land outdoors: all of it
            outdoor = dr.gather(mi.Float, self.outdoor, cell_offset + mi.UInt32(row) * g["nx_int"] + mi.UInt32(col))
            w = dr.select(dr.gather(mi.Bool, gat(wide), sel), w * outdoor, w)
        return dr.gather(mi.UInt32, parent, sel), col, row, w

    def collect_lit(self, pairs: bool) -> None:
        """From now on, collect the lattice rays' first hits (global face indices, ``lit_faces``)
        and, with ``pairs``, the (first, second) face pairs of their specular reflections
        (``lit_pairs``): the lit wedges of :class:`simart_pipeline.ckm.diffraction.DiffractionSampler`,
        without casting the rays again. With drawn interactions (a drawn one is no mirror) each first
        hit's mirror ray is cast at depth 0 (:meth:`mirror_pair_keys`); else the tracer's own
        reflected rays give the second faces."""
        self._lit_face_hits = self.dr.zeros(self.mi.UInt32, len(self.faces.normals))
        self.lit_pairs = [] if pairs else None

    @property
    def lit_faces(self) -> list[np.ndarray] | None:
        """The lit faces collected since :meth:`collect_lit` (one sorted array in a list, as
        ``lit_pairs`` holds its keys), None where nothing is collected."""
        if self._lit_face_hits is None:
            return None
        return [np.flatnonzero(self._lit_face_hits.numpy()).astype(np.uint64)]

    @property
    def lit_face_hits(self) -> np.ndarray | None:
        """``[num faces]`` how many lattice rays hit each face first since :meth:`collect_lit`
        (each ray ``4 pi / num_rays`` sr of the transmitter's sphere: a face's share of the
        directly incident power, up to the antenna pattern), None where nothing is collected."""
        if self._lit_face_hits is None:
            return None
        return np.asarray(self._lit_face_hits.numpy(), np.float64)

    def _record_lit(self, depth: int, ids, prim, hit, prev, st=None, t=None):
        """Collect the lit faces (depth 0) and, after a specular reflection, the (first, second)
        face pairs (depth 1) of the lattice rays, as 64-bit keys ``first << 32 | second``;
        returns what depth 1 needs of depth 0 (its faces and hits). ``st``, ``t``: the depth-0
        rays and their hit distances, whose mirror rays give the pairs where interactions are drawn."""
        dr, mi = self.dr, self.mi
        if self._lit_face_hits is None:
            return None
        face, n = self.face_at(ids, prim, hit)
        if depth == 0:  # counts on the device: nothing comes back per batch
            dr.scatter_add(self._lit_face_hits, mi.UInt32(1), face, hit)
            if self.sampled and self.lit_pairs is not None:
                self.lit_pairs.append(self.mirror_pair_keys(st["o"], st["d"], t, face, n, hit))
            return face, hit
        if self.lit_pairs is not None and prev is not None and not self.sampled:
            # _reflect keeps the hit lanes in order: the reflected ray j is lattice ray compress(hit)[j]
            first = dr.gather(mi.UInt32, prev[0], dr.compress(prev[1]))
            self.lit_pairs.append(_unique_keys(dr, (mi.UInt64(first) << 32) | mi.UInt64(face), hit))
        return None

    def mirror_pair_keys(self, o, d, t, face, n, hit) -> np.ndarray:
        """The distinct (first, second) face pairs, as keys ``first << 32 | second``, of rays from
        ``o`` along ``d`` that hit global face ``face`` (normal ``n``) at distance ``t`` (``hit``)
        and go on as its mirror image: each reflected ray cast once."""
        dr, mi = self.dr, self.mi
        n = dr.select(dr.dot(d, n) > 0, -n, n)  # towards the side the ray comes from
        p = o + dr.select(hit, t, 0.0) * d
        d_r = d - 2.0 * dr.dot(d, n) * n
        o_r = p + (1.0 + dr.max(dr.abs(p))) * _SPAWN_EPSILON * n
        pi = self.scene.ray_intersect_preliminary(mi.Ray3f(o_r, d_r), False, hit)
        hit2 = hit & pi.is_valid()
        face2, _ = self.face_at(dr.reinterpret_array(mi.UInt32, pi.shape), pi.prim_index, hit2)
        return _unique_keys(dr, (mi.UInt64(face) << 32) | mi.UInt64(face2), hit2)

    def face_at(self, ids, prim, active):
        """Global face index and unit normal of the hit (Mitsuba shape id ``ids``, primitive
        ``prim``) on the active lanes; misses carry no valid triangle index, so inactive lanes
        never gather with it (no bounds checks)."""
        dr, mi = self.dr, self.mi
        face = dr.gather(mi.UInt32, self.face_offset, ids, active) + dr.select(active, prim, 0)
        return face, dr.gather(mi.Vector3f, self.face_normals, face, active)

    def _reach(self, o, d):
        """How far along each ray (origin ``o``, direction ``d``) its last crossing of a grid plane
        that can deposit lies (the same ``t_h`` as :meth:`_deposits`; a crossing whose footprint
        cannot reach the grid does not count); 0 where no such crossing lies ahead."""
        dr, g = self.dr, self.g
        # a footprint's half-extent is at most max_footprint_cells x sqrt(2) cells (_footprint):
        # crossings farther than this margin outside the grid deposit nothing in _deposits
        margin = 2.0 * max(float(self.max_footprint_cells), 1.0) + 1.0
        reach = self.mi.Float(0.0)
        for height, _ in self.heights:
            t_h = (height - o.z) / d.z
            px = (o.x + t_h * d.x - g["x_lo"]) / g["dx"]
            py = (o.y + t_h * d.y - g["y_lo"]) / g["dy"]
            near = (px > -margin) & (px < g["nx"] + margin) & (py > -margin) & (py < g["ny"] + margin)
            reach = dr.select((d.z != 0) & near & (t_h > reach), t_h, reach)
        return reach

    def _reflect(self, st, t, ids, prim, keep, last: bool = False):
        """The specular reflection of each hit ``keep``; ``last``: the reflected rays only deposit
        (the next segment is the last), those with no crossing that can deposit are dropped
        (:meth:`_reach`)."""
        dr, mi = self.dr, self.mi
        d = st["d"]
        _, n = self.face_at(ids, prim, keep)
        n = dr.select(dr.dot(d, n) > 0, -n, n)
        eta_re, eta_im, thick, spec = (dr.gather(mi.Float, table, ids, keep) for table in self.mat)
        r = reflection_terms(dr, mi, d, n, st["e_re"], st["e_im"], eta_re, eta_im, thick, self.wavelength)
        e_s, e_pr, d_r = r["e_s"], r["e_pr"], r["d_r"]
        a_r, a_i, b_r, b_i = r["a_r"], r["a_i"], r["b_r"], r["b_i"]
        p = st["o"] + t * d
        # leave the face on the side the ray came from, like Mitsuba's spawn_ray offset
        offset = (1.0 + dr.max(dr.abs(p))) * _SPAWN_EPSILON
        new = dict(
            o=mi.Point3f(p + offset * n), d=d_r,
            e_re=spec * (a_r * e_s + b_r * e_pr), e_im=spec * (a_i * e_s + b_i * e_pr),
            length=st["length"] + t,
            **{k: st[k] - 2.0 * dr.dot(n, st[k]) * n for k in ("m0", "m1", "m2")},
            back_reach=_back_reach(dr, d_r, n),  # the face it leaves bounds its footprints
            **{k: st[k] for k in _CARRIED if k in st})
        if last:
            keep = keep & (self._reach(new["o"], new["d"]) > 0)
        return _compact(dr, new, keep)

    def _uniform(self, idx, depth: int, purpose: int):
        """Uniform float in [0, 1) (24 bits) from the ray's lattice index, the depth and a purpose."""
        dr, mi = self.dr, self.mi
        h = _hash32(_hash32(idx + _RNG_SEED) ^ dr.opaque(mi.UInt32, _key(depth, purpose)))
        return mi.Float(h >> 8) * (2.0**-24)

    def _bits(self, idx, depth: int, purpose: int, sub):
        """32 random bits from the ray's lattice index, the depth, a purpose and ``sub`` (UInt32:
        which of a hit's connections)."""
        dr, mi = self.dr, self.mi
        h = _hash32(idx + _RNG_SEED) ^ dr.opaque(mi.UInt32, _key(depth, purpose))
        return _hash32(h ^ _hash32(sub + 0x68E31DA4))

    def _diffuse_direction(self, d, n, d_r, pat, idx, depth):
        """Scattered direction, pattern weight ``f_s / q`` and sampling density ``q`` (per sr) per
        ray (see the module docstring)."""
        dr, mi = self.dr, self.mi
        u1, u2 = self._uniform(idx, depth, _DRAW_DIR1), self._uniform(idx, depth, _DRAW_DIR2)
        frame = mi.Frame3f(n)
        ko_cos = frame.to_world(mi.warp.square_to_cosine_hemisphere(mi.Point2f(u1, u2)))
        # Lambertian f_s = cos / pi, sampled with q = cos / pi
        ko, weight, q = ko_cos, mi.Float(1.0), dr.maximum(dr.dot(ko_cos, n), 0.0) * (1.0 / np.pi)
        if len(self.patterns) == 1:
            return ko, weight, q
        from sionna.rt.radio_materials.scattering_pattern import BackscatteringPattern

        ki_local = frame.to_local(d)
        for k, pattern in enumerate(self.patterns[1:], start=1):
            if isinstance(pattern, BackscatteringPattern):  # directive too (lambda = 1)
                lam = float(np.array(pattern.lambda_).ravel()[0])
                a_r, a_i = int(pattern.alpha_r), int(pattern.alpha_i)
                lobe_r = self._uniform(idx, depth, _DRAW_LOBE) < lam
                alpha = dr.select(lobe_r, float(a_r), float(a_i))
                axis = dr.select(lobe_r, d_r, -d)
                # lobe (1 + cos psi)^a / 2^a about its axis: ((1 + c) / 2) = u^(1 / (a + 1))
                c = dr.clip(2.0 * dr.exp(dr.log(u1) / (alpha + 1.0)) - 1.0, -1.0, 1.0)
                sp, cp = dr.sincos(2.0 * dr.pi * u2)
                sn = dr.sqrt(dr.maximum(1.0 - c * c, 0.0))
                ko_k = mi.Frame3f(axis).to_world(mi.Vector3f(sn * cp, sn * sp, c))
            else:  # any other registered pattern: cosine-weighted, weighted by f_s / q
                ko_k = ko_cos
            fs, q_k = self._pattern_density(pattern, frame, ki_local, d, d_r, ko_k)
            up = (dr.dot(ko_k, n) > 0) & (q_k > 0)
            sel = pat == k
            ko = dr.select(sel, ko_k, ko)
            weight = dr.select(sel, dr.select(up, fs / dr.select(up, q_k, 1.0), 0.0), weight)
            q = dr.select(sel, q_k, q)
        return ko, weight, q

    def _pattern_density(self, pattern, frame, ki_local, d, d_r, ko):
        """``f_s`` of a registered (not Lambertian) scattering pattern towards ``ko`` and the
        density ``q`` (per sr) with which :meth:`_diffuse_direction` draws ``ko``."""
        dr = self.dr
        from sionna.rt.radio_materials.scattering_pattern import BackscatteringPattern

        if isinstance(pattern, BackscatteringPattern):
            lam = float(np.array(pattern.lambda_).ravel()[0])
            a_r, a_i = int(pattern.alpha_r), int(pattern.alpha_i)
            v_r = dr.power(dr.maximum(0.5 * (1.0 + dr.dot(d_r, ko)), 0.0), a_r)
            v_i = dr.power(dr.maximum(0.5 * (1.0 - dr.dot(d, ko)), 0.0), a_i)
            q = (lam * (a_r + 1) * v_r + (1.0 - lam) * (a_i + 1) * v_i) * (1.0 / (4.0 * np.pi))
        else:
            q = dr.maximum(frame.to_local(ko).z, 0.0) * (1.0 / np.pi)
        return pattern(ki_local, frame.to_local(ko)), q

    def _scattering_density(self, d, n, d_r, pat, ko):
        """``f_s`` of each hit's scattering pattern towards ``ko`` (above the face) and the density
        ``q`` (per sr) with which :meth:`_diffuse_direction` draws it."""
        dr, mi = self.dr, self.mi
        fs = dr.maximum(dr.dot(ko, n), 0.0) * (1.0 / np.pi)
        q = fs
        if len(self.patterns) > 1:
            frame = mi.Frame3f(n)
            ki_local = frame.to_local(d)
            for k, pattern in enumerate(self.patterns[1:], start=1):
                fs_k, q_k = self._pattern_density(pattern, frame, ki_local, d, d_r, ko)
                sel = pat == k
                fs, q = dr.select(sel, fs_k, fs), dr.select(sel, q_k, q)
        return fs, q

    def _scattered_field(self, d, ko, er, ei, kx, magnitude2):
        """The scattered field towards ``ko`` of an incident field ``(er, ei)`` along ``d``: the
        XPD rotation from the incident (theta, phi) basis to the scattered one, scaled to
        ``|E_s|^2 = magnitude2`` (module docstring)."""
        dr, mi = self.dr, self.mi
        th_i, ph_i = _theta_phi_hat(dr, mi, d)
        th_o, ph_o = _theta_phi_hat(dr, mi, ko)
        e2 = dr.squared_norm(er) + dr.squared_norm(ei)
        scale = dr.sqrt(magnitude2 / dr.select(e2 > 0, e2, 1.0))
        ca, cb = dr.sqrt(1.0 - kx), dr.sqrt(kx)
        out = []
        for e in (er, ei):
            et, ep = dr.dot(e, th_i), dr.dot(e, ph_i)
            out.append(scale * ((ca * et - cb * ep) * th_o + (cb * et + ca * ep) * ph_o))
        return out

    def _interact(self, st, t, ids, prim, keep, depth: int, sink=None, last: bool = False):
        """One interaction per ray, drawn among the enabled ones in proportion to their energies
        and weighted by ``1 / sqrt(probability)`` (module docstring); with refraction and a
        reflection both on, each hit is split instead: its transmitted ray goes on with its own
        field ``T E``, beside the reflected one, drawn between specular and diffuse. Rays with no
        interaction left (no energy, a diffuse direction below the face) stop; with ``last`` (the
        next segment only deposits) so do those with no crossing ahead that can deposit
        (:meth:`_reach`)."""
        dr, mi = self.dr, self.mi
        split = self.refraction and (self.specular or self.diffuse)
        if split:
            # the hits only (the misses are not carried to the compaction at the end); each makes
            # a reflected and a transmitted ray below from terms evaluated once per hit (on two
            # lanes per hit they were evaluated twice; the two-sided compaction costs about what
            # that saves, docs/ckm-one-pass.md "Session 33")
            hits = dr.compress(keep)
            n_hits = dr.width(hits)
            if n_hits == 0:
                return None
            st_in, st = st, {k: dr.gather(type(v), v, hits) for k, v in st.items()}
            t, ids, prim = (dr.gather(type(v), v, hits) for v in (t, ids, prim))
            keep = dr.full(mi.Bool, True, n_hits)
        d = st["d"]
        _, n = self.face_at(ids, prim, keep)
        n = dr.select(dr.dot(d, n) > 0, -n, n)  # faces the side the ray comes from
        eta_re, eta_im, thick, _ = (dr.gather(mi.Float, table, ids, keep) for table in self.mat)
        s_coef, kx, pat = (dr.gather(type(table), table, ids, keep) for table in self.scat)
        er, ei = st["e_re"], st["e_im"]
        r = reflection_terms(dr, mi, d, n, er, ei, eta_re, eta_im, thick, self.wavelength)
        cos_i, e_s, e_pi, e_pr, d_r = r["cos_i"], r["e_s"], r["e_pi"], r["e_pr"], r["d_r"]
        s_r, s_i, p_r, p_i = r["s_r"], r["s_i"], r["p_r"], r["p_i"]
        a_r, a_i, b_r, b_i = r["a_r"], r["a_i"], r["b_r"], r["b_i"]
        e_refl = a_r * a_r + a_i * a_i + b_r * b_r + b_i * b_i  # |R E|^2
        s2 = s_coef * s_coef
        zero = dr.zeros(mi.Float, dr.width(cos_i))
        w_spec = (1.0 - s2) * e_refl if self.specular else zero
        w_diff = s2 * e_refl if self.diffuse and not (self.diffuse_last_only and "tube_c" in st) else zero
        if self.refraction:
            (ue_r, ue_i), (um_r, um_i) = _slab_transmission(dr, cos_i, eta_re, eta_im, thick, self.wavelength)
            c_r, c_i = _cmul(ue_r, ue_i, s_r, s_i)
            g_r, g_i = _cmul(um_r, um_i, p_r, p_i)
            w_refr = c_r * c_r + c_i * c_i + g_r * g_r + g_i * g_i  # |T E|^2
        else:
            w_refr = zero
        hit = keep  # the hits, before the roulette below
        if split:  # each ray's energy: the reflected one's W_r = w_spec + w_diff, drawn; T E exact
            total_r = w_spec + w_diff
            u = self._uniform(st["idx"], depth, _DRAW_EVENT) * total_r
            spec = u < w_spec
            diff, refr = ~spec, False
            # Russian roulette on the weak side of a split: a ray with less than SPLIT_MIN_SHARE
            # of the hit's energy goes on with probability share / SPLIT_MIN_SHARE, weighted by
            # its inverse (unbiased; most of Munich's walls transmit under 5 %)
            both = dr.maximum(total_r + w_refr, 1e-30)
            keep_p = dr.minimum(total_r / both * (1.0 / SPLIT_MIN_SHARE), 1.0)
            keep = keep & (self._uniform(st["idx"], depth, _DRAW_ROULETTE) < keep_p)
            total = total_r / dr.maximum(keep_p, 1e-30)
        else:
            total = w_spec + w_diff + w_refr
            u = self._uniform(st["idx"], depth, _DRAW_EVENT) * total
            spec = u < w_spec
            diff = ~spec & (u < w_spec + w_diff)
            refr = ~spec & ~diff
        chosen = dr.select(spec, w_spec, dr.select(diff, w_diff, w_refr))
        alive = keep & (total > 0) & (chosen > 0)
        if self.diffuse_last_only:  # a ray diffused before (its delay restarted there) ends here
            undiffused = st["anchor"] == (st["tube_l0"] if "tube_l0" in st else 0.0)
            alive &= undiffused
        p = st["o"] + t * d
        offset = (1.0 + dr.max(dr.abs(p))) * _SPAWN_EPSILON
        length = st["length"] + t
        # specular: R E, and refraction: T E, each times sqrt(W / |R E|^2) or sqrt(W / |T E|^2)
        k_spec = dr.sqrt(total / dr.select(spec & alive, e_refl, 1.0))
        new_re = k_spec * (a_r * e_s + b_r * e_pr)
        new_im = k_spec * (a_i * e_s + b_i * e_pr)
        new_d, new_o = d_r, mi.Point3f(p + offset * n)
        m = [st[k] - 2.0 * dr.dot(n, st[k]) * n for k in ("m0", "m1", "m2")]
        anchor = st["anchor"]
        if self.refraction and refr is not False:
            k_refr = dr.sqrt(total / dr.select(refr & alive, w_refr, 1.0))
            new_re = dr.select(refr, k_refr * (c_r * e_s + g_r * e_pi), new_re)
            new_im = dr.select(refr, k_refr * (c_i * e_s + g_i * e_pi), new_im)
            new_d = dr.select(refr, d, new_d)
            new_o = dr.select(refr, mi.Point3f(p - offset * n), new_o)
            alive &= ~(refr & (d.z < 0) & (p.z <= self.floor_z))
            m = [dr.select(refr, st[k], mk) for k, mk in zip(("m0", "m1", "m2"), m)]
        extra, connections = {}, None
        if self.diffuse:
            p_diff = w_diff / dr.select(total > 0, total, 1.0)  # the probability of drawing diffuse
            if (self.nee is not None or self.photons is not None) and sink is not None and not self.undiffused_only:
                connect = hit & (w_diff > 0)
                if self.diffuse_last_only:
                    connect &= undiffused
                connections = (p, n, d, d_r, w_diff, p_diff, kx, pat, length, connect)
            ko, w_pat, q_dir = self._diffuse_direction(d, n, d_r, pat, st["idx"], depth)
            alive &= ~diff | (w_pat > 0)
            # XPD rotation from the incident (theta, phi) basis to the scattered one, magnitude
            # sqrt(W f_s / q) (Sionna: S Gamma sqrt(f_s * solid angle) / sqrt(probability))
            out = self._scattered_field(d, ko, er, ei, kx, total * w_pat)
            if self.nee is not None or self.tag_diffuse_last:  # the scattered ray's density: its
                # first crossings' MIS weight (and their mark: > 0 only on the scattered rays)
                extra["dir_pdf"] = dr.select(diff, p_diff * q_dir, 0.0)
            new_re = dr.select(diff, out[0], new_re)
            new_im = dr.select(diff, out[1], new_im)
            new_d = dr.select(diff, ko, new_d)
            new_o = dr.select(diff, mi.Point3f(p + offset * n), new_o)
            # the launch direction, from now on the path's departure (on the departure grid)
            dep = on_departure_grid(mi.Vector3f(*(dr.dot(st[k], d) for k in ("m0", "m1", "m2"))))
            m = [dr.select(diff, dep[i] * ko, mk) for i, mk in enumerate(m)]
            anchor = dr.select(diff, length, anchor)
        if self.undiffused_only:
            alive &= ~diff
        if last:
            alive &= self._reach(new_o, new_d) > 0
        carried = {k: st[k] for k in _CARRIED if k in st}
        # the face it leaves bounds its footprints: on its other side for a transmitted ray
        back = _back_reach(dr, new_d, n if refr is False else dr.select(refr, -n, n))
        new = dict(o=new_o, d=new_d, e_re=new_re, e_im=new_im, length=length, m0=m[0], m1=m[1], m2=m[2],
                   back_reach=back, idx=st["idx"], anchor=anchor, **extra, **carried)
        pending = (alive, *new.values())  # the next state(s), evaluated with the connections
        if split:  # the transmitted rays: T E, on their own random stream keyed by the parent's
            idx_t = _hash32(st["idx"] ^ dr.opaque(mi.UInt32, _key(depth, _DRAW_SPLIT)))
            keep_p_t = dr.minimum(w_refr / both * (1.0 / SPLIT_MIN_SHARE), 1.0)
            total_t = w_refr / dr.maximum(keep_p_t, 1e-30)
            alive_t = hit & (self._uniform(idx_t, depth, _DRAW_ROULETTE) < keep_p_t) & (total_t > 0) & (w_refr > 0)
            if self.diffuse_last_only:
                alive_t &= undiffused
            k_refr = dr.sqrt(total_t / dr.select(alive_t, w_refr, 1.0))
            new_t = dict(o=mi.Point3f(p - offset * n), d=d, e_re=k_refr * (c_r * e_s + g_r * e_pi),
                         e_im=k_refr * (c_i * e_s + g_i * e_pi), length=length, m0=st["m0"], m1=st["m1"],
                         m2=st["m2"], back_reach=_back_reach(dr, d, -n), idx=idx_t, anchor=st["anchor"],
                         **carried)
            if "dir_pdf" in extra:
                new_t["dir_pdf"] = dr.zeros(mi.Float, dr.width(alive_t))
            new_t = {k: new_t[k] for k in new}  # the same fields in the same order
            alive_t &= ~((d.z < 0) & (p.z <= self.floor_z))
            if last:
                alive_t &= self._reach(new_t["o"], d) > 0
            pending += (alive_t, *new_t.values())
        if connections is not None:
            # the next state and the connections' inputs in one kernel over the hits: both are
            # lazy expressions of the same reflection terms, and evaluated apart (a gather from a
            # lazy array evaluates it in a kernel of its own) those ran up to four times a bounce
            # (the street canyon, every mechanism, 1e7 rays: 2.9 s of kernels in _connect, 1.7 after)
            dr.eval(*pending, *connections)
            # the connections read the incoming state where it is evaluated (a gather from the
            # hits' lazy gathers would evaluate each field in a kernel of its own)
            if self.photons is not None:  # a photon pass: the hits recorded, no connections
                self._record_photons(st_in if split else st, *connections, hits if split else None)
            else:
                self._connect(st_in if split else st, *connections, depth, sink, hits if split else None)
        if split:  # the reflected rays first, then the transmitted ones
            return _compact_pair(dr, mi, new, alive, new_t, alive_t)
        return _compact(dr, new, alive)

    def _connect(self, st, p, n, d, d_r, w_diff, p_diff, kx, pat, length, active, depth: int, sink,
                 st_lanes=None) -> None:
        """Next-event estimation of the diffuse reflections: each active hit (point ``p``, face
        normal ``n`` towards the incoming side, diffuse energy ``w_diff``, path length ``length``
        to ``p``) is joined to ``per_hit`` cells on average (``floor`` of them always, one more
        with the fractional part's probability), drawn uniformly among the candidate cells
        (:meth:`_setup_connections`), at a uniform point in the cell; a shadow ray checks that
        the point sees the hit. The point's power is Sionna's scattered field there,
        ``|E_s|^2 = w_diff f_s``, spread as ``(lambda / 4 pi)^2 / r^2`` like a ray's, and it is
        combined with the scattered ray's own crossings (:meth:`_deposits`) by the balance
        heuristic of multiple importance sampling (Veach and Guibas, SIGGRAPH 1995): each
        estimate is divided by the sum of the two strategies' densities per m^2 of the plane,
        ``per_hit / (candidates * cell area)`` and ``p_diff q |k_z| / r^2`` (``q``: the density of
        the drawn direction, :meth:`_diffuse_direction`). A far cell that a scattered ray
        crosses by chance once in millions gets its share from every hit it sees; near the hit
        the scattered rays carry it. Delay and directions are the cell centre's, as every other
        deposit's. Its inputs come evaluated (:meth:`_interact` evaluates them with the next ray
        state in one kernel); ``st_lanes``: the lane of ray state ``st`` that each of their lanes
        is (None: the same lane)."""
        dr, mi, nee, g = self.dr, self.mi, self.nee, self.g
        lanes = dr.compress(active)
        m = dr.width(lanes)
        if m == 0:
            return
        # three stages, each on the lanes the last one kept (a kernel computes its masked lanes
        # too): the connections drawn, those whose point sees the hit, their deposits
        def of_st(key):  # the ray state's field on the lanes src names now
            at = src if st_lanes is None else dr.gather(mi.UInt32, st_lanes, src)
            return dr.gather(type(st[key]), st[key], at)

        k_max = int(np.ceil(nee["per_hit"]))
        rep = dr.arange(mi.UInt32, k_max * m)
        k = rep // m
        src = dr.gather(mi.UInt32, lanes, rep - k * m)
        unit = lambda b: mi.Float(b >> 8) * (2.0**-24)  # noqa: E731
        if nee["per_hit"] != k_max:  # the last connection of a hit is drawn
            idx = of_st("idx")
            drawn = unit(self._bits(idx, depth, _DRAW_NEE_TAKE, k)) < dr.clip(nee["per_hit"] - mi.Float(k), 0.0, 1.0)
            src, k = _kept(dr, drawn, src, k)
            if src is None:
                return
        take = lambda v: dr.gather(type(v), v, src)  # noqa: E731
        idx = of_st("idx")
        # a candidate cell with probability 1 / candidates (64-bit product: no bias from rounding)
        j = mi.UInt32((mi.UInt64(self._bits(idx, depth, _DRAW_NEE_CELL, k)) * nee["num"]) >> 32)
        x0, y0, z = (dr.gather(mi.Float, nee[c], j) for c in ("x0", "y0", "z"))
        target = mi.Point3f(x0 + unit(self._bits(idx, depth, _DRAW_NEE_X, k)) * g["dx"],
                            y0 + unit(self._bits(idx, depth, _DRAW_NEE_Y, k)) * g["dy"], z)
        ph, nh = take(p), take(n)
        v = target - ph
        r = dr.norm(v)
        ko = v / dr.maximum(r, 1e-12)
        fs, q = self._scattering_density(take(d), nh, take(d_r), take(pat), ko)
        ok = (dr.dot(ko, nh) > 0) & (r > 0) & (fs > 0)
        origin = mi.Point3f(ph + (1.0 + dr.max(dr.abs(ph))) * _SPAWN_EPSILON * nh)
        ray = mi.Ray3f(origin, ko)
        ray.maxt = r * (1.0 - 1e-5)
        ok &= ~self.scene.ray_test(ray, ok)
        src, j, tx, ty, tz, fs, q = _kept(dr, ok, src, j, target.x, target.y, target.z, fs, q)
        if src is None:
            return
        ph, dh = take(p), take(d)
        v = mi.Point3f(tx, ty, tz) - ph
        r2 = dr.squared_norm(v)
        ko = v / dr.sqrt(r2)
        e_re, e_im = self._scattered_field(dh, ko, of_st("e_re"), of_st("e_im"), take(kx), take(w_diff) * fs)
        # a crossing's power scale and 1 / |cos| times the crossing density |cos| / r^2, over the
        # two strategies' densities per m^2 (the balance heuristic)
        p_ray = take(p_diff) * q * dr.abs(ko.z) / r2
        power = self._received(e_re, e_im, ko) * self.power_scale / r2 / (p_ray + nee["density"])
        cell_lo = mi.Point3f(*(dr.gather(mi.Float, nee[c], j) for c in ("x0", "y0", "z")))
        v_c = cell_lo + mi.Vector3f(0.5 * g["dx"], 0.5 * g["dy"], 0.0) - ph
        r_c = dr.norm(v_c)
        d_c = v_c / dr.maximum(r_c, 1e-12)
        # the launch direction: the mirror product's transpose applied to the incoming direction
        # (rank one after a diffuse bounce or a diffraction: the departure it carries), on the
        # departure grid as the scattered ray's own
        d_dep = on_departure_grid(mi.Vector3f(*(dr.dot(of_st(c), dh) for c in ("m0", "m1", "m2"))))
        out = dict(cell=dr.gather(mi.UInt32, nee["cell"], j), power=power, dist=take(length) + r_c)
        if self.tag_diffuse_last:  # a connection ends its path with the diffuse reflection
            out["diffuse_last"] = dr.full(mi.Bool, "tube_c" not in st, dr.width(power))
        out.update({k_: of_st(k_) for k_ in TAGS if k_ in st})
        if "lattice_bin" in out:  # a diffuse hit's connection: no bin's
            out["lattice_bin"] = dr.full(mi.UInt32, NOT_A_BIN, dr.width(power))
        out.update(direction_terms(d_c, d_dep, self.rot, self.with_beams))
        dr.eval(*out.values())
        sink(out if self.device_deposits else {k_: v_.numpy() for k_, v_ in out.items()}, False)

    def _record_photons(self, st, p, n, d, d_r, w_diff, p_diff, kx, pat, length, active, st_lanes=None) -> None:
        """A photon pass (:attr:`photons`, :mod:`.gather`): the active hits whose point the
        recorder keeps (near a gather point), with what a connection from them needs: point,
        face normal towards the incoming side, incoming direction and field, diffuse energy
        ``w_diff``, XPD, pattern, path length, departure direction (on the departure grid)."""
        dr, mi = self.dr, self.mi
        lanes = dr.compress(active)
        if dr.width(lanes) == 0:
            return
        take = lambda v: dr.gather(type(v), v, lanes)  # noqa: E731
        ph = take(p)
        keep = self.photons.keep(np.stack([c.numpy() for c in (ph.x, ph.y, ph.z)], -1))
        if not keep.any():
            return
        lanes = dr.gather(mi.UInt32, lanes, mi.UInt32(np.flatnonzero(keep).astype(np.uint32)))
        at = lanes if st_lanes is None else dr.gather(mi.UInt32, st_lanes, lanes)
        of_st = lambda key: dr.gather(type(st[key]), st[key], at)  # noqa: E731
        dh = take(d)
        dep = on_departure_grid(mi.Vector3f(*(dr.dot(of_st(c), dh) for c in ("m0", "m1", "m2"))))
        rec = dict(p=take(p), n=take(n), d=dh, e_re=of_st("e_re"), e_im=of_st("e_im"), dep=dep)
        scalars = dict(w_diff=take(w_diff), kx=take(kx), pat=take(pat), length=take(length))
        dr.eval(*rec.values(), *scalars.values())
        out = {k: np.stack([c.numpy() for c in (v.x, v.y, v.z)], -1) for k, v in rec.items()}
        out.update({k: v.numpy() for k, v in scalars.items()})
        self.photons.store(out)

    def trace(self, start: int, stop: int, sink, **rays) -> None:
        """Trace lattice rays ``start..stop-1`` (or the rays ``rays`` name, :meth:`launch`);
        ``sink(deposits, line_of_sight)`` per crossing set."""
        n = len(rays["indices"]) if rays.get("indices") is not None else stop - start
        if n > 0:
            self.propagate(self.launch(start, stop, **rays), sink, self.max_depth, from_transmitter=True)

    def propagate(self, st, sink, max_depth: int, from_transmitter: bool, first_hit=None) -> None:
        """Trace ray state ``st`` (:meth:`launch`'s form) through up to ``max_depth``
        interactions. ``from_transmitter``: its first segment is line of sight (deposited only
        with ``los``, and flagged so); False: rays of a secondary source (diffraction), every
        segment deposited, none line of sight. ``first_hit``: (distance, inf for a miss; Mitsuba
        shape id; primitive) of the first segment when the caller has cast it already."""
        dr, mi = self.dr, self.mi
        dr.eval(*st.values())
        hit_prev = None
        # the last segment only deposits (no lit faces to record from it): a ray that crosses no
        # grid plane ahead, or only outside the grid, is dropped, and the others are cast no
        # farther than their last crossing that can deposit (a hit beyond it changes no deposit);
        # the maps are the same bit for bit
        trim_last = not (from_transmitter and max_depth <= 1)
        for depth in range(max_depth + 1):
            if depth == max_depth and self.photons is not None:
                break  # a photon pass: the last segment would only deposit
            if depth == 0 and first_hit is not None:
                t_hit, ids, prim = first_hit
                hit = t_hit < dr.inf
            else:
                ray = mi.Ray3f(st["o"], st["d"])
                if depth == max_depth and trim_last:
                    ray.maxt = self._reach(ray.o, ray.d) * (1.0 + 2.0**-10)
                # the preliminary intersection (distance, shape, triangle) is a third of the cost
                # of a full surface interaction; face normals come from our own table
                pi = self.scene.ray_intersect_preliminary(ray, False)
                hit = pi.is_valid()
                t_hit = dr.select(hit, pi.t, dr.inf)
                ids = dr.reinterpret_array(mi.UInt32, pi.shape)
                prim = pi.prim_index
            dr.eval(t_hit, hit, ids, prim)
            line_of_sight = from_transmitter and depth == 0
            if from_transmitter and depth <= 1:
                hit_prev = self._record_lit(depth, ids, prim, hit, hit_prev if depth else None, st, t_hit)
            if (self.los or not line_of_sight) and self.photons is None:
                for height, cell_offset in self.heights:
                    # line of sight ends at sharp shadow edges, which a footprint would blur
                    # across; the lattice's own tubes are narrow there at useful ray counts
                    dep = self._deposits(st, t_hit, height, cell_offset, spread=not line_of_sight)
                    if dep is not None:
                        sink(dep, line_of_sight)
            if depth == max_depth:
                break
            last = trim_last and depth + 1 == max_depth  # the rays it makes only deposit
            if self.sampled:
                st = self._interact(st, t_hit, ids, prim, hit, depth, sink, last)
            else:
                st = self._reflect(st, t_hit, ids, prim, hit, last)
            if st is None:
                break


def _back_reach(dr, d, n):
    """How far back along the grid plane a footprint of a ray leaving a face may reach, per metre
    of ray from the face to its crossing (:meth:`Tracer._footprint`): ``d`` the ray's direction,
    ``n`` the face's normal on the side the ray leaves on. A crossing ``t`` along the ray lies
    ``t (d . n)`` from the face's plane, which the plane meets ``t (d . n) / (u . n)`` back along the
    ray's horizontal direction ``u``; a face that the plane does not meet behind the ray
    (horizontal, or turned away) bounds nothing: inf."""
    rho = dr.sqrt(dr.maximum(d.x * d.x + d.y * d.y, 0.0))
    k = (d.x * n.x + d.y * n.y) / dr.maximum(rho, 1e-12)
    return dr.select(k > 1e-6, dr.dot(d, n) / k, dr.inf)


def _cumulative_lanes(dr, mi, n):
    """For counts ``n`` (UInt32, each >= 1): the lanes of their concatenation as (the count each
    lane belongs to, the lane's index within it), on the device (an exclusive prefix sum, its
    starts marked and summed again); None where every count is 1. One number comes back to the
    host, the total, which sizes the output."""
    total = int(dr.sum(n)[0])
    if total == dr.width(n):
        return None
    start = dr.prefix_sum(n)
    mark = dr.zeros(mi.UInt32, total)
    dr.scatter(mark, mi.UInt32(1), start)
    parent = dr.prefix_sum(mark) + mark - 1  # inclusive sum of the marks, from 0
    local = mi.Float(dr.arange(mi.UInt32, total) - dr.gather(mi.UInt32, start, parent))
    dr.eval(parent, local)
    return parent, local


def _kept(dr, active, *arrays):
    """``arrays`` on the ``active`` lanes only, evaluated (all None where none is)."""
    dr.eval(active, *arrays)
    sel = dr.compress(active)
    if dr.width(sel) == 0:
        return (None,) * len(arrays)
    out = tuple(dr.gather(type(a), a, sel) for a in arrays)
    dr.eval(*out)
    return out


def _compact(dr, state: dict, active) -> dict | None:
    """The ray state's ``active`` lanes only, evaluated (None when none is left): the rays that
    go on after an interaction."""
    kept = _kept(dr, active, *state.values())
    return None if kept[0] is None else dict(zip(state, kept))


def _compact_pair(dr, mi, first: dict, active_first, second: dict, active_second) -> dict | None:
    """The ``active_first`` lanes of ray state ``first`` followed by the ``active_second`` lanes
    of ``second`` (the same fields), evaluated in one kernel (None when none is left)."""
    dr.eval(active_first, active_second, *first.values(), *second.values())
    sel_a, sel_b = dr.compress(active_first), dr.compress(active_second)
    n_a, n_b = dr.width(sel_a), dr.width(sel_b)
    if n_a + n_b == 0:
        return None
    if n_a == 0 or n_b == 0:  # one side only
        state, sel = (first, sel_a) if n_b == 0 else (second, sel_b)
        out = {k: dr.gather(type(v), v, sel) for k, v in state.items()}
    else:  # masked gathers: each output lane reads one of the two
        lane = dr.arange(mi.UInt32, n_a + n_b)
        in_a = lane < n_a
        i_a, i_b = dr.gather(mi.UInt32, sel_a, lane, in_a), dr.gather(mi.UInt32, sel_b, lane - n_a, ~in_a)
        out = {k: dr.select(in_a, dr.gather(type(a), a, i_a, in_a), dr.gather(type(second[k]), second[k], i_b, ~in_a))
               for k, a in first.items()}
    dr.eval(*out.values())
    return out


def _unique_keys(dr, key, active, rounds: int = 2) -> np.ndarray:
    """Distinct values of the UInt32/UInt64 ``key`` over the active lanes, as uint64 (millions of
    hits, few distinct keys). Most duplicates are dropped on the device first: each lane writes
    its index into a table slot picked by a hash of its key, and only the slot's winner and the
    lanes whose key differs from the winner's go on (so every distinct key survives), ``rounds``
    times with a new hash; the few left come to the host for ``pandas.unique``. On a GPU the
    host's copy and hashing of every lane took 13 ms a batch (canyon, docs/ckm-one-pass.md)."""
    import mitsuba as mi

    dr.eval(key, active)  # one kernel: the key's gather would evaluate their shared graph (a ray cast) again
    idx = dr.compress(active)
    if dr.width(idx) == 0:
        return np.zeros(0, np.uint64)
    k = dr.gather(type(key), key, idx)
    wide = isinstance(k, mi.UInt64)
    for r in range(rounds):
        n = dr.width(k)
        if n <= _DEDUP_MIN_LANES:
            break
        h32 = mi.UInt32(k ^ (k >> 32)) if wide else k
        slot = _hash32(h32 ^ _key(r, _DEDUP_PURPOSE)) >> (32 - _DEDUP_TABLE_BITS)
        lane = dr.arange(mi.UInt32, n)
        table = dr.zeros(mi.UInt32, 1 << _DEDUP_TABLE_BITS)
        dr.scatter(table, lane, slot)  # one writer per slot wins, whichever
        winner = dr.gather(mi.UInt32, table, slot)
        keep = (winner == lane) | (dr.gather(type(k), k, winner) != k)
        k = dr.gather(type(k), k, dr.compress(keep))
    dr.eval(k)
    return pd.unique(k.numpy().astype(np.uint64))
