"""One shoot-and-bounce pass over a CKM grid: every propagation layer of every cell at once.

The fast CKM mode (docs/ckm-one-pass.md). Rays leave the transmitter on a Fibonacci lattice (each
carries the solid angle ``4 pi / num_rays``) and bounce through the radio mesh (specular and
diffuse reflection, refraction: :mod:`simart_pipeline.ckm.shoot_bounce`); where a segment crosses a grid height plane inside the
grid it deposits into that cell. Every deposit adds to the per-cell power moments of
:mod:`simart_pipeline.ckm.moments`, the definitions the reference mode (PathSolver at cell
centres) shares, so both modes write the same layers.

What a deposit adds (``p``: power gain, ``tau``: delay):

- ``p = |E|^2 * (4 pi / N) / |cos theta_z| * (lambda / 4 pi)^2 / cell_area``: the cell-mean path
  gain estimator of Sionna's RadioMapSolver (ray-tube footprint on the plane), element to
  element, the transmit element pattern included as in PathSolver's ``a``; the receiver is
  isotropic and, by default, polarisation-blind (``|E|^2``, RadioMapSolver's); with
  ``rx_polarization="V"`` or ``"H"`` an isotropic element of that polarisation (PathSolver's
  ``iso`` receiver);
- delays and directions are moved to the cell centre along the ray's image source ``s = o - L d``
  (``o`` the segment's origin, ``L`` the path length there): ``tau = |c - s| / c0``, arrival
  direction ``(c - s) / |c - s|``, departure direction the same mirrored back through the ray's
  reflections (refraction leaves all three unchanged; after a diffuse bounce the delay restarts at
  the hit point and the departure is the launch direction, see below). This is exact for line of
  sight and for specular paths off planar faces (the
  spherical form of the plane-wave correction ``tau + d . (c - hit) / c0``, equal to it at first
  order): one path gives zero spreads, and ToA is the centre's, not the cell's nearest corner;
- delays are summed as excess over ``tau0 = |c - tx| / c0``, in float64 on the numpy side;
- beam gains ``p |w_b^T v(d_dep)|^2``, incoherent over paths, with the project's precoder
  convention (:mod:`simart_pipeline.link.beams`: ``v_n = exp(+j 2 pi / lambda p_n . d)``, no
  conjugation): once per cell for line of sight (all its deposits leave towards the centre), once
  per group of a cell's deposits sharing a quantised departure direction for reflections.

Where a ray stands for more than a cell (far from an edge a diffracted sample does, and a
reflected ray at grazing incidence), a deposit into the one cell it crosses is a spike there and a
hole beside it: the estimate is unbiased but heavy-tailed (a few rays carry a cell). Such a
crossing is spread over the cells its ray tube's footprint covers instead: the tube's
cross-section ``A`` at that path length (``4 pi / num_rays L^2`` for a lattice ray, ``L`` the
unfolded length; a diffracted ray's own, :mod:`simart_pipeline.ckm.diffraction`) gives a tent
kernel ``sqrt(A)`` wide across the ray and ``sqrt(A) / |cos theta_z|`` along it, evaluated at
each covered cell's centre and normalised to the crossing's power (what falls off the grid is
lost, as for a point); each covered cell gets its own centre-corrected delay and directions and
counts the ray as one hit, and of its share only its part outside buildings (the part inside
never reaches the plane; after the division by the outdoor part below the density is the
unobstructed one). Line-of-sight crossings stay points (they end at sharp shadow edges,
which a footprint would blur; at useful ray counts their tubes are narrow). Munich with
diffraction, 1e7 rays, two diffraction samples per ray: against a map of 32x the diffraction
samples, gain p95 8.0 -> 3.0 dB and p99 25 -> 13 dB, 5 % more cells with a value, for 25 % more
time; at one sample per ray (the default since) p95 3.9 dB in the time two took before
(docs/ckm-one-pass.md). It is
a smoothing at the scale of the ray spacing (a kernel density estimate): structure finer than
that, which the rays cannot resolve either, is blurred.

With ``diffraction_resample_factor`` f > 1 a second pass aims diffraction samples at the cells
left with too few hits: the stretches of edge whose diffracted rays reached them are traced again
exactly (taken out of those cells) and with f times the samples (put in), an unbiased swap
(:func:`_resample_undersampled`; off by default, docs/ckm-one-pass.md "Session 15" says why).
With ``lattice_resample_factor`` f > 1 a second pass does the same for the lattice rays: the sphere
of launch directions is cut into equal-area bins of about 16 lattice points
(:class:`~simart_pipeline.ckm.shoot_bounce.LatticeBins`), every deposit of a lattice ray that
never scattered diffusely is tagged with its launch bin, and in the cells with too few effective
hits whose noise those deposits make, the bins that reached them (and the bins beside those) are
traced again exactly (taken out) and with f times the rays (put in) (:func:`_resample_lattice`;
docs/ckm-one-pass.md "Session 29").

Cells are masked (zero moments) where the caller says ``indoor`` or where less than
``min_outdoor_fraction`` of their area is outside buildings; the others have their sums divided by
that share. Spreads and mean angles need ``min_hits_for_spread`` ray hits and an effective count
(Kish) of ``min_effective_hits_for_spread`` (:meth:`OnePassMoments.layers`).

Handled: line of sight, specular reflection, diffuse reflection and refraction, up to
``max_depth`` interactions, and first-order wedge and edge diffraction
(:mod:`simart_pipeline.ckm.diffraction`: the diffracted rays go on through the same tracer). With
specular reflection alone every ray reflects deterministically (a scattering coefficient ``S``
lowers its field by ``sqrt(1 - S^2)``, as in Sionna RT). With diffuse reflection or refraction on,
each ray draws ONE interaction per hit among the enabled ones, with probabilities proportional to
their energies, and its field is divided by the square root of that probability (an unbiased
estimator; Sionna's RadioMapSolver samples the radio material the same way): refraction goes
straight through with the ITU slab transmission coefficients (image source and departure
direction unchanged); diffuse reflection samples a direction from the material's scattering
pattern and restarts the ray's delay at the hit point (``tau = (L_hit + |c - p'|) / c0``, ``p'``
the hit point's image through later specular reflections), its departure direction fixed at the
launch direction. Details: :mod:`simart_pipeline.ckm.shoot_bounce`. Random numbers are a hash of
(lattice index, depth, purpose).
Rays are traced in batches of lattice sub-ranges (bounded memory; the same rays whatever the
batch size) and accumulated in float64 with numpy, so results depend on the batch size only
through float64 summation order, and the same call twice gives bitwise-equal moments.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import pandas as pd

from simart_pipeline.ckm.compiled import compiled as _compiled
from simart_pipeline.ckm.moments import CellMoments, effective_count, layers_from_moments, too_few_hits
from simart_pipeline.ckm.diffraction import STRETCHES_PER_PAIR
from simart_pipeline.ckm.gather import (DEFAULT_GATHER_AUTO_MIN_SHARE, DEFAULT_GATHER_BELOW_EFFECTIVE_HITS,
                                        DEFAULT_GATHER_DIRECTIONS_PER_POINT, DEFAULT_GATHER_GUIDED_SHARE,
                                        DEFAULT_GATHER_PILOT_DIRECTIONS, DEFAULT_PHOTON_RAY_SHARE,
                                        GATHER_AUTO_REFERENCE_RAYS)
from simart_pipeline.ckm.outdoor import DEFAULT_MIN_OUTDOOR_FRACTION, outdoor_fraction, radio_solids
from simart_pipeline.ckm.shoot_bounce import (DIRECTION_QUANTUM, NOT_A_BIN, Q_BITS, Q_OFFSET, TAGS, Grid,
                                              LatticeBins, Tracer, grid_from_centres)
from simart_pipeline.link.beams import rotation_local_to_world
from simart_pipeline.scene.solids import Solids
from simart_pipeline.vocabulary import SPEED_OF_LIGHT_MPS

__all__ = ["OnePassMoments", "adaptive_one_pass_moments", "beam_factors", "default_batch_rays", "one_pass_moments",
           "outdoor_fraction", "undersampled_fraction"]

DEFAULT_BATCH_RAYS = 1 << 20  # about 0.5 GB of ray state on the LLVM backend
# on a GPU each batch costs Python a fixed time to trace its kernels: 4M rays took an H200 0.33 s
# on the canyon at 1e7 rays against 0.44-0.53 s in 1M batches (8M: no faster; Munich 2.8 against
# 1.9 s), docs/ckm-one-pass.md "Session 24". Its memory on the GPU was not measured: about 2 GB if
# the LLVM backend's 0.5 GB per million rays holds there
DEFAULT_BATCH_RAYS_GPU = 1 << 22
DEFAULT_MIN_HITS_FOR_SPREAD = 10
DEFAULT_MIN_EFFECTIVE_HITS_FOR_SPREAD = 10.0  # config.Ckm.min_effective_hits_for_spread's default
DEFAULT_MIN_HITS_FOR_POWER = 5  # config.Ckm.min_hits_for_power's default; the reasoning is there
DEFAULT_MAX_FOOTPRINT_CELLS = 8.0
DEFAULT_LATTICE_BIN_RAYS = 16  # lattice points per bin of the lattice's second pass (LatticeBins)
RANDOM_STREAMS = 2**32  # the tracer's random streams are keyed by a UInt32 ray number
# the lattice's second pass swaps a few-hit cell's binned part (lattice rays never diffused) where
# that part holds at least this share of the cell's sum of squared deposits: where it makes the
# cell's noise. Elsewhere the noise is the diffracted or diffused rays' (urban: 93 % of the
# undersampled cells' power came from diffraction), which finer lattice rays would not change
LATTICE_NOISE_SHARE = 0.5
# config.Ckm.diffuse_connections' default: the run-time/error front chose it (the config says why)
DEFAULT_DIFFUSE_CONNECTIONS = 0.5
BEAM_CHUNK = 4096  # directions per step of beam_factors (3x faster than all at once on 2e5)
_INF_BITS = 0x7F800000  # float32 +inf as uint32
# (cell, direction) groups whose beams wait for one evaluation (a codebook that is not a Kronecker
# product; a Kronecker one's: BEAM_CACHE_BITS): their table (_GroupSums, at most half full, 24
# bytes a slot) with one more deposit set's groups fits a 32 MB cache. Few groups
# recur between evaluations (street canyon, every mechanism, 1e7 rays: 4.7 M groups in 15, 4.4 M
# in 2), and the table's random accesses cost 1.4 s at this size against 3.0 s at 4 M groups
MAX_PENDING_GROUPS = 1 << 18
# slots of the direct-mapped cache in which a Kronecker codebook's beam sums combine deposits of
# the same (cell, direction) before their beams are added (_SeparableBeamSums), 24 bytes a slot.
# The street canyon's 27.6 M deposits (every mechanism, 1e7 rays) leave 27.4 M / 5.15 M / 4.91 M
# sums to add at 2^0 / 2^12 / 2^15 slots; 2^12 (96 kB) stays in a core's L2 beside the tracer
BEAM_CACHE_BITS = 12


@dataclass
class OnePassMoments(CellMoments):
    """:class:`CellMoments` of the one-pass solver, grid shape ``[num_heights, ny, nx]``, plus what
    it was run with: ``min_count_for_spread`` (ray hits a cell needs for spreads and mean angles),
    ``min_count_for_power`` (for path gain, ToA, LoS and beams) and ``outdoor_fraction`` (``[num_heights, ny, nx]``, share of the cell's area outside buildings;
    cells below the solver's ``min_outdoor_fraction`` or flagged ``indoor`` hold zero moments)."""

    min_count_for_spread: int = 1
    min_count_for_power: int = 1
    min_effective_count_for_power: float = 1.0  # Kish effective count (layers_from_moments)
    min_effective_count_for_spread: float = 1.0  # likewise, for spreads and mean angles
    outdoor_fraction: np.ndarray | None = None
    masked: np.ndarray | None = None  # [num_heights, ny, nx] bool: indoor or too little outdoor area
    num_rays: int = 0                 # rays of the pass (0: a merge of passes)
    second_pass: dict | None = None   # the diffraction second pass on undersampled cells (one_pass_moments)
    lattice_second_pass: dict | None = None  # the lattice rays' second pass on undersampled cells
    diffuse_gather: dict | None = None  # the diffuse gather on few-hit cells (ckm/gather.py)

    def layers(self) -> dict[str, np.ndarray]:
        """:func:`layers_from_moments` with this run's ``min_count_for_spread`` and
        ``min_count_for_power`` (the pipeline's ckm/layers.py applies the same config values)."""
        return layers_from_moments(self, self.min_count_for_spread, self.min_count_for_power,
                                   self.min_effective_count_for_power, self.min_effective_count_for_spread)

    def merge(self, other: "CellMoments") -> "OnePassMoments":
        """Sums of two disjoint sets of rays over the same grid (e.g. two solver runs)."""
        base = [f.name for f in fields(CellMoments)]
        merged = CellMoments(**{k: getattr(self, k) for k in base}).merge(
            CellMoments(**{k: getattr(other, k) for k in base}))
        return OnePassMoments(**{k: getattr(merged, k) for k in base}, num_rays=0,
                              min_count_for_spread=self.min_count_for_spread,
                              min_count_for_power=self.min_count_for_power,
                              min_effective_count_for_power=self.min_effective_count_for_power,
                              min_effective_count_for_spread=self.min_effective_count_for_spread,
                              outdoor_fraction=self.outdoor_fraction, masked=self.masked)


class _Accumulator:
    """numpy side: float64 per-cell sums over deposits (summation order the only batch effect)."""

    def __init__(self, grid: Grid, tx_position_m, codebook, ant_positions_m, tx_rotation, wavelength_m):
        self.shape = grid.shape
        ncell = int(np.prod(self.shape))
        self.m = CellMoments.zeros((ncell,), None if codebook is None else codebook.shape[0])
        self.centres = grid.centres()
        self.tx = np.asarray(tx_position_m, np.float64)
        self.m.tau0_s = np.linalg.norm(self.centres - self.tx, axis=-1) / SPEED_OF_LIGHT_MPS
        self.codebook = codebook
        self.ant = ant_positions_m
        # a Kronecker codebook's beams from their axes' factors (separable_codebook)
        self.separable = None if codebook is None else separable_codebook(codebook, ant_positions_m)
        self.rot = tx_rotation
        self.k = 2 * np.pi / wavelength_m
        # per tag (shoot_bounce.TAGS: a diffracted ray's stretch of edge, a lattice ray's bin): the
        # distinct (cell << 32 | tag) of the tagged deposits
        self.tag_keys: dict[str, list[np.ndarray]] = {k: [] for k in TAGS}
        # sum p and sum p^2 per cell of the deposits with a lattice bin (lattice rays never diffused)
        self.binned_power: np.ndarray | None = None
        self.binned_power_sq: np.ndarray | None = None
        # power sums per (cell, direction key) of the deposits whose beams are still to add (a
        # Kronecker codebook's: _SeparableBeamSums, made at the first deposit set)
        self.beam_groups = _GroupSums()
        self.beam_sums: _SeparableBeamSums | None = None
        # set: the deposits tagged diffuse_last (Tracer.tag_diffuse_last) are also summed there, the
        # part the diffuse gather replaces in few-hit cells (_gather_diffuse)
        self.diffuse_last: _Accumulator | None = None

    def __call__(self, dep: dict[str, np.ndarray], line_of_sight: bool) -> None:
        m = self.m
        if self.diffuse_last is not None and "diffuse_last" in dep:
            # a set's tagged deposits by index: a boolean mask per field counts the mask each time
            # (a tenth of the canyon's 29 M deposits are tagged: 0.26 -> 0.08 s of the sums' thread)
            tagged = np.flatnonzero(dep["diffuse_last"])
            if len(tagged) == len(dep["cell"]):
                self.diffuse_last({k: v for k, v in dep.items() if k != "diffuse_last"}, line_of_sight)
            elif len(tagged):
                self.diffuse_last({k: v[tagged] for k, v in dep.items() if k != "diffuse_last"}, line_of_sight)
        cell = dep["cell"].astype(np.int64)
        for tag in TAGS:
            if tag in dep:
                self._tag(tag, cell, dep[tag], dep["power"])
        p = dep["power"]
        _accumulate_deposits(cell, p, dep["dist"], *(dep[f"cos{k}"] for k in range(4)),
                             *(dep[f"sin{k}"] for k in range(4)), line_of_sight, m.tau0_s, m.power, m.power_sq,
                             m.los_power, m.count, m.min_delay_s, m.p_excess_delay_s, m.p_excess_delay2_s2,
                             m.p_cos, m.p_sin)
        if self.codebook is not None and not line_of_sight:  # line of sight: in moments()
            dkey = dep["dkey"]  # Dr.Jit's UInt64: the same bits as int64 (keys use 3 Q_BITS < 63 bits)
            dkey = dkey.view(np.int64) if dkey.dtype == np.uint64 else dkey.astype(np.int64)
            if self.separable is not None:  # per deposit, from its key's axis factors
                if self.beam_sums is None:
                    self.beam_sums = _SeparableBeamSums(len(self.m.power), self.separable, self.k)
                self.beam_sums.add(cell, dkey, p)
                return
            # Deposits of a cell that share a departure direction (one path: the same direction up
            # to float32 noise after the image-source correction) share a beam factor: summed per
            # group here, the factors evaluated once per direction for many sets in _add_beams
            # (a path's direction recurs in every batch: per set, a quarter of a GPU run's time).
            self.beam_groups.add(cell, dkey, p)
            if len(self.beam_groups) > MAX_PENDING_GROUPS:
                self._add_beams()

    def _tag(self, tag: str, cell: np.ndarray, value: np.ndarray, power: np.ndarray | None) -> None:
        """Records which tags (numpy) reached which cells; for lattice bins also the binned
        deposits' power sums (a deposit after a diffuse reflection has no bin: NOT_A_BIN)."""
        if tag == "lattice_bin":
            binned = value != NOT_A_BIN
            cell, value, power = cell[binned], value[binned], power[binned].astype(np.float64)
            n = len(self.m.power)
            if self.binned_power is None:
                self.binned_power, self.binned_power_sq = np.zeros(n), np.zeros(n)
            self.binned_power += np.bincount(cell, power, n)
            self.binned_power_sq += np.bincount(cell, power * power, n)
        self.tag_keys[tag].append(pd.unique((cell.astype(np.uint64) << np.uint64(32)) | value.astype(np.uint64)))

    def summed(self) -> CellMoments:
        """The running sums, every deposit's beams included (line of sight's come in moments())."""
        self._add_beams()
        return self.m

    def _add_beams(self) -> None:
        """Adds the pending groups' beam powers: the factor of each group's direction, quantised
        to DIRECTION_QUANTUM in the device frame (the key, made on the Dr.Jit side: the same for a
        ray whatever its batch), times the group's power; a Kronecker codebook's sums folded in."""
        if self.beam_sums is not None:
            self.beam_sums.fold_into(self.m.beam_power)
        if not len(self.beam_groups):
            return
        g_cell, g_dkey, pg = self.beam_groups.drain()
        # many cells share a direction (diffracted and diffuse paths: on DEPARTURE_QUANTUM's
        # grid): evaluate each distinct direction once
        inverse, keys = pd.factorize(g_dkey, sort=False)
        mask = (1 << Q_BITS) - 1
        u = (np.stack([(keys >> (k * Q_BITS)) & mask for k in (2, 1, 0)], -1) - Q_OFFSET) * DIRECTION_QUANTUM
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        gains = beam_factors(self.codebook, self.ant, u, self.k)  # groups: not a Kronecker codebook
        # beam power of a cell = sum over its groups of group power x the group direction's factors
        # (a compiled loop: no sort of the groups by cell, no sparse matrix, no gathered copy)
        _add_group_beams(self.m.beam_power, g_cell, inverse.astype(np.int64), pg, gains)

    def tags_into(self, cells: np.ndarray, tag: str = "stretch") -> np.ndarray:
        """The tags (``stretch``: stretches of edge, DiffractionSampler's; ``lattice_bin``: bins of
        the lattice) whose rays reached any of the flat ``cells`` (a lookup per key: sorting every
        key costs seconds on a city grid)."""
        keys = self.tag_keys[tag]
        if not keys or not len(cells):
            return np.zeros(0, np.int64)
        chosen = np.zeros(len(self.m.power), bool)
        chosen[cells] = True
        into = [k[chosen[(k >> np.uint64(32)).astype(np.int64)]] for k in keys]
        return np.unique((np.concatenate(into) & np.uint64(0xFFFFFFFF)).astype(np.int64))

    def replace(self, cells: np.ndarray, old: CellMoments, new: CellMoments) -> None:
        """In the flat ``cells``: take out what ``old`` added (the same deposits again) and add
        ``new`` instead (sums; float64 leaves about 1e-16 of the old part, clipped at zero). The
        earliest delay is the smaller of this and ``new``'s (both sample the same paths)."""
        m = self.summed()
        beams = ("beam_power",) if m.beam_power is not None else ()
        for f in ("power", "power_sq", "los_power", "p_excess_delay_s", "p_excess_delay2_s2", "p_cos", "p_sin",
                  "count") + beams:
            getattr(m, f)[cells] += getattr(new, f)[cells] - getattr(old, f)[cells]
        for f in ("power", "power_sq", "los_power") + beams:
            np.maximum(getattr(m, f), 0.0, out=getattr(m, f))
        m.min_delay_s[cells] = np.minimum(m.min_delay_s[cells], new.min_delay_s[cells])

    def moments(self) -> CellMoments:
        s = self.shape
        m = self.summed()
        if self.codebook is not None:
            # every line-of-sight deposit of a cell leaves towards the cell centre exactly (its image
            # source is the transmitter): one beam factor per cell, at the unquantised direction
            lit = np.flatnonzero(m.los_power > 0)
            u = self.centres[lit] - self.tx
            u = (u / np.linalg.norm(u, axis=1, keepdims=True)) @ self.rot  # device frame
            m.beam_power[lit] += m.los_power[lit, None] * beam_factors(self.codebook, self.ant, u, self.k,
                                                                       self.separable)
        return CellMoments(
            power=m.power.reshape(s), los_power=m.los_power.reshape(s), count=m.count.reshape(s),
            min_delay_s=m.min_delay_s.reshape(s), tau0_s=m.tau0_s.reshape(s),
            p_excess_delay_s=m.p_excess_delay_s.reshape(s), p_excess_delay2_s2=m.p_excess_delay2_s2.reshape(s),
            p_cos=m.p_cos.reshape(s + (4,)), p_sin=m.p_sin.reshape(s + (4,)),
            beam_power=None if m.beam_power is None else m.beam_power.reshape(s + (-1,)),
            power_sq=m.power_sq.reshape(s))


class _DeviceAccumulator(_Accumulator):
    """The per-cell sums kept on the Dr.Jit device, for the ``cuda`` variant: a GPU traces a
    batch in milliseconds, and copying its deposits to numpy and summing them there took most of
    a call (docs/ckm-one-pass.md, "Session 22"). Each deposit set is added with
    ``dr.scatter_reduce`` into float64 per-cell arrays (``min`` for the earliest arrival) and its
    beam powers with it: the factor of the deposit's quantised departure direction (the same key
    as :meth:`_Accumulator._add_beams`, so the same directions), evaluated per deposit in float32
    on the device. Only the finished sums come back (:meth:`summed`). The same moments as
    :class:`_Accumulator` up to float64 summation order and the beam factors' float32 rounding
    (about 1e-6 relative); on a GPU the atomics' order varies, so two runs differ in the last bits
    (the host accumulator, bitwise repeatable, stays the CPU's)."""

    def __init__(self, grid: Grid, tx_position_m, codebook, ant_positions_m, tx_rotation, wavelength_m):
        import drjit as dr
        import mitsuba as mi

        super().__init__(grid, tx_position_m, codebook, ant_positions_m, tx_rotation, wavelength_m)
        self.dr, self.mi = dr, mi
        n = len(self.m.power)
        self.d_sums = {f: dr.zeros(mi.Float64, n) for f in ("power", "power_sq", "los_power", "p_excess_delay_s",
                                                             "p_excess_delay2_s2")}
        self.d_angles = {f: dr.zeros(mi.Float64, 4 * n) for f in ("p_cos", "p_sin")}
        self.d_count = dr.zeros(mi.UInt32, n)
        # the earliest arrival: a min over float32 distances (m, tau = dist / c0) as their bits, an
        # integer min (non-negative floats order as their bit patterns; no float atomic min needed)
        self.d_min_dist_bits = dr.full(mi.UInt32, _INF_BITS, n)
        self.d_tau0 = mi.Float64(self.m.tau0_s)
        self.num_beams = 0 if codebook is None else codebook.shape[0]
        if self.num_beams:
            self.d_beams = dr.zeros(mi.Float64, n * self.num_beams)
            if self.separable is None:  # the looped form's phases and weights
                self.kpos = np.asarray(ant_positions_m, np.float64) * self.k  # rad/m x m: phase per unit direction
                w = np.asarray(codebook, np.complex64).ravel()  # [beam, antenna], row-major
                self.d_codebook = (mi.Float(w.real.copy()), mi.Float(w.imag.copy()))

    def __call__(self, dep: dict, line_of_sight: bool) -> None:
        dr, mi = self.dr, self.mi
        add = dr.ReduceOp.Add
        if self.diffuse_last is not None and "diffuse_last" in dep:
            sel = dr.compress(dep["diffuse_last"])
            if dr.width(sel):
                self.diffuse_last({k: dr.gather(type(v), v, sel) for k, v in dep.items() if k != "diffuse_last"},
                                  line_of_sight)
        cell = dep["cell"]
        for tag in TAGS:  # the second passes' bookkeeping stays on the host
            if tag in dep:
                self._tag(tag, cell.numpy().astype(np.int64), dep[tag].numpy(),
                          dep["power"].numpy() if tag == "lattice_bin" else None)
        p = mi.Float64(dep["power"])
        s = self.d_sums
        dr.scatter_reduce(add, s["power"], p, cell)
        dr.scatter_reduce(add, s["power_sq"], p * p, cell)
        if line_of_sight:
            dr.scatter_reduce(add, s["los_power"], p, cell)
        dr.scatter_reduce(add, self.d_count, mi.UInt32(1), cell)
        dr.scatter_reduce(dr.ReduceOp.Min, self.d_min_dist_bits, dr.reinterpret_array(mi.UInt32, dep["dist"]), cell)
        dtau = mi.Float64(dep["dist"]) / SPEED_OF_LIGHT_MPS - dr.gather(mi.Float64, self.d_tau0, cell)
        p_dtau = p * dtau
        dr.scatter_reduce(add, s["p_excess_delay_s"], p_dtau, cell)
        dr.scatter_reduce(add, s["p_excess_delay2_s2"], p_dtau * dtau, cell)
        for k in range(4):
            dr.scatter_reduce(add, self.d_angles["p_cos"], p * mi.Float64(dep[f"cos{k}"]), cell * 4 + k)
            dr.scatter_reduce(add, self.d_angles["p_sin"], p * mi.Float64(dep[f"sin{k}"]), cell * 4 + k)
        if self.num_beams and not line_of_sight:  # line of sight: in moments(), as on the host
            self._add_beam_powers(cell, p, dep["dkey"])
        dr.eval()  # the scatters, now: the deposits' memory is released with this set

    def _add_beam_powers(self, cell, p, dkey) -> None:
        """Adds ``p |w_b^T v(u)|^2`` per deposit to its cell's beam ``b``, every beam: ``u`` the
        direction of ``dkey`` (decoded as :meth:`_Accumulator._add_beams` does), ``v_n = exp(+j k
        p_n . u)`` in float32. A symbolic loop over the beams, the antennas unrolled in it: the
        fully unrolled form (beams x antennas complex products) took Python 13 ms a set to trace."""
        dr, mi = self.dr, self.mi
        mask = (1 << Q_BITS) - 1
        u = [mi.Float(mi.Int32(mi.UInt32((dkey >> (k * Q_BITS)) & mask)) - Q_OFFSET) * DIRECTION_QUANTUM
             for k in (2, 1, 0)]
        if self.separable is not None:  # at the key's direction cosines as they are (_SeparableBeamSums)
            self._add_separable_beam_powers(cell, p, u)
            return
        inv = dr.rsqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
        u = [c * inv for c in u]
        v = [dr.sincos(u[0] * float(q[0]) + u[1] * float(q[1]) + u[2] * float(q[2])) for q in self.kpos]
        num_beams, num_ant = self.num_beams, len(v)
        w_re, w_im = self.d_codebook
        first = cell * num_beams

        def body(b):
            y_re, y_im = mi.Float(0.0), mi.Float(0.0)
            for n, (v_im, v_re) in enumerate(v):
                a, c = (dr.gather(mi.Float, w, b * num_ant + n) for w in (w_re, w_im))
                y_re = dr.fma(v_re, a, dr.fma(v_im, -c, y_re))
                y_im = dr.fma(v_re, c, dr.fma(v_im, a, y_im))
            dr.scatter_reduce(dr.ReduceOp.Add, self.d_beams, p * mi.Float64(y_re * y_re + y_im * y_im), first + b)
            return (b + 1,)

        dr.while_loop(state=(dr.zeros(mi.UInt32, dr.width(p)),), cond=lambda b: b < num_beams, body=body)

    def _add_separable_beam_powers(self, cell, p, u) -> None:
        """:meth:`_add_beam_powers` for a Kronecker codebook (:func:`separable_codebook`): per
        deposit the distinct factors' powers along each axis, ``|a_k^T v_x|^2`` and ``|c_k^T
        v_y|^2`` (``n1 + n2`` phases), and each beam their product times ``s_b^2``. An 8 x 8 DFT
        grid: 16 phases and 16 eight-term sums instead of 64 phases and 64 x 64 products per
        deposit (on an H200 the looped form was half of the one-pass's kernel time)."""
        dr, mi = self.dr, self.mi
        sep = self.separable
        powers = []
        for d, x, f in zip(sep["axes"], sep["coords"], (sep["a"], sep["c"])):
            v = [dr.sincos(u[d] * float(self.k * xi)) for xi in x]
            axis = []
            for k in range(f.shape[1]):
                y_re, y_im = mi.Float(0.0), mi.Float(0.0)
                for (v_im, v_re), w in zip(v, f[:, k]):
                    a, c = float(w.real), float(w.imag)
                    y_re = dr.fma(v_re, a, dr.fma(v_im, -c, y_re))
                    y_im = dr.fma(v_re, c, dr.fma(v_im, a, y_im))
                axis.append(y_re * y_re + y_im * y_im)
            powers.append(axis)
        first = cell * self.num_beams
        for b in range(self.num_beams):
            g = powers[0][sep["a_of_beam"][b]] * powers[1][sep["c_of_beam"][b]] * float(sep["scale"][b])
            dr.scatter_reduce(dr.ReduceOp.Add, self.d_beams, p * mi.Float64(g), first + b)

    def summed(self) -> CellMoments:
        """The device sums added into the host's (then zeroed on the device), as
        :meth:`_Accumulator.summed`."""
        dr, mi = self.dr, self.mi
        m = self.m
        for f, a in self.d_sums.items():
            getattr(m, f)[:] += a.numpy()
            self.d_sums[f] = dr.zeros(mi.Float64, len(m.power))
        for f, a in self.d_angles.items():
            getattr(m, f)[:] += a.numpy().reshape(-1, 4)
            self.d_angles[f] = dr.zeros(mi.Float64, 4 * len(m.power))
        m.count += self.d_count.numpy().astype(np.int64)
        self.d_count = dr.zeros(mi.UInt32, len(m.power))
        dist = self.d_min_dist_bits.numpy().astype(np.uint32).view(np.float32)
        m.min_delay_s = np.minimum(m.min_delay_s, dist.astype(np.float64) / SPEED_OF_LIGHT_MPS)
        self.d_min_dist_bits = dr.full(mi.UInt32, _INF_BITS, len(m.power))
        if self.num_beams:
            m.beam_power += self.d_beams.numpy().reshape(-1, self.num_beams)
            self.d_beams = dr.zeros(mi.Float64, len(m.power) * self.num_beams)
        return super().summed()


class _InOrderWorker:
    """Runs the numpy accumulation on one worker thread, in submission order (so the sums are the
    same as in line), while the caller traces the next segment: numpy and the Dr.Jit kernels
    overlap on two cores. At most ``max_pending`` deposit sets wait, which bounds memory."""

    def __init__(self, fn, max_pending: int = 3):
        import threading
        from concurrent.futures import ThreadPoolExecutor

        self.fn, self.pool = fn, ThreadPoolExecutor(max_workers=1)
        self.slots, self.futures = threading.Semaphore(max_pending), []

    def __call__(self, *args) -> None:
        self.slots.acquire()
        fut = self.pool.submit(self.fn, *args)
        fut.add_done_callback(lambda _: self.slots.release())
        self.futures.append(fut)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.pool.shutdown(wait=True)
        for fut in self.futures:
            fut.result()  # re-raise the first accumulation error, if any


def _sink(acc: _Accumulator):
    """The tracer's sink into ``acc``: the host sums on a worker thread beside the tracer
    (:class:`_InOrderWorker`); the device sums in line (Dr.Jit queues their kernels itself)."""
    import contextlib

    return contextlib.nullcontext(acc) if isinstance(acc, _DeviceAccumulator) else _InOrderWorker(acc)


@_compiled
def _accumulate_deposits(cell, power, dist, cos0, cos1, cos2, cos3, sin0, sin1, sin2, sin3, line_of_sight,
                         tau0_s, m_power, m_power_sq, m_los_power, m_count, m_min_delay_s, m_p_excess_delay_s,
                         m_p_excess_delay2_s2, m_p_cos, m_p_sin):
    """Every per-cell sum of one deposit set in one loop, in deposit order, without the GIL: it runs
    beside the tracer. The sums of one ``np.bincount`` per moment to float64 rounding (they add
    into the running totals directly, not a set's sum first); ``count`` and ``min_delay_s`` equal."""
    for i in range(len(cell)):
        c = cell[i]
        p = np.float64(power[i])
        m_power[c] += p
        m_power_sq[c] += p * p
        if line_of_sight:
            m_los_power[c] += p
        m_count[c] += 1
        tau = np.float64(dist[i]) / SPEED_OF_LIGHT_MPS
        if tau < m_min_delay_s[c]:
            m_min_delay_s[c] = tau
        dtau = tau - tau0_s[c]
        p_dtau = p * dtau
        m_p_excess_delay_s[c] += p_dtau
        m_p_excess_delay2_s2[c] += p_dtau * dtau
        m_p_cos[c, 0] += p * cos0[i]
        m_p_cos[c, 1] += p * cos1[i]
        m_p_cos[c, 2] += p * cos2[i]
        m_p_cos[c, 3] += p * cos3[i]
        m_p_sin[c, 0] += p * sin0[i]
        m_p_sin[c, 1] += p * sin1[i]
        m_p_sin[c, 2] += p * sin2[i]
        m_p_sin[c, 3] += p * sin3[i]


class _GroupSums:
    """Sums of deposit powers per distinct (cell, direction key), in deposit order, for a codebook
    that is not a Kronecker product (a Kronecker one's: :class:`_SeparableBeamSums`): an
    open-addressing hash table (linear probing, at most half full) that a compiled loop fills
    without the GIL, beside the tracer. Diffracted and diffuse paths leave on
    DEPARTURE_QUANTUM's grid, so a cell gets many directions (the street canyon, every mechanism,
    1e7 rays: 29 M deposits, 4.7 M groups); drained every MAX_PENDING_GROUPS the table stays in
    cache. It replaces a ``pandas.factorize`` per deposit set and the sets' groups merged again,
    3.3 s of that run's 5.4 s of host sums (docs/ckm-one-pass.md, "Session 32")."""

    def __init__(self, bits: int = 16):
        self._alloc(bits)

    def _alloc(self, bits: int) -> None:
        self.cell = np.full(1 << bits, -1, np.int64)  # -1: an empty slot
        self.dkey = np.zeros(1 << bits, np.int64)
        self.sum = np.zeros(1 << bits, np.float64)
        self.used = np.zeros(1, np.int64)

    def __len__(self) -> int:
        return int(self.used[0])

    def add(self, cell: np.ndarray, dkey: np.ndarray, power: np.ndarray) -> None:
        i, n = 0, len(cell)
        while True:
            i = _add_to_groups(self.cell, self.dkey, self.sum, self.used, cell, dkey, power, i)
            if i == n:
                return
            old = self.cell, self.dkey, self.sum  # half full: twice the slots, the groups again
            self._alloc(int(len(old[0])).bit_length())
            keep = old[0] >= 0
            _add_to_groups(self.cell, self.dkey, self.sum, self.used, old[0][keep], old[1][keep], old[2][keep], 0)

    def drain(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cells, keys, sums) in the table's order (deterministic: the keys decide it); the table
        emptied."""
        out = np.empty(len(self), np.int64), np.empty(len(self), np.int64), np.empty(len(self), np.float64)
        _drain_groups(self.cell, self.dkey, self.sum, *out)
        self.used[0] = 0
        return out


class _SeparableBeamSums:
    """Beam powers of a Kronecker codebook (:func:`separable_codebook`), summed without grouping
    every deposit first. A beam's factor is the product of its two axes' factors, and an axis
    factor ``|a_k^T v_x(u)|^2`` depends on one direction cosine alone, which the direction key
    holds on DIRECTION_QUANTUM's grid: each axis gets a table over that grid (2 x 2^15 x 8
    values for an 8 x 8 DFT grid), and a cell sums ``p |a_i^T v_x|^2 |c_j^T v_y|^2`` per factor
    pair (i, j), scaled into its beams at the end (:meth:`fold_into`). Deposits of the same (cell,
    direction) in a row combine first in a small direct-mapped cache (BEAM_CACHE_BITS slots): the
    street canyon's 27.6 M deposits (every mechanism, 1e7 rays) make 4.5 M groups, mostly within
    a batch. The axis factors are evaluated at the key's direction cosines as they are (no
    renormalisation of the quantised vector: the quantum bounds either's error), in deposit
    order: bitwise repeatable. It replaced a hash table of every group, the factors of each
    distinct direction and a loop over the groups (street canyon: 2.4 s of the sums' 4.0 s;
    docs/ckm-one-pass.md, "Session 33")."""

    def __init__(self, num_cells: int, separable: dict, wavenumber_rad_per_m: float):
        a, c = separable["a"], separable["c"]
        self.pair_power = np.zeros((num_cells, a.shape[1] * c.shape[1]))
        u = (np.arange(1 << Q_BITS) - Q_OFFSET) * DIRECTION_QUANTUM  # every value a key's field holds
        self.axis_power = []
        for x, f in zip(separable["coords"], (a, c)):
            v = np.exp(1j * wavenumber_rad_per_m * u[:, None] * np.asarray(x)[None, :])
            self.axis_power.append(np.ascontiguousarray(np.abs(v @ f) ** 2))
        # a key's fields, from the top: the device-frame components 0, 1, 2 (_Accumulator._add_beams)
        self.shifts = [(2 - d) * Q_BITS for d in separable["axes"]]
        self.pair_of_beam = separable["a_of_beam"] * c.shape[1] + separable["c_of_beam"]
        self.scale = separable["scale"]
        self.t_cell = np.full(1 << BEAM_CACHE_BITS, -1, np.int64)  # -1: an empty slot
        self.t_dkey = np.zeros(1 << BEAM_CACHE_BITS, np.int64)
        self.t_sum = np.zeros(1 << BEAM_CACHE_BITS, np.float64)

    def add(self, cell: np.ndarray, dkey: np.ndarray, power: np.ndarray) -> None:
        _add_to_beam_cache(self.t_cell, self.t_dkey, self.t_sum, self.pair_power, *self.axis_power, *self.shifts,
                           cell, dkey, power)

    def fold_into(self, beam_power: np.ndarray) -> None:
        """Adds the sums so far to ``beam_power`` [cells, beams], each beam its factor pair's sum
        times its scale; the sums emptied."""
        _flush_beam_cache(self.t_cell, self.t_dkey, self.t_sum, self.pair_power, *self.axis_power, *self.shifts)
        _fold_pairs(beam_power, self.pair_power, self.pair_of_beam, self.scale)


@_compiled
def _slot_of(c, k, mask):
    """The hash slot of (cell ``c``, key ``k``) in a table of ``mask + 1`` slots: splitmix64's
    finaliser, so that every key bit reaches the low bits the mask keeps."""
    h = np.uint64(c) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(k)
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return np.int64((h ^ (h >> np.uint64(31))) & mask)


@_compiled
def _add_pair_power(pair_power, power0, power1, shift0, shift1, c, k, s):
    """``pair_power[c, i * n_c + j] += s * power0[u0, i] * power1[u1, j]``, ``u0`` and ``u1`` the
    fields of key ``k`` at ``shift0`` and ``shift1``, ``n_c`` the second axis's factors."""
    mask = np.int64((1 << Q_BITS) - 1)
    r0, r1 = power0[(k >> shift0) & mask], power1[(k >> shift1) & mask]
    row, n_c = pair_power[c], len(r1)
    for i in range(len(r0)):
        w = s * r0[i]
        for j in range(n_c):
            row[i * n_c + j] += w * r1[j]


