"""The one-pass CKM solver against PathSolver and RadioMapSolver, per scene and mechanism set.

    python -m benchmarks.ckm_solver [--quick] --out DIR [--scenes ...] [--sets ...]

Scenes (:data:`SCENES`): Sionna RT's street canyon (its whole footprint) and Munich (300 m x 300 m
around the station), both shipped with sionna-rt, and the project's own OSM scene ``scenes/urban``
(its radio mesh built as ``simart scene build`` / the ``paired_meshes`` asset build it, into a
temporary folder; the grid is the scene's CKM footprint, the transmitter its ``bs0``). A 2 m grid at
1.5 m, one 8 x 8 tr38901 base station with the 64-beam DFT codebook, depth 3.

Mechanism sets (:data:`MECHANISM_SETS`): ``los_specular`` (LoS + specular reflection, issue 8's
benchmark), ``diffraction`` (+ wedge diffraction) and ``all`` (+ wedge and edge diffraction,
diffuse reflection and refraction). The scenes' materials scatter nothing (Sionna's and the
project's radio materials have a scattering coefficient of 0, so diffuse reflection would be a
no-op): the ``all`` set gives every material ``S =`` :data:`ALL_SCATTERING_COEFFICIENT` (Sionna's
default Lambertian pattern), for both solvers. Each set is a scene config (:func:`_config`) whose
``ray_tracing`` switches drive the one-pass call, PathSolver (``RadioScene.trace``) and
RadioMapSolver (:func:`simart_pipeline.ckm.radiomap.radio_map_path_gain_db`) alike.

Per scene and set:

- the one-pass solver (:func:`simart_pipeline.ckm.one_pass.one_pass_moments`, 1e7 rays, iso V
  receiver) fills every cell;
- PathSolver (deterministic, ``samples_per_src`` :data:`REFERENCE_SAMPLES` of the set, iso V receiver,
  the set's mechanisms) traces
  n x n points (:data:`REFERENCE_POINTS_PER_SIDE` of the set: 3 x 3, 5 x 5 with diffraction) of a random sample of cells that lie wholly outside buildings (the same random order
  of those cells for every set; a set's sample is the first :data:`COMPARE_CELLS` of it); the
  middle point is the cell centre. Both reduce to the same moments
  (:mod:`simart_pipeline.ckm.moments`), so the layers compare by definition;
- **coverage**: of the sampled cells where PathSolver finds a path (at any of the n x n points),
  the share where the one-pass layers hold a value (at least ``ckm.min_hits_for_power`` ray hits);
  for the cells it misses, PathSolver's power per interaction sequence (``R`` specular, ``S``
  diffuse, ``T`` refraction, ``D`` diffraction, in path order) and the share of it in paths the
  one-pass does not trace (two interactions, or a diffuse or refracting one, before the diffraction);
- **errors** ``|one-pass - PathSolver|`` over the sampled cells where both hold a value: p50 / p95
  of path gain (dB), ToA, RMS delay spread (ns), the four angular spreads (deg), LoS and best-beam
  agreement (%), and top-3 agreement (PathSolver's best beam among the one-pass's three best), against
  the centre and against the n x n points pooled (their paths together, each point weighted 1/n^2:
  the gain is their mean). The cell layers are judged against the n x n points (ToA at the centre,
  the layer's definition);
- **the reference's convergence** (the sets of :data:`REFERENCE_CHECK_SETS`): PathSolver finds a
  wedge, and a diffusely reflecting point, only where its samples hit it, so the centres of the
  cells with the largest gain errors are traced again at :data:`REFERENCE_CHECK_SAMPLES` samples
  (:func:`reference_check`: gains and best beams against both references), and
  the centres of a random subset of the compared cells at :data:`CONVERGED_REFERENCE_SAMPLES`
  (:func:`against_converged_reference`: the errors against a reference whose reflection-diffraction
  chains have converged further; with diffuse reflection its diffuse paths from a deterministic run
  at :data:`CONVERGED_DIFFUSE_SAMPLES`; ``--converged-points 9``: at 3 x 3 points per cell, about
  4x the time, Munich 143 s a cell against 36 s at the centre; the errors also split by whether
  that reference has settled in the cell, traced again with a tenth of its samples,
  :func:`settled_cells`, at the points too with ``--converged-points 9``; ``--converged-seeds K``:
  the union of K seeded runs' paths instead of one run, settled by its two halves,
  :data:`CONVERGED_SEEDS`; and each layer where it has settled in that layer,
  :func:`settled_by_layer`: gain, ToA and beams where gain and best beam have, spreads where every
  layer has, ``targets_met_where_converged_reference_settled_by_layer``);
- **speed**: the one-pass time for the whole grid (warm: kernels compiled), one PathSolver call per
  cell (timed on random outdoor cells, at most :data:`LOOP_CELLS` calls or :data:`LOOP_BUDGET_S`
  seconds, and extrapolated to the grid's cells with outdoor area, which the reference mode would
  trace) and PathSolver batched over receivers (the n x n run, per receiver);
  ``speedup_vs_per_cell_loop`` and ``speedup_vs_batched_pathsolver`` are ratios of those times.

Against Sionna's RadioMapSolver, side by side in the same run, on the same grid (cell size, centre,
height), the same transmitter and orientation, the set's mechanisms, depth 3, one element of the
tr38901 pattern:

- what each path gain is: RadioMapSolver's is the mean over the cell's whole area of the ray tubes'
  power crossing it, ``|E|^2`` (an isotropic receiver blind to polarisation: it ignores the scene's
  receive array), Monte-Carlo over ``samples_per_tx`` rays; the one-pass layer is the same ray-tube
  cell mean, but over the cell's outdoor area (it divides by that share and masks cells less than
  half outdoor) and, for the PathSolver comparison, projected on a V element. So the like-for-like
  run is a second one-pass run with ``rx_polarization=None`` (``|E|^2``), its gain taken back to
  the whole cell area (``+ 10 log10(outdoor share)``), compared over the cells both cover;
- speed: RadioMapSolver warm (a second call: the first compiles) at its default ``samples_per_tx``
  (1e6) and at the one-pass's ray count; ``one_pass_over_radio_map_time`` is the one-pass warm time
  (every layer, 64 beams) over RadioMapSolver's (path gain only) at the same ray count, each the
  fastest of its warm call and :data:`SIDE_BY_SIDE_ROUNDS` more calls made in turn with the other
  solver's (not in ``--quick``, which times first calls).
- the same mechanisms, not the same paths: with diffraction RadioMapSolver diffracts only the
  transmitter's own rays, into the grid, with no reflection before or after the wedge. The
  like-for-like path gain (``path_gain_agreement_like_for_like``, which the target reads) is a
  third one-pass run restricted to that model (``diffraction_with_reflections=False``); the full
  run's difference is reported beside it. RadioMapSolver with another seed at the same rays gives
  the two Monte-Carlo runs' own spread (an exact map would differ from one run by about 1/sqrt(2)
  of it).
- at equal Monte-Carlo error (the sets of :data:`EQUAL_ERROR_SETS`, :func:`equal_error_front`; full
  runs without ``--no-converged-map`` only, so not in ``simart bench``: about 6 min per scene):
  each solver's map at 1e6 .. 1e7 rays against its own map at 1e8 rays (RadioMapSolver's at
  another seed), and the time of the fewest one-pass rays that reach RadioMapSolver's p50, p95 and
  coverage at the main ray count, over RadioMapSolver's time there; the two models like for like
  at 1e8 rays, where the Monte-Carlo floor of the path gain comparison is sqrt(10) lower.
- where both converge: :mod:`benchmarks.radio_map_agreement` (RadioMapSolver at 1e9 rays as the
  mean of ten seeded runs, also judged on the cells where that mean's standard error is at most
  0.05 dB; about an hour on 2 cores, so not part of this benchmark).

Ray count against error (the sets of :data:`SWEEP_SETS`; above the main ray count only on the scenes
it names): the one-pass (V, as against PathSolver) and RadioMapSolver at 1e5 .. 1e8 rays
(``--quick``: up to 1e7), each timed warm and compared with
the same PathSolver reference (the n x n points pooled and the centre): coverage (share of the cells
at least half outdoor that hold a path gain, and share of the sampled cells PathSolver reaches),
path gain p50 / p95, and for the one-pass ToA, RMS delay spread and best beam. A count whose time,
extrapolated linearly from the previous count's, would pass ``MAX_POINT_S`` is not run (the
results say so). RadioMapSolver has no delays or beams; being polarisation-blind, it differs from
the V reference on reflected paths by their cross-polar share. The plot
``DIR/ckm_rays_vs_error.png`` draws the curves: path gain p50 error and coverage against warm time.

Timing: ``los_specular`` keeps issue 8's :data:`WARM_REPEATS` timed calls after a compiling one;
the other sets one (their calls take ten times longer); ``--quick`` times their first call only
(compilation included: a small share of a call with diffraction). Above the main ray count every
solver is timed once.

Writes ``DIR/results.json``, ``DIR/report.md`` and the plot. ``--quick`` samples fewer cells and
runs the street canyon only when ``simart bench --quick`` runs it (a few minutes on 2 cores); the
main one-pass runs keep their 1e7 rays.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import platform
import tempfile
import time
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from scipy.constants import c as SPEED_OF_LIGHT

from simart_pipeline import engine
from simart_pipeline.ckm import one_pass as op
from simart_pipeline.ckm.gather import DEFAULT_GATHER_PILOT_DIRECTIONS
from simart_pipeline.ckm.moments import CellMoments, layers_from_moments, path_moments
from simart_pipeline.config import SceneConfig
from simart_pipeline.link.beams import dft_codebook
from simart_pipeline.vocabulary import InteractionKind

ROOT = Path(__file__).resolve().parents[1]

# Grids: the canyon's whole footprint; 300 m x 300 m of Munich around the base station; the urban
# scene's CKM footprint (scenes/urban/scene.yaml's ckm) with its bs0 (position, orientation).
# ``reference_samples``: a scene's own PathSolver samples for a set, where REFERENCE_SAMPLES' would
# cost too much (Munich with diffraction at 1e6: 469 s for the 200 cells' 3 x 3 points against 63 s,
# and its far chains need more than 1e8 anyway, docs/ckm-one-pass.md "Session 15"; its converged
# check is the 1e8 subset).
SCENES = {
    "street_canyon": dict(attr="simple_street_canyon", tx=(-40.0, 0.0, 20.0), yaw_pitch_deg=(0.0, 10.0),
                          centre=(0.0, 0.0), size=(188.0, 122.0)),
    "munich": dict(attr="munich", tx=(8.5, 21.0, 27.0), yaw_pitch_deg=(62.0, 10.0),
                   centre=(8.5, 21.0), size=(300.0, 300.0), reference_samples={"diffraction": 100_000}),
    "urban": dict(project="urban", tx=(-60.0, -48.0, 20.0), yaw_pitch_deg=(45.0, 0.0),
                  centre=(0.0, 0.0), size=(200.0, 160.0)),
}
HEIGHT_M = 1.5
CELL_M = 2.0
MAX_DEPTH = 3
# PathSolver's samples per source for the main reference and the per-cell loop, per set. 1e5
# finds every specular path (1e4 ... 1e7 give the same ones). With diffraction it misses the
# (diffraction, reflection) chains that leave a wedge into the lit region: on the street canyon
# at (13, -42) m a -113.7 dB D-R path (half the cell's power) appears at 1e6 and stays up to 4e8,
# and the 200 sampled cells' gain error falls from p95 2.36 to 1.08 dB, best beam 91 -> 94 %
# (urban: 89.9 -> 96.0 %). With diffuse reflection ("all") PathSolver's diffuse paths are a
# sampling of the lit surfaces: at 1e5 samples a far Munich cell held 4 of them, at 1e6 30-85, and
# the 1e5 reference picked another best beam than the 1e6 one at 7 of 39 centres (docs/ckm-one-pass.md
# "Session 23"). 1e6 costs 0.7-1.7 s per receiver since duplicate paths are found per primitive
# sequence (20 s in session 16, when that search compared every pair).
REFERENCE_SAMPLES = {"los_specular": 100_000, "diffraction": 1_000_000, "all": 1_000_000}
# Points per side of the square grid of PathSolver receivers that estimates a cell's mean (odd: the
# centre among them), per set. The layers are ray-tube means over the cell; with diffraction the
# beams of a cell near a shadow boundary are close (near-ties within 0.1 - 1.5 dB), and 3 x 3 points
# choose another best beam than 5 x 5 in 2.0 % of the street canyon's 200 cells, 2 of the 5 points
# the 95 % target leaves: the one-pass agrees with 5 x 5 (and 6 x 6) in 96.0 %, with 3 x 3 in 94.0 %
# (2.5x the reference's time). Specular paths vary little within a 2 m cell: 3 x 3.
REFERENCE_POINTS_PER_SIDE = {"los_specular": 3, "diffraction": 5, "all": 3}
# With diffuse reflection, where a scene's reference samples for the set are fewer than these, the
# reference merges two PathSolver runs of the same receivers: every path without a diffuse
# reflection from a run with diffuse reflection off at these samples (diffraction needs 1e6,
# above), and the diffuse paths from the run at the set's samples (:func:`merged_paths`).
REFERENCE_NON_DIFFUSE_SAMPLES = 1_000_000
SPREADS = ("asa_deg", "asd_deg", "zsa_deg", "zsd_deg")
RAY_COUNTS = (10**5, 10**6, 10**7, 10**8)
QUICK_RAY_COUNTS = (10**5, 10**6, 10**7)
RADIO_MAP_DEFAULT_SAMPLES = 10**6  # RadioMapSolver's own default samples_per_tx
MAX_POINT_S = 300.0  # a ray count predicted to take longer than this (one solver call) is not run
SIDE_BY_SIDE_ROUNDS = 2  # one-pass and RadioMapSolver timed again in turn (_against_radio_map)
WARM_REPEATS = 2  # los_specular: timed calls (best kept) at up to the main ray count; above it, one

# The ray_tracing switches of each mechanism set (LoS and specular reflection: RayTracing's
# defaults; the others named in every set, since the defaults turn diffraction on).
SWITCHES = ("los", "specular_reflection", "diffraction", "edge_diffraction", "diffuse_reflection", "refraction")
MECHANISM_SETS = {
    "los_specular": {"diffraction": False, "edge_diffraction": False, "diffuse_reflection": False},
    "diffraction": {"diffraction": True, "edge_diffraction": False, "diffuse_reflection": False},
    "all": {"diffraction": True, "edge_diffraction": True, "diffuse_reflection": True, "refraction": True},
}
SET_LABELS = {"los_specular": "LoS + specular", "diffraction": "+ wedge diffraction",
              "all": "+ wedge and edge diffraction, diffuse reflection (S 0.3), refraction"}
# Every material's scattering coefficient in the "all" set (the scenes' own is 0: nothing to scatter).
ALL_SCATTERING_COEFFICIENT = 0.3
# Sets with a ray-count sweep, and the scenes where it goes above the main ray count (with
# diffraction a 1e8-ray pass of either solver takes minutes: the street canyon alone).
SWEEP_SETS = {"los_specular": tuple(SCENES), "diffraction": ("street_canyon",)}
# Sampled cells per set (quick, full). PathSolver with diffuse reflection at 1e6 samples finds up to
# 25,000 paths per receiver (0.7-1.7 s each, 2 cores): the "all" set's sample is the small one.
COMPARE_CELLS = {"los_specular": (40, 600), "diffraction": (12, 200), "all": (12, 40)}
# The reference's own convergence where diffraction is on: PathSolver finds a wedge only where its
# samples hit it, and at 1e5 samples it misses first-order diffracted paths that 1e6 and 1e7 find
# (urban scene: cells 30-50 dB below the one-pass, which 1e6 samples bring to it; Munich, 200 cell
# centres: 1e5 against 1e7 samples p95 16 dB, 1e6 against 1e7 p95 6 dB). A whole 1e7-sample
# reference costs 4.9 s per receiver (9 points x 200 cells: 2.5 h): the centres of the cells with
# the largest gain errors are traced again at REFERENCE_CHECK_SAMPLES. With diffuse reflection too:
# on Munich PathSolver's far diffuse paths are still a few samples at 1e6 (its best beam agrees with
# its own 1e7 one at 74 % of 39 centres, docs/ckm-one-pass.md "Session 23"); 1e7 costs about 11 s a
# receiver there.
REFERENCE_CHECK_SETS = ("diffraction", "all")
REFERENCE_CHECK_CELLS = (3, 10)  # (quick, full)
REFERENCE_CHECK_SAMPLES = 10**7
# A converged reference: with diffraction PathSolver finds reflection-diffraction-reflection chains
# only with ~1e8 samples (two Munich cells: the 1e6 / 1e7 references 73 and 40 dB below the
# one-pass, 1e8 within 0.1 dB of it; not everywhere: at a Munich cell whose chains run from corners
# 250-320 m away, R-D-R and D-R-R still grew 7-12 dB from 1e8 to 5e8 samples, docs/ckm-one-pass.md
# "Session 15"). The centres of a random subset of the compared cells (the
# first CONVERGED_REFERENCE_CELLS of the random order) are traced at CONVERGED_REFERENCE_SAMPLES with
# Sionna's default (non-deterministic) candidate generator: the deterministic one holds 48 B x depth
# x samples per receiver (14 GB at 1e8) and costs 4 s per receiver at 1e7 on Munich, the default
# one 5 s at 1e8. Centres only (9 points per cell would cost 9x): a cell whose shadow edge crosses
# it differs at its centre from its mean, so these errors bound the one-pass's from above.
CONVERGED_REFERENCE_SETS = ("diffraction", "all")
CONVERGED_REFERENCE_CELLS = (4, 40)  # (quick, full)
CONVERGED_REFERENCE_SAMPLES = 10**8
# With diffuse reflection the converged reference merges two runs (merged_paths): the diffuse paths
# of a deterministic run at CONVERGED_DIFFUSE_SAMPLES (PathSolver makes one per sampled hit on a lit
# surface: 1e8 samples would hold ten times 1e7's paths per receiver, up to 250,000 on the canyon,
# every antenna pair), every other path of a default-generator run at CONVERGED_REFERENCE_SAMPLES
# with diffuse reflection off. Munich, 40 cells of the every-mechanism set at their centres: the
# 1e6 reference is 21.2 dB p95 from this one and picks another best beam in 26 % of them; 28 s per
# receiver. Below -110 dB it is still a few heavy-tailed samples (docs/ckm-one-pass.md, "Session
# 34"). Traced CONVERGED_CELLS_PER_TRACE cells at a time.
CONVERGED_DIFFUSE_SAMPLES = 10**7
CONVERGED_CELLS_PER_TRACE = 2
# Which of those cells the converged reference has itself settled in: the same cells traced again
# with 1 / CONVERGED_SETTLE_FACTOR of its samples (both runs'); a cell has settled where both traces
# reach it, its path gain moves within the sampling check's tolerance (radio.convergence: 1 dB), its
# RMS delay spread by at most CONVERGED_SETTLE_DELAY_SPREAD_S and its best beam stays. The errors are
# also given on those cells alone: elsewhere (Munich's cells behind the station, 17-23 dB apart
# between 1e6 and 1e7 diffuse samples, session 34) a difference says how far PathSolver is from its
# own limit as much as how far the one-pass is from it.
CONVERGED_SETTLE_FACTOR = 10
# The sampling check's spread rule, max(10 ns, 20 %), lets a 100 ns spread move by 20 ns, four times
# the 5 ns p50 that issue 17 asks of the one-pass: a reference moving that much cannot judge it
# (Munich's (41.5, 14) m cell moved 25 ns and counted settled, session 41). So the benchmark asks its
# reference to move by no more than that target: the finer trace, with ten times the samples, is then
# within about a third of it (its error about 1/sqrt(10) of the coarser one's).
CONVERGED_SETTLE_DELAY_SPREAD_S = 5e-9
# --converged-seeds K (even): the converged reference from K seeded runs instead of one, for cells
# where one run of 1e8 samples has not settled (Munich's behind the station). PathSolver's specular,
# refracted and diffracted paths are exact once its samples find their chain (the image method on the
# chain), so more samples only find more of them: the distinct paths of K runs with other seeds
# (:func:`union_of_runs`) are what one run of K times the samples finds. Its diffuse paths are a
# Monte-Carlo estimate: the mean of K seeded runs (:func:`mean_of_runs`). The cell has settled where
# the first K / 2 runs and the last K / 2, two independent references, agree (:func:`settled_cells`);
# the reference judged is all K. Cost: K times one run (one run and its settle trace: 1.1 times).
CONVERGED_SEEDS = 1
# The estimator's own convergence, apart from PathSolver's: the one-pass map against the same
# solver's map with CONVERGED_SAMPLES_FACTOR times the diffraction samples and point deposits (the
# unbiased estimator; on Munich its 8x map is within 1.7 dB p95 of its 32x one), and the point
# estimator at the default samples beside it (docs/ckm-one-pass.md, "Session 12").
CONVERGED_MAP_SETS = ("diffraction",)
# Time at equal Monte-Carlo error against RadioMapSolver (equal_error_front): each solver's map at
# these ray counts (and the main one) against its own at the reference's rays (quick, full; quick:
# not run, its minutes would double; skipped with --no-converged-map too, as in `simart bench`)
EQUAL_ERROR_SETS = ("all",)
EQUAL_ERROR_COUNTS = (10**6, 2 * 10**6, 3 * 10**6, 5 * 10**6)
EQUAL_ERROR_REFERENCE_RAYS = (0, 10**8)
CONVERGED_SAMPLES_FACTOR = (4, 16)  # (quick, full)
# The second pass on undersampled cells (ckm.diffraction_resample_factor): its run-time/error front,
# beside the converged map (off by default: docs/ckm-one-pass.md, "Session 15")
SECOND_PASS_FACTORS = (4, 8)
LOOP_CELLS = (6, 30)          # single PathSolver calls timed per set, at most (quick, full) ...
LOOP_BUDGET_S = (10.0, 20.0)  # ... or until this many seconds have passed (at least MIN_LOOP_CALLS)
MIN_LOOP_CALLS = 3

# Issue 8's targets, and issue 17's (benchmarks.targets reads them too).
TARGET_SPEEDUP_VS_LOOP = 100.0
TARGET_GAIN_P50_DB = 0.5
TARGET_TOA_P50_NS = 1.0
TARGET_BEST_BEAM_PCT = 95.0
TARGET_RADIO_MAP_TIME_RATIO = 2.0
TARGET_RADIO_MAP_GAIN_P50_DB = 0.1
TARGET_COVERAGE_PCT = 99.0
TARGET_GAIN_P95_DB = 3.0
TARGET_DELAY_SPREAD_P50_NS = 5.0
TARGET_SPREAD_P50_DEG = 5.0
TARGET_TOP3_PCT = 99.0
TARGET_SETS = ("all",)  # the sets issue 17's targets are judged on ("with the mechanisms on")

# Interaction sequences' letters (PathSolver's interaction types)
_LETTERS = {int(InteractionKind.SPECULAR): "R", int(InteractionKind.DIFFUSE): "S",
            int(InteractionKind.REFRACTION): "T", int(InteractionKind.DIFFRACTION): "D"}


# --diffuse-gather: the one-pass's diffuse_gather
GATHER_CHOICES = {"on": True, "off": False, "auto": "auto"}


def reference_samples(spec: dict, mechanisms: str) -> int:
    """PathSolver's samples per source for the main reference and the per-cell loop of a set on a scene."""
    return int(spec.get("reference_samples", {}).get(mechanisms, REFERENCE_SAMPLES[mechanisms]))


