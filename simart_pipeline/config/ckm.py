"""Channel knowledge map: the grid, its heights, region and tiles, and the solver mode."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from simart_pipeline.config.base import Vec2, _Model
from simart_pipeline.vocabulary import WeatherName


MAX_TILES_PER_AXIS = 4  # the static tile partitions are r0c0 .. r3c3 (partitions/__init__.py)


# Bounds that keep a typo from asking for a grid no machine holds: a 100 km side; 1e8 cells
# (a 10 km x 10 km district at 1 m, one height; each layer is then 400 MB of float32).
MAX_GRID_SIDE_M = 100_000.0
MAX_CELLS = 100_000_000


class Ckm(_Model):
    """Channel-knowledge-map grid: horizontal planes at one or more heights, split into tiles (the
    tile partitions). Cells inside buildings or outside ``region_m`` are masked and never traced."""

    center_m: Vec2 = (0.0, 0.0)
    size_m: Vec2 = (100.0, 100.0)
    cell_size_m: float = Field(5.0, gt=0)
    height_m: float | None = Field(None, description="one receiver height (m); or use heights_m")
    heights_m: tuple[float, ...] | None = Field(None, description="several heights: a 3D voxel map")
    region_m: tuple[Vec2, ...] | None = Field(
        None, description="polygon (ENU x, y vertices) of the region of interest; default the whole grid")
    tiles: tuple[int, int] = Field((2, 2), description="tiles along x, along y")
    mode: Literal["reference", "fast"] = Field(
        "reference", description="reference: PathSolver at cell centres; fast: one shoot-and-bounce pass")
    deterministic_solver: bool = Field(
        False, description="reference mode: PathSolver(deterministic=True) instead of its default "
        "candidate generator, which finds the same paths here at a fraction of the time and memory "
        "per receiver (docs/ckm.md)")
    num_rays: int = Field(10_000_000, ge=1_000, description="fast mode: rays per transmitter")
    # Memory, not results: a batch's ray state is about 0.5 GB per million rays (measured on the
    # LLVM backend; on a GPU not measured); the sums change
    # only in float64 summation order (GPU: 4M rays a batch, docs/ckm-one-pass.md "Session 24")
    batch_rays: int | None = Field(
        None, ge=1_000, description="fast mode: rays traced at once (about 0.5 GB of ray state per million); "
        "lower it where a GPU's memory is small; null: 1M on a CPU, 4M on a GPU")
    min_hits_for_spread: int = Field(10, ge=1, description="fast mode: fewer ray hits mask the spreads")
    # 10, the hits a second moment needs, counted as effective hits: a cell with many hits of
    # which one or two carry the sum holds a spread that is mostly that ray's. Munich, every
    # mechanism, 1e7 rays against the same solver at 1e8: delay spread 8.7 ns p50 over every cell,
    # 45 ns in the cells below 10 effective hits (42 % of them), 4.2 ns in the rest; angle spread
    # of arrival 2.4 -> 1.2 deg. It masks the spreads of 8 % of the street canyon's cells with a
    # spread, 22 % of urban's, 42 % of Munich's at 1e7 rays (docs/ckm-one-pass.md, "Session 37").
    min_effective_hits_for_spread: float = Field(
        10.0, ge=1.0, description="fast mode: cells whose effective number of ray hits "
        "(sum p)^2 / sum p^2 (layer effective_count) stays below this hold no delay or angle "
        "spreads and no mean angles; 1: no such mask")
    # 5: a cell's power from n ray hits has a relative sampling error of about 1/sqrt(n) (the hit
    # count's own fluctuation), about 2 dB at 5 hits, while one or two hits can be tens of dB off
    # (a single reflected tube clipping the cell). Below min_hits_for_spread: a first moment needs
    # fewer hits than the second moments of the spreads.
    min_hits_for_power: int = Field(5, ge=1, description="fast mode: fewer ray hits mask path gain, "
                                    "ToA, mean delay, LoS and beam layers (layer enough_hits)")
    # 1: off. A cell's gain is a sum over ray tubes; where one tube carries most of it (a
    # diffracted ray at grazing incidence, say) the value can be tens of dB off however many hits
    # the cell has; its effective count (Kish) tells. Masking costs coverage (Munich, diffraction:
    # 2 masks 9 % of the reached cells, 3 masks 15 %; docs/ckm-one-pass.md, "Session 11").
    min_effective_hits_for_power: float = Field(
        1.0, ge=1.0, description="fast mode: cells whose effective number of ray hits "
        "(sum p)^2 / sum p^2 (layer effective_count) stays below this are masked like cells with too "
        "few hits, and count as undersampled for adaptive_max_rays; 1: no such mask")
    # 8: far from an edge a diffracted sample stands for many cells (a ray tube's footprint grows
    # with distance, and at grazing incidence); dropped into one cell it is a spike there and a hole
    # beside it. Spread over its footprint the map converges several times faster (Munich with
    # diffraction, docs/ckm-one-pass.md); the cap bounds the cells one crossing touches.
    max_footprint_cells: float = Field(
        8.0, ge=1.0, description="fast mode: a ray crossing whose tube footprint on the plane is wider "
        "than a cell spreads its power over the cells the footprint covers (a tent kernel as wide as the "
        "tube across the ray and stretched by 1 / |cos theta_z| along it, at most this many cells on a "
        "side); 1: each crossing into its one cell (RadioMapSolver's estimator)")
    # A targeted second pass (one_pass.one_pass_moments): the cells a few diffracted rays reach get
    # the diffracted part of the stretches of edge that reach them again from this many times the
    # samples. Off by default, as the run-time/error front chose (docs/ckm-one-pass.md, "Session
    # 15"; benchmarks.ckm_solver): on Munich (2 m cells, 1e7 rays, footprints on) 4 and 8 give 217
    # and 294 more cells a value (2-3 % of those reached) for 15-18 % more time, but those cells sit
    # at the fringe of diffracted wavefronts and stay 9-17 dB off at p95 (the map's other cells:
    # 3.9); with point deposits (max_footprint_cells 1) it takes a few-hit cell from 2.5 to 0.6 dB (p50).
    diffraction_resample_factor: int = Field(
        1, ge=1, le=64, description="fast mode, with diffraction: cells with a ray hit but fewer than "
        "min_hits_for_power get the diffracted part of the stretches of edge that reached them again from this "
        "many times their samples (a second pass, unbiased); 1: no second pass")
    # The lattice rays' targeted second pass (one_pass.one_pass_moments): the few-hit cells whose
    # noise the lattice rays make get their part again from this many times the rays, over the bins
    # of launch directions that reached them. Off by default, as the front chose (benchmarks.
    # lattice_second_pass, docs/ckm-one-pass.md "Session 29"): at 1e7 rays it swaps 385 of Munich's
    # 3,643 few-hit cells for 1.005x the time (gain p50 0.353 -> 0.337 dB, slightly ahead of more
    # rays), 5-10 cells on urban and the street canyon for 1.08-1.17x (behind more rays there).
    lattice_resample_factor: int = Field(
        1, ge=1, le=64, description="fast mode: cells whose effective number of ray hits stays below "
        "min_hits_for_power, where the lattice rays (before any diffuse reflection) make the noise, get that "
        "part again from this many times the rays, traced over the bins of launch directions (16 lattice rays "
        "each) that reached them and the bins around those (a second pass); 1: no second pass")
    # Next-event estimation of diffuse reflection (shoot_bounce.Tracer._connect): each diffuse hit
    # is also joined by a shadow ray to a point drawn uniformly among the tile's outdoor cells, the
    # two estimates weighted by the balance heuristic (unbiased either way). 0.5, as the run-time/
    # error front chose (benchmarks.diffuse_connections, docs/ckm-one-pass.md "Session 25"): on the
    # street canyon and urban at 1e7 rays, gain p95 and delay spread lower than without at the rays
    # that cost the same time (1.4-1.6x), gain p50 and best beam as good or better; 1 costs 1.8-1.9x.
    diffuse_connections: float = Field(
        0.5, ge=0, le=64, description="fast mode, with diffuse reflection: cells each diffuse hit is joined to "
        "on average (a shadow ray to a point drawn uniformly among the outdoor cells, weighted with the "
        "scattered ray by multiple importance sampling); 0: the scattered ray alone")
    # Final gathering of the last diffuse reflection in few-hit cells (ckm/gather.py): a forward
    # estimate weighs a scatter point by 1 / r^2 from the cell, so a cell that no strong path reaches
    # is carried by the few samples that fall near it; gathered from the cell over solid angle it is
    # not (docs/ckm-one-pass.md "Session 35"). "auto", as the run-time/error front chose ("Session
    # 36"): on Munich, where 47 % of the cells are few-hit cells, it takes the map's mean error from
    # -1.8 to -0.6 dB and p95 from 16.5 to 12.5 dB for 1.2x the time (twice the rays: 1.7x, -1.3 and
    # 14.4 dB); where few cells need it (the street canyon's 8 %, urban's 22 %) more rays buy more at
    # its cost. The share is counted at 1e7 rays whatever num_rays (ckm/gather.py).
    diffuse_gather: Literal["auto"] | bool = Field(
        "auto", description="fast mode, with diffuse reflection: in cells whose effective number of ray hits "
        "stays below 10 (or that no ray reached), estimate the last diffuse reflection again by gathering "
        "from the cell (photons of a second pass of a quarter of num_rays, 256 gather rays a cell) and "
        "weigh it with the rays' estimate by their relative variances; 'auto': only where those cells are "
        "at least 25 % of the cells outside the mask (counted at 1e7 rays)")
    # Guided gathering (ckm/gather.py guide_faces): 8 pilot rays a gather point find the faces the
    # transmitter lights directly, and 8 of its 16 gather rays go to points drawn on them (multiple
    # importance sampling with the other 8 uniform: unbiased whatever the guide). On Munich's 20
    # benchmark cells against a PathSolver reference of 4 seeded runs (docs/ckm-one-pass.md
    # "Session 43"): where that reference has settled in gain and best beam, gain p95 8.1 -> 5.3 dB,
    # largest error 21.7 -> 5.7 dB, best beam 83 -> 94 %, for about 1.1x the one-pass's time.
    gather_guided: bool = Field(
        True, description="fast mode, with the diffuse gather: aim half the gather rays at the faces the "
        "transmitter lights directly that pilot rays from the cell and its neighbours found (multiple "
        "importance sampling with the uniform half); false: uniform gather rays")
    adaptive_max_rays: int | None = Field(
        None, ge=1_000, description="fast mode: where more than max_undersampled_fraction of the reached "
        "cells have fewer than min_hits_for_power hits, the pass is rerun with 4x the rays while that "
        "stays within this many (docs/ckm-one-pass.md); None: one pass of num_rays")
    max_undersampled_fraction: float = Field(
        0.05, ge=0, le=1, description="fast mode, with adaptive_max_rays: the share of reached cells "
        "left masked for too few hits that stops the refinement")
    weathers: tuple[WeatherName, ...] | None = Field(
        None, description="weathers whose radio materials get a map (default: the scene's); weathers "
        "with equal materials share one map")

    @field_validator("size_m")
    @classmethod
    def _size(cls, v):
        if not all(0 < s <= MAX_GRID_SIDE_M for s in v):
            raise ValueError(f"size_m: each side must be within (0, {MAX_GRID_SIDE_M:g}] m")
        return v

    @field_validator("tiles")
    @classmethod
    def _tiles(cls, v):
        if not (1 <= v[0] <= MAX_TILES_PER_AXIS and 1 <= v[1] <= MAX_TILES_PER_AXIS):
            raise ValueError(f"tiles per axis must be within 1..{MAX_TILES_PER_AXIS}")
        return v

    @model_validator(mode="after")
    def _heights(self):
        if self.height_m is not None and self.heights_m is not None:
            raise ValueError("give height_m or heights_m, not both")
        if self.heights_m is not None and (not self.heights_m or len(set(self.heights_m)) != len(self.heights_m)):
            raise ValueError("heights_m: at least one height, none repeated")
        if self.region_m is not None and len(self.region_m) < 3:
            raise ValueError("region_m: a polygon needs at least three vertices")
        if self.adaptive_max_rays is not None and self.adaptive_max_rays < self.num_rays:
            raise ValueError(f"adaptive_max_rays ({self.adaptive_max_rays:,}) is below num_rays "
                             f"({self.num_rays:,}): give at least num_rays, or null for one pass")
        cells = self.shape[0] * self.shape[1] * len(self.heights)
        if cells > MAX_CELLS:
            raise ValueError(f"the grid has {cells:,} cells (size_m / cell_size_m per side, times the heights); "
                             f"at most {MAX_CELLS:,}: make cell_size_m larger or the grid smaller")
        return self

    @property
    def heights(self) -> tuple[float, ...]:
        """Receiver heights (m): ``heights_m``, else ``(height_m,)``, else 1.5 m."""
        if self.heights_m is not None:
            return tuple(self.heights_m)
        return (1.5 if self.height_m is None else self.height_m,)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows along y, cols along x)."""
        return (max(1, round(self.size_m[1] / self.cell_size_m)),
                max(1, round(self.size_m[0] / self.cell_size_m)))