@_compiled
def _add_to_beam_cache(t_cell, t_dkey, t_sum, pair_power, power0, power1, shift0, shift1, cell, dkey, power):
    """Each deposit into its slot of the direct-mapped cache: added to the slot's sum where the
    slot holds its (cell, key), else the slot's sum goes to ``pair_power`` and the deposit takes it."""
    mask = np.uint64(len(t_cell) - 1)
    for i in range(len(cell)):
        c, k = np.int64(cell[i]), np.int64(dkey[i])
        slot = _slot_of(c, k, mask)
        if t_cell[slot] == c and t_dkey[slot] == k:
            t_sum[slot] += np.float64(power[i])
            continue
        if t_cell[slot] >= 0:
            _add_pair_power(pair_power, power0, power1, shift0, shift1, t_cell[slot], t_dkey[slot], t_sum[slot])
        t_cell[slot], t_dkey[slot], t_sum[slot] = c, k, np.float64(power[i])


@_compiled
def _flush_beam_cache(t_cell, t_dkey, t_sum, pair_power, power0, power1, shift0, shift1):
    """Every occupied slot's sum to ``pair_power``, in slot order; the cache emptied."""
    for slot in range(len(t_cell)):
        if t_cell[slot] >= 0:
            _add_pair_power(pair_power, power0, power1, shift0, shift1, t_cell[slot], t_dkey[slot], t_sum[slot])
            t_cell[slot], t_sum[slot] = -1, 0.0


