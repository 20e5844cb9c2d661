"""The one-pass's path gain against Sionna's RadioMapSolver where both have converged (issue 17's
"the path gain of both agrees to p50 <= 0.1 dB").

At :mod:`benchmarks.ckm_solver`'s 1e7 rays that comparison measures Monte-Carlo noise: with every
mechanism RadioMapSolver differs from itself with another seed by 0.4-0.65 dB p50, and the
one-pass's like-for-like difference sits at that floor (docs/ckm-one-pass.md, "Session 27").
Here both solvers get ``--rays`` (1e9 by default) on the ``all`` set of each scene (every
mechanism, diffuse reflection with S 0.3, the benchmark's grid, station and seed):

- **RadioMapSolver** as the mean of ``--runs`` calls of ``rays / runs`` rays each, seeds
  :data:`SEED_OFFSET` + 0, 1, ... after the scene's (the same estimator at ``rays``: its per-cell
  mean over independent rays; one call of 1e9 rays would hold the whole wavefront at once). The
  means of its first and second halves of runs differ by its own noise at ``rays / 2``; that
  difference is about twice its error at ``rays`` (two estimates of half the rays each), so it
  bounds what any comparison with it can resolve.
- **The one-pass** in RadioMapSolver's model, like for like as in ``ckm_solver``
  (``|E|^2``: no V projection, gain taken back to the whole cell area, diffraction without
  reflections before or after the wedge), at each of ``--one-pass-rays`` (default ``rays / 100``,
  ``rays / 10``, ``rays``) in one call each, every layer produced, against the RadioMapSolver mean.

Reported per scene: ``|one-pass - RadioMapSolver|`` p50 / p95 (dB) over the cells both value,
RadioMapSolver's halves against each other, and each solver's time. Over all cells the p50 is
RadioMapSolver's noise where few of its rays reach (Munich: its halves differ by 0.52 dB p50 at 1e9
rays, session 31), so the same figures are also given **where RadioMapSolver has converged**: the
cells every run values whose mean's standard error, from the runs' spread
(:func:`standard_error_db`), is at most :data:`CONVERGED_ERROR_DB`. That choice reads
RadioMapSolver's runs only, never the one-pass. The maps themselves are kept in
``DIR/SCENE_maps.npz`` (every RadioMapSolver run and each one-pass map, dB) for other statistics.

    python -m benchmarks.radio_map_agreement --out DIR [--scenes ...] [--rays 1e9] [--runs 10]

Writes ``DIR/results.json`` (after each scene) and ``DIR/report.md``. On 2 CPU cores at 1e9 rays:
about 10 min for urban, 20 for the street canyon, 35 for Munich.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import ckm_solver as cs
from benchmarks.bench import machine
from benchmarks.ckm_variants import SceneRuns
from simart_pipeline import engine
from simart_pipeline.link.budget import power_db

SCENE_ORDER = ("urban", "street_canyon", "munich")  # the quickest first: a long run leaves results early
SEED_OFFSET = 100  # RadioMapSolver's runs: seeds after the scene's own (ckm_solver's main map uses it)
# a cell where RadioMapSolver's mean is known to this (one standard error, dB) has converged for a
# 0.1 dB comparison: its own share of a difference there is half the bound or less
CONVERGED_ERROR_DB = 0.05


def mean_of_runs_db(runs_db) -> np.ndarray:
    """The mean path gain (dB) of independent Monte-Carlo maps ``runs_db`` [runs, ...] (dB, NaN where
    a run's rays missed the cell): their mean in linear power, a miss counting as zero power (what
    that run's estimator says there); NaN where every run missed."""
    runs = np.asarray(runs_db, dtype=np.float64)
    return power_db(np.where(np.isfinite(runs), 10.0 ** (runs / 10.0), 0.0).mean(axis=0))


def halves_db(runs_db) -> tuple[np.ndarray, np.ndarray]:
    """The means (:func:`mean_of_runs_db`) of the first and the second half of ``runs_db`` (an even
    number of runs): two independent estimates at half the rays."""
    runs = np.asarray(runs_db)
    if runs.shape[0] < 2 or runs.shape[0] % 2:
        raise ValueError(f"halves need an even number of runs, at least 2; got {runs.shape[0]}")
    h = runs.shape[0] // 2
    return mean_of_runs_db(runs[:h]), mean_of_runs_db(runs[h:])


def standard_error_db(runs_db) -> np.ndarray:
    """Per cell, the standard error of :func:`mean_of_runs_db` in dB: the runs' linear powers (a miss
    as zero power) have sample standard deviation ``sd``, their mean ``m`` over ``R`` runs is known
    to ``sd / sqrt(R)``, which is ``10 log10(1 + sd / (sqrt(R) m))`` dB; NaN where every run missed.
    It estimates the spread from the runs themselves: where a few rare rays carry a cell it is low
    by chance, which is why :func:`converged_cells` also asks every run to value the cell."""
    runs = np.asarray(runs_db, dtype=np.float64)
    if runs.shape[0] < 2:
        raise ValueError(f"a standard error needs at least 2 runs; got {runs.shape[0]}")
    p = np.where(np.isfinite(runs), 10.0 ** (runs / 10.0), 0.0)
    mean = p.mean(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = p.std(axis=0, ddof=1) / (np.sqrt(runs.shape[0]) * mean)
    return np.where(mean > 0, 10.0 * np.log10(1.0 + rel), np.nan)


def converged_cells(runs_db, max_error_db: float = CONVERGED_ERROR_DB) -> np.ndarray:
    """The cells where RadioMapSolver's mean of ``runs_db`` has converged: valued by every run, one
    standard error (:func:`standard_error_db`) at most ``max_error_db``."""
    runs = np.asarray(runs_db, dtype=np.float64)
    se = standard_error_db(runs)
    return np.isfinite(runs).all(axis=0) & (np.nan_to_num(se, nan=np.inf) <= max_error_db)


def _agreement(a_db: np.ndarray, b_db: np.ndarray) -> dict:
    out = cs.map_agreement(a_db, b_db)
    both = np.isfinite(a_db) & np.isfinite(b_db)
    # the signed median tells a bias from noise: noise spreads it both ways, a bias moves it (a
    # mean of dB would not: where a few rays carry a cell its dB value is skewed)
    out["median_signed_diff_db"] = round(float(np.median((a_db - b_db)[both])), 4) if both.any() else None
    return out


def run_scene(name: str, rays: int, runs: int, one_pass_rays, log=print, maps_to: Path | None = None) -> dict:
    """RadioMapSolver's mean of ``runs`` maps of ``rays // runs`` rays each, and the one-pass like
    for like at each of ``one_pass_rays``, on scene ``name`` (the ``all`` set); every map (dB)
    saved to ``maps_to`` (``.npz``) when given."""
    per_run = rays // runs
    with tempfile.TemporaryDirectory(prefix="radio-map-agreement-") as tmp:
        s = SceneRuns(name, Path(tmp))
        seed = int(s.cfg.ray_tracing.seed)
        from simart_pipeline.ckm.radiomap import radio_map_path_gain_db

        s.radio_map(10**6)()  # compiles RadioMapSolver's kernels outside the timed runs
        maps, rm_s = [], 0.0
        for i in range(runs):
            rt = s.cfg.ray_tracing.model_copy(update={"seed": seed + SEED_OFFSET + i})
            cfg = s.cfg.model_copy(update={"ray_tracing": rt})
            t = time.perf_counter()
            maps.append(radio_map_path_gain_db(s.radio, cfg, cs.HEIGHT_M, per_run)[0])
            rm_s += time.perf_counter() - t
            log(f"{name} RadioMapSolver run {i + 1}/{runs} ({per_run:.0e} rays): {time.perf_counter() - t:.1f} s",
                flush=True)
        rm = mean_of_runs_db(maps)
        first, second = halves_db(maps)
        converged = converged_cells(maps)
        rm_converged = np.where(converged, rm, np.nan)
        out = {"radio_map_solver": {"rays": per_run * runs, "runs": runs, "rays_per_run": per_run,
                                    "seeds": [seed + SEED_OFFSET + i for i in range(runs)],
                                    "s": round(rm_s, 1), "cells_valued": int(np.isfinite(rm).sum()),
                                    "halves": _agreement(first, second),
                                    "converged_error_db": CONVERGED_ERROR_DB,
                                    "cells_converged": int(converged.sum()),
                                    "halves_where_converged": _agreement(np.where(converged, first, np.nan), second)},
               "one_pass": {}}
        saved = {"radio_map_solver_runs_db": np.asarray(maps, np.float64)}
        del maps
        cs._release_memory()
        for n in one_pass_rays:
            t = time.perf_counter()
            m = s.one_pass(int(n), None, diffraction_with_reflections=False)()
            op_s = time.perf_counter() - t
            whole = cs.whole_cell_db(m)
            out["one_pass"][str(int(n))] = {"rays": int(n), "s": round(op_s, 1),
                                            "cells_valued": int(np.isfinite(whole).sum()),
                                            "against_radio_map_solver": _agreement(whole, rm),
                                            "where_radio_map_solver_converged": _agreement(whole, rm_converged)}
            saved[f"one_pass_{int(n)}_db"] = np.asarray(whole, np.float64)
            log(f"{name} one-pass {n:.0e}: {op_s:.1f} s, {out['one_pass'][str(int(n))]['against_radio_map_solver']}",
                flush=True)
            del m
            cs._release_memory()
    if maps_to is not None:
        np.savez_compressed(maps_to, **saved)
    return out


def _pp(d: dict) -> str:
    a = d["abs_diff_db"]
    return "-" if a["p50"] is None else f"{a['p50']:.3f} / {a['p95']:.2f}"


def report(results: dict) -> str:
    st = results["settings"]
    lines = ["# The one-pass against RadioMapSolver, both converged", "",
             f"`python -m benchmarks.radio_map_agreement` ({st['machine']['cpu']}, {st['machine']['cores']} cores, "
             f"{st['variant']}): the `all` set of "
             f"`benchmarks.ckm_solver` (every mechanism, S {cs.ALL_SCATTERING_COEFFICIENT}); RadioMapSolver as "
             f"the mean of {st['runs']} runs of {st['rays'] // st['runs']:.0e} rays (its estimator at "
             f"{st['rays']:.0e}), the one-pass like for like (`|E|^2`, whole cell, RadioMapSolver's "
             "first-order diffraction) in one call per ray count. `|dB|` p50 / p95 over the cells both "
             "value; signed p50: the median of one-pass minus RadioMapSolver (a bias moves it, noise does not). "
             f"Where converged: the cells every RadioMapSolver run values and whose mean's standard error "
             f"(from the runs' spread) is at most {CONVERGED_ERROR_DB} dB.", "",
             "| scene | RadioMapSolver rays | its halves p50 / p95 | one-pass rays | one-pass s | "
             "against RadioMapSolver p50 / p95 | signed p50 dB | cells both | where converged: its halves | "
             "one-pass p50 / p95 | signed p50 dB | cells |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in results["scenes"].items():
        rm = r["radio_map_solver"]
        for i, (n, p) in enumerate(r["one_pass"].items()):
            a, c = p["against_radio_map_solver"], p.get("where_radio_map_solver_converged")
            head = (f"| {name} | {rm['rays']:.0e} ({rm['s']} s) | {_pp(rm['halves'])} |" if i == 0 else "| | | |")
            conv = ("| - | - | - | - |" if c is None else
                    f"| {_pp(rm['halves_where_converged']) if i == 0 else ''} | {_pp(c)} | "
                    f"{c['median_signed_diff_db']} | {c['cells_both']} |")
            lines.append(f"{head} {int(n):.0e} | {p['s']} | {_pp(a)} | {a['median_signed_diff_db']} | "
                         f"{a['cells_both']} {conv}")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--scenes", nargs="+", default=list(SCENE_ORDER), choices=list(cs.SCENES))
    ap.add_argument("--rays", type=float, default=1e9, help="RadioMapSolver's rays in all (default 1e9)")
    ap.add_argument("--runs", type=int, default=10, help="RadioMapSolver runs they are split into (even)")
    ap.add_argument("--one-pass-rays", type=float, nargs="+", default=None,
                    help="the one-pass's ray counts (default rays / 100, rays / 10, rays)")
    a = ap.parse_args(argv)
    if a.runs < 2 or a.runs % 2:
        ap.error("--runs: an even number, at least 2 (its halves measure RadioMapSolver's own noise)")
    rays = int(a.rays)
    one_pass_rays = [int(n) for n in (a.one_pass_rays or (rays / 100, rays / 10, rays))]
    results = {"settings": {"rays": rays, "runs": a.runs, "one_pass_rays": one_pass_rays,
                            "variant": engine.init(), "machine": machine(), "versions": engine.versions(),
                            "seed_offset": SEED_OFFSET}, "scenes": {}}
    a.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for name in a.scenes:
        results["scenes"][name] = run_scene(name, rays, a.runs, one_pass_rays, maps_to=a.out / f"{name}_maps.npz")
        results["settings"]["total_s"] = round(time.perf_counter() - t0, 1)
        (a.out / "results.json").write_text(json.dumps(results, indent=2))
        (a.out / "report.md").write_text(report(results))
    print(report(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
