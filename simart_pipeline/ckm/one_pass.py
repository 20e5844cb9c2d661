"""One shoot-and-bounce pass over a CKM grid: every propagation layer of every cell at once.

The fast CKM mode. Rays leave the transmitter on a Fibonacci lattice (each carries the solid angle
``4 pi / num_rays``) and bounce specularly through the radio mesh (Mitsuba ``ray_intersect``);
where a segment crosses a grid height plane inside the grid it deposits into that cell. Every
deposit adds to the per-cell power moments of :mod:`simart_pipeline.ckm.moments`, the definitions
the reference mode (PathSolver at cell centres) shares, so both modes write the same layers.

What a ray carries: its polarised field (a complex world-frame 3-vector, started from the transmit
element pattern of the scene's ``tx_array``; at each reflection split into TE and TM and multiplied
by the ITU-R P.2040 slab coefficients of the hit object's radio material), its path length, and
the product of its mirror reflections (to map arrival directions back to departure directions).

What a deposit adds (``p``: power gain, ``tau``: delay):

- ``p = |E|^2 * (4 pi / N) / |cos theta_z| * (lambda / 4 pi)^2 / cell_area``: the cell-mean path
  gain estimator of Sionna's RadioMapSolver (ray-tube footprint on the plane), element to
  element; the receiver is isotropic and, by default, polarisation-blind (``|E|^2``; pass
  ``rx_polarization="V"`` or ``"H"`` for an isotropic element of that polarisation, PathSolver's
  ``iso`` receiver);
- delays and directions are moved to the cell centre along the ray's image source ``s = o - L d``
  (``o`` the segment's origin, ``L`` the path length there): ``tau = |c - s| / c0``, arrival
  direction ``(c - s) / |c - s|``, departure direction the same mirrored back through the ray's
  reflections. This is exact for line of sight and for specular paths off planar faces (it is the
  spherical form of the plane-wave correction ``tau + d . (c - hit) / c0``, equal to it at first
  order), so a single path gives zero spreads, and ToA is the centre's, not the cell's nearest corner;
- delays are summed as excess over ``tau0 = |c - tx| / c0`` (float64 on the numpy side), so
  sums keep ps precision at km range;
- beam gains: ``p |w_b^T v(d_dep)|^2`` with the project's precoder convention
  (:mod:`simart_pipeline.link.beams`: ``v_n = exp(+j 2 pi / lambda p_n . d)``, no conjugation),
  incoherent over paths, evaluated per group of deposits of a cell sharing one departure direction.

Handled: line of sight, specular reflection up to ``max_depth``. Refused with a ValueError:
refraction, diffraction, diffuse reflection (a material's scattering coefficient ``S`` only
lowers the specular field by ``sqrt(1 - S^2)``, as in Sionna RT; the diffuse energy is not traced).
Rays are traced in batches of lattice sub-ranges (bounded memory; the same rays whatever the
batch size) and accumulated in float64 with numpy, so results depend on the batch size only
through float64 summation order.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from scipy.constants import c as SPEED_OF_LIGHT
from scipy.constants import epsilon_0

from simart_pipeline.ckm.moments import CellMoments, layers_from_moments
from simart_pipeline.link.beams import rotation_local_to_world

DEFAULT_BATCH_RAYS = 1 << 20  # about 0.5 GB of ray state on the LLVM backend
DEFAULT_MIN_HITS_FOR_SPREAD = 10
DEFAULT_MIN_OUTDOOR_FRACTION = 0.5
OUTDOOR_SAMPLES_PER_AXIS = 4
# Departure directions are grouped for the beam gains on a grid of 2**-13 in direction cosines:
# a phase error below pi * 2**-13 * sqrt(3) * (largest element offset in wavelengths) per element,
# 1.2e-3 rad for an 8 x 8 half-wavelength array. 15 bits per component.
_Q_BITS = 15
_DIRECTION_QUANTUM = 2.0**-13
_Q_OFFSET = 1 << 13
_GOLDEN_RATIO = (1.0 + 5.0**0.5) / 2.0


@dataclass
class OnePassMoments(CellMoments):
    """:class:`CellMoments` of the one-pass solver, grid shape ``[num_heights, ny, nx]``, plus what
    it was run with: ``min_count_for_spread`` (ray hits a cell needs for spreads and mean angles)
    and ``outdoor_fraction`` (``[num_heights, ny, nx]``, share of the cell's area outside buildings;
    cells below the solver's ``min_outdoor_fraction`` or flagged ``indoor`` hold zero moments)."""

    min_count_for_spread: int = 1
    outdoor_fraction: np.ndarray | None = None
    masked: np.ndarray | None = None  # [num_heights, ny, nx] bool: indoor or too little outdoor area

    def layers(self) -> dict[str, np.ndarray]:
        """:func:`layers_from_moments` with this run's ``min_count_for_spread``."""
        return layers_from_moments(self, self.min_count_for_spread)

    def merge(self, other: "CellMoments") -> "OnePassMoments":
        """Sums of two disjoint sets of rays over the same grid (e.g. two solver runs)."""
        base = [f.name for f in fields(CellMoments)]
        merged = CellMoments(**{k: getattr(self, k) for k in base}).merge(
            CellMoments(**{k: getattr(other, k) for k in base}))
        return OnePassMoments(**{k: getattr(merged, k) for k in base},
                              min_count_for_spread=self.min_count_for_spread,
                              outdoor_fraction=self.outdoor_fraction, masked=self.masked)


@dataclass(frozen=True)
class _Grid:
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


def _grid(x_m, y_m, heights_m) -> _Grid:
    x0, dx = _regular_axis(x_m, "x_m")
    y0, dy = _regular_axis(y_m, "y_m")
    if dx is None and dy is None:
        raise ValueError("x_m, y_m: a single cell has no spacing to take the cell size from")
    dx, dy = dx or dy, dy or dx  # one-cell axis: square cells
    h = np.atleast_1d(np.asarray(heights_m, np.float64))
    if h.ndim != 1 or not np.isfinite(h).all():
        raise ValueError("heights_m: expected finite heights, m")
    return _Grid(x0 - dx / 2, y0 - dy / 2, dx, dy, len(np.atleast_1d(x_m)), len(np.atleast_1d(y_m)), h)


def fibonacci_directions(start: int, stop: int, num_rays: int) -> np.ndarray:
    """Unit vectors ``[stop - start, 3]`` of lattice points ``start..stop-1`` of the ``num_rays``
    point spherical Fibonacci lattice (Gonzalez 2010, Math. Geosci. 42: 49-64): ``z = 1 - 2 i /
    (N - 1)``, azimuth ``2 pi frac(i / golden ratio)``; float64, independent of batching."""
    i = np.arange(start, stop, dtype=np.float64)
    z = 1.0 - 2.0 * i / max(num_rays - 1, 1) if num_rays > 1 else np.zeros_like(i)
    phi = 2.0 * np.pi * np.mod(i / _GOLDEN_RATIO, 1.0)
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def fibonacci_directions_dr(start: int, stop: int, num_rays: int):
    """:func:`fibonacci_directions` on the Dr.Jit backend (lattice arithmetic in float64), as a
    ``mi.Vector3f``."""
    import drjit as dr
    import mitsuba as mi

    i = mi.Float64(dr.arange(mi.UInt32, start, stop))
    z = mi.Float(1.0 - 2.0 * i / max(num_rays - 1, 1)) if num_rays > 1 else dr.zeros(mi.Float, stop - start)
    frac = i / _GOLDEN_RATIO
    phi = mi.Float(2.0 * np.pi * (frac - dr.floor(frac)))
    r = dr.sqrt(dr.maximum(1.0 - z * z, 0.0))
    sp, cp = dr.sincos(phi)
    return mi.Vector3f(r * cp, r * sp, z)


def _material_tables(radio) -> tuple[np.ndarray, ...]:
    """Per Mitsuba shape id: complex relative permittivity (re, im), thickness m and the specular
    amplitude factor ``sqrt(1 - S^2)``, from the Sionna scene's radio materials (weather applied)."""
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
    size = max(rows, default=0) + 1
    table = np.zeros((4, size))
    table[0] = 1.0  # id 0 (no shape) never reflects; vacuum keeps the arithmetic finite
    for k, row in rows.items():
        table[:, k] = row
    return tuple(table)


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


class _Tracer:
    """Dr.Jit side: launch, intersect, deposit, reflect; hands deposits to numpy per segment."""

    def __init__(self, radio, tx_position_m, tx_rotation: np.ndarray, grid: _Grid, num_rays: int,
                 max_depth: int, los: bool, rx_polarization: str | None, with_beams: bool = False):
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
        self.mat = tuple(mi.Float(np.asarray(a, np.float32)) for a in (eta_re, eta_im, thick, spec))
        # p = |E|^2 * solid angle / |cos| * (lambda / 4 pi)^2 / cell area (RadioMapSolver's estimator)
        self.power_scale = opaque((4 * np.pi / num_rays) * (radio.wavelength_m / (4 * np.pi)) ** 2
                                  / (grid.dx * grid.dy))

    def launch(self, start: int, stop: int):
        dr, mi = self.dr, self.mi
        d = fibonacci_directions_dr(start, stop, self.num_rays)
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
        return dict(o=o, d=d, e_re=e_re, e_im=e_im, length=dr.zeros(mi.Float, n), m0=mirror[0],
                    m1=mirror[1], m2=mirror[2])

    def _deposits(self, st, t_hit, height, cell_offset) -> dict[str, np.ndarray] | None:
        dr, mi, g = self.dr, self.mi, self.g
        o, d = st["o"], st["d"]
        t_h = (height - o.z) / d.z
        cross = (d.z != 0) & (t_h > 0) & (t_h < t_hit)
        col = dr.floor((o.x + t_h * d.x - g["x_lo"]) / g["dx"])
        row = dr.floor((o.y + t_h * d.y - g["y_lo"]) / g["dy"])
        cross &= (col >= 0) & (col < g["nx"]) & (row >= 0) & (row < g["ny"])
        idx = dr.compress(cross)
        if dr.width(idx) == 0:
            return None
        take = {k: dr.gather(type(v), v, idx) for k, v in st.items()}
        col, row = dr.gather(mi.Float, col, idx), dr.gather(mi.Float, row, idx)
        d = take["d"]
        centre = mi.Point3f(g["x_lo"] + (col + 0.5) * g["dx"], g["y_lo"] + (row + 0.5) * g["dy"], height)
        v = centre - (take["o"] - take["length"] * d)  # cell centre minus the image source
        dist = dr.norm(v)
        d_c = v / dist
        d_dep = mi.Vector3f(dr.dot(take["m0"], d_c), dr.dot(take["m1"], d_c), dr.dot(take["m2"], d_c))
        e_re, e_im = take["e_re"], take["e_im"]
        if self.rx_polarization is None:
            field2 = dr.squared_norm(e_re) + dr.squared_norm(e_im)
        else:  # isotropic element of one polarisation: project on theta-hat or phi-hat of the
            # ray's own arrival direction (the power is the cell mean, so is its projection)
            rho = dr.sqrt(d.x * d.x + d.y * d.y)
            safe = rho > 1e-7
            cphi = dr.select(safe, d.x / rho, 1.0)
            sphi = dr.select(safe, d.y / rho, 0.0)
            if self.rx_polarization == "V":
                u = mi.Vector3f(d.z * cphi, d.z * sphi, -rho)
            else:
                u = mi.Vector3f(-sphi, cphi, 0.0)
            field2 = dr.square(dr.dot(e_re, u)) + dr.square(dr.dot(e_im, u))
        power = field2 * self.power_scale / dr.abs(d.z)
        cell = cell_offset + mi.UInt32(row) * g["nx_int"] + mi.UInt32(col)
        out = dict(cell=cell, power=power, dist=dist)
        # cos and sin of azimuth and zenith, arrival then departure (ANGLES order); arrival angles
        # are those of -d_c, towards where the wave comes from, as PathSolver's
        for k, u in enumerate((-d_c, d_dep)):
            rho = dr.sqrt(dr.maximum(u.x * u.x + u.y * u.y, 0.0))
            safe = rho > 0
            out[f"cos{2 * k}"] = dr.select(safe, u.x / rho, 1.0)
            out[f"sin{2 * k}"] = dr.select(safe, u.y / rho, 0.0)
            out[f"cos{2 * k + 1}"] = dr.clip(u.z, -1.0, 1.0)
            out[f"sin{2 * k + 1}"] = rho
        if self.with_beams:  # departure direction in the device frame, quantised (see _beams)
            key = mi.UInt64(0)
            for k in range(3):
                c = sum(self.rot[i][k] * d_dep[i] for i in range(3))
                q = mi.UInt64(mi.Int32(dr.round(c * (1.0 / _DIRECTION_QUANTUM))) + _Q_OFFSET)
                key = (key << _Q_BITS) | q
            out["dkey"] = key
        dr.eval(*out.values())
        return {k: v.numpy() for k, v in out.items()}

    def _reflect(self, st, si, keep):
        dr, mi = self.dr, self.mi
        d = st["d"]
        n = si.n
        n = dr.select(dr.dot(d, n) > 0, -n, n)
        cos_i = dr.clip(-dr.dot(d, n), 0.0, 1.0)
        ids = dr.reinterpret_array(mi.UInt32, si.shape)
        eta_re, eta_im, thick, spec = (dr.gather(mi.Float, t, ids) for t in self.mat)
        (te_r, te_i), (tm_r, tm_i) = _slab_reflection(dr, cos_i, eta_re, eta_im, thick, self.wavelength)
        e_s = dr.cross(d, n)
        ls = dr.norm(e_s)
        e_s = dr.select(ls > 1e-6, e_s / dr.maximum(ls, 1e-30), mi.coordinate_system(n)[0])
        d_r = d + 2.0 * cos_i * n
        e_pi, e_pr = dr.cross(e_s, d), dr.cross(e_s, d_r)
        er, ei = st["e_re"], st["e_im"]
        s_r, s_i = dr.dot(er, e_s), dr.dot(ei, e_s)
        p_r, p_i = dr.dot(er, e_pi), dr.dot(ei, e_pi)
        a_r, a_i = _cmul(te_r, te_i, s_r, s_i)
        b_r, b_i = _cmul(tm_r, tm_i, p_r, p_i)
        new = dict(
            o=si.spawn_ray(d_r).o, d=d_r,
            e_re=spec * (a_r * e_s + b_r * e_pr), e_im=spec * (a_i * e_s + b_i * e_pr),
            length=st["length"] + si.t,
            **{k: st[k] - 2.0 * dr.dot(n, st[k]) * n for k in ("m0", "m1", "m2")})
        dr.eval(*new.values(), keep)
        idx = dr.compress(keep)
        if dr.width(idx) == 0:
            return None
        out = {k: dr.gather(type(v), v, idx) for k, v in new.items()}
        dr.eval(*out.values())
        return out

    def trace(self, start: int, stop: int, sink) -> None:
        """Trace lattice rays ``start..stop-1``; ``sink(deposits, line_of_sight)`` per crossing set."""
        dr, mi = self.dr, self.mi
        if stop <= start:
            return
        st = self.launch(start, stop)
        dr.eval(*st.values())
        for depth in range(self.max_depth + 1):
            si = self.scene.ray_intersect(mi.Ray3f(st["o"], st["d"]))
            hit = si.is_valid()
            t_hit = dr.select(hit, si.t, dr.inf)
            dr.eval(t_hit, hit, si.n, si.p, si.t, si.shape)
            if depth > 0 or self.los:
                for height, cell_offset in self.heights:
                    dep = self._deposits(st, t_hit, height, cell_offset)
                    if dep is not None:
                        sink(dep, depth == 0)
            if depth == self.max_depth:
                break
            st = self._reflect(st, si, hit)
            if st is None:
                break


class _Accumulator:
    """numpy side: float64 per-cell sums over deposits (summation order the only batch effect)."""

    def __init__(self, grid: _Grid, tx_position_m, codebook, ant_positions_m, tx_rotation, wavelength_m):
        self.shape = grid.shape
        ncell = int(np.prod(self.shape))
        self.m = CellMoments.zeros((ncell,), None if codebook is None else codebook.shape[0])
        self.centres = grid.centres()
        self.tx = np.asarray(tx_position_m, np.float64)
        self.m.tau0_s = np.linalg.norm(self.centres - self.tx, axis=-1) / SPEED_OF_LIGHT
        self.codebook = codebook
        self.ant = ant_positions_m
        self.rot = tx_rotation
        self.k = 2 * np.pi / wavelength_m

    def __call__(self, dep: dict[str, np.ndarray], line_of_sight: bool) -> None:
        m, n = self.m, len(self.m.power)
        cell = dep["cell"].astype(np.int64)
        p = dep["power"].astype(np.float64)
        m.power += np.bincount(cell, p, n)
        if line_of_sight:
            m.los_power += np.bincount(cell, p, n)
        m.count += np.bincount(cell, minlength=n)
        tau = dep["dist"].astype(np.float64) / SPEED_OF_LIGHT
        np.minimum.at(m.min_delay_s, cell, tau)
        dtau = tau - m.tau0_s[cell]
        pd = p * dtau
        m.p_excess_delay_s += np.bincount(cell, pd, n)
        m.p_excess_delay2_s2 += np.bincount(cell, pd * dtau, n)
        for k in range(4):
            m.p_cos[:, k] += np.bincount(cell, p * dep[f"cos{k}"], n)
            m.p_sin[:, k] += np.bincount(cell, p * dep[f"sin{k}"], n)
        if self.codebook is not None and not line_of_sight:  # line of sight: in moments()
            self._beams(cell, p, dep["dkey"].astype(np.int64))

    def _beams(self, cell, p, dkey):
        # Deposits of a cell that share a departure direction (one path: the same direction up to
        # float32 noise after the image-source correction) share a beam factor: evaluate it once
        # per group, at the direction quantised to _DIRECTION_QUANTUM in the device frame (the
        # key, made on the Dr.Jit side: the same for a ray whatever its batch).
        g_cell, g_dkey, pg = _group_sums(cell, dkey, p, len(self.m.power))
        mask = (1 << _Q_BITS) - 1
        u = (np.stack([(g_dkey >> (k * _Q_BITS)) & mask for k in (2, 1, 0)], -1) - _Q_OFFSET) * _DIRECTION_QUANTUM
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        gains = beam_factors(self.codebook, self.ant, u, self.k)
        first = np.flatnonzero(np.r_[True, g_cell[1:] != g_cell[:-1]])  # groups come sorted by cell
        self.m.beam_power[g_cell[first]] += np.add.reduceat(pg[:, None] * gains, first, axis=0)

    def moments(self) -> CellMoments:
        s = self.shape
        m = self.m
        if self.codebook is not None:
            # every line-of-sight deposit of a cell leaves towards the cell centre exactly (its image
            # source is the transmitter): one beam factor per cell, at the unquantised direction
            lit = np.flatnonzero(m.los_power > 0)
            u = self.centres[lit] - self.tx
            u = (u / np.linalg.norm(u, axis=1, keepdims=True)) @ self.rot  # device frame
            m.beam_power[lit] += m.los_power[lit, None] * beam_factors(self.codebook, self.ant, u, self.k)
        return CellMoments(
            power=m.power.reshape(s), los_power=m.los_power.reshape(s), count=m.count.reshape(s),
            min_delay_s=m.min_delay_s.reshape(s), tau0_s=m.tau0_s.reshape(s),
            p_excess_delay_s=m.p_excess_delay_s.reshape(s), p_excess_delay2_s2=m.p_excess_delay2_s2.reshape(s),
            p_cos=m.p_cos.reshape(s + (4,)), p_sin=m.p_sin.reshape(s + (4,)),
            beam_power=None if m.beam_power is None else m.beam_power.reshape(s + (-1,)))


def _group_sums(cell: np.ndarray, dkey: np.ndarray, weight: np.ndarray, num_cells: int):
    """Sum ``weight`` over distinct (cell, direction key) pairs: (cells, keys, sums), sorted by cell."""
    if num_cells <= 1 << (63 - 3 * _Q_BITS):  # one int64 key: a single sort
        key = (cell << (3 * _Q_BITS)) | dkey
        order = np.argsort(key)
        k = key[order]
        new = np.r_[True, k[1:] != k[:-1]]
        c, d = k[new] >> (3 * _Q_BITS), k[new] & ((1 << (3 * _Q_BITS)) - 1)
    else:
        order = np.lexsort((dkey, cell))
        cs, ds = cell[order], dkey[order]
        new = np.r_[True, (cs[1:] != cs[:-1]) | (ds[1:] != ds[:-1])]
        c, d = cs[new], ds[new]
    return c, d, np.add.reduceat(weight[order], np.flatnonzero(new))


def beam_factors(codebook: np.ndarray, ant_positions_m: np.ndarray, directions: np.ndarray,
                 wavenumber_rad_per_m: float) -> np.ndarray:
    """``|w_b^T v(u)|^2`` ``[num_dir, num_beams]`` for unit vectors ``u`` ``[num_dir, 3]`` in the
    array's own frame; ``v_n = exp(+j k p_n . u)`` (the project's precoder convention). Complex64
    arithmetic (relative error about 1e-6, three times faster than complex128), float64 result."""
    phase = ((directions @ np.asarray(ant_positions_m, np.float64).T) * wavenumber_rad_per_m).astype(np.float32)
    v = np.empty(phase.shape, np.complex64)
    v.real, v.imag = np.cos(phase), np.sin(phase)
    y = v @ np.asarray(codebook, np.complex64).T
    return (y.real.astype(np.float64) ** 2 + y.imag.astype(np.float64) ** 2)


def outdoor_fraction(radio, x_m, y_m, heights_m, samples_per_axis: int = OUTDOOR_SAMPLES_PER_AXIS) -> np.ndarray:
    """Share of each cell's area outside buildings, ``[num_heights, ny, nx]``, from
    ``samples_per_axis**2`` points per cell. A point is inside when rays cast from it upwards
    cross the radio mesh an odd number of times (the majority of three rays, straight up and
    tilted 30 degrees two ways): closed meshes of either face orientation (Sionna's bundled
    scenes have inward normals), roofs without floors and the open ground all read right."""
    import drjit as dr
    import mitsuba as mi

    g = _grid(x_m, y_m, heights_m)
    off = (np.arange(samples_per_axis) + 0.5) / samples_per_axis - 0.5
    c = g.centres()
    px = c[:, 0, None, None] + off[None, None, :] * g.dx + 0 * off[None, :, None]
    py = c[:, 1, None, None] + off[None, :, None] * g.dy + 0 * off[None, None, :]
    pz = np.broadcast_to(c[:, 2, None, None], px.shape)
    pts = [np.ascontiguousarray(a, np.float32).ravel() for a in (px, py, pz)]
    n = pts[0].size
    votes = np.zeros(n, np.int64)
    tilt = np.radians(30.0)
    for d in ((0.0, 0.0, 1.0), (np.sin(tilt), 0.0, np.cos(tilt)), (0.0, np.sin(tilt), np.cos(tilt))):
        ray = mi.Ray3f(mi.Point3f(*pts), dr.zeros(mi.Vector3f, n) + mi.Vector3f(*(float(v) for v in d)))
        crossings = dr.zeros(mi.UInt32, n)
        active = dr.full(mi.Bool, True, n)
        for _ in range(64):  # more crossings than any city holds above one point
            si = radio.scene.mi_scene.ray_intersect(ray, active)
            active &= si.is_valid()
            crossings += mi.UInt32(dr.select(active, 1, 0))
            ray = mi.Ray3f(dr.select(active, si.spawn_ray(ray.d).o, ray.o), ray.d)
            dr.eval(ray.o, crossings, active)
            if not dr.any(active):
                break
        votes += crossings.numpy() % 2
    inside = (votes >= 2).reshape(len(c), -1)
    return (1.0 - inside.mean(axis=1)).reshape(g.shape)


def one_pass_moments(radio, tx_position_m, tx_orientation_rad, x_m: np.ndarray, y_m: np.ndarray,
                     heights_m: np.ndarray, num_rays: int, max_depth: int,
                     codebook: np.ndarray | None = None, tx_ant_positions_m: np.ndarray | None = None,
                     batch_rays: int = DEFAULT_BATCH_RAYS, min_hits_for_spread: int = DEFAULT_MIN_HITS_FOR_SPREAD,
                     *, indoor: np.ndarray | None = None,
                     min_outdoor_fraction: float = DEFAULT_MIN_OUTDOOR_FRACTION,
                     rx_polarization: str | None = None, los: bool = True, specular_reflection: bool = True,
                     refraction: bool = False, diffraction: bool = False,
                     diffuse_reflection: bool = False) -> OnePassMoments:
    """Per-cell power moments of one transmitter over a grid, from one shoot-and-bounce pass.

    :param radio: :class:`simart_pipeline.radio.tracer.RadioScene` (mesh, materials of its
        weather, frequency, ``tx_array`` whose element pattern the rays start with)
    :param tx_position_m: ``[3]`` m, world; ``tx_orientation_rad``: ``[3]`` Sionna (yaw, pitch, roll)
    :param x_m: ``[nx]`` cell-centre x, m, increasing and equally spaced (the cell size);
        ``y_m``: ``[ny]`` likewise; ``heights_m``: ``[num_heights]`` grid plane heights, m
    :param num_rays: rays on the Fibonacci lattice (each ``4 pi / num_rays`` sr)
    :param max_depth: most specular reflections per ray (0: line of sight only)
    :param codebook: ``[num_beams, num_tx_ant]`` complex unit-norm precoders, or None (no beams);
        ``tx_ant_positions_m``: ``[num_tx_ant, 3]`` m in the device frame (default: the scene's
        ``tx_array`` positions)
    :param batch_rays: rays traced at once (memory bound; the result does not depend on it)
    :param min_hits_for_spread: hits a cell needs for spreads and mean angles
        (:meth:`OnePassMoments.layers`)
    :param indoor: optional bool mask, broadcastable to ``[num_heights, ny, nx]``: cells to mask
    :param min_outdoor_fraction: cells with less of their area outside buildings
        (:func:`outdoor_fraction`) are masked; the others have their sums divided by that share
        (power normalised by the outdoor area the rays can reach)
    :param rx_polarization: None: isotropic receiver collecting the whole field ``|E|^2``
        (RadioMapSolver's); ``"V"`` / ``"H"``: an isotropic element of that polarisation
    :param los, specular_reflection: interaction types as in Sionna RT; ``refraction``,
        ``diffraction``, ``diffuse_reflection``: not supported, True raises ValueError
    :return: :class:`OnePassMoments` of grid shape ``[num_heights, ny, nx]``
    """
    from simart_pipeline import engine

    for flag, name in ((refraction, "refraction"), (diffraction, "diffraction"),
                       (diffuse_reflection, "diffuse_reflection")):
        if flag:
            raise ValueError(f"{name}: the one-pass CKM solver handles line of sight and specular "
                             "reflection only; use the reference mode (PathSolver) for it")
    if rx_polarization not in (None, "V", "H"):
        raise ValueError(f"rx_polarization must be None, 'V' or 'H', got {rx_polarization!r}")
    if int(num_rays) < 1 or int(batch_rays) < 1:
        raise ValueError(f"num_rays and batch_rays must be >= 1, got {num_rays} and {batch_rays}")
    if int(max_depth) < 0:
        raise ValueError(f"max_depth must be >= 0, got {max_depth}")
    engine.init()
    grid = _grid(x_m, y_m, heights_m)
    rot = rotation_local_to_world(np.asarray(tx_orientation_rad, np.float64))
    if codebook is not None:
        codebook = np.asarray(codebook, np.complex128)
        ant = radio.array_positions_m("tx") if tx_ant_positions_m is None else np.asarray(tx_ant_positions_m, np.float64)
        if codebook.ndim != 2 or ant.shape != (codebook.shape[1], 3):
            raise ValueError(f"codebook [num_beams, num_tx_ant] {codebook.shape} and antenna positions "
                             f"[num_tx_ant, 3] {ant.shape} do not match")
    else:
        ant = None
    depth = int(max_depth) if specular_reflection else 0
    tracer = _Tracer(radio, tx_position_m, rot, grid, int(num_rays), depth, los, rx_polarization,
                     with_beams=codebook is not None)
    acc = _Accumulator(grid, tx_position_m, codebook, ant, rot, radio.wavelength_m)
    for start in range(0, int(num_rays), int(batch_rays)):
        tracer.trace(start, min(start + int(batch_rays), int(num_rays)), acc)
    m = acc.moments()
    frac = outdoor_fraction(radio, x_m, y_m, grid.heights)
    masked = frac < min_outdoor_fraction
    if indoor is not None:
        masked |= np.broadcast_to(np.asarray(indoor, bool), grid.shape)
    scale = np.where(masked, 0.0, 1.0 / np.maximum(frac, 1e-12))
    for f in ("power", "los_power", "p_excess_delay_s", "p_excess_delay2_s2"):
        setattr(m, f, getattr(m, f) * scale)
    m.p_cos, m.p_sin = m.p_cos * scale[..., None], m.p_sin * scale[..., None]
    if m.beam_power is not None:
        m.beam_power = m.beam_power * scale[..., None]
    m.count = np.where(masked, 0, m.count)
    m.min_delay_s = np.where(masked, np.inf, m.min_delay_s)
    return OnePassMoments(**{f.name: getattr(m, f.name) for f in fields(CellMoments)},
                          min_count_for_spread=int(min_hits_for_spread), outdoor_fraction=frac, masked=masked)