def non_diffuse_samples(spec: dict, mechanisms: str, diffuse_reflection: bool) -> int | None:
    """Samples of the second PathSolver run whose paths without a diffuse reflection the reference
    takes (:func:`merged_paths`), or None where it takes them from its one run: diffuse reflection
    off, or the set's samples at least REFERENCE_NON_DIFFUSE_SAMPLES."""
    if not diffuse_reflection or reference_samples(spec, mechanisms) >= REFERENCE_NON_DIFFUSE_SAMPLES:
        return None
    return REFERENCE_NON_DIFFUSE_SAMPLES


@contextlib.contextmanager
def _samples(radio, samples: int, **settings):
    """PathSolver calls of ``radio`` at ``samples`` per source (and its other ``settings``, such
    as ``diffuse_reflection=False``) inside the block, its own after."""
    config = radio.solver_config
    radio.solver_config = config.model_copy(update={"samples_per_src": int(samples), **settings})
    try:
        yield radio
    finally:
        radio.solver_config = config


def _config(spec: dict, mechanisms: str = "los_specular") -> SceneConfig:
    """The scene's station (8 x 8 tr38901) at ``spec``'s position and orientation, its grid as the
    CKM grid (RadioMapSolver's), an iso V receiver, the ray-tracing switches of ``mechanisms``."""
    return SceneConfig.model_validate({
        "name": "ckm-benchmark", "source": {"kind": "procedural"},
        "origin": {"latitude_deg": 48.14, "longitude_deg": 11.58},
        "base_stations": [{"name": "bs", "position_m": list(spec["tx"]),
                           "orientation_deg": [spec["yaw_pitch_deg"][0], spec["yaw_pitch_deg"][1], 0.0],
                           "array": {"rows": 8, "cols": 8, "pattern": "tr38901"}}],
        "ckm": {"center_m": list(spec["centre"]), "size_m": list(spec["size"]), "cell_size_m": CELL_M,
                "height_m": HEIGHT_M, "tiles": [1, 1]},
        "platforms": [{"name": "rx", "kind": "pedestrian", "array": {"pattern": "iso", "polarization": "V"},
                       "trajectory": {"waypoints_m": [[0, 0, 1.5], [1, 0, 1.5]], "speed_mps": 1.0}}],
        "clock": {"duration_s": 1.0},
        "ray_tracing": {"max_depth": MAX_DEPTH, "samples_per_src": reference_samples(spec, mechanisms), "refraction": False,
                        **MECHANISM_SETS[mechanisms]},
    })


def _radio_xml(spec: dict, folder: Path) -> str:
    """The radio scene file: Sionna's bundled scene, or the project scene's radio mesh built into
    ``folder`` the way the ``paired_meshes`` asset builds it."""
    if "attr" in spec:
        import sionna.rt as rt

        return getattr(rt.scene, spec["attr"])
    from simart_pipeline.config import load_scene_config
    from simart_pipeline.scene import meshes
    from simart_pipeline.scene.build import paired_meshes_for_scene
    from simart_pipeline.scene.source import build_source_geometry

    scene_dir = ROOT / "scenes" / spec["project"]
    cfg = load_scene_config(scene_dir)
    paired_meshes_for_scene(cfg, scene_dir, build_source_geometry(cfg, scene_dir)).save(folder / spec["project"])
    return str(meshes.radio_scene_file(folder / spec["project"]))


def _radio_scene(xml: str, cfg: SceneConfig, mechanisms: str):
    """A RadioScene of ``cfg`` (its PathSolver switches); the ``all`` set's scattering materials."""
    from simart_pipeline.radio.tracer import RadioScene

    radio = RadioScene.from_config(xml, cfg)
    if mechanisms == "all":
        for mat in radio.scene.radio_materials.values():
            mat.scattering_coefficient = ALL_SCATTERING_COEFFICIENT
    return radio


