"""The one-pass CKM solver against PathSolver: accuracy and speed on Sionna's bundled scenes.

    python -m benchmarks.ckm_solver [--quick] --out DIR

For Sionna RT's street canyon and Munich (both shipped with sionna-rt), a 2 m grid at 1.5 m, one
8 x 8 tr38901 base station with the 64-beam DFT codebook, LoS + specular reflection, depth 3:

- the one-pass solver (:func:`simart_pipeline.ckm.one_pass.one_pass_moments`) fills every cell;
- PathSolver (deterministic, ``samples_per_src`` 1e5, iso V receiver) traces the centres and 3 x 3
  points of a random sample of cells that lie wholly outside buildings and that the one-pass
  solver reaches; both reduce to the same moments (:mod:`simart_pipeline.ckm.moments`), so the
  layers compare by definition;
- errors ``|one-pass - PathSolver|``: p50 / p95 of path gain (dB), ToA, RMS delay spread (ns), the
  four angular spreads (deg), LoS and best-beam agreement (%), against the centre and against the
  3 x 3 points pooled (their paths together, each point weighted 1/9: the gain is their mean);
- speed: the one-pass time for the whole grid (warm: kernels compiled), one PathSolver call per
  cell (timed on a random subset and extrapolated to the grid's outdoor cells, which the reference
  mode would trace) and PathSolver batched over receivers (the timed centre run, extrapolated);
  ``speedup_vs_per_cell_loop`` and ``speedup_vs_batched_pathsolver`` are ratios of those times.

Writes ``DIR/results.json`` and ``DIR/report.md``. ``--quick`` samples fewer cells (a few minutes
on 2 cores); the one-pass run keeps its 1e7 rays.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
from scipy.constants import c as SPEED_OF_LIGHT

from simart_pipeline import engine
from simart_pipeline.ckm import one_pass as op
from simart_pipeline.ckm.moments import CellMoments, layers_from_moments, path_moments
from simart_pipeline.config import SceneConfig
from simart_pipeline.link.beams import dft_codebook

# Grids: the canyon's whole footprint; 300 m x 300 m of Munich around the base station.
SCENES = {
    "street_canyon": dict(attr="simple_street_canyon", tx=(-40.0, 0.0, 20.0), yaw_pitch_deg=(0.0, 10.0),
                          centre=(0.0, 0.0), size=(188.0, 122.0)),
    "munich": dict(attr="munich", tx=(8.5, 21.0, 27.0), yaw_pitch_deg=(62.0, 10.0),
                   centre=(8.5, 21.0), size=(300.0, 300.0)),
}
HEIGHT_M = 1.5
CELL_M = 2.0
MAX_DEPTH = 3
SAMPLES_PER_SRC = 100_000
SPREADS = ("asa_deg", "asd_deg", "zsa_deg", "zsd_deg")


def _config() -> SceneConfig:
    return SceneConfig.model_validate({
        "name": "ckm-benchmark", "source": {"kind": "procedural"},
        "origin": {"latitude_deg": 48.14, "longitude_deg": 11.58},
        "base_stations": [{"name": "bs", "position_m": [0.0, 0.0, 20.0],
                           "array": {"rows": 8, "cols": 8, "pattern": "tr38901"}}],
        "platforms": [{"name": "rx", "kind": "pedestrian", "array": {"pattern": "iso", "polarization": "V"},
                       "trajectory": {"waypoints_m": [[0, 0, 1.5], [1, 0, 1.5]], "speed_mps": 1.0}}],
        "clock": {"duration_s": 1.0},
        "ray_tracing": {"max_depth": MAX_DEPTH, "samples_per_src": SAMPLES_PER_SRC, "refraction": False},
    })


def _reference_moments(paths, tau0_s: np.ndarray, codebook: np.ndarray, pool: int = 1) -> CellMoments:
    """PathSolver paths of ``cells * pool`` receivers (pool consecutive receivers per cell) as
    per-cell moments, the reference mode's definitions: gain = mean over antenna pairs of |a|^2."""
    a = paths.a[:, :, 0]  # [rx, rx_ant, tx_ant, path]
    power = (np.abs(a) ** 2).mean(axis=(1, 2)) / pool
    y = np.einsum("bn,rmnp->rmbp", codebook.astype(np.complex64), a)
    beam = (np.abs(y) ** 2).mean(1).transpose(0, 2, 1) / pool  # [rx, path, beam]
    ang = np.stack([paths.phi_r[:, 0], paths.theta_r[:, 0], paths.phi_t[:, 0], paths.theta_t[:, 0]], -1)

    def cells(v):  # [cells * pool, path, ...] -> [cells, pool * path, ...]
        return v.reshape((-1, pool * v.shape[1]) + v.shape[2:])

    return path_moments(cells(power), cells(paths.tau_s[:, 0]), cells(paths.valid[:, 0]), cells(paths.los[:, 0]),
                        cells(ang), tau0_s, cells(beam))


