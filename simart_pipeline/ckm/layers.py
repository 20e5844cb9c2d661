"""CKM layers of one tile, in the mode the scene config chooses.

- ``reference``: Sionna RT PathSolver at every traced cell centre, all cells of the tile and all
  base stations in batched calls (``RadioScene.grid_scan``); per-path beam gains from the stored
  per-antenna coefficients.
- ``fast``: one shoot-and-bounce pass per base station over the tile's planes
  (:mod:`simart_pipeline.ckm.one_pass`).

Both reduce what reaches a cell to the same :class:`~simart_pipeline.ckm.moments.CellMoments`, so
both write the same layers with the same definitions (:mod:`simart_pipeline.ckm.moments`); the
link-level layers (best base station, SINR with interference, MCS, BLER, rate) are then computed
per cell from the beam gains (:mod:`simart_pipeline.ckm.link_layers`), with no state carried from
one cell to another. Cells inside buildings or outside the region are masked and never traced; a
tile with no cell to trace returns at once, without loading a scene. A cell's values depend only on
its own centre, never on the tile or the order of tiles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xarray as xr

from simart_pipeline.ckm import moments as mom
from simart_pipeline.ckm.gather import DEFAULT_GATHER_PILOT_DIRECTIONS
from simart_pipeline.ckm.grid import cell_centres, outside_region, tile_slices
from simart_pipeline.ckm.outdoor import DEFAULT_MIN_OUTDOOR_FRACTION, OUTDOOR_SAMPLES_PER_AXIS
from simart_pipeline.config import SceneConfig
from simart_pipeline.link.budget import power_db
from simart_pipeline.scene.geometry import SourceGeometry, inside_buildings
from simart_pipeline.scene.solids import Solids, inside_solids
from simart_pipeline.vocabulary import SPEED_OF_LIGHT_MPS

MASKED = "cell masked (cell_masked), or nothing reached it"
CELL_MASKED = ("masked, no layer holds a value: the centre inside a building or outside the region "
               f"(cell_inside_building, cell_outside_region) or, fast mode, less than "
               f"{100 * DEFAULT_MIN_OUTDOOR_FRACTION:g} % of the cell's area outdoors (cell_outdoor_fraction; the "
               "one-pass divides a cell's sums by that share)")
# the layers that need a second moment's sampling (moments.too_few_hits with the spread minimums)
SPREAD_LAYERS = ("rms_delay_spread_s", *mom.SPREAD_NAMES.values(), *mom.MEAN_ANGLE_NAMES.values())
SPREAD_MASKED = ("; or, fast mode, fewer ray hits than ckm.min_hits_for_spread or fewer effective hits "
                 "than ckm.min_effective_hits_for_spread (one or two rays carry the cell's sums)")
PROPAGATION_FLOAT_LAYERS = ("path_gain_db", "path_loss_db", "path_gain_coherent_db", "rx_power_dbm",
                            "los_power_fraction", "toa_s", "mean_delay_s", "rms_delay_spread_s",
                            *mom.SPREAD_NAMES.values(), *mom.MEAN_ANGLE_NAMES.values(),
                            "best_beam_gain_db")
BEAM_CHUNK_BYTES = 256 * 2**20


@dataclass
class TileGrid:
    """The cells of one tile: coordinates, masks and the points to trace."""

    tile: str
    rows: np.ndarray      # grid row index of each tile row
    cols: np.ndarray
    y: np.ndarray
    x: np.ndarray
    heights: np.ndarray
    inside_building: np.ndarray  # [height, y, x]
    outside_region: np.ndarray   # [y, x]

    @property
    def traced(self) -> np.ndarray:
        return ~self.inside_building & ~self.outside_region[None]


def tile_grid(cfg: SceneConfig, geom: SourceGeometry, tile: str, solids: Solids | None = None) -> TileGrid:
    """The cells of ``tile``. A cell centre is inside a building when it lies inside one of
    ``solids`` (the radio mesh's, :func:`simart_pipeline.ckm.outdoor.mesh_solids_of`: exact, the
    fast mode's own indoor test; a centre on a wall is outdoors); without them, inside a
    footprint's height band of ``geom`` (conservative where a roof or a part overhangs its
    footprint's walls)."""
    ckm = cfg.ckm
    sl = tile_slices(ckm, tile)
    y_all, x_all = cell_centres(ckm)
    rows = np.arange(len(y_all))[sl[0]] if sl else np.arange(0)
    cols = np.arange(len(x_all))[sl[1]] if sl else np.arange(0)
    y, x = y_all[rows], x_all[cols]
    heights = np.asarray(ckm.heights, np.float64)
    yy, xx = np.meshgrid(y, x, indexing="ij")
    if not (len(y) and len(x)):
        inside = np.zeros((len(heights), len(y), len(x)), bool)
    elif solids is not None:
        pts = np.column_stack([np.tile(xx.ravel(), len(heights)), np.tile(yy.ravel(), len(heights)),
                               np.repeat(heights, xx.size)])
        inside = inside_solids(solids, pts, walls_outside=True).reshape(len(heights), len(y), len(x))
    else:
        inside = np.stack([inside_buildings(geom, xx, yy, np.full_like(xx, h)) for h in heights])
    return TileGrid(tile, rows, cols, y, x, heights, inside, outside_region(ckm, x, y))


def codebook_weights(cfg: SceneConfig, tx_ant_positions_m: np.ndarray | None, scene_dir=None) -> np.ndarray:
    """The base stations' codebook ``[num_beams, num_tx_ant]``, the same as the ``kpis`` stage's
    (``link.beams.scene_codebook_weights``). Without antenna positions (a tile with nothing to
    trace needs only the beam count) a half-wavelength-spaced grid of the array stands in."""
    from simart_pipeline.link.beams import scene_codebook_weights

    if tx_ant_positions_m is None:
        a = cfg.base_stations[0].array
        lam = SPEED_OF_LIGHT_MPS / cfg.ofdm.carrier_frequency_hz
        zz, yy = np.meshgrid(np.arange(a.rows), np.arange(a.cols), indexing="ij")
        tx_ant_positions_m = np.column_stack([np.zeros(a.num_antennas), yy.ravel() * a.spacing_wavelengths * lam,
                                              zz.ravel() * a.spacing_wavelengths * lam])
    return scene_codebook_weights(cfg, tx_ant_positions_m, scene_dir)


def reference_moments(radio, cfg: SceneConfig, points: np.ndarray, weights: np.ndarray
                      ) -> tuple[mom.CellMoments, np.ndarray]:
    """PathSolver at ``points [N, 3]`` from every base station: moments ``[B, N]`` and the coherent
    narrowband path gain ``[B, N]`` (antenna-pair mean of ``|sum_p a_p exp(-j 2 pi f_c tau_p)|^2``)."""
    tx = np.array([b.position_m for b in cfg.base_stations], np.float64)
    tx_ori = np.deg2rad(np.array([b.orientation_deg for b in cfg.base_stations], np.float64))
    p = radio.grid_scan(tx, tx_ori, points, deterministic=cfg.ckm.deterministic_solver)
    a = p.a.astype(np.complex128)                          # [N, r, B, n, P]
    power = np.mean(np.abs(a) ** 2, axis=(1, 3))            # [N, B, P]
    tau0 = np.linalg.norm(points[:, None, :] - tx[None], axis=-1) / SPEED_OF_LIGHT_MPS  # [N, B]
    angles = np.stack([p.phi_r, p.theta_r, p.phi_t, p.theta_t], axis=-1)  # [N, B, P, 4] (mom.ANGLES)
    num_beams = weights.shape[0]
    beam = np.zeros(power.shape + (num_beams,))
    # Per-path beam gain, in chunks of cells to bound memory: mean_r |sum_n w_bn a_rnp|^2.
    per_cell = max(1, BEAM_CHUNK_BYTES // max(1, 16 * a[0].size * num_beams))
    w_t = np.ascontiguousarray(weights.T)                   # [n, K]: a BLAS product, not einsum
    for s in range(0, len(points), per_cell):
        y = np.swapaxes(a[s:s + per_cell], -1, -2) @ w_t     # [N, r, B, P, K]
        beam[s:s + per_cell] = np.mean(y.real**2 + y.imag**2, axis=1)
    m = mom.path_moments(power.transpose(1, 0, 2), p.tau_s.transpose(1, 0, 2),
                         p.valid.transpose(1, 0, 2), p.los.transpose(1, 0, 2),
                         angles.transpose(1, 0, 2, 3), tau0.T, beam.transpose(1, 0, 2, 3))
    phase = np.exp(-2j * np.pi * cfg.ofdm.carrier_frequency_hz * np.where(p.valid, p.tau_s, 0.0))
    h = mom.path_sum(a * phase[:, None, :, None, :])        # [N, r, B, n]
    coherent = np.mean(np.abs(h) ** 2, axis=(1, 3)).T        # [B, N]
    return m, coherent


def fast_moments(radio, cfg: SceneConfig, grid: TileGrid, weights: np.ndarray, tx_ant_positions_m
                 ) -> tuple[mom.CellMoments, list[int], list[dict | None], list[dict | None], list[dict | None],
                            np.ndarray, np.ndarray]:
    """One shoot-and-bounce pass per base station over the tile's planes (more where
    ``ckm.adaptive_max_rays`` asks): moments ``[B, H, y, x]``, the rays each station's pass used
    and what each one's second passes on undersampled cells did (None: none), the diffracted
    rays' (``ckm.diffraction_resample_factor``) and the lattice rays'
    (``ckm.lattice_resample_factor``), what each one's diffuse gather did
    (``ckm.diffuse_gather``), the cells' outdoor share and the cells the passes masked ``[H, y, x]``
    (the tile's mask and the cells less than half outdoors)."""
    from simart_pipeline.ckm.one_pass import adaptive_one_pass_moments
    from simart_pipeline.ckm.outdoor import outdoor_fraction, radio_solids

    per_bs = []
    rx = cfg.platforms[0].array
    solids = radio_solids(radio)
    # the cells' outdoor share: the scene's and the grid's, the same for every station and pass
    frac = outdoor_fraction(radio, grid.x, grid.y, grid.heights, cell_size_m=cfg.ckm.cell_size_m, solids=solids)
    for b in cfg.base_stations:
        per_bs.append(adaptive_one_pass_moments(
            radio, np.asarray(b.position_m, np.float64), np.deg2rad(np.asarray(b.orientation_deg, np.float64)),
            grid.x, grid.y, grid.heights, num_rays=cfg.ckm.num_rays, max_rays=cfg.ckm.adaptive_max_rays,
            max_undersampled_fraction=cfg.ckm.max_undersampled_fraction, max_depth=cfg.ray_tracing.max_depth,
            codebook=weights, tx_ant_positions_m=tx_ant_positions_m, batch_rays=cfg.ckm.batch_rays,
            min_hits_for_spread=cfg.ckm.min_hits_for_spread, min_hits_for_power=cfg.ckm.min_hits_for_power,
            min_effective_hits_for_power=cfg.ckm.min_effective_hits_for_power,
            min_effective_hits_for_spread=cfg.ckm.min_effective_hits_for_spread,
            max_footprint_cells=cfg.ckm.max_footprint_cells, cell_size_m=cfg.ckm.cell_size_m,
            diffraction_resample_factor=cfg.ckm.diffraction_resample_factor,
            lattice_resample_factor=cfg.ckm.lattice_resample_factor,
            diffuse_connections=cfg.ckm.diffuse_connections, diffuse_gather=cfg.ckm.diffuse_gather,
            gather_pilot_directions=DEFAULT_GATHER_PILOT_DIRECTIONS if cfg.ckm.gather_guided else 0,
            indoor=grid.inside_building | grid.outside_region[None], solids=solids, cell_outdoor_fraction=frac,
            # as the reference mode's receiver: its polarisation, not the whole field
            rx_polarization=rx.polarization if rx.pattern == "iso" else None,
            # the interaction types of the scene's ray tracing, as the reference mode's PathSolver
            los=cfg.ray_tracing.los, specular_reflection=cfg.ray_tracing.specular_reflection,
            diffraction=cfg.ray_tracing.diffraction, edge_diffraction=cfg.ray_tracing.edge_diffraction,
            refraction=cfg.ray_tracing.refraction, diffuse_reflection=cfg.ray_tracing.diffuse_reflection))
    stacked = {}
    for f in mom.CellMoments.__dataclass_fields__:
        vals = [getattr(m, f) for m in per_bs]
        stacked[f] = None if vals[0] is None else np.stack(vals)
    return (mom.CellMoments(**stacked), [m.num_rays for m in per_bs], [m.second_pass for m in per_bs],
            [m.lattice_second_pass for m in per_bs], [m.diffuse_gather for m in per_bs], frac, per_bs[0].masked)


def tile_layers(radio, cfg: SceneConfig, geom: SourceGeometry, tile: str, scene_dir=None,
                grid: TileGrid | None = None) -> xr.Dataset:
    """Every layer of tile ``tile`` over (bs, height, y, x) and (height, y, x); ``radio`` (a
    ``RadioScene``) may be None when the tile has no cell to trace; ``scene_dir`` resolves
    ``codebook.path``; ``grid`` is ``tile_grid(cfg, geom, tile)`` if the caller has it already."""
    from simart_pipeline.ckm.link_layers import link_layers

    grid = tile_grid(cfg, geom, tile) if grid is None else grid
    B, H = len(cfg.base_stations), len(grid.heights)
    shape = (B, H, len(grid.y), len(grid.x))
    traced = grid.traced
    n_traced = int(traced.sum())
    if n_traced and radio is None:
        raise ValueError(f"tile {tile}: {n_traced} cells to trace but no radio scene given")
    tx_ant = radio.array_positions_m("tx") if n_traced else None
    weights = codebook_weights(cfg, tx_ant, scene_dir)
    hh, yy, xx = np.meshgrid(grid.heights, grid.y, grid.x, indexing="ij")
    m = mom.CellMoments.zeros(shape, weights.shape[0])
    coherent = np.zeros(shape)
    # what the mode masked: the tile's mask; fast mode adds the cells less than half outdoors, whose
    # centre may lie outside every building (a street cell cut by a facade)
    masked, frac = ~traced, np.full(traced.shape, np.nan)
    if n_traced and cfg.ckm.mode == "reference":
        pts = np.column_stack([xx[traced], yy[traced], hh[traced]])
        mt, coh = reference_moments(radio, cfg, pts, weights)
        for f in mom.CellMoments.__dataclass_fields__:
            getattr(m, f)[:, traced] = getattr(mt, f)
        coherent[:, traced] = coh
    elif n_traced:
        m, rays_per_bs, second_pass, lattice_pass, gathered, frac, masked = fast_moments(
            radio, cfg, grid, weights, tx_ant)
        coherent[:] = np.nan
    tx = np.array([b.position_m for b in cfg.base_stations], np.float64)
    centre = np.stack([xx, yy, hh], -1)
    m.tau0_s = np.linalg.norm(centre[None] - tx[:, None, None, None, :], axis=-1) / SPEED_OF_LIGHT_MPS
    # Masked cells hold nothing, whatever a solver deposited there.
    for f in mom.CellMoments.__dataclass_fields__:
        v = getattr(m, f)
        if v is not None and f != "tau0_s":
            v[:, masked] = np.inf if f == "min_delay_s" else 0
    fast = cfg.ckm.mode == "fast"
    layers = mom.layers_from_moments(m, cfg.ckm.min_hits_for_spread if fast else 1,
                                     cfg.ckm.min_hits_for_power if fast else 1,
                                     cfg.ckm.min_effective_hits_for_power if fast else 1.0,
                                     cfg.ckm.min_effective_hits_for_spread if fast else 1.0)
    # Link layers and the coherent gain follow the power layers: none where too few rays arrived.
    has = layers["enough_hits"]
    layers["path_gain_coherent_db"] = np.where(has, power_db(coherent), np.nan)
    power_dbm = np.array([b.power_dbm for b in cfg.base_stations])[:, None, None, None]
    layers["rx_power_dbm"] = power_dbm + layers["path_gain_db"]
    ds = layers_dataset(layers, cfg, grid, B, masked, frac)
    ds = ds.merge(link_layers(cfg, m.beam_power, has, ~masked))
    ds.attrs.update(tile=tile, mode=cfg.ckm.mode, cells_traced=n_traced,
                    in_scene_tiling=int(tile_slices(cfg.ckm, tile) is not None))
    if fast and n_traced:
        ds.attrs["rays_per_bs"] = rays_per_bs  # the adaptive rule may have raised ckm.num_rays
        if any(second_pass):  # ckm.diffraction_resample_factor: what each station's second pass did
            ds.attrs["second_pass_per_bs"] = second_pass
        if any(lattice_pass):  # ckm.lattice_resample_factor: what each station's lattice second pass did
            ds.attrs["lattice_second_pass_per_bs"] = lattice_pass
        if any(gathered):  # ckm.diffuse_gather: what each station's gather did
            ds.attrs["diffuse_gather_per_bs"] = gathered
    return ds


def layers_dataset(layers: dict, cfg: SceneConfig, grid: TileGrid, B: int, masked: np.ndarray,
                   outdoor_fraction: np.ndarray) -> xr.Dataset:
    """The tile's dataset: ``layers`` ``[B, H, y, x]`` with their attrs, the masks and the cells'
    outdoor share (``masked``: every cell the mode masked, ``outdoor_fraction``: NaN where not
    computed; both ``[H, y, x]``)."""
    d4 = ("bs", "height", "y", "x")
    data = {}
    for name, v in layers.items():
        attrs = dict(mom.LAYER_ATTRS.get(name, {}))
        if name == "path_gain_coherent_db":
            attrs = dict(units="dB", long_name="path gain, coherent sum over paths at the carrier "
                         "frequency (antenna-pair mean); reference mode only")
            attrs["nan_means"] = MASKED + "; always in fast mode (a ray tube carries no phase)"
        elif name == "rx_power_dbm":
            attrs = dict(units="dBm", long_name="received power per antenna element: transmit power "
                         "plus path gain (no beamforming gain)")
        if name == "beam_gain_db":
            data[name] = (d4 + ("beam",), v.astype(np.float32), {**attrs, "nan_means": MASKED})
            continue
        if v.dtype.kind == "f":
            attrs.setdefault("nan_means", MASKED + (SPREAD_MASKED if name in SPREAD_LAYERS else
                                                    "; or fewer ray hits than ckm.min_hits_for_power (fast mode)"))
            v = v.astype(np.float64 if name.endswith("_s") else np.float32)
        data[name] = (d4, v, attrs)
    if "beam_gain_db" in layers:
        data_coords_beam = np.arange(layers["beam_gain_db"].shape[-1])
    data["cell_inside_building"] = (("height", "y", "x"), grid.inside_building,
                                    dict(long_name="cell centre inside a building: masked, not traced"))
    data["cell_outside_region"] = (("y", "x"), grid.outside_region,
                                   dict(long_name="cell centre outside the region of interest: masked, not traced"))
    data["cell_masked"] = (("height", "y", "x"), np.asarray(masked, bool), dict(long_name=CELL_MASKED))
    data["cell_outdoor_fraction"] = (("height", "y", "x"), np.asarray(outdoor_fraction, np.float32),
                                     dict(units="1", long_name=f"share of the cell's area outside buildings "
                                          f"({OUTDOOR_SAMPLES_PER_AXIS} x {OUTDOOR_SAMPLES_PER_AXIS} points)",
                                          nan_means="not computed: reference mode (a cell is traced at its centre), or "
                                          "a tile with no cell to trace"))
    coords = map_coords(cfg, grid)
    if "beam_gain_db" in layers:
        coords["beam"] = ("beam", data_coords_beam, dict(long_name="codebook beam index"))
    return xr.Dataset(data, coords=coords)


def map_coords(cfg: SceneConfig, grid: TileGrid) -> dict:
    return {
        "bs": [b.name for b in cfg.base_stations],
        "height": ("height", grid.heights, dict(units="m", long_name="receiver height above the ENU origin")),
        "y": ("y", grid.y, dict(units="m", long_name="cell centre north (ENU)")),
        "x": ("x", grid.x, dict(units="m", long_name="cell centre east (ENU)")),
        "row": ("y", grid.rows, dict(long_name="grid row")),
        "col": ("x", grid.cols, dict(long_name="grid column")),
    }