def _reference_moments(paths, tau0_s: np.ndarray, codebook: np.ndarray, pool: int = 1) -> CellMoments:
    """PathSolver paths of ``cells * pool`` receivers (pool consecutive receivers per cell) as
    per-cell moments, the reference mode's definitions: gain = mean over antenna pairs of |a|^2."""
    a = paths.a[:, :, 0]  # [rx, rx_ant, tx_ant, path]
    power = (np.abs(a) ** 2).mean(axis=(1, 2)) / pool
    y = np.einsum("bn,rmnp->rmbp", codebook.astype(np.complex64), a)
    beam = (np.abs(y) ** 2).mean(1).transpose(0, 2, 1) / pool  # [rx, path, beam]
    ang = np.stack([paths.phi_r[:, 0], paths.theta_r[:, 0], paths.phi_t[:, 0], paths.theta_t[:, 0]], -1)

    def cells(v):  # [cells * pool, path, ...] -> [cells, pool * path, ...]; the cell count spelled
        # out: a batch where no receiver has a path has a path axis of length 0, which -1 cannot infer
        return v.reshape((v.shape[0] // pool, pool * v.shape[1]) + v.shape[2:])

    return path_moments(cells(power), cells(paths.tau_s[:, 0]), cells(paths.valid[:, 0]), cells(paths.los[:, 0]),
                        cells(ang), tau0_s, cells(beam))


def _percentiles(err: np.ndarray) -> dict[str, float | int]:
    err = err[np.isfinite(err)]
    if err.size == 0:
        return {"p50": None, "p95": None, "n": 0}
    return {"p50": round(float(np.percentile(err, 50)), 4), "p95": round(float(np.percentile(err, 95)), 4),
            "n": int(err.size)}


def map_agreement(a_db: np.ndarray, b_db: np.ndarray) -> dict:
    """Two path-gain maps (dB, NaN where a map has no value): how many cells each covers, how many
    both, and p50 / p95 of ``|a - b|`` over the cells both cover."""
    a, b = np.isfinite(a_db), np.isfinite(b_db)
    return {"cells_a": int(a.sum()), "cells_b": int(b.sum()), "cells_both": int((a & b).sum()),
            "abs_diff_db": _percentiles(np.abs(a_db - b_db)[a & b])}


def _curve_point(e: dict) -> dict:
    """The figures of a :func:`_compare` result that the ray-count curves keep."""
    return {"cells_in_both": e["cells_with_paths_in_both"], "path_gain_db": e["path_gain_db"],
            "toa_ns_p50": e["toa_ns"]["p50"], "rms_delay_spread_ns_p50": e["rms_delay_spread_ns"]["p50"],
            "best_beam_agreement_pct": e["best_beam_agreement_pct"],
            "best_beam_top3_agreement_pct": e.get("best_beam_top3_agreement_pct")}


def _compare(fast: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> dict:
    """Errors over the cells where both hold a value (``has_path``); ``best_beam_top3_agreement_pct``
    (where ``fast`` has ``beam_gain_db`` [cells, beams]): the reference's best beam is among the
    fast layer's three best."""
    both = fast["has_path"] & ref["has_path"]
    out = {"cells": int(len(both)), "cells_with_paths_in_both": int(both.sum()),
           "cells_with_paths_only_in_one": int((fast["has_path"] != ref["has_path"]).sum())}
    out["path_gain_db"] = _percentiles(np.abs(fast["path_gain_db"] - ref["path_gain_db"])[both])
    for k in ("toa_s", "rms_delay_spread_s"):
        out[k[:-2] + "_ns"] = _percentiles(1e9 * np.abs(fast[k] - ref[k])[both])
    for k in SPREADS:
        out[k] = _percentiles(np.abs(fast[k] - ref[k])[both])
    out["los_agreement_pct"] = round(100 * float((fast["los"] == ref["los"])[both].mean()), 2) if both.any() else None
    out["best_beam_agreement_pct"] = (round(100 * float((fast["best_beam"] == ref["best_beam"])[both].mean()), 2)
                                      if both.any() else None)
    if "beam_gain_db" in fast:
        top3 = np.argsort(-np.nan_to_num(fast["beam_gain_db"][both], nan=-np.inf), axis=1, kind="stable")[:, :3]
        out["best_beam_top3_agreement_pct"] = (
            round(100 * float((top3 == ref["best_beam"][both][:, None]).any(1).mean()), 2) if both.any() else None)
    # what taking the one-pass best beam costs in the reference's own beam gains (0 where they agree)
    bg = ref["beam_gain_db"][both]
    rows = np.arange(len(bg))
    out["best_beam_loss_db"] = _percentiles(bg[rows, ref["best_beam"][both]] - bg[rows, fast["best_beam"][both]])
    return out


def _timed(fn):
    """(fn(), seconds), Dr.Jit's queued work included."""
    import drjit as dr

    t = time.perf_counter()
    out = fn()
    dr.sync_thread()
    return out, time.perf_counter() - t


def _warm(fn, repeats: int = 1) -> tuple:
    """fn() once to compile its kernels, then ``repeats`` timed calls: (last result, first call s,
    fastest timed call s). Other work on a shared machine only ever adds time, hence the minimum.
    ``repeats`` 0: one call, its time (compilation included) the only one: (result, None, s)."""
    out, first_s = _timed(fn)
    if repeats == 0:
        return out, None, first_s
    runs = [_timed(fn) for _ in range(repeats)]
    return runs[-1][0], first_s, min(s for _, s in runs)


def _r3(v: float | None) -> float | None:
    return None if v is None else round(v, 3)


def _layers_at(m: op.OnePassMoments, pick: np.ndarray) -> dict[str, np.ndarray]:
    """One-pass layers at the flat cell indices ``pick``; spreads NaN below the hit minimums."""
    fast = m.layers()
    at = {k: v[0].ravel()[pick] for k, v in fast.items() if v.ndim == 3}
    at["best_beam"] = fast["best_beam"][0].ravel()[pick]
    if "beam_gain_db" in fast:
        at["beam_gain_db"] = fast["beam_gain_db"][0].reshape(-1, fast["beam_gain_db"].shape[-1])[pick]
    # A cell reached by fewer than min_hits_for_power rays holds no gain, ToA, LoS or beam (best
    # beam -1): it is not covered, and must not be compared as a cell with a value.
    at["has_path"] = at["enough_hits"]  # spreads: NaN already where the layers' spread minimums mask them
    return at


def _coverage_pct(gain_db: np.ndarray, eligible: np.ndarray) -> float:
    """Share of the eligible cells (at least half outdoor) that hold a path gain, %."""
    return round(100 * float(np.isfinite(gain_db[eligible]).mean()), 2)


def _covered_of_reached_pct(fast_has: np.ndarray, ref_has: np.ndarray) -> float | None:
    """Of the cells the reference reaches, the share where the fast layers hold a value, %."""
    return round(100 * float(fast_has[ref_has].mean()), 2) if ref_has.any() else None


def _one_pass_point(m: op.OnePassMoments, pick, refs: dict, eligible) -> dict:
    """A one-pass run against the PathSolver references (centre, n x n points)."""
    at = _layers_at(m, pick)
    return {"coverage_pct": _coverage_pct(m.layers()["path_gain_db"][0], eligible),
            "covered_of_reached_pct": _covered_of_reached_pct(at["has_path"], refs["vs_cell_points"]["has_path"]),
            **{k: _curve_point(_compare(at, ref)) for k, ref in refs.items()}}


def _radio_map_point(gain_db: np.ndarray, pick, refs: dict, eligible) -> dict:
    """A RadioMapSolver map against the PathSolver references' path gain (it has nothing else)."""
    g = gain_db.ravel()[pick]
    out = {"coverage_pct": _coverage_pct(gain_db, eligible),
           "covered_of_reached_pct": _covered_of_reached_pct(np.isfinite(g), refs["vs_cell_points"]["has_path"])}
    for k, ref in refs.items():
        a = map_agreement(g, ref["path_gain_db"])
        out[k] = {"cells_in_both": a["cells_both"], "path_gain_db": a["abs_diff_db"]}
    return out


def _sweep(counts, run, error_of) -> list[dict]:
    """Per ray count: ``run(n)`` -> (result, first call s, warm s), ``error_of(result)`` -> figures.
    A count whose warm time, extrapolated linearly from the last one run, would pass MAX_POINT_S
    is not run; its entry says why."""
    points, last = [], None
    for n in counts:
        predicted_s = last and last["warm_s"] * n / last["rays"]
        if predicted_s and predicted_s > MAX_POINT_S:
            points.append({"rays": n, "skipped": f"predicted {predicted_s:.0f} s per call > {MAX_POINT_S:.0f} s"})
            continue
        res, first_s, warm_s = run(n)
        last = {"rays": n, "first_call_s": _r3(first_s), "warm_s": round(warm_s, 3), **error_of(res)}
        points.append(last)
    return points


def _memo(fn):
    cache = {}
    return lambda n: cache[n] if n in cache else cache.setdefault(n, fn(n))


def sequence_name(key: int) -> str:
    """An interaction sequence packed 4 bits per bounce (first bounce lowest) as letters: ``R``
    specular, ``S`` diffuse, ``T`` refraction, ``D`` diffraction, in path order; ``LoS``: none."""
    letters = []
    while key:
        letters.append(_LETTERS.get(key & 0xF, "?"))
        key >>= 4
    return "-".join(letters) or "LoS"


def interaction_shares(interaction: np.ndarray, power: np.ndarray, valid: np.ndarray, pool: int,
                       cells: np.ndarray, top: int = 8) -> dict:
    """PathSolver's power per interaction sequence over the chosen cells.

    ``interaction`` [rx, depth, path] (``cells * pool`` receivers, ``pool`` consecutive per cell),
    ``power`` and ``valid`` [rx, path], ``cells`` bool [num_cells]. Per sequence: ``share_pct``, the
    mean over the chosen cells of its share of the cell's power, and ``paths``, its valid paths
    there; the ``top`` largest shares, largest first. ``untraced_pct``: p50 / p95 / mean over
    those cells of the power share of the paths the one-pass solver does not trace: a diffraction
    after two or more interactions, or after a diffuse reflection or a refraction (its diffracted
    rays start at the transmitter or at its image in one specular reflector)."""
    depth = interaction.shape[1]
    inter = interaction.astype(np.int64)
    key = sum(inter[:, k] << (4 * k) for k in range(depth))  # [rx, path]
    is_d = inter == int(InteractionKind.DIFFRACTION)
    late_diffraction = is_d[:, 2:].any(1)  # [rx, path]
    if depth >= 2:
        late_diffraction |= is_d[:, 1] & (inter[:, 0] != int(InteractionKind.SPECULAR))

    def per_cell(v):  # the cell count spelled out, as in _reference_moments (an empty path axis)
        return v.reshape(v.shape[0] // pool, pool * v.shape[1])[cells]

    p = per_cell(np.where(valid, power, 0.0))
    tot = p.sum(-1, keepdims=True)
    share = p / np.where(tot > 0, tot, 1.0)
    n_cells = int(cells.sum())
    if n_cells == 0:
        return {"cells": 0, "sequences": {}, "untraced_pct": _percentiles(np.array([]))}
    keys, inv = np.unique(per_cell(key), return_inverse=True)
    pct = 100 * np.bincount(inv.ravel(), weights=share.ravel(), minlength=len(keys)) / n_cells
    paths = np.bincount(inv.ravel(), weights=per_cell(valid).ravel().astype(float), minlength=len(keys))
    order = [i for i in np.argsort(-pct, kind="stable") if paths[i] > 0][:top]
    untraced = 100 * (share * per_cell(late_diffraction)).sum(-1)
    u = _percentiles(untraced)
    u["mean"] = round(float(untraced.mean()), 4)
    return {"cells": n_cells,
            "sequences": {sequence_name(int(keys[i])): {"share_pct": round(float(pct[i]), 2), "paths": int(paths[i])}
                          for i in order},
            "untraced_pct": u}


def coverage(fast_at: dict, refs: dict, paths, pool: int = 9) -> dict:
    """Of the sampled cells where PathSolver finds a path, how many the one-pass layers cover.

    ``fast_at``: :func:`_layers_at`; ``refs``: ``vs_cell_points`` and ``vs_centre`` layers; ``paths``: the
    reference run's TracedPaths or :class:`PathPowers` (``pool`` receivers per cell), whose
    interaction sequences say what the one-pass misses (``missed``) and what PathSolver finds in
    every cell it reaches (``reached``)."""
    fast_has, reached = fast_at["has_path"], refs["vs_cell_points"]["has_path"]
    missed = reached & ~fast_has
    pp = paths if isinstance(paths, PathPowers) else PathPowers.of(paths)
    power, inter, valid = pp.power, pp.interaction, pp.valid
    return {"sampled_cells": int(len(reached)), "reached_by_pathsolver": int(reached.sum()),
            "covered_of_reached_pct": _covered_of_reached_pct(fast_has, reached),
            "missed": int(missed.sum()),
            "missed_with_too_few_hits": int((missed & (fast_at["count"] > 0)).sum()),
            "covered_not_reached": int((fast_has & ~reached).sum()),
            "missed_pathsolver_gain_db": _percentiles(refs["vs_cell_points"]["path_gain_db"][missed]),
            "vs_centre": {"reached_by_pathsolver": int(refs["vs_centre"]["has_path"].sum()),
                          "covered_of_reached_pct": _covered_of_reached_pct(fast_has, refs["vs_centre"]["has_path"])},
            "pathsolver_interactions": {"reached": interaction_shares(inter, power, valid, pool, reached),
                                        "missed": interaction_shares(inter, power, valid, pool, missed)}}


def merged_paths(without_diffuse, with_diffuse):
    """One TracedPaths of the same receivers: every path of ``without_diffuse`` (a PathSolver run
    with diffuse reflection off) and the paths of ``with_diffuse`` (the same mechanisms with it on)
    that hold a diffuse reflection. The other paths of ``with_diffuse`` are ``without_diffuse``'s
    own (PathSolver's specular and diffracted paths do not depend on the diffuse switch), found with
    its samples; each path is counted once."""
    return _concat_paths([without_diffuse, diffuse_paths(with_diffuse)])


def _concat_paths(parts: list):
    """One TracedPaths of the same receivers holding every path of ``parts`` (along the path axis;
    a field that one part lacks, such as the vertices, is dropped)."""
    def cat(name):
        vs = [getattr(p, name) for p in parts]
        if any(v is None for v in vs):
            return None
        return np.concatenate(vs, axis=-2 if name == "vertices_m" else -1)

    return type(parts[0])(**{f.name: cat(f.name) for f in fields(parts[0])})


def union_of_runs(runs: list):
    """The distinct paths of PathSolver runs of the same receivers (each traced with vertices):
    a path that several runs found is kept once (:func:`~simart_pipeline.radio.tracer.drop_duplicate_paths`:
    the same interaction kinds and every vertex within its tolerance; the runs' object and primitive
    ids are not kept, and two paths whose every vertex agrees to a millimetre are one). The
    specular, refracted and diffracted paths of a run are exact once found, so this is what one run
    of the runs' samples together would find."""
    from simart_pipeline.radio.tracer import drop_duplicate_paths

    both = _concat_paths(runs)
    d = {f.name: getattr(both, f.name) for f in fields(both)}
    if d["vertices_m"] is None:
        raise ValueError("union_of_runs needs every run's vertices (trace with with_vertices=True)")
    d["objects"] = d["primitives"] = np.zeros(d["interaction"].shape, np.int64)
    kept = drop_duplicate_paths(d)
    return type(both)(**{f.name: kept.get(f.name) for f in fields(both)})


def mean_of_runs(runs: list):
    """Monte-Carlo estimates of the same receivers' paths (PathSolver's diffuse paths of seeded
    runs) as one: every run's paths, amplitudes scaled by ``1 / sqrt(len(runs))``, so that every
    power sum is the runs' mean."""
    scale = np.float32(1.0 / np.sqrt(len(runs)))
    both = _concat_paths(runs)
    return type(both)(**{f.name: (getattr(both, f.name) * scale if f.name == "a" else getattr(both, f.name))
                         for f in fields(both)})


def diffuse_paths(paths):
    """``paths`` with only the valid paths that hold a diffuse reflection valid."""
    diffuse = (paths.interaction == int(InteractionKind.DIFFUSE)).any(axis=-2) & paths.valid
    return type(paths)(**{f.name: diffuse if f.name == "valid" else getattr(paths, f.name) for f in fields(paths)})


def _slice_paths(paths, rows):
    """The TracedPaths of the receivers ``rows``."""
    return type(paths)(**{f.name: None if getattr(paths, f.name) is None else getattr(paths, f.name)[rows]
                          for f in fields(paths)})


def _cell_points(centres: np.ndarray, per_side: int = 3) -> np.ndarray:
    """``[cells * n * n, 3]`` (``n = per_side``, odd): the centres of each cell's n x n sub-cells,
    cell by cell, the middle one of each n * n the cell's centre."""
    if per_side % 2 != 1:
        raise ValueError(f"per_side must be odd (the cell's centre among the points), got {per_side}")
    offsets = (np.arange(per_side) - per_side // 2) * CELL_M / per_side
    ox, oy = (a.ravel() for a in np.meshgrid(offsets, offsets))
    return (centres[:, None, :] + np.stack([ox, oy, np.zeros(ox.size)], -1)[None]).reshape(-1, 3)


@dataclass
class PathPowers:
    """What :func:`coverage` reads of a reference run, per receiver and path: the power (mean over
    the antenna pairs), the interaction sequence and validity; a few MB where the run's amplitudes
    (every antenna pair) take GBs."""

    power: np.ndarray        # [rx, path]
    interaction: np.ndarray  # [rx, depth, path]
    valid: np.ndarray        # [rx, path]

    @classmethod
    def of(cls, paths) -> "PathPowers":
        """From a TracedPaths of one transmitter."""
        return cls((np.abs(paths.a[:, :, 0]) ** 2).mean(axis=(1, 2)), paths.interaction[:, 0], paths.valid[:, 0])

    @classmethod
    def concat(cls, parts: list["PathPowers"]) -> "PathPowers":
        """Receivers of several runs, their paths padded to the most (power 0, invalid)."""
        n = max(p.power.shape[-1] for p in parts)

        def pad(a):  # zeros: no power, no interaction, not valid
            return np.pad(a, [(0, 0)] * (a.ndim - 1) + [(0, n - a.shape[-1])])

        return cls(*(np.concatenate([pad(getattr(p, k)) for p in parts]) for k in ("power", "interaction", "valid")))


# Cells whose points one PathSolver trace of the reference holds. With diffuse reflection at 1e6
# samples a receiver holds up to 25,000 paths, and the amplitudes of 360 receivers at once (every
# antenna pair, padded to the most paths) took this 24 GB machine out of memory. (PathSolver's
# diffuse paths depend a little on which receivers share a call, as with RadioScene.trace's own
# batches: street canyon, 11 cells at 1e4 samples, 8 against all at once, gain at most 0.05 dB.)
REFERENCE_CELLS_PER_TRACE = 8


def _layers_in_parts(tx, centres, codebook, per_side: int, cells_per_trace: int, trace,
                     keep=None) -> tuple[dict, dict, float, list]:
    """``trace(points)`` (PathSolver paths) at n x n points in each cell (``n = per_side``, odd;
    1: the centres), ``cells_per_trace`` cells at a time, each part reduced to its layers as it
    comes (a part's paths, every antenna pair, can take GBs): (centre layers, pooled n x n layers,
    trace seconds, ``keep(paths)`` of each part). A ``trace`` that returns a tuple of paths (several
    references of the same points) gives a tuple of each layers."""
    tau0 = np.linalg.norm(centres - tx, axis=-1) / SPEED_OF_LIGHT
    centre_parts, pooled_parts, kept, trace_s, many = [], [], [], 0.0, False
    for lo in range(0, len(centres), cells_per_trace):
        part = slice(lo, lo + cells_per_trace)
        t = time.perf_counter()
        paths = trace(_cell_points(centres[part], per_side))
        trace_s += time.perf_counter() - t
        many = isinstance(paths, tuple)
        layers = [_centre_and_pooled_layers(p, tau0[part], codebook, per_side * per_side)
                  for p in (paths if many else (paths,))]
        centre_parts.append([c for c, _ in layers])
        pooled_parts.append([p for _, p in layers])
        if keep is not None:
            kept.append(keep(paths))
        del paths

    def cat(parts):  # parts: [part][reference] -> one layer dict per reference
        out = tuple({k: np.concatenate([p[i][k] for p in parts]) for k in parts[0][i]} for i in range(len(parts[0])))
        return out if many else out[0]

    return cat(centre_parts), cat(pooled_parts), trace_s, kept


def _pathsolver_reference(radio, tx, ori, centres, codebook, per_side: int = 3,
                          non_diffuse_samples: int | None = None) -> tuple[dict, dict, float, PathPowers]:
    """PathSolver at n x n points in each cell (``n = per_side``; the middle one its centre):
    (centre layers, pooled n x n layers, s per receiver of the batched runs, the runs'
    :class:`PathPowers`). ``non_diffuse_samples`` (diffuse reflection on): the paths without a
    diffuse reflection from a second run at these samples with it off (:func:`merged_paths`).
    Traced :data:`REFERENCE_CELLS_PER_TRACE` cells at a time, each part reduced to its layers."""
    def trace(points):
        paths = radio.trace(tx[None], ori[None], points)
        if non_diffuse_samples is not None and radio.solver_config.diffuse_reflection:
            with _samples(radio, non_diffuse_samples, diffuse_reflection=False):
                paths = merged_paths(radio.trace(tx[None], ori[None], points), paths)
        return paths

    at_centre, pooled, trace_s, powers = _layers_in_parts(tx, centres, codebook, per_side, REFERENCE_CELLS_PER_TRACE,
                                                          trace, PathPowers.of)
    return at_centre, pooled, trace_s / (len(centres) * per_side * per_side), PathPowers.concat(powers)


def _centre_and_pooled_layers(paths, tau0_s: np.ndarray, codebook, pool: int) -> tuple[dict, dict]:
    """Layers at the cell centres and over each cell's points pooled, from the paths of ``cells *
    pool`` receivers (:func:`_cell_points`' order: ``pool`` consecutive per cell, the middle one at
    offset (0, 0)); with ``pool`` 1 both are the centres'."""
    centre = paths if pool == 1 else _slice_paths(paths, slice(pool // 2, None, pool))
    at_centre = layers_from_moments(_reference_moments(centre, tau0_s, codebook))
    if pool == 1:
        return at_centre, at_centre
    return at_centre, layers_from_moments(_reference_moments(paths, tau0_s, codebook, pool=pool))


def reference_check(radio, tx, ori, centres_xyz: np.ndarray, fast_at: dict, ref_centre: dict, codebook,
                    cells: int, samples: int = REFERENCE_CHECK_SAMPLES) -> dict:
    """The ``cells`` sampled cells whose centre gain differs most from the one-pass layer, traced
    again at their centre with ``samples`` per source: |one-pass - PathSolver| p50 / p95 there
    against the main reference and against this one, and how many of those reference gains moved
    by more than 1 dB. ``centres_xyz`` [sampled cells, 3]; ``fast_at``, ``ref_centre``: layers."""
    both = fast_at["has_path"] & ref_centre["has_path"]
    err = np.where(both, np.abs(fast_at["path_gain_db"] - ref_centre["path_gain_db"]), -np.inf)
    worst = np.sort(np.argsort(-err, kind="stable")[:min(cells, int(both.sum()))])
    if worst.size == 0:
        return {"samples_per_src": samples, "cells": 0}
    with _samples(radio, samples):
        t = time.perf_counter()
        paths = radio.trace(tx[None], ori[None], centres_xyz[worst])
        s = time.perf_counter() - t
    tau0 = np.linalg.norm(centres_xyz[worst] - tx, axis=-1) / SPEED_OF_LIGHT
    again = layers_from_moments(_reference_moments(paths, tau0, codebook))
    fast_g, before = fast_at["path_gain_db"][worst], ref_centre["path_gain_db"][worst]
    after = np.where(again["has_path"], again["path_gain_db"], np.nan)
    fast_bb = np.where(fast_at["has_path"][worst], fast_at["best_beam"][worst], -1)

    def beams_agree_pct(ref_bb):
        both = (fast_bb >= 0) & (ref_bb >= 0)
        return round(100 * float((fast_bb[both] == ref_bb[both]).mean()), 1) if both.any() else None

    return {"samples_per_src": int(samples), "cells": int(worst.size), "s": round(s, 2),
            "abs_err_db_main_reference": _percentiles(np.abs(fast_g - before)),
            "abs_err_db_this_reference": _percentiles(np.abs(fast_g - after)),
            "reference_moved_gt_1_db": int((~(np.abs(after - before) <= 1.0)).sum()),
            "best_beam_agree_pct_main_reference": beams_agree_pct(
                np.where(ref_centre["has_path"][worst], ref_centre["best_beam"][worst], -1)),
            "best_beam_agree_pct_this_reference": beams_agree_pct(np.where(again["has_path"], again["best_beam"], -1)),
            "signed_err_db_main_reference": np.round(fast_g - before, 2).tolist(),
            "signed_err_db_this_reference": np.round(fast_g - after, 2).tolist()}


def settled_cells(coarse: dict, fine: dict, delay_spread_tolerance_s: float = CONVERGED_SETTLE_DELAY_SPREAD_S,
                  delay_spread: bool = True) -> np.ndarray:
    """The cells whose reference layers ``fine`` (more samples, :data:`CONVERGED_SETTLE_FACTOR`, or
    the last half of seeded runs) and ``coarse`` (the first half) agree: both reach the cell, its path gain agrees by the sampling
    checks' rule (:func:`simart_pipeline.radio.convergence.within_tolerance`), its RMS delay spread
    (where both hold one) by at most ``delay_spread_tolerance_s`` as well
    (:data:`CONVERGED_SETTLE_DELAY_SPREAD_S`), and the best beam is the same. ``delay_spread=False``:
    gain and best beam alone (the layers a far cell's few long paths leave settled while its spread
    still moves: where those are judged, :func:`settled_by_layer`)."""
    from simart_pipeline.radio.convergence import within_tolerance

    both = coarse["has_path"] & fine["has_path"]
    ds = np.stack([coarse["rms_delay_spread_s"], fine["rms_delay_spread_s"]])
    if not delay_spread:
        ds = np.full_like(ds, np.nan)
    agree = within_tolerance(np.stack([coarse["path_gain_db"], fine["path_gain_db"]]), ds)
    with np.errstate(invalid="ignore"):
        ds_ok = ~np.isfinite(ds).all(0) | (np.abs(ds[1] - ds[0]) <= delay_spread_tolerance_s)
    return both & agree & ds_ok & (coarse["best_beam"] == fine["best_beam"])


def settled_by_layer(fast_at: dict, ref: dict, coarse: dict, fine: dict) -> dict:
    """Each layer judged where the reference has settled in it: gain, ToA and the beams on the
    cells settled in gain and best beam (:func:`settled_cells` without the delay-spread rule), the
    delay and angular spreads on the cells settled in every layer. ``errors``: a :func:`_compare`
    result that merges the two (what :func:`targets` reads); the cells of each."""
    gain_and_beam = settled_cells(coarse, fine, delay_spread=False)
    every = settled_cells(coarse, fine)
    e_gb = _compare(_subset(fast_at, gain_and_beam), _subset(ref, gain_and_beam))
    e_all = _compare(_subset(fast_at, every), _subset(ref, every))
    merged = {**e_gb, "rms_delay_spread_ns": e_all["rms_delay_spread_ns"], **{k: e_all[k] for k in SPREADS}}
    return {"gain_and_beam_cells": int(gain_and_beam.sum()), "gain_and_beam_cell_index": np.flatnonzero(gain_and_beam).tolist(),
            "every_layer_cells": int(every.sum()), "errors": merged,
            "errors_unsettled_gain_and_beam": _compare(_subset(fast_at, ~gain_and_beam), _subset(ref, ~gain_and_beam))}


def per_cell_values(layers: dict) -> dict:
    """A cell's judged layers as plain lists (JSON; None where it holds none), so that a saved run
    can be judged again by another rule: path gain dB, ToA and RMS delay spread ns, best beam (-1:
    no path)."""
    has = np.asarray(layers["has_path"], bool)

    def col(v, scale=1.0):
        v = np.where(has, np.asarray(v, float) * scale, np.nan)
        return [round(float(x), 4) if np.isfinite(x) else None for x in v]

    return {"path_gain_db": col(layers["path_gain_db"]), "toa_ns": col(layers["toa_s"], 1e9),
            "rms_delay_spread_ns": col(layers["rms_delay_spread_s"], 1e9),
            "best_beam": np.where(has, layers["best_beam"], -1).astype(int).tolist()}


def _subset(layers: dict, sel: np.ndarray) -> dict:
    """The layers (arrays over cells first) of the cells ``sel`` (a boolean mask)."""
    return {k: v[sel] if isinstance(v, np.ndarray) and v.shape[:1] == sel.shape else v for k, v in layers.items()}


def against_converged_reference(radio, tx, ori, centres_xyz: np.ndarray, fast_at: dict, codebook,
                                samples: int = CONVERGED_REFERENCE_SAMPLES, points_per_cell: int = 1,
                                diffuse_samples: int = CONVERGED_DIFFUSE_SAMPLES,
                                settle_factor: int = CONVERGED_SETTLE_FACTOR, seeds: int = CONVERGED_SEEDS) -> dict:
    """PathSolver at ``samples`` per source (Sionna's default candidate generator) at the cell
    centres ``centres_xyz`` [cells, 3] (``points_per_cell`` 9: at 3 x 3 points per cell, like the main
    reference, about 4x the time): the one-pass layers ``fast_at`` of those cells against it
    (:func:`_compare`: at the centres, and against the 3 x 3 points pooled), the cells each
    reaches, and the time. With diffuse reflection on, the diffuse paths come from a deterministic
    run at ``diffuse_samples`` (:func:`merged_paths`, :data:`CONVERGED_DIFFUSE_SAMPLES`), traced
    :data:`CONVERGED_CELLS_PER_TRACE` cells at a time. With ``settle_factor`` > 1 the centres are
    traced again with 1 / ``settle_factor`` of both runs' samples, and the errors at the centres are
    also given on the cells where the two agree (:func:`settled_cells`); at 3 x 3 points per cell
    also the errors against the points pooled, on the cells whose pooled layers agree
    (``settled["cell_points"]``): a centre's delay spread can differ from its cell's by more than the
    issue's 5 ns (Munich, docs/ckm-one-pass.md "Session 41").

    ``seeds`` K > 1 (even; :data:`CONVERGED_SEEDS`): K runs of each kind with consecutive seeds from
    the radio scene's, every one traced: the reference is the union of their non-diffuse paths
    (:func:`union_of_runs`) and the mean of their diffuse paths (:func:`mean_of_runs`, seeded runs
    of the default generator instead of the deterministic one), and a cell has settled where the
    references of the first K / 2 runs and of the last K / 2 agree (``settle_factor`` unused)."""
    if points_per_cell not in (1, 9):
        raise ValueError(f"points_per_cell must be 1 or 9, got {points_per_cell}")
    if seeds < 1 or (seeds > 1 and seeds % 2):
        raise ValueError(f"seeds must be 1 or an even count (two halves to settle by), got {seeds}")
    diffuse = bool(radio.solver_config.diffuse_reflection)

    def tracer(n, n_diffuse):
        def trace(points):
            with _samples(radio, n, diffuse_reflection=False):
                paths = radio.trace(tx[None], ori[None], points, deterministic=False)
            if diffuse:
                with _samples(radio, n_diffuse):
                    paths = merged_paths(paths, radio.trace(tx[None], ori[None], points))
            return paths
        return trace

    def seeded(points):  # (all K runs, the first K / 2, the last K / 2)
        seed0, runs, diffuse_runs = int(radio.solver_config.seed), [], []
        for k in range(seeds):
            with _samples(radio, samples, diffuse_reflection=False, seed=seed0 + k):
                runs.append(radio.trace(tx[None], ori[None], points, deterministic=False, with_vertices=True))
            if diffuse:  # seeds of their own: independent of the runs above
                with _samples(radio, diffuse_samples, seed=seed0 + seeds + k):
                    diffuse_runs.append(diffuse_paths(radio.trace(tx[None], ori[None], points, deterministic=False)))

        def reference(sel):
            found = union_of_runs(runs[sel])
            return _concat_paths([found, mean_of_runs(diffuse_runs[sel])]) if diffuse else found

        return tuple(reference(sel) for sel in (slice(None), slice(None, seeds // 2), slice(seeds // 2, None)))

    per_trace = CONVERGED_CELLS_PER_TRACE if diffuse else len(centres_xyz)
    per_side = 1 if points_per_cell == 1 else 3
    if seeds > 1:
        (ref, first, last), (pooled, first_pooled, last_pooled), s, _ = _layers_in_parts(
            tx, centres_xyz, codebook, per_side, per_trace, seeded)
    else:
        ref, pooled, s, _ = _layers_in_parts(tx, centres_xyz, codebook, per_side, per_trace,
                                             tracer(samples, diffuse_samples))
    out = {"samples_per_src": int(samples), "generator": "default (non-deterministic)", "cells": int(len(centres_xyz)),
           "points_per_cell": points_per_cell, "s": round(s, 1), "seeds": int(seeds),
           "diffuse_samples_per_src": int(diffuse_samples) if diffuse else None,
           "diffuse_generator": None if not diffuse else ("deterministic" if seeds == 1 else "default (non-deterministic)")}
    out.update(reached_by_pathsolver=int(ref["has_path"].sum()),
               covered_of_reached_pct=_covered_of_reached_pct(fast_at["has_path"], ref["has_path"]),
               errors_vs_centre=_compare(fast_at, ref))
    # every cell's values, so that a saved run can be judged again by another rule
    out["per_cell"] = {"centre_m": np.round(np.asarray(centres_xyz, float), 3).tolist(),
                       "one_pass": per_cell_values(fast_at), "reference_centre": per_cell_values(ref)}
    if points_per_cell == 9:
        out["per_cell"]["reference_cell_points"] = per_cell_values(pooled)
    settle = None  # (coarse, fine, their pooled layers, what the settled cells' record says of them)
    if seeds > 1:
        half = seeds // 2
        settle = (first, last, first_pooled, last_pooled,
                  {"by": f"the references of the first {half} and the last {half} of {seeds} seeded runs",
                   "samples_per_src": int(samples * half),
                   "diffuse_samples_per_src": int(diffuse_samples * half) if diffuse else None, "s": None})
        out["per_cell"].update(first_half_centre=per_cell_values(first), last_half_centre=per_cell_values(last))
        if points_per_cell == 9:
            out["per_cell"].update(first_half_cell_points=per_cell_values(first_pooled),
                                   last_half_cell_points=per_cell_values(last_pooled))
    elif settle_factor > 1:
        coarse, coarse_pooled, s_coarse, _ = _layers_in_parts(
            tx, centres_xyz, codebook, per_side, per_trace, tracer(samples // settle_factor, diffuse_samples // settle_factor))
        settle = (coarse, ref, coarse_pooled, pooled,
                  {"by": f"traced again with 1/{settle_factor} of its samples",
                   "samples_per_src": int(samples // settle_factor),
                   "diffuse_samples_per_src": int(diffuse_samples // settle_factor) if diffuse else None,
                   "s": round(s_coarse, 1)})
        out["per_cell"]["settle_trace_centre"] = per_cell_values(coarse)
        if points_per_cell == 9:
            out["per_cell"]["settle_trace_cell_points"] = per_cell_values(coarse_pooled)
    if settle is not None:
        coarse, fine, coarse_pooled, fine_pooled, record = settle
        settled = settled_cells(coarse, fine)
        out["settled"] = {"delay_spread_tolerance_ns": round(1e9 * CONVERGED_SETTLE_DELAY_SPREAD_S, 3), **record,
                          "cells": int(settled.sum()),
                          "cells_reached": int(ref["has_path"].sum()),
                          "settled_cell_index": np.flatnonzero(settled).tolist(),
                          "errors_vs_centre": _compare(_subset(fast_at, settled), _subset(ref, settled)),
                          "errors_vs_centre_unsettled": _compare(_subset(fast_at, ~settled), _subset(ref, ~settled)),
                          "by_layer": settled_by_layer(fast_at, ref, coarse, fine)}
        if points_per_cell == 9:  # the cell's layers settle on their own: its nine points pooled, both traces
            at = settled_cells(coarse_pooled, fine_pooled)
            out["settled"]["cell_points"] = {
                "cells": int(at.sum()), "cells_reached": int(pooled["has_path"].sum()),
                "settled_cell_index": np.flatnonzero(at).tolist(),
                "errors": _compare(_subset(fast_at, at), _subset(pooled, at)),
                "errors_vs_centre": _compare(_subset(fast_at, at), _subset(ref, at)),  # ToA: the layer's definition
                "errors_unsettled": _compare(_subset(fast_at, ~at), _subset(pooled, ~at)),
                "by_layer": settled_by_layer(fast_at, pooled, coarse_pooled, fine_pooled)}
    if points_per_cell == 9:  # the cell: reached where any of its nine points is
        out.update(reached_by_pathsolver_cell_points=int(pooled["has_path"].sum()),
                   covered_of_reached_pct_cell_points=_covered_of_reached_pct(fast_at["has_path"], pooled["has_path"]),
                   errors_vs_cell_points=_compare(fast_at, pooled))
    return out


def against_converged_map(one_pass, num_rays: int, gain_db: np.ndarray, eligible: np.ndarray, factor: int,
                          fast_s: float | None = None) -> dict:
    """The path gain map ``gain_db`` (dB, NaN: no value) against the one-pass map with ``factor``
    times the diffraction samples and point deposits, and the point map at the default samples
    against the same, over the ``eligible`` cells; and the front of the second pass on
    undersampled cells (:data:`SECOND_PASS_FACTORS`, :func:`second_pass_front`).
    ``one_pass(n, rx_polarization, **kw)``: a callable making the solver run (:func:`run_set`'s);
    ``fast_s``: the main run's time."""
    from simart_pipeline.ckm.diffraction import DIRECT_SAMPLES_PER_RAY

    t = time.perf_counter()
    dense = one_pass(num_rays, diffraction_samples=factor * DIRECT_SAMPLES_PER_RAY * num_rays, max_footprint_cells=1,
                     diffraction_resample_factor=1)()
    dense_s = time.perf_counter() - t
    points = one_pass(num_rays, max_footprint_cells=1)()
    truth_map = dense.layers()["path_gain_db"][0]
    truth = truth_map[eligible]
    return {"diffraction_samples_factor": factor, "converged_map_s": round(dense_s, 1),
            "this_map": map_agreement(gain_db[eligible], truth),
            "point_deposits_at_default_samples": map_agreement(points.layers()["path_gain_db"][0][eligible], truth),
            "second_pass": second_pass_front(one_pass, num_rays, gain_db, eligible, truth_map, fast_s)}


def second_pass_front(one_pass, num_rays: int, gain_db: np.ndarray, eligible: np.ndarray, truth_db: np.ndarray,
                      fast_s: float | None) -> list[dict]:
    """``diffraction_resample_factor`` against run time and error: per factor of
    :data:`SECOND_PASS_FACTORS`, the run's time (and over ``fast_s``, the map without it), what
    the pass did, the cells it gives a value that ``gain_db`` had none (``newly_valued``, their
    gain against the converged map ``truth_db``) and the whole map against it."""
    out = []
    for f in SECOND_PASS_FACTORS:
        m, _, s = _warm(one_pass(num_rays, diffraction_resample_factor=f))
        g = m.layers()["path_gain_db"][0]
        new = eligible & np.isfinite(g) & ~np.isfinite(gain_db)
        out.append({"factor": f, "s": round(s, 2), "over_one_pass_time": None if not fast_s else round(s / fast_s, 3),
                    "pass": m.second_pass, "cells_valued": int((eligible & np.isfinite(g)).sum()),
                    "newly_valued": map_agreement(g[new], truth_db[new]),
                    "whole_map": map_agreement(g[eligible], truth_db[eligible])})
    return out


def _per_cell_loop_s(radio, tx, ori, cells_xyz: np.ndarray, budget_s: float = float("inf"),
                     min_calls: int = MIN_LOOP_CALLS) -> tuple[float, int]:
    """Mean s of one PathSolver call per cell (after a warm-up of the single-receiver shape), over
    the cells in order until all are done or ``budget_s`` has passed (at least ``min_calls``)."""
    radio.trace(tx[None], ori[None], cells_xyz[:1])
    times = []
    for c in cells_xyz:
        if len(times) >= min_calls and sum(times) >= budget_s:
            break
        t = time.perf_counter()
        radio.trace(tx[None], ori[None], c[None])
        times.append(time.perf_counter() - t)
    return float(np.mean(times)), len(times)


def whole_cell_db(m: op.OnePassMoments) -> np.ndarray:
    """The one-pass's path gain (dB) over the whole cell area, RadioMapSolver's normalisation: the
    layer is per outdoor area, so the cells outside the mask get their outdoor share back."""
    return m.layers()["path_gain_db"][0] + 10 * np.log10(np.where(~m.masked[0], m.outdoor_fraction[0], 1))


def _against_radio_map(one_pass_unpolarised, radio_map, num_rays: int, n_cells: int,
                       one_pass_v_s: float, repeats: int = WARM_REPEATS, first_order_one_pass=None,
                       radio_map_other_seed=None, equal_error=None, radio_map_call=None) -> dict:
    """The one-pass run like for like with RadioMapSolver (``|E|^2``, no V projection, every layer
    still produced; gain taken back to the whole cell area) against ``radio_map(n)`` at its
    default samples and at ``num_rays``: warm times, cells per second, path-gain agreement.

    With diffraction RadioMapSolver traces first-order diffraction from the transmitter alone
    (no reflection before or after the wedge), the one-pass more: ``first_order_one_pass`` is the
    one-pass restricted to RadioMapSolver's model, and its agreement is the like-for-like one
    (``path_gain_agreement_like_for_like``; without diffraction the full run's).
    ``radio_map_other_seed(n)``: RadioMapSolver at ``n`` rays with another seed; at ``num_rays``
    its agreement with the first is the Monte-Carlo floor of any comparison at that ray count.
    ``equal_error``: {"counts", "reference_rays", "one_pass_at(n, **kw)"} for
    :func:`equal_error_front` (RadioMapSolver's reference: ``radio_map_other_seed``).
    ``radio_map_call(n)``: RadioMapSolver itself, not memoised; with it and ``repeats`` the two
    solvers are timed again in :data:`SIDE_BY_SIDE_ROUNDS` alternating rounds after their warm
    calls, each keeping its fastest call: the ratio of two calls minutes apart in a long run moved
    by 10 % with the machine's state (Munich, session 36: 2.05x there, 1.86-1.93x side by side)."""
    m, first_s, warm_s = _warm(one_pass_unpolarised, repeats)
    whole = whole_cell_db(m)
    rms_side_by_side_s = None
    if radio_map_call is not None and repeats:
        radio_map(num_rays)  # compiled and timed first, as before
        rounds = [(_timed(one_pass_unpolarised)[1], _timed(lambda: radio_map_call(num_rays))[1])
                  for _ in range(SIDE_BY_SIDE_ROUNDS)]  # one-pass, then RadioMapSolver, in each round
        warm_s = min([warm_s] + [op_s for op_s, _ in rounds])
        rms_side_by_side_s = min(rms_s for _, rms_s in rounds)

    def summary(n):
        g, first, warm = radio_map(n)
        if n == num_rays and rms_side_by_side_s is not None:
            warm = min(warm, rms_side_by_side_s)
        return {"samples_per_tx": n, "first_call_s": _r3(first), "warm_s": round(warm, 3),
                "cells_per_s": round(n_cells / warm, 1), "cells_covered": int(np.isfinite(g).sum()),
                "path_gain_agreement_with_one_pass": map_agreement(whole, g)}

    same = summary(num_rays)
    out = {"one_pass_unpolarised": {"rays": num_rays, "first_call_s": _r3(first_s), "warm_s": round(warm_s, 3),
                                    "cells_per_s": round(n_cells / warm_s, 1),
                                    "cells_covered": int(np.isfinite(whole).sum())},
           "default_samples": summary(RADIO_MAP_DEFAULT_SAMPLES), "at_one_pass_rays": same,
           "one_pass_over_radio_map_time": round(warm_s / same["warm_s"], 3),
           "side_by_side_rounds": SIDE_BY_SIDE_ROUNDS if rms_side_by_side_s is not None else 0,
           "one_pass_v_over_radio_map_time": round(one_pass_v_s / same["warm_s"], 3),
           "path_gain_agreement_like_for_like": same["path_gain_agreement_with_one_pass"],
           "first_order_diffraction_one_pass": None, "radio_map_solver_other_seed": None}
    if first_order_one_pass is not None:
        m1, first1, warm1 = _warm(first_order_one_pass, repeats)
        agree = map_agreement(whole_cell_db(m1), radio_map(num_rays)[0])
        out["first_order_diffraction_one_pass"] = {
            "first_call_s": _r3(first1), "warm_s": round(warm1, 3),
            "over_radio_map_time": round(warm1 / same["warm_s"], 3), "path_gain_agreement": agree,
            "agreement_with_full_one_pass": map_agreement(whole, whole_cell_db(m1))}
        out["path_gain_agreement_like_for_like"] = agree
    if radio_map_other_seed is not None:
        out["radio_map_solver_other_seed"] = map_agreement(radio_map(num_rays)[0], radio_map_other_seed(num_rays))
    if equal_error is not None:
        one_pass_at = equal_error["one_pass_at"]

        def one_pass_db(n):
            if n == num_rays:
                return whole, warm_s
            if n < num_rays:  # below one batch a kernel shape of its own: compile first
                mm, _, s = _warm(one_pass_at(n), 1)
            else:
                mm, s = _timed(one_pass_at(n))
            return whole_cell_db(mm), s

        reference_rays = equal_error["reference_rays"]
        # RadioMapSolver's reference at another seed: with the same seed a ray's random numbers
        # depend on its index alone, and the first rays of the reference would be the count's own
        rm_reference = _timed(lambda: radio_map_other_seed(reference_rays))
        op_reference = one_pass_db(reference_rays)
        out["equal_error"] = equal_error_front(
            {"one_pass": (one_pass_db, op_reference),
             "radio_map_solver": (lambda n: (radio_map(n)[0], radio_map(n)[2]), rm_reference)},
            num_rays, equal_error["counts"], reference_rays)
        # the models' own difference at the reference's rays: with diffraction the one-pass in
        # RadioMapSolver's first-order model, as at num_rays; without, its reference itself
        lfl = (whole_cell_db(one_pass_at(reference_rays, diffraction_with_reflections=False)())
               if first_order_one_pass is not None else op_reference[0])
        out["equal_error"]["like_for_like_at_reference_rays"] = map_agreement(lfl, rm_reference[0])
    return out


def equal_error_front(solvers: dict, num_rays: int, counts, reference_rays: int) -> dict:
    """Run time at equal Monte-Carlo error. Each solver's path gain map at ``counts`` rays against
    its own map at ``reference_rays`` (its converged limit: the error of a count is its Monte-Carlo
    error, whatever the two solvers' models differ in): p50 / p95 of ``|dB|`` over the cells both
    value, and the share of the reference's cells the count values. ``solvers``: {"one_pass":
    (run, reference), "radio_map_solver": (run, reference)}, ``run(n)`` -> (map dB, NaN: no value;
    warm s), ``reference``: (map, s).

    ``one_pass_rays_at_radio_map_error``: the fewest one-pass rays of ``counts`` whose p50 and p95
    are no larger and whose coverage is no smaller than RadioMapSolver's at ``num_rays``;
    ``one_pass_over_radio_map_time_at_equal_error``: its time over RadioMapSolver's (None where no
    count matches)."""
    fronts = {}
    for name, (run, (ref, ref_s)) in solvers.items():
        points = []
        for n in counts:
            g, s = run(n)
            agree = map_agreement(g, ref)
            points.append({"rays": n, "warm_s": round(s, 3), "error_db": agree["abs_diff_db"],
                           "covered_of_reference_pct": round(100.0 * agree["cells_both"] / max(agree["cells_b"], 1), 2)})
        fronts[name] = {"reference_rays": reference_rays, "reference_s": round(ref_s, 1), "points": points}
    rm = next((p for p in fronts["radio_map_solver"]["points"] if p["rays"] == num_rays), None)
    match = None
    if rm is not None:
        match = next((p for p in fronts["one_pass"]["points"]
                      if p["error_db"]["p50"] is not None and rm["error_db"]["p50"] is not None
                      and p["error_db"]["p50"] <= rm["error_db"]["p50"] and p["error_db"]["p95"] <= rm["error_db"]["p95"]
                      and p["covered_of_reference_pct"] >= rm["covered_of_reference_pct"]), None)
    return {**fronts, "radio_map_solver_rays": num_rays,
            "one_pass_rays_at_radio_map_error": None if match is None else match["rays"],
            "one_pass_over_radio_map_time_at_equal_error": None if match is None else round(match["warm_s"] / rm["warm_s"], 3)}


def run_set(name: str, mechanisms: str, xml: str, spec: dict, num_rays: int, order: dict, sizes: dict,
            ray_counts, sample: dict) -> dict:
    """One mechanism set on scene ``name``. ``order``: {"compare": , "loop": } random orders of
    the cells wholly outdoor (flat indices; filled by the first set, the outdoor mask being the
    scene's); ``sizes``: compare cells, loop cells, loop budget s and warm repeats of this set;
    ``sample``: the grid's ``x``, ``y`` and the ``seed``, to which the first set adds the outdoor
    cell counts."""
    from simart_pipeline.ckm.outdoor import outdoor_fraction, radio_solids
    from simart_pipeline.ckm.radiomap import radio_map_path_gain_db

    cfg = _config(spec, mechanisms)
    rt_cfg = cfg.ray_tracing
    radio = _radio_scene(xml, cfg, mechanisms)
    tx = np.array(spec["tx"])
    ori = np.radians([spec["yaw_pitch_deg"][0], spec["yaw_pitch_deg"][1], 0.0])
    x, y = sample["x"], sample["y"]
    codebook = dft_codebook(radio.array_positions_m("tx"), radio.wavelength_m, 8, 8).weights
    switches = {k: bool(getattr(rt_cfg, k)) for k in SWITCHES}
    repeats = sizes["repeats"]

    solids = radio_solids(radio)  # once per radio scene, as ckm_layers does once per tile
    frac = outdoor_fraction(radio, x, y, [HEIGHT_M], solids=solids)  # likewise

    def one_pass(n, rx_polarization="V", **kw):
        kw.setdefault("diffraction_resample_factor", cfg.ckm.diffraction_resample_factor)  # the config's default
        kw.setdefault("diffuse_gather", cfg.ckm.diffuse_gather if sizes.get("diffuse_gather") is None
                      else sizes["diffuse_gather"])
        kw.setdefault("gather_pilot_directions", DEFAULT_GATHER_PILOT_DIRECTIONS if cfg.ckm.gather_guided else 0)
        return lambda: op.one_pass_moments(radio, tx, ori, x, y, [HEIGHT_M], n, MAX_DEPTH, codebook=codebook,
                                           rx_polarization=rx_polarization, solids=solids,
                                           cell_outdoor_fraction=frac, **switches, **kw)

    m, first_s, fast_s = _warm(one_pass(num_rays), repeats)
    fast = m.layers()
    outdoor = m.outdoor_fraction[0] == 1.0
    eligible = ~m.masked[0]
    covered = fast["enough_hits"][0] & eligible
    n_cells, n_outdoor = x.size * y.size, int((m.outdoor_fraction[0] > 0).sum())
    sample.update(cells_with_outdoor_area=n_outdoor, cells_wholly_outdoor=int(outdoor.sum()))
    if not order:  # the outdoor mask is the scene's: one random order of its cells for every set
        rng = np.random.default_rng(sample["seed"])
        pool = np.flatnonzero(outdoor.ravel())
        order.update(compare=rng.permutation(pool), loop=rng.permutation(pool))

    pick = np.sort(order["compare"][:sizes["compare_cells"]])
    X, Y = np.meshgrid(x, y)
    cells_xyz = np.stack([X.ravel(), Y.ravel(), np.full(X.size, HEIGHT_M)], -1)
    retries0 = radio.cap_retries
    per_side = sizes.get("points_per_side", REFERENCE_POINTS_PER_SIDE[mechanisms])
    ref_centre, ref_points, s_per_rx, paths = _pathsolver_reference(
        radio, tx, ori, cells_xyz[pick], codebook, per_side,
        non_diffuse_samples=non_diffuse_samples(spec, mechanisms, switches["diffuse_reflection"]))
    refs = {"vs_centre": ref_centre, "vs_cell_points": ref_points}
    fast_at = _layers_at(m, pick)
    cov = coverage(fast_at, refs, paths, pool=per_side * per_side)
    # PathSolver keeps one path per primitive sequence where a diffuse reflection is followed by
    # more interactions, and none with diffraction and diffuse reflection together: the one-pass
    # in that model too (diffuse_last_only), to tell its own error from the models' difference
    diffuse_model = (_compare(_layers_at(one_pass(num_rays, diffuse_last_only=True)(), pick), ref_points)
                     if switches["diffuse_reflection"] else None)
    del paths
    check = (reference_check(radio, tx, ori, cells_xyz[pick], fast_at, ref_centre, codebook, sizes["check_cells"])
             if mechanisms in REFERENCE_CHECK_SETS else None)
    converged = None
    if mechanisms in CONVERGED_REFERENCE_SETS and sizes["converged_reference_cells"] > 0:
        sub = np.sort(order["compare"][:min(sizes["converged_reference_cells"], pick.size)])
        converged = against_converged_reference(radio, tx, ori, cells_xyz[sub], _layers_at(m, sub), codebook,
                                                points_per_cell=sizes["converged_reference_points"],
                                                seeds=sizes.get("converged_reference_seeds", CONVERGED_SEEDS))
    loop_cells = cells_xyz[order["loop"][:sizes["loop_cells"]]]
    per_call_s, calls_timed = _per_cell_loop_s(radio, tx, ori, loop_cells, sizes["loop_budget_s"])
    # the loop at the fewest samples of any set too (what the speed-up was judged on before the
    # diffraction reference needed more): a loop that misses paths, so a lower bound of the speed-up
    fewest = min(REFERENCE_SAMPLES.values())
    per_call_fewest_s = None
    if reference_samples(spec, mechanisms) != fewest:
        with _samples(radio, fewest):
            per_call_fewest_s, _ = _per_cell_loop_s(radio, tx, ori, loop_cells, sizes["loop_budget_s"])

    # RadioMapSolver's Monte-Carlo spread at the main ray count: the same call with another seed
    other_seed = cfg.model_copy(update={"ray_tracing": rt_cfg.model_copy(update={"seed": rt_cfg.seed + 1})})
    def radio_map_call(n):  # RadioMapSolver itself; radio_map: its warm calls, once per ray count
        return radio_map_path_gain_db(radio, cfg, HEIGHT_M, n)[0]

    radio_map = _memo(lambda n: _warm(lambda: radio_map_call(n), repeats if n <= num_rays else 0))

    def one_pass_point(n):
        if n == num_rays:
            return m, first_s, fast_s
        if n < num_rays:  # below one batch a kernel shape of its own: compile first
            return _warm(one_pass(n), repeats)
        res, warm_s = _timed(one_pass(n))  # whole batches, the main run's shape: compiled already
        return res, None, warm_s

    out = {
        "mechanisms": switches, "label": SET_LABELS[mechanisms],
        "scattering_coefficient": ALL_SCATTERING_COEFFICIENT if mechanisms == "all" else None,
        "cells_covered": int(covered.sum()),
        "one_pass": {"rays": num_rays, "max_depth": MAX_DEPTH, "beams": int(codebook.shape[0]),
                     "first_call_s": _r3(first_s), "warm_s": round(fast_s, 3), "timed_calls": repeats or 1,
                     "ray_hits": int(m.count.sum()), "cells_per_s": round(n_cells / fast_s, 1),
                     "second_pass": m.second_pass,
                     "coverage_pct": _coverage_pct(fast["path_gain_db"][0], eligible),
                     # the spreads need more (op.DEFAULT_MIN_EFFECTIVE_HITS_FOR_SPREAD effective hits)
                     "delay_spread_coverage_pct": _coverage_pct(fast["rms_delay_spread_s"][0], eligible)},
        "pathsolver": {"samples_per_src": reference_samples(spec, mechanisms),
                       "non_diffuse_samples_per_src": non_diffuse_samples(spec, mechanisms, switches["diffuse_reflection"]),
                       "compared_cells": int(pick.size),
                       "points_per_cell": per_side * per_side, "cap_retries": int(radio.cap_retries - retries0),
                       "per_cell_call_s": round(per_call_s, 4), "per_cell_calls_timed": calls_timed,
                       "batched_s_per_cell": round(s_per_rx, 4),
                       "cells_per_s_per_cell_loop": round(1 / per_call_s, 2),
                       "cells_per_s_batched": round(1 / s_per_rx, 2)},
        "coverage": cov,
        "reference_check": check,
        "against_converged_reference": converged,
        "speedup_vs_per_cell_loop": round(per_call_s * n_outdoor / fast_s, 1),
        "speedup_vs_per_cell_loop_all_cells": round(per_call_s * n_cells / fast_s, 1),
        "speedup_vs_per_cell_loop_at_fewest_samples": (
            {"samples_per_src": fewest, "per_cell_call_s": round(per_call_fewest_s, 4),
             "speedup": round(per_call_fewest_s * n_outdoor / fast_s, 1)} if per_call_fewest_s else None),
        "speedup_vs_batched_pathsolver": round(s_per_rx * n_outdoor / fast_s, 1),
        "errors_vs_centre": _compare(fast_at, ref_centre),
        "errors_vs_cell_points": _compare(fast_at, ref_points),
        "errors_vs_cell_points_pathsolver_diffuse_model": diffuse_model,
        "radio_map_solver": _against_radio_map(
            one_pass(num_rays, None), radio_map, num_rays, n_cells, fast_s, repeats,
            one_pass(num_rays, None, diffraction_with_reflections=False) if switches["diffraction"] else None,
            lambda n: radio_map_path_gain_db(radio, other_seed, HEIGHT_M, n)[0],
            {"counts": sorted({c for c in EQUAL_ERROR_COUNTS if c < num_rays} | {num_rays}),
             "reference_rays": sizes["equal_error_reference_rays"],
             "one_pass_at": lambda n, **kw: one_pass(n, None, **kw)}
            if mechanisms in EQUAL_ERROR_SETS and sizes.get("equal_error_reference_rays", 0) > num_rays else None,
            radio_map_call),
    }
    if mechanisms in CONVERGED_MAP_SETS and sizes["converged_factor"] > 0:
        out["against_converged_map"] = against_converged_map(one_pass, num_rays, fast["path_gain_db"][0], eligible,
                                                             sizes["converged_factor"], fast_s)
    if mechanisms in SWEEP_SETS:
        if name not in SWEEP_SETS[mechanisms]:
            ray_counts = [n for n in ray_counts if n <= num_rays]
        out["rays_vs_error"] = {
            "one_pass": _sweep(ray_counts, one_pass_point, lambda mm: _one_pass_point(mm, pick, refs, eligible)),
            "radio_map_solver": _sweep(ray_counts, radio_map, lambda g: _radio_map_point(g, pick, refs, eligible))}
    out["targets_met"] = targets(out, mechanisms)
    if converged and converged.get("errors_vs_cell_points"):
        out["targets_met_vs_converged_reference"] = targets_vs_converged(out, mechanisms)
        if (converged.get("settled") or {}).get("cell_points"):
            out["targets_met_where_converged_reference_settled"] = targets_vs_converged(out, mechanisms, settled=True)
    if converged and (converged.get("settled") or {}).get("by_layer"):
        out["targets_met_where_converged_reference_settled_by_layer"] = targets_where_settled_by_layer(out, mechanisms)
    return out


def sizes_of_run(sets, quick: bool, cells: dict | None = None,
                 converged_cells: int | None = None) -> tuple[dict[str, int], int]:
    """({set: compared cells}, converged-reference cells): ``cells`` and ``converged_cells`` where
    given, else :data:`COMPARE_CELLS` and :data:`CONVERGED_REFERENCE_CELLS` (quick or full)."""
    q = 0 if quick else 1
    return ({s: (cells or {}).get(s, COMPARE_CELLS[s][q]) for s in sets},
            CONVERGED_REFERENCE_CELLS[q] if converged_cells is None else converged_cells)


def grid_axes(spec: dict) -> tuple[np.ndarray, np.ndarray]:
    """Cell-centre x and y (m) of a scene's grid: ``spec``'s centre and size in CELL_M cells."""
    nx, ny = (int(round(s / CELL_M)) for s in spec["size"])
    x = spec["centre"][0] - spec["size"][0] / 2 + (np.arange(nx) + 0.5) * CELL_M
    y = spec["centre"][1] - spec["size"][1] / 2 + (np.arange(ny) + 0.5) * CELL_M
    return x, y


def run_scene(name: str, spec: dict, num_rays: int, sets, quick: bool, seed: int, ray_counts=RAY_COUNTS,
              log=print, converged_points: int = 1, cells: dict | None = None,
              converged_cells: int | None = None, converged_map: bool = True,
              points_per_side: dict | None = None, diffuse_gather: bool | str | None = None,
              converged_seeds: int = CONVERGED_SEEDS) -> dict:
    """Every mechanism set of ``sets`` on one scene (``diffuse_gather``: the one-pass's
    ``diffuse_gather``, None: the config's ``ckm.diffuse_gather``); a set's sizes from :data:`COMPARE_CELLS`,
    :data:`LOOP_CELLS`, :data:`LOOP_BUDGET_S` (``quick`` picks the first of each pair), or ``cells``
    {set: compared cells} and ``converged_cells`` where given (:func:`sizes_of_run`)."""
    x, y = grid_axes(spec)
    nx, ny = x.size, y.size
    q = 0 if quick else 1
    out = {"scene": spec.get("attr") or f"scenes/{spec['project']} (OSM, the project's radio mesh)",
           "tx_position_m": list(spec["tx"]),
           "tx_orientation_rad": np.radians([spec["yaw_pitch_deg"][0], spec["yaw_pitch_deg"][1], 0.0]).round(6).tolist(),
           "grid": {"nx": nx, "ny": ny, "cell_m": CELL_M, "height_m": HEIGHT_M, "cells": nx * ny},
           "sets": {}}
    order: dict = {}
    sample = {"x": x, "y": y, "seed": seed}
    with tempfile.TemporaryDirectory(prefix="ckm-bench-") as tmp:
        t0 = time.perf_counter()
        xml = _radio_xml(spec, Path(tmp))
        out["scene_build_s"] = round(time.perf_counter() - t0, 3)
        compare, n_converged = sizes_of_run(sets, quick, cells, converged_cells)
        for s in sets:
            t0 = time.perf_counter()
            sizes = {"compare_cells": compare[s], "loop_cells": LOOP_CELLS[q],
                     "loop_budget_s": LOOP_BUDGET_S[q], "check_cells": REFERENCE_CHECK_CELLS[q],
                     "converged_factor": CONVERGED_SAMPLES_FACTOR[q] if converged_map else 0,
                     "equal_error_reference_rays": EQUAL_ERROR_REFERENCE_RAYS[q] if converged_map else 0,
                     "converged_reference_cells": n_converged,
                     "converged_reference_points": converged_points,
                     "converged_reference_seeds": converged_seeds,
                     "repeats": WARM_REPEATS if s == "los_specular" else (0 if quick else 1),
                     "points_per_side": (points_per_side or {}).get(s, REFERENCE_POINTS_PER_SIDE[s]),
                     "diffuse_gather": diffuse_gather}
            out["sets"][s] = run_set(name, s, xml, spec, num_rays, order, sizes, ray_counts, sample)
            out["sets"][s]["wall_s"] = round(time.perf_counter() - t0, 1)
            _release_memory()
            log(f"{name} {s}: {out['sets'][s]['wall_s']} s", flush=True)
    out["grid"].update({k: sample[k] for k in ("cells_with_outdoor_area", "cells_wholly_outdoor") if k in sample})
    return out


def _release_memory() -> None:
    """Between sets: each set's one-pass buffers have sizes of their own, and Dr.Jit keeps freed
    blocks cached for reuse, so a run kept every set's (the full run's peak was 22.4 GB on a
    24 GB machine). A set's first call refills it (untimed, or with its compilation in a quick run)."""
    import gc

    gc.collect()  # the set's radio scene and arrays, some of them held in reference cycles
    engine.release_memory_cache()


def largest_spread_p50(e: dict) -> float | None:
    """The largest p50 error of the four angular spreads in a :func:`_compare` result (None: none)."""
    v = [e[k]["p50"] for k in SPREADS if e.get(k, {}).get("p50") is not None]
    return max(v) if v else None


def _le(v, bound) -> bool | None:
    return None if v is None else v <= bound


def _ge(v, bound) -> bool | None:
    return None if v is None else v >= bound


def targets(r: dict, mechanisms: str = "los_specular") -> dict[str, bool | None]:
    """The issues' targets on one set's results (None: not measured).

    ``los_specular``, issue 8's: speed-up >= 100 over one PathSolver call per cell; gain within
    0.5 dB at p50 of the cell's points' mean (:data:`REFERENCE_POINTS_PER_SIDE`); ToA within 1 ns at p50 (at the centre: the layer's
    definition); best beam equal to PathSolver's incoherent best in >= 95 % of cells, for the cell as
    the gain is (its points pooled): the layer is the best beam of the cell's mean beam gains,
    and where a shadow edge crosses a cell the centre alone can prefer another beam (the report gives
    both); and issue 17's against RadioMapSolver at the same ray count: the one-pass (every layer)
    within 2x of its time, path gain agreeing to 0.1 dB at p50 over the cells both cover (like for
    like: with diffraction the one-pass in RadioMapSolver's diffraction model).

    The other sets, issue 17's with the same mechanisms in PathSolver: coverage >= 99 % of the
    sampled cells PathSolver reaches; against the cell's points, path gain p50 <= 0.5 dB and p95 <=
    3 dB, RMS delay spread p50 <= 5 ns, every angular spread p50 <= 5 deg, best beam >= 95 %, top-3
    >= 99 %; ToA p50 <= 1 ns at the centre; speed-up >= 100; the RadioMapSolver pair above."""
    e3, ec = r["errors_vs_cell_points"], r["errors_vs_centre"]
    rm = r["radio_map_solver"]
    like = rm.get("path_gain_agreement_like_for_like")  # absent from results before session 14
    a = None if like is None else like["abs_diff_db"]["p50"]
    speed = {"speedup_vs_per_cell_loop_ge_100": _ge(r["speedup_vs_per_cell_loop"], TARGET_SPEEDUP_VS_LOOP)}
    radio_map = {"one_pass_within_2x_of_radio_map_solver":
                 _le(rm["one_pass_over_radio_map_time"], TARGET_RADIO_MAP_TIME_RATIO),
                 "path_gain_p50_vs_radio_map_solver_le_0.1_db": _le(a, TARGET_RADIO_MAP_GAIN_P50_DB)}
    ee = rm.get("equal_error")  # at equal Monte-Carlo error (equal_error_front), where run
    if ee is not None:
        ratio = ee["one_pass_over_radio_map_time_at_equal_error"]
        lfl = (ee.get("like_for_like_at_reference_rays") or {}).get("abs_diff_db", {}).get("p50")
        radio_map.update({
            "one_pass_within_2x_of_radio_map_solver_at_equal_error": False if ratio is None else ratio <= TARGET_RADIO_MAP_TIME_RATIO,
            "path_gain_p50_vs_radio_map_solver_at_reference_rays_le_0.1_db": _le(lfl, TARGET_RADIO_MAP_GAIN_P50_DB)})
    if mechanisms == "los_specular":
        return {**speed,
                "path_gain_p50_vs_cell_points_le_0.5_db": _le(e3["path_gain_db"]["p50"], TARGET_GAIN_P50_DB),
                "toa_p50_vs_centre_le_1_ns": _le(ec["toa_ns"]["p50"], TARGET_TOA_P50_NS),
                "best_beam_agreement_ge_95_pct": _ge(e3["best_beam_agreement_pct"], TARGET_BEST_BEAM_PCT),
                **radio_map}
    return {"coverage_of_pathsolver_cells_ge_99_pct": _ge(r["coverage"]["covered_of_reached_pct"], TARGET_COVERAGE_PCT),
            "path_gain_p50_vs_cell_points_le_0.5_db": _le(e3["path_gain_db"]["p50"], TARGET_GAIN_P50_DB),
            "path_gain_p95_vs_cell_points_le_3_db": _le(e3["path_gain_db"]["p95"], TARGET_GAIN_P95_DB),
            "toa_p50_vs_centre_le_1_ns": _le(ec["toa_ns"]["p50"], TARGET_TOA_P50_NS),
            "rms_delay_spread_p50_vs_cell_points_le_5_ns": _le(e3["rms_delay_spread_ns"]["p50"], TARGET_DELAY_SPREAD_P50_NS),
            "angular_spreads_p50_vs_cell_points_le_5_deg": _le(largest_spread_p50(e3), TARGET_SPREAD_P50_DEG),
            "best_beam_agreement_ge_95_pct": _ge(e3["best_beam_agreement_pct"], TARGET_BEST_BEAM_PCT),
            "best_beam_top3_agreement_ge_99_pct": _ge(e3.get("best_beam_top3_agreement_pct"), TARGET_TOP3_PCT),
            **speed, **radio_map}


def targets_vs_converged(r: dict, mechanisms: str, settled: bool = False) -> dict[str, bool | None]:
    """:func:`targets` with the accuracy read against the converged reference at 3 x 3 points
    (``--converged-points 9``: 1e8 samples, fewer cells) instead of the main one:
    coverage and the errors against the pooled points, ToA at the centres; speed and
    RadioMapSolver as in :func:`targets`. ``settled``: the errors on the cells where that reference
    has settled (:func:`settled_cells`; at the points pooled, ToA at those cells' centres); the
    coverage of every cell it reaches."""
    c = r["against_converged_reference"]
    e3, ec = c["errors_vs_cell_points"], c["errors_vs_centre"]
    if settled:
        e3, ec = c["settled"]["cell_points"]["errors"], c["settled"]["cell_points"]["errors_vs_centre"]
    return targets({**r, "coverage": {"covered_of_reached_pct": c["covered_of_reached_pct_cell_points"]},
                    "errors_vs_cell_points": e3, "errors_vs_centre": ec}, mechanisms)


def targets_where_settled_by_layer(r: dict, mechanisms: str) -> dict[str, bool | None]:
    """:func:`targets` with each accuracy figure read where the converged reference has settled in
    that layer (:func:`settled_by_layer`: at the 3 x 3 points pooled where those were traced, else at
    the centres; ToA at the centres); coverage of every cell it reaches; speed and RadioMapSolver as
    in :func:`targets`."""
    c = r["against_converged_reference"]
    at = c["settled"].get("cell_points") or c["settled"]
    e = at["by_layer"]["errors"]
    ec = {**e, "toa_ns": c["settled"]["by_layer"]["errors"]["toa_ns"]}
    covered = c.get("covered_of_reached_pct_cell_points", c.get("covered_of_reached_pct"))
    return targets({**r, "coverage": {"covered_of_reached_pct": covered},
                    "errors_vs_cell_points": e, "errors_vs_centre": ec}, mechanisms)


def judgement(met: dict[str, bool | None]) -> str:
    """Targets as "name met / NOT met / n/a", comma-separated (the report's and ``simart bench``'s)."""
    return ", ".join(f"{k} {'met' if v else 'NOT met' if v is False else 'n/a'}" for k, v in met.items())


def _pp(v: dict) -> str:
    return "-" if v["p50"] is None else f"{v['p50']:.3g} / {v['p95']:.3g}"


def _f(v, fmt: str = ".3g") -> str:
    return "-" if v is None else format(v, fmt)


def _row(label: str, e: dict) -> str:
    pp = _pp
    return (f"| {label} | {e['cells_with_paths_in_both']} | {pp(e['path_gain_db'])} | {pp(e['toa_ns'])} | "
            f"{pp(e['rms_delay_spread_ns'])} | {pp(e['asa_deg'])} | {pp(e['asd_deg'])} | {pp(e['zsa_deg'])} | "
            f"{pp(e['zsd_deg'])} | {e['los_agreement_pct']} | {e['best_beam_agreement_pct']} | "
            f"{_f(e.get('best_beam_top3_agreement_pct'))} | {pp(e['best_beam_loss_db'])} |")


def _each_set(results: dict):
    for name, sc in results["scenes"].items():
        for s, r in sc["sets"].items():
            yield name, s, r


def _fewer_samples(v: dict | None) -> str:
    return "-" if not v else f"{v['samples_per_src']:.0e}: {v['per_cell_call_s']}, {v['speedup']}"


def report(results: dict) -> str:
    s = results["settings"]
    lines = [
        "# One-pass CKM solver vs PathSolver and RadioMapSolver, per mechanism set", "",
        f"{s['machine']}; Mitsuba variant `{s['variant']}`; {'quick' if s['quick'] else 'full'} run, "
        f"{s['total_s']:.0f} s in all. Grid {CELL_M:g} m at {HEIGHT_M:g} m, depth {MAX_DEPTH}, "
        f"one-pass {s['rays']:.0e} rays with 64 DFT beams; PathSolver deterministic, "
        + ", ".join(f"{v:.0e} samples for `{k}`" for k, v in REFERENCE_SAMPLES.items())
        + "".join(f"; {n}: " + ", ".join(f"{v:.0e} for `{k}`" for k, v in sp["reference_samples"].items())
                  for n, sp in SCENES.items() if sp.get("reference_samples"))
        + " (the per-cell loop likewise), iso V receiver (the one-pass solver projects on V likewise), "
        + ", ".join(f"{n} x {n} points per sampled cell for `{k}`"
                    for k, n in {**REFERENCE_POINTS_PER_SIDE, **s.get("points_per_side", {})}.items())
        + ". Mechanism sets: "
        + "; ".join(f"`{k}` {v}" for k, v in SET_LABELS.items()) + f" (S = {ALL_SCATTERING_COEFFICIENT:g} on "
        "every material, Lambertian: the scenes' own materials scatter nothing). Sampled cells lie wholly "
        "outside buildings (one random order per scene; a set takes its first "
        + ", ".join(f"{k} {v}" for k, v in s["compare_cells"].items()) + ").", "",
        "## Summary", "",
        "Coverage: of the sampled cells where PathSolver with the same mechanisms finds a path (any of the "
        "n x n points), the share where the one-pass layers hold a value. Errors against the n x n points "
        "pooled (the cell), ToA at the centre; spreads: the largest p50 of ASA / ASD / ZSA / ZSD. Top-3: "
        "PathSolver's best beam among the one-pass's three best. RMS: RadioMapSolver at the same rays "
        "and mechanisms (time ratio: one-pass with every layer over RadioMapSolver's path gain; gain "
        "|difference| p50 / p95).", "",
        "| scene | set | coverage % (missed / reached) | gain dB p50 / p95 | ToA ns p50 | DS ns p50 (cells with a DS / with a gain) | "
        "spreads deg p50 | best beam % | top-3 % | speed-up vs loop | one-pass s | one-pass / RMS time | "
        "gain vs RMS dB |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, st, r in _each_set(results):
        e3, ec, c = r["errors_vs_cell_points"], r["errors_vs_centre"], r["coverage"]
        rm = r["radio_map_solver"]
        lines.append(
            f"| {name} | {st} | {_f(c['covered_of_reached_pct'])} ({c['missed']} / {c['reached_by_pathsolver']}) | "
            f"{_pp(e3['path_gain_db'])} | {_f(ec['toa_ns']['p50'])} | {_f(e3['rms_delay_spread_ns']['p50'])} "
            f"({e3['rms_delay_spread_ns']['n']} / {e3['cells_with_paths_in_both']}) | "
            f"{_f(largest_spread_p50(e3))} | {e3['best_beam_agreement_pct']} | "
            f"{_f(e3.get('best_beam_top3_agreement_pct'))} | {r['speedup_vs_per_cell_loop']} | "
            f"{r['one_pass']['warm_s']} | {rm['one_pass_over_radio_map_time']} | "
            f"{_pp(rm['at_one_pass_rays']['path_gain_agreement_with_one_pass']['abs_diff_db'])} |")
    lines += ["", "## Errors", "",
              "Errors |one-pass - PathSolver|, p50 / p95, over the sampled cells where both hold a value "
              "(the one-pass: at least min_hits_for_power ray hits); spreads where the cell has at least "
              f"{s['min_hits_for_spread']} ray hits. 'points' pools the paths of the set's n x n points inside the cell "
              "(gain: their mean), 'centre' is the cell centre alone. Best-beam loss: the reference's gain of "
              "its own best beam minus its gain of the one-pass best beam (0 where they agree).", "",
              "| scene, set, reference | cells | gain dB | ToA ns | DS ns | ASA deg | ASD deg | ZSA deg | ZSD deg | "
              "LoS agree % | best beam agree % | top-3 % | best-beam loss dB |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, st, r in _each_set(results):
        lines.append(_row(f"{name}, {st}, centre", r["errors_vs_centre"]))
        n = (r.get("pathsolver") or {}).get("points_per_cell", 9)  # results before session 17: 3 x 3
        lines.append(_row(f"{name}, {st}, points ({n})", r["errors_vs_cell_points"]))
        if r.get("errors_vs_cell_points_pathsolver_diffuse_model"):
            lines.append(_row(f"{name}, {st}, points ({n}), PathSolver's diffuse model",
                              r["errors_vs_cell_points_pathsolver_diffuse_model"]))
    lines += ["", "'PathSolver's diffuse model': the one-pass with a diffuse reflection as a path's last "
              "interaction and none after a diffraction (`diffuse_last_only`), as PathSolver 2.2 finds them: it "
              "keeps one path per primitive sequence where more interactions follow a diffuse reflection."]
    lines += (_coverage_lines(results) + _reference_check_lines(results) + _converged_reference_lines(results)
              + _converged_map_lines(results) + _second_pass_lines(results))
    lines += ["", "## Speed", "",
              "Times measured side by side in this run; the per-cell loop was timed on random outdoor cells "
              "(n calls) and extrapolated to every cell with outdoor area, as was the batched run (s per "
              "receiver of the 3 x 3 run). One-pass warm: the best timed call after a first that compiles "
              "(in brackets; '-': the first call is the only one, compilation included). PathSolver at the "
              "set's reference samples; the last but two column also at the fewest samples of any set, "
              "where the set's are more (a loop that misses paths: a lower bound).", "",
              "| scene | set | cells (outdoor / covered) | one-pass warm s (first call) | cells/s one-pass | "
              "PathSolver s per call | batched s per receiver | speedup vs per-cell loop (all cells) | "
              "at fewer samples: s per call, speedup | speedup vs batched | set wall s |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, st, r in _each_set(results):
        g, o, p = results["scenes"][name]["grid"], r["one_pass"], r["pathsolver"]
        lines.append(f"| {name} | {st} | {g['cells']} ({g.get('cells_with_outdoor_area')} / {r['cells_covered']}) | "
                     f"{o['warm_s']} ({_f(o['first_call_s'])}) | {o['cells_per_s']} | {p['per_cell_call_s']} "
                     f"(n={p['per_cell_calls_timed']}) | {p['batched_s_per_cell']} | "
                     f"{r['speedup_vs_per_cell_loop']} ({r['speedup_vs_per_cell_loop_all_cells']}) | "
                     f"{_fewer_samples(r.get('speedup_vs_per_cell_loop_at_fewest_samples'))} | "
                     f"{r['speedup_vs_batched_pathsolver']} | {r.get('wall_s', '-')} |")
    lines += _radio_map_lines(results) + _equal_error_lines(results) + _rays_vs_error_lines(results)
    lines += ["", "## Targets", "",
              "Issue 8's on `los_specular` (speed-up >= 100 x per-cell loop; gain p50 <= 0.5 dB vs the cell's "
              "points' mean; ToA p50 <= 1 ns at the centre; best beam = PathSolver's incoherent best of the cell "
              "(its points pooled) in >= 95 %), issue 17's on every set (one-pass time <= 2 x RadioMapSolver's "
              "at the same ray count, path gain p50 |difference| <= 0.1 dB against it) and, with the "
              f"mechanisms on, coverage >= {TARGET_COVERAGE_PCT:g} %, gain p50 <= {TARGET_GAIN_P50_DB:g} / p95 <= "
              f"{TARGET_GAIN_P95_DB:g} dB, DS p50 <= {TARGET_DELAY_SPREAD_P50_NS:g} ns, spreads p50 <= "
              f"{TARGET_SPREAD_P50_DEG:g} deg, best beam >= {TARGET_BEST_BEAM_PCT:g} %, top-3 >= {TARGET_TOP3_PCT:g} %, "
              "ToA and speed-up as above. `simart bench` judges issue 17's on the sets "
              + ", ".join(f"`{t}`" for t in TARGET_SETS) + ":", ""]
    for name, st, r in _each_set(results):
        lines.append(f"- {name}, {st}: " + judgement(r["targets_met"]))
    again = [(n, st, r) for n, st, r in _each_set(results) if r.get("targets_met_vs_converged_reference")]
    if again:
        lines += ["", "The same, the accuracy judged against the converged reference at 3 x 3 points "
                  f"({CONVERGED_REFERENCE_SAMPLES:.0e} samples, its cells; speed and RadioMapSolver as above):", ""]
        lines += [f"- {n}, {st}: " + judgement(r["targets_met_vs_converged_reference"]) for n, st, r in again]
    where = [(n, st, r) for n, st, r in _each_set(results) if r.get("targets_met_where_converged_reference_settled")]
    if where:
        lines += ["", "The same on the cells where that reference has settled (its 3 x 3 points pooled, against a trace "
                  "with fewer samples or between the two halves of its seeded runs, `settled_cells`; coverage of "
                  "every cell it reaches):", ""]
        lines += [f"- {n}, {st}: " + judgement(r["targets_met_where_converged_reference_settled"]) for n, st, r in where]
    by_layer = [(n, st, r) for n, st, r in _each_set(results)
                if r.get("targets_met_where_converged_reference_settled_by_layer")]
    if by_layer:
        lines += ["", "The same with each layer judged where that reference has settled in it (`settled_by_layer`: "
                  "gain, ToA and beams where its gain and best beam have, spreads where every layer has):", ""]
        for n, st, r in by_layer:
            b = r["against_converged_reference"]["settled"]
            b = (b.get("cell_points") or b)["by_layer"]
            lines.append(f"- {n}, {st} ({b['gain_and_beam_cells']} cells settled in gain and beam, "
                         f"{b['every_layer_cells']} in every layer): "
                         + judgement(r["targets_met_where_converged_reference_settled_by_layer"]))
    return "\n".join(lines) + "\n"


def _shares(d: dict) -> str:
    return ", ".join(f"{k} {v['share_pct']:g} %" for k, v in d["sequences"].items()) or "-"


def _coverage_lines(results: dict) -> list[str]:
    lines = ["", "## Coverage", "",
             "Sampled cells wholly outdoor; reached: PathSolver finds a path at one of the n x n points "
             "(centre alone in brackets); missed: reached, and the one-pass holds no value (of them, with "
             "a few ray hits below min_hits_for_power); extra: the one-pass holds a value where PathSolver "
             "finds none. PathSolver's power per interaction sequence (R specular, S diffuse, T refraction, "
             "D diffraction, in path order; mean over the cells of each sequence's share of the cell's power) "
             "and the share in paths the one-pass does not trace: a diffraction after two interactions, or after a "
             "diffuse reflection or a refraction (p50 / p95, mean).", "",
             "| scene | set | sampled | reached (centre) | covered % (centre) | missed (few hits) | extra | "
             "missed cells' PathSolver gain dB p50 / p95 | untraced power % in reached cells | in missed cells | "
             "sequences in missed cells | sequences in reached cells |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, st, r in _each_set(results):
        c = r["coverage"]
        pi = c["pathsolver_interactions"]

        def u(d):
            v = d["untraced_pct"]
            return "-" if v["p50"] is None else f"{v['p50']:.3g} / {v['p95']:.3g}, {v['mean']:.3g}"

        lines.append(f"| {name} | {st} | {c['sampled_cells']} | {c['reached_by_pathsolver']} "
                     f"({c['vs_centre']['reached_by_pathsolver']}) | {_f(c['covered_of_reached_pct'])} "
                     f"({_f(c['vs_centre']['covered_of_reached_pct'])}) | {c['missed']} ({c['missed_with_too_few_hits']}) | "
                     f"{c['covered_not_reached']} | {_pp(c['missed_pathsolver_gain_db'])} | {u(pi['reached'])} | "
                     f"{u(pi['missed'])} | {_shares(pi['missed'])} | {_shares(pi['reached'])} |")
    return lines


def _set_section(results: dict, key: str, title: str, intro: str, columns: list[str], row) -> list[str]:
    """A report section with a table row per set that has a ``key`` result (none: no section):
    ``columns`` after scene and set, ``row(result)`` their cells, joined by " | "."""
    rows = [(name, st, r[key]) for name, st, r in _each_set(results) if r.get(key)]
    if not rows:
        return []
    columns = ["scene", "set"] + columns
    return (["", f"## {title}", "", intro, "", "| " + " | ".join(columns) + " |", "|---" * len(columns) + "|"]
            + [f"| {name} | {st} | {row(c)} |" for name, st, c in rows])


def _reference_check_lines(results: dict) -> list[str]:
    def row(c):
        if not c.get("cells"):
            return f"0 | {c['samples_per_src']:.0e} | | | | | | |"
        return (f"{c['cells']} | {c['samples_per_src']:.0e} | {c['s']} | "
                f"{_pp(c['abs_err_db_main_reference'])} | {_pp(c['abs_err_db_this_reference'])} | "
                f"{c['reference_moved_gt_1_db']} | {_f(c.get('best_beam_agree_pct_main_reference'))} / "
                f"{_f(c.get('best_beam_agree_pct_this_reference'))} | "
                f"{' '.join(f'{v:g}' for v in c['signed_err_db_main_reference'])} | "
                f"{' '.join(f'{v:g}' for v in c['signed_err_db_this_reference'])}")

    return _set_section(
        results, "reference_check", "The reference's convergence",
        "The sampled cells whose centre gain differs most from the one-pass layer, traced again at their "
        "centre with more PathSolver samples: |one-pass - PathSolver| there against the main reference "
        "(the set's samples, see above) and against this one, and how many reference gains moved by more "
        "than 1 dB (or appeared); the one-pass's best beam against each reference's in those cells. "
        "Signed errors (one-pass - PathSolver, dB) in cell order.",
        ["cells", "samples", "s", "error dB p50 / p95, main reference", "with more samples", "moved > 1 dB",
         "best beam % main / more samples", "signed, main", "signed, more samples"], row)


def _converged_reference_lines(results: dict) -> list[str]:
    def row(c, e, reached, covered):
        return (f"{c['cells']} | {c.get('points_per_cell', 1)} | {c['s']} | {reached} | "
                f"{_f(covered)} | {_pp(e['path_gain_db'])} | {_f(e['toa_ns']['p50'])} | "
                f"{_pp(e['rms_delay_spread_ns'])} | {_f(largest_spread_p50(e))} | {e['best_beam_agreement_pct']} | "
                f"{_f(e.get('best_beam_top3_agreement_pct'))}")

    columns = ["cells", "points per cell", "s", "reached", "covered %", "gain dB p50 / p95", "ToA ns p50",
               "DS ns p50 / p95", "spreads deg p50", "best beam %", "top-3 %"]
    lines = _set_section(
        results, "against_converged_reference", "Against a converged PathSolver reference",
        f"A random subset of the sampled cells, traced with {CONVERGED_REFERENCE_SAMPLES:.0e} "
        "samples (Sionna's default candidate generator), where most of PathSolver's reflection-diffraction chains "
        "have converged (not all: docs/ckm-one-pass.md, sessions 15 and 34); with diffuse reflection its diffuse "
        f"paths come from a deterministic run at {CONVERGED_DIFFUSE_SAMPLES:.0e} samples. The one-pass cell layers "
        "against their centres (a centre differs from its cell's mean where a "
        "shadow edge crosses the cell: these errors bound the one-pass's from above). The main reference's figures "
        "for the same set are in the tables above. Where `seeds` is more than 1 it is the union of that many "
        "seeded runs' paths (each path once; their diffuse paths' mean, from seeded runs of the default "
        "generator): what one run of their samples together finds.", ["seeds"] + columns,
        lambda c: f"{c.get('seeds', 1)} | " + row(c, c["errors_vs_centre"], c["reached_by_pathsolver"],
                                                   c["covered_of_reached_pct"]))
    settled = [(n, st, r["against_converged_reference"]["settled"]) for n, st, r in _each_set(results)
               if (r.get("against_converged_reference") or {}).get("settled")]

    def settled_table(intro: str, rows) -> list[str]:  # rows: (scene, set, cells, reached, errors, unsettled)
        out = ["", intro, "",
               "| scene | set | settled / reached | settled: gain dB p50 / p95 | ToA ns p50 | DS ns p50 / p95 | "
               "spreads deg p50 | best beam % | top-3 % | not settled: gain dB p50 / p95 | best beam % | top-3 % |",
               "|---" * 12 + "|"]
        for n, st, cells, reached, e, u in rows:
            out.append(f"| {n} | {st} | {cells} / {reached} | {_pp(e['path_gain_db'])} | {_f(e['toa_ns']['p50'])} | "
                       f"{_pp(e['rms_delay_spread_ns'])} | {_f(largest_spread_p50(e))} | "
                       f"{_f(e['best_beam_agreement_pct'])} | {_f(e.get('best_beam_top3_agreement_pct'))} | "
                       f"{_pp(u['path_gain_db'])} | {_f(u['best_beam_agreement_pct'])} | "
                       f"{_f(u.get('best_beam_top3_agreement_pct'))} |")
        return out

    if settled:
        lines += settled_table(
            "The same at the centres, split by whether the converged reference has settled there: "
            + "; ".join(sorted({f"{n} {st}: {c.get('by', f'traced again with 1/{CONVERGED_SETTLE_FACTOR} of its samples')}"
                                for n, st, c in settled}))
            + f". Both reach the cell, its gain moves by at most 1 dB, its delay spread by at most "
            f"{1e9 * CONVERGED_SETTLE_DELAY_SPREAD_S:g} ns and its best beam stays (`settled_cells`). Elsewhere "
            "the reference is still moving with its samples:",
            [(n, st, c["cells"], c["cells_reached"], c["errors_vs_centre"], c["errors_vs_centre_unsettled"])
             for n, st, c in settled])
    at_points = [(n, st, c["cell_points"]) for n, st, c in settled if c.get("cell_points")]
    if at_points:
        lines += settled_table(
            "The same against the 3 x 3 points of each cell pooled (the cell, as the issue compares it; ToA at "
            "the centre), on the cells whose pooled layers have settled by the same rule (both traces at 3 x 3 "
            "points):",
            [(n, st, c["cells"], c["cells_reached"], {**c["errors"], "toa_ns": c["errors_vs_centre"]["toa_ns"]},
              c["errors_unsettled"]) for n, st, c in at_points])
    pooled = [(n, st, r["against_converged_reference"]) for n, st, r in _each_set(results)
              if (r.get("against_converged_reference") or {}).get("errors_vs_cell_points")]
    if pooled:
        lines += ["", "The same against its 3 x 3 points per cell pooled (the cell, like the main reference; ToA at the "
                  "centre); coverage of the cells any of the nine points reaches:", "",
                  "| " + " | ".join(["scene", "set"] + columns) + " |", "|---" * (len(columns) + 2) + "|"]
        lines += [f"| {n} | {st} | {row(c, {**c['errors_vs_cell_points'], 'toa_ns': c['errors_vs_centre']['toa_ns']}, c['reached_by_pathsolver_cell_points'], c['covered_of_reached_pct_cell_points'])} |"
                  for n, st, c in pooled]
    return lines


def _converged_map_lines(results: dict) -> list[str]:
    def row(c):
        a, b = c["this_map"], c["point_deposits_at_default_samples"]
        return (f"{c['diffraction_samples_factor']} | {c['converged_map_s']} | "
                f"{a['cells_a']} / {a['cells_b']} / {a['cells_both']} | {_pp(a['abs_diff_db'])} | "
                f"{b['cells_a']} | {_pp(b['abs_diff_db'])}")

    return _set_section(
        results, "against_converged_map", "Against the solver's own converged map",
        "The one-pass path gain map against the same solver with more diffraction samples and point deposits "
        "(an unbiased estimator, converged: what PathSolver's sampled reference cannot give where it misses "
        "diffracted paths), over the cells both cover; and the point estimator at the default samples "
        "against the same map.",
        ["samples x", "converged map s", "cells: this / converged / both", "gain dB p50 / p95, this map",
         "cells with points", "gain dB p50 / p95, points"], row)


def _second_pass_lines(results: dict) -> list[str]:
    rows = [(n, st, p) for n, st, r in _each_set(results)
            for p in ((r.get("against_converged_map") or {}).get("second_pass") or [])]
    if not rows:
        return []
    lines = ["", "## Second pass on undersampled cells", "",
             "`ckm.diffraction_resample_factor` (off by default): the cells left with 1 to min_hits_for_power - 1 "
             "hits get the diffracted part of the stretches of edge that reached them again from this many times "
             "the samples. The cells it gives a value and the whole map, against the converged map above.", "",
             "| scene | set | factor | s | over the map without it | undersampled cells | stretches | new samples "
             "| left undersampled | newly valued cells | their gain dB p50 / p95 | whole map dB p50 / p95 |",
             "|---" * 12 + "|"]
    for n, st, p in rows:
        q = p["pass"] or {}
        lines.append(f"| {n} | {st} | {p['factor']} | {p['s']} | {_f(p['over_one_pass_time'])} | "
                     f"{q.get('undersampled_cells', '-')} | {q.get('stretches', '-')} | {q.get('new_samples', '-')} | "
                     f"{q.get('still_undersampled', '-')} | {p['newly_valued']['cells_a']} | "
                     f"{_pp(p['newly_valued']['abs_diff_db'])} | {_pp(p['whole_map']['abs_diff_db'])} |")
    return lines


def _equal_error_lines(results: dict) -> list[str]:
    rows = [(name, st, r["radio_map_solver"]["equal_error"]) for name, st, r in _each_set(results)
            if (r.get("radio_map_solver") or {}).get("equal_error")]
    if not rows:
        return []
    lines = ["", "## Time at equal Monte-Carlo error (RadioMapSolver)", "",
             "Each solver's path gain map (the one-pass like for like: `|E|^2`, whole cell) against its own map "
             "at the reference's rays (RadioMapSolver's at another seed): p50 / p95 of |dB| over the cells both "
             "value, and the share of the reference's cells the count values. The match: the fewest one-pass rays "
             "whose p50 and p95 are no larger and whose coverage is no smaller than RadioMapSolver's at the main "
             "ray count; the like-for-like column is the two solvers' models against each other at the "
             "reference's rays (RadioMapSolver's diffraction model; the Monte-Carlo floor of the main comparison "
             "shrinks by sqrt(10)).", "",
             "| scene | set | solver | rays | warm s | gain dB p50 / p95 | coverage % |", "|---|---|---|---|---|---|---|"]
    for name, st, e in rows:
        for solver in ("one_pass", "radio_map_solver"):
            for p in e[solver]["points"]:
                lines.append(f"| {name} | {st} | {solver} | {p['rays']:.0e} | {p['warm_s']} | "
                             f"{_pp(p['error_db'])} | {p['covered_of_reference_pct']} |")
    lines += ["", "| scene | set | RadioMapSolver rays | one-pass rays at its error | time ratio at equal error | "
              "references (rays, s: one-pass / RadioMapSolver) | like for like at the reference's rays, p50 / p95 dB |",
              "|---|---|---|---|---|---|---|"]
    for name, st, e in rows:
        lfl = e.get("like_for_like_at_reference_rays")
        lines.append(f"| {name} | {st} | {e['radio_map_solver_rays']:.0e} | {_f(e['one_pass_rays_at_radio_map_error'])} | "
                     f"{_f(e['one_pass_over_radio_map_time_at_equal_error'])} | {e['one_pass']['reference_rays']:.0e}: "
                     f"{e['one_pass']['reference_s']} / {e['radio_map_solver']['reference_s']} | "
                     f"{_pp(lfl['abs_diff_db']) if lfl else '-'} |")
    return lines


def _radio_map_lines(results: dict) -> list[str]:
    lines = ["", "## Against RadioMapSolver", "",
             "Same grid, transmitter and mechanisms (both |E|^2 cell means; the one-pass run here without the V "
             "projection, every layer and 64 beams, its gain taken back to the whole cell area; in brackets the "
             "ratio for the V run above, the pipeline's layer for an iso V receiver). Warm times: best of the "
             "timed calls after a first that compiles (in brackets). Gain |difference| over the cells both "
             f"cover; the one-pass covers a cell from {op.DEFAULT_MIN_HITS_FOR_POWER} ray hits, RadioMapSolver "
             "from one:", "",
             "| scene | set | rays | one-pass warm s | RMS warm s at 1e6 (default) | RMS warm s at the same rays | "
             "cells/s one-pass / RMS | one-pass / RMS time (V run's) | cells covered one-pass / RMS / both | "
             "gain diff dB p50 / p95 | same at RMS 1e6 |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, st, r in _each_set(results):
        rm = r["radio_map_solver"]
        o, d, same = rm["one_pass_unpolarised"], rm["default_samples"], rm["at_one_pass_rays"]
        a = same["path_gain_agreement_with_one_pass"]
        lines.append(f"| {name} | {st} | {o['rays']:.0e} | {o['warm_s']} ({_f(o['first_call_s'])}) | {d['warm_s']} "
                     f"({_f(d['first_call_s'])}) | {same['warm_s']} ({_f(same['first_call_s'])}) | {o['cells_per_s']} / "
                     f"{same['cells_per_s']} | {rm['one_pass_over_radio_map_time']} ({rm['one_pass_v_over_radio_map_time']}) | "
                     f"{a['cells_a']} / {a['cells_b']} / {a['cells_both']} | {_pp(a['abs_diff_db'])} | "
                     f"{_pp(d['path_gain_agreement_with_one_pass']['abs_diff_db'])} |")
    lines += ["", "Like for like. With diffraction RadioMapSolver traces only the transmitter's own rays diffracted "
              "into the grid (no reflection before the wedge, none after it); the one-pass also traces "
              "(reflection, diffraction) and (diffraction, reflection) chains, which PathSolver finds too. The "
              "one-pass restricted to RadioMapSolver's model (`diffraction_with_reflections=False`) against it, "
              "and RadioMapSolver against itself with another seed at the same rays (the Monte-Carlo floor of "
              "any comparison at that ray count); the target reads the like-for-like column:", "",
              "| scene | set | first-order one-pass warm s (/ RMS time) | like for like: gain diff dB p50 / p95 "
              "(cells both) | RMS seed against seed: p50 / p95 | first-order against full one-pass: p50 / p95 |",
              "|---|---|---|---|---|---|"]
    for name, st, r in _each_set(results):
        rm = r["radio_map_solver"]
        fo, own, like = rm.get("first_order_diffraction_one_pass"), rm.get("radio_map_solver_other_seed"), \
            rm.get("path_gain_agreement_like_for_like")
        if like is None:
            continue
        first = f"{fo['warm_s']} ({fo['over_radio_map_time']})" if fo else "the full run"
        lines.append(f"| {name} | {st} | {first} | "
                     f"{_pp(like['abs_diff_db'])} ({like['cells_both']}) | {_pp(own['abs_diff_db']) if own else '-'} | "
                     f"{_pp(fo['agreement_with_full_one_pass']['abs_diff_db']) if fo else '-'} |")
    return lines


def _rays_vs_error_lines(results: dict) -> list[str]:
    lines = ["", "## Ray count against error", "",
             "Both solvers against the same PathSolver reference (gain: n x n points pooled, and centre; ToA at "
             "the centre; delay spread and best beam against the n x n points; RadioMapSolver gives path gain "
             "only, polarisation-blind against the V reference). Coverage: cells at least half outdoor holding a "
             f"path gain (one-pass: {op.DEFAULT_MIN_HITS_FOR_POWER} ray hits or more; RadioMapSolver: one), and "
             "the sampled cells PathSolver reaches that hold one. Warm s: best of the timed calls up to the main "
             "ray count, one call above it; above the main ray count: "
             + "; ".join(f"`{k}` on {', '.join(v)}" for k, v in SWEEP_SETS.items())
             + ". Plot: `ckm_rays_vs_error.png` (path gain p50 error and coverage against warm time).", "",
             "| scene | set | solver | rays | warm s | coverage % | of PathSolver's cells % | gain dB p50 / p95 (points) | "
             "gain dB p50 / p95 (centre) | ToA ns p50 | DS ns p50 | best beam agree % | top-3 % |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, st, r in _each_set(results):
        for solver, points in (r.get("rays_vs_error") or {}).items():
            for p in points:
                if "skipped" in p:
                    lines.append(f"| {name} | {st} | {solver} | {p['rays']:.0e} | not run: {p['skipped']} "
                                 "| | | | | | | | |")
                    continue
                c, q = p["vs_centre"], p["vs_cell_points"]
                lines.append(f"| {name} | {st} | {solver} | {p['rays']:.0e} | {p['warm_s']} | {p['coverage_pct']} | "
                             f"{_f(p.get('covered_of_reached_pct'))} | {_pp(q['path_gain_db'])} | "
                             f"{_pp(c['path_gain_db'])} | {c.get('toa_ns_p50', '-')} | "
                             f"{q.get('rms_delay_spread_ns_p50', '-')} | {q.get('best_beam_agreement_pct', '-')} | "
                             f"{_f(q.get('best_beam_top3_agreement_pct'))} |")
    return lines


def write_rays_vs_error_plot(curves: dict[str, dict[str, list[dict]]], path: Path) -> Path:
    """``curves[label][solver]`` (label: a scene, or a scene and mechanism set): points with
    ``rays``, ``warm_s``, ``coverage_pct`` and ``vs_cell_points.path_gain_db.p50`` (skipped points have
    none). Two panels against warm time (log): path gain p50 error and coverage, each point
    labelled with its ray count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_gain, ax_cov) = plt.subplots(1, 2, figsize=(13, 5))
    for colour, (scene, solvers) in enumerate(curves.items()):
        for style, (solver, points) in zip(("o-", "s--", "^:"), solvers.items()):
            pts = [p for p in points if "warm_s" in p]
            t = [p["warm_s"] for p in pts]
            for ax, ys in ((ax_gain, [p["vs_cell_points"]["path_gain_db"]["p50"] for p in pts]),
                           (ax_cov, [p["coverage_pct"] for p in pts])):
                ys = [np.nan if v is None else v for v in ys]
                ax.plot(t, ys, style, color=f"C{colour % 10}", label=f"{scene}, {solver}")
                for ti, yi, p in zip(t, ys, pts):
                    ax.annotate(f"{p['rays']:.0e}", (ti, yi), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax_gain.set(xscale="log", xlabel="warm time (s)", ylabel="path gain |error| p50 vs PathSolver n x n (dB)")
    ax_gain.set_yscale("symlog", linthresh=0.01)  # errors span 0.01 .. 1 dB; symlog keeps a 0
    ax_gain.set_ylim(bottom=0)
    ax_cov.set(xscale="log", xlabel="warm time (s)", ylabel="coverage (% of cells at least half outdoor)")
    for ax in (ax_gain, ax_cov):
        ax.grid(True, which="both", alpha=0.3)
    ax_gain.legend(fontsize=7)
    fig.suptitle("CKM: ray count against error (points: rays)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def parse_args(argv=None) -> tuple[argparse.Namespace, dict[str, int]]:
    """The command line, and ``--cells`` as {set: compared cells}."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer compared and timed cells (minutes)")
    ap.add_argument("--out", required=True, type=Path, help="folder for results.json and report.md")
    ap.add_argument("--rays", type=float, default=1e7, help="one-pass rays (default 1e7)")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--sets", nargs="+", default=list(MECHANISM_SETS), choices=list(MECHANISM_SETS),
                    help="mechanism sets (default: all of them)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ray-counts", type=float, nargs="+", default=None,
                    help="ray counts of the error curves (default 1e5 .. 1e8; --quick: up to 1e7)")
    ap.add_argument("--converged-points", type=int, choices=(1, 9), default=1,
                    help="points per cell of the converged reference: 1 (the centre) or 9 (3 x 3; "
                         "about 4x its time: Munich 143 s a cell against 36 s)")
    ap.add_argument("--converged-seeds", type=int, default=CONVERGED_SEEDS, metavar="K",
                    help="seeded runs of the converged reference: 1 (one run, settled against a tenth of its "
                         "samples) or an even K (the union of K runs' paths, settled by its two halves; "
                         "K times one run's time; CONVERGED_SEEDS)")
    ap.add_argument("--cells", nargs="+", default=[], metavar="SET=N",
                    help="compared cells of a set instead of COMPARE_CELLS' (e.g. diffraction=100)")
    ap.add_argument("--converged-cells", type=int, default=None, metavar="N",
                    help="cells of the converged 1e8-sample reference (default 40, --quick 4; 0: none)")
    ap.add_argument("--points-per-side", nargs="+", default=[], metavar="SET=N",
                    help="the reference's n x n points per sampled cell of a set instead of "
                         "REFERENCE_POINTS_PER_SIDE's (e.g. all=5, to judge near-tie beams)")
    ap.add_argument("--diffuse-gather", choices=tuple(GATHER_CHOICES), default=None,
                    help="the one-pass's diffuse gather on few-hit cells (default: the config's ckm.diffuse_gather)")
    ap.add_argument("--no-converged-map", action="store_true",
                    help="skip the one-pass map at CONVERGED_SAMPLES_FACTOR times the samples")
    args = ap.parse_args(argv)
    cells, points = {}, {}
    for option, items, into in (("--cells", args.cells, cells), ("--points-per-side", args.points_per_side, points)):
        for item in items:
            key, _, n = item.partition("=")
            if key not in MECHANISM_SETS or not n.isdigit() or int(n) < 1:
                ap.error(f"{option} {item}: expected SET=N with SET one of {', '.join(MECHANISM_SETS)} and N >= 1")
            into[key] = int(n)
    args.points_per_side = points
    if args.converged_seeds < 1 or (args.converged_seeds > 1 and args.converged_seeds % 2):
        ap.error(f"--converged-seeds {args.converged_seeds}: expected 1 or an even count (two halves to settle by)")
    return args, cells


def main(argv=None) -> int:
    args, cells = parse_args(argv)
    q = 0 if args.quick else 1
    compare_cells, converged_cells = sizes_of_run(args.sets, args.quick, cells, args.converged_cells)
    ray_counts = [int(n) for n in args.ray_counts] if args.ray_counts else (
        QUICK_RAY_COUNTS if args.quick else RAY_COUNTS)
    t0 = time.perf_counter()
    variant = engine.init()
    results = {"settings": {"quick": args.quick, "rays": int(args.rays), "sets": list(args.sets),
                            "compare_cells": compare_cells, "converged_reference_cells": converged_cells,
                            "converged_map": not args.no_converged_map,
                            "per_cell_loop_cells": LOOP_CELLS[q], "per_cell_loop_budget_s": LOOP_BUDGET_S[q],
                            "variant": variant, "seed": args.seed, "ray_counts": list(ray_counts),
                            "converged_reference_points_per_cell": args.converged_points,
                            "converged_reference_seeds": args.converged_seeds,
                            "points_per_side": args.points_per_side,
                            "diffuse_gather": args.diffuse_gather,
                            "sweep_sets": {k: list(SWEEP_SETS[k]) for k in args.sets if k in SWEEP_SETS},
                            "max_point_s": MAX_POINT_S,
                            "scattering_coefficient_all": ALL_SCATTERING_COEFFICIENT,
                            "min_hits_for_spread": op.DEFAULT_MIN_HITS_FOR_SPREAD,
                            "min_effective_hits_for_spread": op.DEFAULT_MIN_EFFECTIVE_HITS_FOR_SPREAD,
                            "min_hits_for_power": op.DEFAULT_MIN_HITS_FOR_POWER,
                            "machine": f"{platform.machine()}, {__import__('os').cpu_count()} CPU cores",
                            "versions": engine.versions()},
               "scenes": {}}
    for name in args.scenes:
        results["scenes"][name] = run_scene(name, SCENES[name], int(args.rays), args.sets, args.quick, args.seed,
                                            ray_counts, converged_points=args.converged_points, cells=cells,
                                            converged_cells=args.converged_cells,
                                            converged_map=not args.no_converged_map,
                                            points_per_side=args.points_per_side,
                                            diffuse_gather=GATHER_CHOICES.get(args.diffuse_gather),
                                            converged_seeds=args.converged_seeds)
        print(json.dumps({name: results["scenes"][name]}, indent=1), flush=True)
    results["settings"]["total_s"] = round(time.perf_counter() - t0, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    (args.out / "report.md").write_text(report(results))
    write_rays_vs_error_plot({f"{name} {st}": r["rays_vs_error"] for name, st, r in _each_set(results)
                              if "rays_vs_error" in r}, args.out / "ckm_rays_vs_error.png")
    print(report(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