@_compiled
def _fold_pairs(beam_power, pair_power, pair_of_beam, scale):
    """``beam_power[c, b] += pair_power[c, pair_of_beam[b]] * scale[b]``; ``pair_power`` zeroed."""
    for c in range(len(beam_power)):
        row, pairs = beam_power[c], pair_power[c]
        for b in range(len(row)):
            row[b] += pairs[pair_of_beam[b]] * scale[b]
        pairs[:] = 0.0


@_compiled
def _add_group_beams(beam_power, cell, direction, power, factors):
    """``beam_power[cell[g]] += power[g] * factors[direction[g]]`` for every group ``g``."""
    for g in range(len(cell)):
        row, f, p = beam_power[cell[g]], factors[direction[g]], power[g]
        for b in range(len(row)):
            row[b] += p * f[b]


@_compiled
def _drain_groups(t_cell, t_dkey, t_sum, cell, dkey, power):
    """The occupied slots' groups into ``cell``, ``dkey``, ``power``, in slot order; each slot emptied."""
    j = 0
    for slot in range(len(t_cell)):
        if t_cell[slot] >= 0:
            cell[j], dkey[j], power[j] = t_cell[slot], t_dkey[slot], t_sum[slot]
            t_cell[slot], t_sum[slot] = -1, 0.0
            j += 1


