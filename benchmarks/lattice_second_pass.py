"""Run time against error of the lattice rays' second pass on undersampled cells (``ckm.lattice_resample_factor``).

The one-pass with every mechanism (the ``all`` set of :mod:`benchmarks.ckm_solver`) at ``--rays``
rays, once per factor (1: no second pass), timed warm and alternated (the fastest of
``--repeats``), against the same solver at ``--reference-rays`` without a second pass: both are
unbiased estimates of the same map, so the reference's own noise is the floor. Over the cells the
reference gives a value: how many each run covers, path gain |dB| p50 / p95, best-beam agreement,
RMS delay spread |ns| p50; and how many cells stay with an effective count below
``min_hits_for_power``. Factor 1 runs again at the rays each other factor's time buys it: at equal
time, which error is lower (``--no-equal-time`` skips it). The rows are
:func:`benchmarks.diffuse_connections.sweep`'s.

    python -m benchmarks.lattice_second_pass --out DIR [--scenes munich urban street_canyon]
        [--rays 1e7] [--reference-rays 1e8] [--factors 1 8 16] [--repeats 2] [--no-equal-time]
"""

from __future__ import annotations

from benchmarks.ckm_variants import SceneRuns
from benchmarks.diffuse_connections import run_sweeps, sweep, sweep_parser
from simart_pipeline.ckm import one_pass as op

SCENES = ("munich", "urban", "street_canyon")
FACTORS = (1, 8, 16)


def _solve(s: SceneRuns, n: int, factor: int) -> op.OnePassMoments:
    return s.one_pass(n, lattice_resample_factor=int(factor))()


def main(argv=None) -> int:
    ap = sweep_parser(__doc__, SCENES)
    ap.add_argument("--factors", type=int, nargs="+", default=list(FACTORS))
    a = ap.parse_args(argv)
    if a.factors[0] != 1 or min(a.factors) < 1:
        ap.error("--factors: the first must be 1 (no second pass, the time unit), every one >= 1")
    return run_sweeps(a, ap, lambda name, a: sweep(
        name, int(a.rays), int(a.reference_rays), a.factors, 1, _solve, "factor", max(1, a.repeats),
        not a.no_equal_time), "lattice resample factor")


if __name__ == "__main__":
    raise SystemExit(main())