def _percentiles(err: np.ndarray) -> dict[str, float | int]:
    err = err[np.isfinite(err)]
    if err.size == 0:
        return {"p50": None, "p95": None, "n": 0}
    return {"p50": round(float(np.percentile(err, 50)), 4), "p95": round(float(np.percentile(err, 95)), 4),
            "n": int(err.size)}


def _compare(fast: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> dict:
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
    # what taking the one-pass best beam costs in the reference's own beam gains (0 where they agree)
    bg = ref["beam_gain_db"][both]
    rows = np.arange(len(bg))
    out["best_beam_loss_db"] = _percentiles(bg[rows, ref["best_beam"][both]] - bg[rows, fast["best_beam"][both]])
    return out


def run_scene(name: str, spec: dict, num_rays: int, compare_cells: int, loop_cells: int, seed: int) -> dict:
    import sionna.rt as rt

    from simart_pipeline.radio.tracer import RadioScene

    cfg = _config()
    t0 = time.perf_counter()
    radio = RadioScene.from_config(getattr(rt.scene, spec["attr"]), cfg)
    load_s = time.perf_counter() - t0
    tx = np.array(spec["tx"])
    ori = np.radians([spec["yaw_pitch_deg"][0], spec["yaw_pitch_deg"][1], 0.0])
    nx, ny = (int(round(s / CELL_M)) for s in spec["size"])
    x = spec["centre"][0] - spec["size"][0] / 2 + (np.arange(nx) + 0.5) * CELL_M
    y = spec["centre"][1] - spec["size"][1] / 2 + (np.arange(ny) + 0.5) * CELL_M
    codebook = dft_codebook(radio.array_positions_m("tx"), radio.wavelength_m, 8, 8).weights
    kw = dict(codebook=codebook, rx_polarization="V")

    def one_pass():
        import drjit as dr

        t = time.perf_counter()
        m = op.one_pass_moments(radio, tx, ori, x, y, [HEIGHT_M], num_rays, MAX_DEPTH, **kw)
        dr.sync_thread()
        return m, time.perf_counter() - t

    _, first_s = one_pass()  # compiles the kernels
    m, fast_s = one_pass()
    fast = m.layers()
    outdoor = m.outdoor_fraction[0] == 1.0
    covered = fast["has_path"][0] & ~m.masked[0]
    n_cells, n_outdoor = nx * ny, int((m.outdoor_fraction[0] > 0).sum())

    rng = np.random.default_rng(seed)
    pool = np.flatnonzero((outdoor & fast["has_path"][0]).ravel())
    pick = np.sort(rng.choice(pool, min(compare_cells, pool.size), replace=False))
    X, Y = np.meshgrid(x, y)
    centres = np.stack([X.ravel()[pick], Y.ravel()[pick], np.full(pick.size, HEIGHT_M)], -1)
    tau0 = np.linalg.norm(centres - tx, axis=-1) / SPEED_OF_LIGHT
    txs, oris = tx[None], ori[None]

    t = time.perf_counter()
    p_centre = radio.trace(txs, oris, centres)
    batched_s_per_cell = (time.perf_counter() - t) / pick.size
    offsets = (np.arange(3) - 1) * CELL_M / 3  # centres of the 3 x 3 sub-cells
    ox, oy = (a.ravel() for a in np.meshgrid(offsets, offsets))
    points = (centres[:, None, :] + np.stack([ox, oy, np.zeros(9)], -1)[None]).reshape(-1, 3)
    p_points = radio.trace(txs, oris, points)

    ref_centre = layers_from_moments(_reference_moments(p_centre, tau0, codebook))
    ref_points = layers_from_moments(_reference_moments(p_points, tau0, codebook, pool=9))
    fast_at = {k: v[0].ravel()[pick] for k, v in fast.items() if v.ndim == 3}
    stable = fast_at["count"] >= m.min_count_for_spread
    fast_at["best_beam"] = fast["best_beam"][0].ravel()[pick]
    for k in ("rms_delay_spread_s",) + SPREADS:
        fast_at[k] = np.where(stable, fast_at[k], np.nan)

    loop_pick = rng.choice(pool, min(loop_cells, pool.size), replace=False)
    radio.trace(txs, oris, centres[:1])  # warm-up for the single-receiver shape
    times = []
    for i in loop_pick:
        t = time.perf_counter()
        radio.trace(txs, oris, np.array([[X.ravel()[i], Y.ravel()[i], HEIGHT_M]]))
        times.append(time.perf_counter() - t)
    per_call_s = float(np.mean(times))

    return {
        "scene": spec["attr"], "tx_position_m": list(spec["tx"]), "tx_orientation_rad": ori.round(6).tolist(),
        "grid": {"nx": nx, "ny": ny, "cell_m": CELL_M, "height_m": HEIGHT_M, "cells": n_cells,
                 "cells_with_outdoor_area": n_outdoor, "cells_covered": int(covered.sum())},
        "scene_load_s": round(load_s, 3),
        "one_pass": {"rays": num_rays, "max_depth": MAX_DEPTH, "beams": int(codebook.shape[0]),
                     "first_call_s": round(first_s, 3), "warm_s": round(fast_s, 3),
                     "ray_hits": int(m.count.sum()), "cells_per_s": round(n_cells / fast_s, 1)},
        "pathsolver": {"samples_per_src": SAMPLES_PER_SRC, "compared_cells": int(pick.size),
                       "per_cell_call_s": round(per_call_s, 4), "per_cell_calls_timed": int(len(times)),
                       "batched_s_per_cell": round(batched_s_per_cell, 4),
                       "cells_per_s_per_cell_loop": round(1 / per_call_s, 2),
                       "cells_per_s_batched": round(1 / batched_s_per_cell, 2)},
        "speedup_vs_per_cell_loop": round(per_call_s * n_outdoor / fast_s, 1),
        "speedup_vs_per_cell_loop_all_cells": round(per_call_s * n_cells / fast_s, 1),
        "speedup_vs_batched_pathsolver": round(batched_s_per_cell * n_outdoor / fast_s, 1),
        "errors_vs_centre": _compare(fast_at, ref_centre),
        "errors_vs_3x3_points": _compare(fast_at, ref_points),
    }


def targets(r: dict) -> dict[str, bool | None]:
    """The issue's targets: speed-up >= 100 over one PathSolver call per cell; gain within 0.5 dB
    at p50 of the 3 x 3-point mean; ToA within 1 ns at p50 (at the centre: the layer's definition);
    best beam equal to PathSolver's incoherent best in >= 95 % of cells, for the cell as the gain is
    (the 3 x 3 points pooled): the layer is the best beam of the cell's mean beam gains, and where a
    shadow edge crosses a cell the centre alone can prefer another beam (the report gives both)."""
    g, t = r["errors_vs_3x3_points"]["path_gain_db"]["p50"], r["errors_vs_centre"]["toa_ns"]["p50"]
    b = r["errors_vs_3x3_points"]["best_beam_agreement_pct"]
    return {"speedup_vs_per_cell_loop_ge_100": r["speedup_vs_per_cell_loop"] >= 100,
            "path_gain_p50_vs_3x3_le_0.5_db": None if g is None else g <= 0.5,
            "toa_p50_vs_centre_le_1_ns": None if t is None else t <= 1.0,
            "best_beam_agreement_ge_95_pct": None if b is None else b >= 95.0}


def _row(label: str, e: dict) -> str:
    def pp(v):
        return "-" if v["p50"] is None else f"{v['p50']:.3g} / {v['p95']:.3g}"

    return (f"| {label} | {e['cells_with_paths_in_both']} | {pp(e['path_gain_db'])} | {pp(e['toa_ns'])} | "
            f"{pp(e['rms_delay_spread_ns'])} | {pp(e['asa_deg'])} | {pp(e['asd_deg'])} | {pp(e['zsa_deg'])} | "
            f"{pp(e['zsd_deg'])} | {e['los_agreement_pct']} | {e['best_beam_agreement_pct']} | "
            f"{pp(e['best_beam_loss_db'])} |")


def report(results: dict) -> str:
    s = results["settings"]
    lines = [
        "# One-pass CKM solver vs PathSolver", "",
        f"{s['machine']}; Mitsuba variant `{s['variant']}`; {'quick' if s['quick'] else 'full'} run, "
        f"{s['total_s']:.0f} s in all. Grid {CELL_M:g} m at {HEIGHT_M:g} m, LoS + specular, depth {MAX_DEPTH}, "
        f"one-pass {s['rays']:.0e} rays with 64 DFT beams; PathSolver deterministic, "
        f"{SAMPLES_PER_SRC:.0e} samples, iso V receiver (the one-pass solver projects on V likewise).", "",
        "Errors |one-pass - PathSolver|, p50 / p95, over a random sample of cells wholly outside "
        "buildings that the one-pass solver reaches; spreads where the cell has at least "
        f"{s['min_hits_for_spread']} ray hits. '3x3' pools the paths of 3 x 3 points inside the cell "
        "(gain: their mean), 'centre' is the cell centre alone. Best-beam loss: the reference's gain of "
        "its own best beam minus its gain of the one-pass best beam (0 where they agree).", "",
        "| scene, reference | cells | gain dB | ToA ns | DS ns | ASA deg | ASD deg | ZSA deg | ZSD deg | "
        "LoS agree % | best beam agree % | best-beam loss dB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in results["scenes"].items():
        lines.append(_row(f"{name}, centre", r["errors_vs_centre"]))
        lines.append(_row(f"{name}, 3x3", r["errors_vs_3x3_points"]))
    lines += ["", "Speed (times measured side by side in this run; the per-cell loop was timed on a random "
              "subset of cells and extrapolated to every cell with outdoor area, as was the batched run):", "",
              "| scene | cells (outdoor / covered) | one-pass warm s (first call) | cells/s one-pass | "
              "PathSolver s per call | batched s per cell | speedup vs per-cell loop (all cells) | "
              "speedup vs batched |", "|---|---|---|---|---|---|---|---|"]
    for name, r in results["scenes"].items():
        g, o, p = r["grid"], r["one_pass"], r["pathsolver"]
        lines.append(f"| {name} | {g['cells']} ({g['cells_with_outdoor_area']} / {g['cells_covered']}) | "
                     f"{o['warm_s']} ({o['first_call_s']}) | {o['cells_per_s']} | {p['per_cell_call_s']} "
                     f"(n={p['per_cell_calls_timed']}) | {p['batched_s_per_cell']} | "
                     f"{r['speedup_vs_per_cell_loop']} ({r['speedup_vs_per_cell_loop_all_cells']}) | "
                     f"{r['speedup_vs_batched_pathsolver']} |")
    lines += ["", "Targets of the issue (speed-up >= 100 x per-cell loop; gain p50 <= 0.5 dB vs the 3 x 3 "
              "mean; ToA p50 <= 1 ns at the centre; best beam = PathSolver's incoherent best of the cell "
              "(3 x 3 points pooled) in >= 95 %):", ""]
    for name, r in results["scenes"].items():
        lines.append(f"- {name}: " + ", ".join(f"{k} {'met' if v else 'NOT met' if v is False else 'n/a'}"
                                                for k, v in r["targets_met"].items()))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer compared and timed cells (minutes)")
    ap.add_argument("--out", required=True, type=Path, help="folder for results.json and report.md")
    ap.add_argument("--rays", type=float, default=1e7, help="one-pass rays (default 1e7)")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    compare_cells, loop_cells = (40, 6) if args.quick else (600, 30)
    t0 = time.perf_counter()
    variant = engine.init()
    results = {"settings": {"quick": args.quick, "rays": int(args.rays), "compare_cells": compare_cells,
                            "per_cell_loop_cells": loop_cells, "variant": variant, "seed": args.seed,
                            "min_hits_for_spread": op.DEFAULT_MIN_HITS_FOR_SPREAD,
                            "machine": f"{platform.machine()}, {__import__('os').cpu_count()} CPU cores",
                            "versions": engine.versions()},
               "scenes": {}}
    for name in args.scenes:
        results["scenes"][name] = run_scene(name, SCENES[name], int(args.rays), compare_cells, loop_cells, args.seed)
        results["scenes"][name]["targets_met"] = targets(results["scenes"][name])
        print(json.dumps({name: results["scenes"][name]}, indent=1), flush=True)
    results["settings"]["total_s"] = round(time.perf_counter() - t0, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    (args.out / "report.md").write_text(report(results))
    print(report(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