@_compiled
def _add_to_groups(t_cell, t_dkey, t_sum, used, cell, dkey, power, start):
    """Adds deposits ``start..`` into the table; returns where it stopped: ``len(cell)``, or the
    first deposit that would have filled the table past half (the caller grows it)."""
    mask = np.uint64(len(t_cell) - 1)
    for i in range(start, len(cell)):
        c, k = np.int64(cell[i]), np.int64(dkey[i])
        slot = _slot_of(c, k, mask)
        while t_cell[slot] >= 0 and (t_cell[slot] != c or t_dkey[slot] != k):
            slot = np.int64((np.uint64(slot) + np.uint64(1)) & mask)
        if t_cell[slot] < 0:
            if 2 * (used[0] + 1) > len(t_cell):
                return i
            t_cell[slot], t_dkey[slot] = c, k
            used[0] += 1
        t_sum[slot] += np.float64(power[i])
    return len(cell)


def beam_factors(codebook: np.ndarray, ant_positions_m: np.ndarray, directions: np.ndarray,
                 wavenumber_rad_per_m: float, separable: dict | None = None) -> np.ndarray:
    """``|w_b^T v(u)|^2`` ``[num_dir, num_beams]`` for unit vectors ``u`` ``[num_dir, 3]`` in the
    array's own frame; ``v_n = exp(+j k p_n . u)`` (the project's precoder convention). With
    ``separable`` (:func:`separable_codebook` of this codebook and array) from its axes' factors:
    an 8 x 8 DFT grid costs 16 phases and 2 x 8 x 8 products per direction instead of 64 phases
    and 64 x 64, in a compiled loop without the GIL, in complex128 (it runs beside the tracer,
    where numpy's form ran 3-10x slower than alone: docs/ckm-one-pass.md, "Session 32").
    Otherwise complex64 arithmetic (relative error about 1e-6, three times faster than
    complex128); a float64 result either way."""
    if separable is not None:
        sep = separable
        out = np.empty((len(directions), len(sep["scale"])), np.float64)
        _separable_beam_factors(np.ascontiguousarray(directions, np.float64), *sep["axes"], *sep["coords"],
                                sep["a"], sep["c"], sep["a_of_beam"], sep["c_of_beam"],
                                sep["scale"], float(wavenumber_rad_per_m), out)
        return out
    pos = np.asarray(ant_positions_m, np.float64).T * wavenumber_rad_per_m
    w = np.asarray(codebook, np.complex64).T
    out = np.empty((len(directions), w.shape[1]), np.float64)
    for lo in range(0, len(directions), BEAM_CHUNK):  # temporaries that stay in cache, not page-faulted
        phase = (directions[lo:lo + BEAM_CHUNK] @ pos).astype(np.float32)
        v = np.empty(phase.shape, np.complex64)
        v.real, v.imag = np.cos(phase), np.sin(phase)
        y = v @ w
        out[lo:lo + len(y)] = y.real.astype(np.float64) ** 2 + y.imag.astype(np.float64) ** 2
    return out


@_compiled
def _separable_beam_factors(u, axis0, axis1, x0, x1, a, c, a_of_beam, c_of_beam, scale, wavenumber, out):
    """:func:`beam_factors` of a Kronecker codebook: per direction ``u[i]`` the powers of the
    distinct axis factors, ``|a_k^T v_0(u)|^2`` and ``|c_k^T v_1(u)|^2``, and each beam's their
    product times ``scale``, into ``out[i]``."""
    v0, v1 = np.empty(len(x0), np.complex128), np.empty(len(x1), np.complex128)
    p0, p1 = np.empty(a.shape[1]), np.empty(c.shape[1])
    for i in range(len(u)):
        for v, x, f, p, d in ((v0, x0, a, p0, axis0), (v1, x1, c, p1, axis1)):
            for e in range(len(x)):
                phase = wavenumber * u[i, d] * x[e]
                v[e] = complex(np.cos(phase), np.sin(phase))
            for k in range(f.shape[1]):
                y = 0j
                for e in range(len(x)):
                    y += f[e, k] * v[e]
                p[k] = y.real * y.real + y.imag * y.imag
        for b in range(len(scale)):
            out[i, b] = p0[a_of_beam[b]] * p1[c_of_beam[b]] * scale[b]


SEPARABLE_RANK_TOLERANCE = 1e-6  # a beam is a Kronecker product where its second singular value is below this share


def separable_codebook(codebook: np.ndarray, ant_positions_m: np.ndarray) -> dict | None:
    """A codebook whose every beam is the Kronecker product of weights along the two axes of a
    full planar grid of elements (``w_b[i, j] = a_b[i] c_b[j]``, element ``(i, j)`` at ``x_i``
    along one axis and ``y_j`` along the other, the third coordinate the same for all), as its
    factors: ``|w_b^T v(u)|^2 = s_b^2 |a_b^T v_x(u)|^2 |c_b^T v_y(u)|^2`` (unit ``a_b``, ``c_b``;
    the third coordinate's phase is common to all elements). The distinct ``a`` and ``c`` (up to
    a phase) are kept once: a DFT grid of 8 x 8 beams has 8 of each. Keys: ``axes`` (the two
    varying coordinates), ``coords`` (their element positions, m), ``a`` ``[n1, K1]`` and ``c``
    ``[n2, K2]`` (complex), ``a_of_beam`` / ``c_of_beam`` (each beam's factors), ``scale``
    (``s_b^2``). None for any other codebook or array."""
    w = np.asarray(codebook, np.complex128)
    pos = np.asarray(ant_positions_m, np.float64)
    if w.ndim != 2 or pos.shape != (w.shape[1], 3) or w.shape[1] < 4:
        return None
    span = np.ptp(pos, axis=0)
    tol = 1e-9 * max(float(span.max()), 1e-12)
    axes = [d for d in range(3) if span[d] > tol]
    if len(axes) != 2:
        return None
    coords, index = [], []
    for d in axes:
        _, first, inv = np.unique(np.round(pos[:, d] / tol), return_index=True, return_inverse=True)
        coords.append(pos[first, d])
        index.append(inv.ravel())
    n1, n2 = len(coords[0]), len(coords[1])
    if n1 * n2 != w.shape[1] or len(np.unique(index[0] * n2 + index[1])) != w.shape[1]:
        return None  # not a full grid
    grid = np.zeros((w.shape[0], n1, n2), np.complex128)
    grid[:, index[0], index[1]] = w
    u, sv, vh = np.linalg.svd(grid)
    if np.any(sv[:, 1] > SEPARABLE_RANK_TOLERANCE * np.maximum(sv[:, 0], 1e-300)):
        return None
    out = {"axes": axes, "coords": coords, "scale": sv[:, 0] ** 2}
    for name, f in (("a", u[:, :, 0]), ("c", vh[:, 0, :])):
        # a common phase does not change |.|^2: each factor's first element of at least half the
        # largest magnitude made real (not the largest: a DFT beam's are equal up to rounding)
        mag = np.abs(f)
        ref = f[np.arange(len(f)), np.argmax(mag >= 0.5 * mag.max(axis=1, keepdims=True), axis=1)]
        f = f * (np.abs(ref) / ref)[:, None]
        key = np.round(np.concatenate([f.real, f.imag], axis=1) * 1e7).astype(np.int64)
        _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
        out[name], out[name + "_of_beam"] = f[first].T, inv.ravel()
    return out


def one_pass_moments(radio, tx_position_m, tx_orientation_rad, x_m: np.ndarray, y_m: np.ndarray,
                     heights_m: np.ndarray, num_rays: int, max_depth: int,
                     codebook: np.ndarray | None = None, tx_ant_positions_m: np.ndarray | None = None,
                     batch_rays: int | None = None, min_hits_for_spread: int = DEFAULT_MIN_HITS_FOR_SPREAD,
                     *, min_hits_for_power: int = DEFAULT_MIN_HITS_FOR_POWER, min_effective_hits_for_power: float = 1.0,
                     min_effective_hits_for_spread: float = DEFAULT_MIN_EFFECTIVE_HITS_FOR_SPREAD,
                     cell_size_m: float | None = None, indoor: np.ndarray | None = None,
                     min_outdoor_fraction: float = DEFAULT_MIN_OUTDOOR_FRACTION,
                     rx_polarization: str | None = None, los: bool = True, specular_reflection: bool = True,
                     refraction: bool = False, diffraction: bool = False, edge_diffraction: bool = False,
                     diffuse_reflection: bool = False, diffraction_samples: int | None = None,
                     max_footprint_cells: float = DEFAULT_MAX_FOOTPRINT_CELLS,
                     solids: Solids | None = None, diffraction_with_reflections: bool = True,
                     diffraction_resample_factor: int = 1, diffuse_last_only: bool = False,
                     diffuse_connections: float = DEFAULT_DIFFUSE_CONNECTIONS,
                     accumulate_on_device: bool | None = None,
                     cell_outdoor_fraction: np.ndarray | None = None, lattice_resample_factor: int = 1,
                     lattice_bin_rays: int = DEFAULT_LATTICE_BIN_RAYS, diffuse_gather: bool | str = False,
                     gather_below_effective_hits: float = DEFAULT_GATHER_BELOW_EFFECTIVE_HITS,
                     gather_auto_min_share: float = DEFAULT_GATHER_AUTO_MIN_SHARE,
                     gather_photon_share: float = DEFAULT_PHOTON_RAY_SHARE,
                     gather_directions_per_point: int = DEFAULT_GATHER_DIRECTIONS_PER_POINT,
                     gather_radius_m: float | None = None,
                     gather_pilot_directions: int = DEFAULT_GATHER_PILOT_DIRECTIONS,
                     gather_guided_share: float = DEFAULT_GATHER_GUIDED_SHARE) -> OnePassMoments:
    """Per-cell power moments of one transmitter over a grid, from one shoot-and-bounce pass.

    :param radio: :class:`simart_pipeline.radio.tracer.RadioScene` (mesh, materials of its
        weather, frequency, ``tx_array`` whose element pattern the rays start with)
    :param tx_position_m: ``[3]`` m, world; ``tx_orientation_rad``: ``[3]`` Sionna (yaw, pitch, roll)
    :param x_m: ``[nx]`` cell-centre x, m, increasing and equally spaced (the cell size);
        ``y_m``: ``[ny]`` likewise; ``heights_m``: ``[num_heights]`` grid plane heights, m;
        ``cell_size_m``: needed only where both axes have a single cell (square cells)
    :param num_rays: rays on the Fibonacci lattice (each ``4 pi / num_rays`` sr)
    :param max_depth: most interactions (reflections, refractions) per ray (0: line of sight only)
    :param codebook: ``[num_beams, num_tx_ant]`` complex unit-norm precoders, or None (no beams);
        ``tx_ant_positions_m``: ``[num_tx_ant, 3]`` m in the device frame (default: the scene's
        ``tx_array`` positions)
    :param batch_rays: rays traced at once (memory bound; the result does not depend on it);
        None: :func:`default_batch_rays`
    :param min_hits_for_spread: hits a cell needs for spreads and mean angles
        (:meth:`OnePassMoments.layers`); ``min_hits_for_power``: for path gain, ToA, LoS and beams;
        ``min_effective_hits_for_power``: the effective count (Kish, ``(sum p)^2 / sum p^2``)
        they also need (1: no such condition); ``min_effective_hits_for_spread``: the effective
        count the spreads and mean angles need (:func:`~simart_pipeline.ckm.moments.too_few_hits`)
    :param indoor: optional bool mask, broadcastable to ``[num_heights, ny, nx]``: cells to mask
    :param min_outdoor_fraction: cells with less of their area outside buildings
        (:func:`outdoor_fraction`) are masked; the others have their sums divided by that share
        (power normalised by the outdoor area the rays can reach); ``solids``: the radio scene's
        (:func:`simart_pipeline.ckm.outdoor.radio_solids`), if the caller has them already;
        ``cell_outdoor_fraction``: that share itself, ``[num_heights, ny, nx]``, if the caller has
        it already (it depends on the scene and the grid alone: one per tile, not per station)
    :param rx_polarization: None: isotropic receiver collecting the whole field ``|E|^2``
        (RadioMapSolver's); ``"V"`` / ``"H"``: an isotropic element of that polarisation
    :param los, specular_reflection, refraction, diffuse_reflection: interaction types as in
        Sionna RT. With ``refraction`` (straight through, ITU slab transmission) or
        ``diffuse_reflection`` (the material's scattering coefficient, XPD and pattern) a hit is
        split into its transmitted ray (``T E`` exactly) and its reflected one, drawn between
        specular and diffuse in proportion to their energies and weighted by ``1 /
        sqrt(probability)``; a side of a split with less than ``SPLIT_MIN_SHARE`` of the hit's
        energy goes on by Russian roulette (unbiased; random numbers hashed from the lattice index
        and the depth, so still deterministic and batch-independent): :mod:`.shoot_bounce`.
    :param diffuse_last_only: True: PathSolver's model of diffuse reflection, to compare the two
        like for like: a diffusely reflected ray ends at its next hit (a diffuse reflection is the
        last interaction of a path) and diffracted rays do not scatter (PathSolver leaves out paths
        with both); False: any interaction after it, as RadioMapSolver
    :param max_footprint_cells: a crossing (other than line of sight) whose ray tube's footprint on
        the plane is larger than a cell spreads its deposit over the cells that footprint covers
        (a tent kernel normalised to the crossing's power, at most this many cells on a side, see
        the module docstring); 1: every crossing into the one cell it crosses
    :param diffraction, edge_diffraction: first-order wedge (and free-edge) diffraction,
        :mod:`simart_pipeline.ckm.diffraction`, with ``diffraction_samples`` points on the lit
        wedges (default ``DIRECT_SAMPLES_PER_RAY * num_rays``; an eighth of that again on the
        wedges lit through one reflection)
    :param diffraction_with_reflections: True: diffracted paths with a specular reflection before
        the wedge (depth >= 2) and specular reflections after it, up to ``max_depth``; False:
        RadioMapSolver's diffraction alone (transmitter, wedge, grid plane: nothing before or
        after it), to compare the two like for like
    :param diffraction_resample_factor: a second pass on undersampled cells (1: none): where a
        cell outside the mask has at least one ray hit but fewer than ``min_hits_for_power`` (or an
        effective count below ``min_effective_hits_for_power``), the stretches of edge whose
        diffracted rays reached it are sampled again with this many times their samples, and in
        those cells their first-pass part is replaced by the finer one
        (:func:`_resample_undersampled`); ``second_pass`` of the result says what it did
    :param lattice_resample_factor: the lattice rays' second pass on undersampled cells (1: none):
        where a cell outside the mask has at least one ray hit but an effective count (Kish) below
        ``max(min_hits_for_power, min_effective_hits_for_power)`` and the lattice rays that never
        scattered diffusely make its noise (:data:`LATTICE_NOISE_SHARE`), the bins of launch directions
        (:class:`simart_pipeline.ckm.shoot_bounce.LatticeBins`, ``lattice_bin_rays`` lattice points
        each) whose rays reached it are traced again and with this many times their rays, and in
        those cells their first-pass part is replaced by the finer one (:func:`_resample_lattice`);
        ``lattice_second_pass`` of the result says what it did
    :param diffuse_connections: with ``diffuse_reflection``, the cells each diffuse hit is also
        joined to by a shadow ray, on average (next-event estimation weighted with the scattered
        ray by the balance heuristic, :meth:`simart_pipeline.ckm.shoot_bounce.Tracer._connect`);
        0: the scattered ray alone
    :param diffuse_gather: with ``diffuse_reflection``, estimate the last diffuse reflection again
        from the cells whose effective count (Kish) stays below ``gather_below_effective_hits``
        (or that no ray reached), by final gathering from photons (:mod:`simart_pipeline.ckm.gather`):
        ``gather_directions_per_point`` gather rays from each of a cell's outdoor sample points, a
        photon pass of ``gather_photon_share x num_rays`` rays, a kernel of at most
        ``gather_radius_m`` (None: one cell size), ``gather_guided_share`` of the gather rays
        aimed at the faces the transmitter lights that ``gather_pilot_directions`` pilot rays a
        point found (:func:`simart_pipeline.ckm.gather.guide_faces`; 0 pilots: uniform rays); in those cells it is weighed with the main
        pass's deposits whose last interaction was a lattice ray's diffuse reflection by their
        relative variances. ``"auto"``: so where the cells that would be few-hit cells at
        ``GATHER_AUTO_REFERENCE_RAYS`` (1e7) rays are at least ``gather_auto_min_share`` of the
        cells outside the mask (where few are, more rays buy more than the gather at its cost;
        docs/ckm-one-pass.md "Session 36"), else not. ``diffuse_gather`` of the result says what it did
    :param accumulate_on_device: sum the deposits on the Dr.Jit device (:class:`_DeviceAccumulator`)
        instead of on the host with numpy (:class:`_Accumulator`); None: on the device where the
        variant is ``cuda`` (a GPU), on the host otherwise (bitwise repeatable; on two CPU cores
        the host sums run beside the tracer's kernels)
    :return: :class:`OnePassMoments` of grid shape ``[num_heights, ny, nx]``
    """
    from simart_pipeline import engine

    if rx_polarization not in (None, "V", "H"):
        raise ValueError(f"rx_polarization must be None, 'V' or 'H', got {rx_polarization!r}")
    variant = engine.init()
    batch_rays = default_batch_rays(variant) if batch_rays is None else batch_rays
    if not 1 <= int(num_rays) < 2**32 or int(batch_rays) < 1:
        raise ValueError(f"num_rays must lie in 1 .. 2**32 - 1 and batch_rays be >= 1, got {num_rays} "
                         f"and {batch_rays}")
    if int(max_depth) < 0:
        raise ValueError(f"max_depth must be >= 0, got {max_depth}")
    on_device = variant.startswith("cuda") if accumulate_on_device is None else bool(accumulate_on_device)
    grid = grid_from_centres(x_m, y_m, heights_m, cell_size_m)
    rot = rotation_local_to_world(np.asarray(tx_orientation_rad, np.float64))
    if codebook is not None:
        codebook = np.asarray(codebook, np.complex128)
        ant = radio.array_positions_m("tx") if tx_ant_positions_m is None else np.asarray(tx_ant_positions_m, np.float64)
        if codebook.ndim != 2 or ant.shape != (codebook.shape[1], 3):
            raise ValueError(f"codebook [num_beams, num_tx_ant] {codebook.shape} and antenna positions "
                             f"[num_tx_ant, 3] {ant.shape} do not match")
        norms = np.linalg.norm(codebook, axis=1)
        if not np.allclose(norms, 1.0, rtol=0, atol=1e-6):
            raise ValueError(f"codebook: precoders must have unit norm (the transmit power is the "
                             f"station's); norms range {norms.min():.6g} .. {norms.max():.6g}")
    else:
        ant = None
    depth = int(max_depth) if (specular_reflection or refraction or diffuse_reflection) else 0
    if cell_outdoor_fraction is None:
        frac = outdoor_fraction(radio, x_m, y_m, grid.heights, cell_size_m=cell_size_m, solids=solids)
    else:
        frac = np.asarray(cell_outdoor_fraction, np.float64)
        if frac.shape != grid.shape:
            raise ValueError(f"cell_outdoor_fraction: shape {frac.shape} is not the grid's [num_heights, ny, nx] "
                             f"= {list(grid.shape)}")
    tracer = Tracer(radio, tx_position_m, rot, grid, int(num_rays), depth, los, rx_polarization,
                     with_beams=codebook is not None, specular=specular_reflection, refraction=refraction,
                     diffuse=diffuse_reflection, max_footprint_cells=max_footprint_cells,
                     outdoor_fraction=frac, diffuse_last_only=diffuse_last_only,
                     diffuse_connections=float(diffuse_connections))
    tracer.device_deposits = on_device
    accumulator = _DeviceAccumulator if on_device else _Accumulator
    acc = accumulator(grid, tx_position_m, codebook, ant, rot, radio.wavelength_m)
    with_diffraction = diffraction and int(max_depth) > 0
    reflections_before = 1 if specular_reflection and depth >= 2 and diffraction_with_reflections else 0
    masked = frac < min_outdoor_fraction
    if indoor is not None:
        try:
            masked |= np.broadcast_to(np.asarray(indoor, bool), grid.shape)
        except ValueError:
            raise ValueError(f"indoor: shape {np.shape(indoor)} does not broadcast to the grid "
                             f"[num_heights, ny, nx] = {list(grid.shape)}") from None
    resample = int(diffraction_resample_factor)
    if resample < 1:
        raise ValueError(f"diffraction_resample_factor must be >= 1, got {diffraction_resample_factor}")
    lattice_factor = int(lattice_resample_factor)
    if lattice_factor < 1:
        raise ValueError(f"lattice_resample_factor must be >= 1, got {lattice_resample_factor}")
    if lattice_factor > 1:  # the lattice rays' deposits tagged with their bin, for the second pass
        tracer.lattice_bins = LatticeBins(int(num_rays), int(lattice_bin_rays))
    if isinstance(diffuse_gather, str) and diffuse_gather != "auto":
        raise ValueError(f"diffuse_gather must be True, False or 'auto', got {diffuse_gather!r}")
    gathering = bool(diffuse_gather) and diffuse_reflection and depth > 0
    # the lattice rays' first hits name the lit wedges and the faces the gather aims at
    # (gather.guide_faces): collected as they are traced
    if with_diffraction or gathering:
        tracer.collect_lit(pairs=bool(reflections_before) and with_diffraction)
    if gathering:  # the part the gather replaces, summed apart as well
        tracer.tag_diffuse_last = True
        acc.diffuse_last = accumulator(grid, tx_position_m, codebook, ant, rot, radio.wavelength_m)
    wedges = None
    with _sink(acc) as sink:
        for start in range(0, int(num_rays), int(batch_rays)):
            tracer.trace(start, min(start + int(batch_rays), int(num_rays)), sink)
        if with_diffraction:  # Sionna counts a diffraction as one interaction of max_depth
            from simart_pipeline.ckm.diffraction import (DIRECT_SAMPLES_PER_RAY, SAMPLES_PER_BATCH_RAY,
                                                          DiffractionSampler)

            # the diffraction is one of max_depth interactions; specular ones may follow it
            after = depth - 1 if depth and diffraction_with_reflections else 0
            wedges = DiffractionSampler(radio, tracer, tx_position_m, rot, grid, after,
                                        edge_diffraction,
                                        reflections_before=reflections_before, solids=solids)
            wedges.find_wedges(int(num_rays), int(batch_rays))
            wedges.trace(int(DIRECT_SAMPLES_PER_RAY * num_rays if diffraction_samples is None else diffraction_samples),
                         SAMPLES_PER_BATCH_RAY * int(batch_rays), sink, tag_stretches=resample > 1)
    second_pass = None
    if wedges is not None and resample > 1:
        second_pass = _resample_undersampled(
            acc, wedges, resample, masked.ravel(), frac.ravel(), int(min_hits_for_power),
            float(min_effective_hits_for_power), SAMPLES_PER_BATCH_RAY * int(batch_rays),
            lambda: accumulator(grid, tx_position_m, codebook, ant, rot, radio.wavelength_m))
    lattice_pass = None
    if lattice_factor > 1:
        lattice_pass = _resample_lattice(
            acc, tracer, lattice_factor, masked.ravel(), frac.ravel(), int(min_hits_for_power),
            max(float(min_effective_hits_for_power), float(min_hits_for_power)), int(batch_rays),
            lambda: accumulator(grid, tx_position_m, codebook, ant, rot, radio.wavelength_m))
    gather = None
    if gathering:
        tracer.tag_diffuse_last = False
        gather = _gather_diffuse(
            acc, radio, tracer, grid, masked.ravel(), frac.ravel(), float(gather_below_effective_hits),
            float(gather_auto_min_share) if diffuse_gather == "auto" else 0.0, int(num_rays), solids,
            int(max(1, round(float(gather_photon_share) * int(num_rays)))), int(batch_rays),
            int(gather_directions_per_point), gather_radius_m, int(gather_pilot_directions), float(gather_guided_share),
            lambda: accumulator(grid, tx_position_m, codebook, ant, rot, radio.wavelength_m))
    m = acc.moments()
    scale = np.where(masked, 0.0, 1.0 / np.maximum(frac, 1e-12))
    for f in ("power", "los_power", "p_excess_delay_s", "p_excess_delay2_s2"):
        setattr(m, f, getattr(m, f) * scale)
    m.p_cos, m.p_sin = m.p_cos * scale[..., None], m.p_sin * scale[..., None]
    m.power_sq = m.power_sq * scale**2
    if m.beam_power is not None:
        m.beam_power = m.beam_power * scale[..., None]
    m.count = np.where(masked, 0, m.count)
    m.min_delay_s = np.where(masked, np.inf, m.min_delay_s)
    return OnePassMoments(**{f.name: getattr(m, f.name) for f in fields(CellMoments)},
                          min_count_for_spread=int(min_hits_for_spread),
                          min_count_for_power=int(min_hits_for_power),
                          min_effective_count_for_power=float(min_effective_hits_for_power),
                          min_effective_count_for_spread=float(min_effective_hits_for_spread),
                          outdoor_fraction=frac, masked=masked,
                          num_rays=int(num_rays), second_pass=second_pass, lattice_second_pass=lattice_pass,
                          diffuse_gather=gather)


def default_batch_rays(variant: str) -> int:
    """Rays a batch of :func:`one_pass_moments` traces by default on Mitsuba ``variant``:
    :data:`DEFAULT_BATCH_RAYS_GPU` on ``cuda``, :data:`DEFAULT_BATCH_RAYS` on LLVM."""
    return DEFAULT_BATCH_RAYS_GPU if variant.startswith("cuda") else DEFAULT_BATCH_RAYS


def _undersampled_cells(acc: _Accumulator, masked, frac, min_hits: int, min_effective: float) -> np.ndarray:
    """Flat cells outside the mask with a ray hit but too few for a path gain (the layers' rule,
    :func:`too_few_hits`, on the accumulator's sums: the outdoor share scales power and
    power squared alike, the effective count not)."""
    m = acc.summed()  # the device's sums come to the host here
    few = too_few_hits(m, min_hits, min_effective)
    return np.flatnonzero((m.count >= 1) & few & ~masked & (frac > 0))


def _resample_undersampled(acc: _Accumulator, wedges, factor: int, masked, frac, min_hits: int,
                           min_effective: float, batch: int, new_accumulator) -> dict:
    """The second pass of ``one_pass_moments(diffraction_resample_factor=factor)``: the cells
    left with too few hits for a path gain (:func:`_undersampled_cells`), the stretches of edge
    whose diffracted rays reached them (deposits tagged in the first pass,
    :meth:`DiffractionSampler.resample`), those stretches' first-pass samples traced again (the
    same rays, bit for bit) and ``factor`` times as many new ones; in the undersampled cells the
    first are taken out and the new ones put in. Each is an unbiased estimate of the stretches'
    part, and the new one is independent of the choice of cells, so the swap keeps the estimator
    unbiased. A new sample's tube is ``1 / factor`` of a first-pass one's: where footprints are
    smaller than a cell the cell gets about ``factor`` times the hits; where they are wider (far
    from the edge) about the same hits from narrower footprints, i.e. less smoothing. Cells whose
    few hits are not diffracted (a grazing reflected tube) keep them. Returns what it did."""
    cells = _undersampled_cells(acc, masked, frac, min_hits, min_effective)
    stretches = acc.tags_into(cells, "stretch")
    out = {"factor": int(factor), "undersampled_cells": int(len(cells)), "stretches": int(len(stretches)),
           "pairs": int(len(np.unique(stretches // STRETCHES_PER_PAIR))), "new_samples": 0}
    if not len(stretches):
        return out
    replay, finer = new_accumulator(), new_accumulator()
    with _sink(replay) as replay_sink, _sink(finer) as finer_sink:
        out["new_samples"] = wedges.resample(stretches, factor, batch, replay_sink, finer_sink)
    acc.replace(cells, replay.summed(), finer.summed())
    out["still_undersampled"] = int(len(_undersampled_cells(acc, masked, frac, min_hits, min_effective)))
    return out


def _gather_diffuse(acc: _Accumulator, radio, tracer: Tracer, grid, masked, frac, below: float, min_share: float,
                    num_rays: int, solids, photon_rays: int, batch: int, directions_per_point: int, radius_m,
                    pilot_directions: int, guided_share: float, new_accumulator) -> dict:
    """The diffuse gather of ``one_pass_moments(diffuse_gather=True)``: the cells outside the mask
    that no ray reached or whose effective count stays below ``below``, their last diffuse
    reflection gathered (:func:`simart_pipeline.ckm.gather.diffuse_gather`) and weighed there with
    the main pass's deposits tagged ``diffuse_last`` by their relative variances; none where those
    cells are fewer than ``min_share`` of the cells outside the mask (``diffuse_gather="auto"``),
    counted at :data:`GATHER_AUTO_REFERENCE_RAYS` rays (``auto_share``). Returns what it did."""
    from simart_pipeline.ckm.gather import diffuse_gather

    m = acc.summed()
    effective = effective_count(m)
    # every few-hit cell, whatever makes its few hits: in Munich's far cells the rays' few large
    # deposits are specular or diffracted and the diffuse power from the walls beside the cell is
    # what they miss (taking only cells whose diffuse-last deposits make the noise, as the lattice's
    # second pass does, left Munich's map as without the gather; docs/ckm-one-pass.md "Session 35")
    open_cells = ~masked & (frac > 0)
    cells = np.flatnonzero(open_cells & (effective < below))
    share = len(cells) / max(int(open_cells.sum()), 1)
    # auto decides on the cells that would be few-hit cells at GATHER_AUTO_REFERENCE_RAYS rays (the
    # effective count grows in proportion to the rays): a scene's property, not its sampling's. By
    # the share at the call's own rays urban was gathered at 3e6 rays (45 %: twice the time, where
    # 1.3x the rays did better) and Munich not at 1e8 (28 %), the gather helping there
    # (docs/ckm-one-pass.md "Session 36")
    auto_share = float(np.count_nonzero(open_cells & (effective < below * num_rays / GATHER_AUTO_REFERENCE_RAYS))
                       ) / max(int(open_cells.sum()), 1)
    record = {"few_hit_cells": int(len(cells)), "few_hit_share": round(share, 4), "below_effective_hits": float(below),
              "auto_share": round(auto_share, 4)}
    if min_share > 0:
        record["auto_min_share"] = float(min_share)
    if auto_share < min_share:
        return {"cells": 0, **record, "photons": 0, "pairs": 0}
    if solids is None:
        solids = radio_solids(radio)
    gathered = new_accumulator()
    with _sink(gathered) as sink:
        out, var_gather = diffuse_gather(radio, tracer, grid, cells, solids, sink, photon_rays=photon_rays,
                                         batch_rays=batch, directions_per_point=directions_per_point,
                                         radius_m=radius_m, pilot_directions=pilot_directions,
                                         guided_share=guided_share)
    out.update(record)
    if var_gather is None:
        return out
    old, new = acc.diffuse_last.summed(), gathered.summed()
    # the two estimates of the cell's last diffuse reflection weighted by their inverse relative
    # variances: the main pass's where a far scatter point lit brightly makes few gather rays carry
    # the cell, the gather's where a few near scatter points carry the main pass's
    # (docs/ckm-one-pass.md, "Session 35"). Relative (for the rays 1 / their effective count): a few
    # deposits that missed a cell's rare large ones say little about its absolute variance, their
    # spread still says how few carry it; no deposit at all: no estimate (weight 0)
    rel_rays = np.where(old.power > 0, old.power_sq / np.where(old.power > 0, old.power, 1.0) ** 2, np.inf)
    rel_gather = np.where(new.power > 0, var_gather / np.where(new.power > 0, new.power, 1.0) ** 2, np.inf)
    with np.errstate(invalid="ignore"):
        w_gather = np.where(np.isinf(rel_rays), np.where(np.isinf(rel_gather), 0.5, 1.0),
                            np.where(np.isinf(rel_gather), 0.0, rel_rays / np.maximum(rel_rays + rel_gather, 1e-300)))
    out["gather_weight_median"] = float(np.median(w_gather[cells])) if len(cells) else 0.0
    acc.replace(cells, old, _weighted_moments(old, new, 1.0 - w_gather, w_gather, var_gather))
    return out


def _weighted_moments(a: CellMoments, b: CellMoments, wa: np.ndarray, wb: np.ndarray, var_b: np.ndarray) -> CellMoments:
    """``wa a + wb b`` per cell (flat sums) for every sum linear in the deposits' powers; the sum of
    squares as the weighted variance ``wa^2 sum p_a^2 + wb^2 var_b``; hits added; earliest delay the
    smaller."""
    out = CellMoments.zeros(a.power.shape, None if a.beam_power is None else a.beam_power.shape[1])
    for f in ("power", "los_power", "p_excess_delay_s", "p_excess_delay2_s2", "p_cos", "p_sin", "beam_power"):
        va, vb = getattr(a, f), getattr(b, f)
        if va is None:
            continue
        shape = (-1,) + (1,) * (va.ndim - 1)
        setattr(out, f, wa.reshape(shape) * va + wb.reshape(shape) * vb)
    out.power_sq = wa**2 * a.power_sq + wb**2 * var_b
    out.count = a.count + b.count
    out.min_delay_s = np.minimum(a.min_delay_s, b.min_delay_s)
    return out


def _resample_lattice(acc: _Accumulator, tracer: Tracer, factor: int, masked, frac, min_hits: int,
                      min_effective: float, batch: int, new_accumulator) -> dict:
    """The lattice rays' second pass of ``one_pass_moments(lattice_resample_factor=factor)``: the
    cells whose effective count stays below ``min_effective`` (:func:`_undersampled_cells`) and
    whose binned deposits (lattice rays that never scattered diffusely) hold at least
    :data:`LATTICE_NOISE_SHARE` of their sum of squared deposits, the
    bins of launch directions whose lattice rays reached them (their deposits tagged in the first
    pass, :class:`LatticeBins`) and the bins beside those (:meth:`LatticeBins.with_neighbours`),
    those bins' lattice rays traced again (the same rays, bit for
    bit: the same directions, solid angle and random streams) and ``factor`` times as many new
    rays over the same bins (:meth:`LatticeBins.finer_directions`, each ray ``4 pi / (bins x
    rays per bin)`` sr, random streams numbered after the lattice's), both stopped at their first
    diffuse reflection (``Tracer.undiffused_only``); in those cells the first are taken out and the
    new ones put in. A bin is chosen for a cell when any of its rays reached the cell, so a chosen
    cell's whole binned part is swapped (its diffracted part is the diffraction pass's business,
    its diffused part stays: a diffused ray lands where its scattering sends it, not where its
    bin points, so finer bins would not aim at the cell). The new estimate is unbiased for the chosen bins'
    part of the cell; a bin that reaches the cell but sent none of its few first-pass rays there
    is missed unless it lies beside one that did (hence the neighbours: measured in the tests on
    free space, the swapped cells' total stays the closed form's). Returns what it did."""
    bins_of = tracer.lattice_bins
    few = _undersampled_cells(acc, masked, frac, min_hits, min_effective)
    m = acc.summed()
    if acc.binned_power_sq is None:
        cells = few[:0]
    else:  # the binned deposits carry the cell's noise (most of its sum of squares)
        cells = few[acc.binned_power_sq[few] >= LATTICE_NOISE_SHARE * m.power_sq[few]]
    reaching = acc.tags_into(cells, "lattice_bin")
    bins = bins_of.with_neighbours(reaching)
    per_bin = max(1, int(round(factor * bins_of.num_rays / bins_of.num_bins)))
    out = {"factor": int(factor), "undersampled_cells": int(len(few)), "cells_swapped": int(len(cells)),
           "bins_reaching": int(len(reaching)),
           "bins": int(len(bins)),
           "num_bins": bins_of.num_bins, "replayed_rays": 0, "new_rays": int(len(bins) * per_bin)}
    if not len(bins):
        return out
    first_stream = bins_of.num_rays  # the new rays' random streams follow the lattice's
    if first_stream + len(bins) * per_bin > RANDOM_STREAMS:
        raise ValueError(f"lattice_resample_factor {factor}: {len(bins) * per_bin} new rays after {first_stream} "
                         "lattice rays exceed the 2**32 random streams; lower the factor or num_rays")
    rays = bins_of.rays_in(bins)
    out["replayed_rays"] = int(len(rays))
    # the second pass's rays are not tagged again; their first hits name no new wedges
    tracer.lattice_bins, lit = None, tracer._lit_face_hits
    tracer._lit_face_hits, tracer.undiffused_only = None, True
    replay, finer = new_accumulator(), new_accumulator()
    try:
        with _sink(replay) as sink:
            for lo in range(0, len(rays), batch):
                tracer.trace(0, 0, sink, indices=rays[lo:lo + batch])
        tracer.set_solid_angle(4 * np.pi / (bins_of.num_bins * per_bin))
        step = max(1, batch // per_bin)  # bins per batch
        with _sink(finer) as sink:
            for lo in range(0, len(bins), step):
                chunk = bins[lo:lo + step]
                streams = first_stream + lo * per_bin + np.arange(len(chunk) * per_bin, dtype=np.int64)
                tracer.trace(0, 0, sink, indices=streams.astype(np.uint32),
                             directions=bins_of.finer_directions(chunk, per_bin))
    finally:
        tracer.set_solid_angle(4 * np.pi / tracer.num_rays)
        tracer.lattice_bins, tracer._lit_face_hits, tracer.undiffused_only = bins_of, lit, False
    acc.replace(cells, replay.summed(), finer.summed())
    out["still_undersampled"] = int(len(_undersampled_cells(acc, masked, frac, min_hits, min_effective)))
    return out


def undersampled_fraction(m: OnePassMoments) -> float:
    """Share of the reached, unmasked cells whose ray hits stay below ``min_count_for_power`` (or
    whose effective count stays below ``min_effective_count_for_power``)
    (cells whose layers are masked for too few rays); 0 where nothing is reached."""
    reached = (m.count >= 1) & ~m.masked
    n = int(reached.sum())
    few = too_few_hits(m, m.min_count_for_power, m.min_effective_count_for_power)
    return 0.0 if n == 0 else float((reached & few).sum() / n)


ADAPTIVE_GROWTH = 4  # rays per refinement step: hits per cell grow 4x, their sampling error halves


def adaptive_one_pass_moments(*args, num_rays: int, max_rays: int | None,
                              max_undersampled_fraction: float, **kwargs) -> OnePassMoments:
    """:func:`one_pass_moments` with the adaptive rule of ``ckm.adaptive_max_rays``: while more
    than ``max_undersampled_fraction`` of the reached cells have too few hits for a value
    (:func:`undersampled_fraction`), the pass is run again with :data:`ADAPTIVE_GROWTH` times the
    rays, as long as that stays within ``max_rays`` (None: one pass). The result is that of the
    last pass alone, so it equals a single pass at its ``num_rays`` (the lattices of two ray
    counts are different rays: the passes are not summed). The other arguments are
    :func:`one_pass_moments`'s."""
    n = int(num_rays)
    m = one_pass_moments(*args, num_rays=n, **kwargs)
    while (max_rays is not None and n * ADAPTIVE_GROWTH <= max_rays
           and undersampled_fraction(m) > max_undersampled_fraction):
        n *= ADAPTIVE_GROWTH
        m = one_pass_moments(*args, num_rays=n, **kwargs)
    return m
